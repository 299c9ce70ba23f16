"""Chains of touching bodies and piles: Newton's cradle (one and two balls in), a pyramid of discs that must hold
and a column of discs that must rest, in every solver that takes contacts."""
from __future__ import annotations

import math

import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import G, SOLVERS, Outcome, case


# ---- Newton's cradle ------------------------------------------------------------------------------------------
R_BALL, M_BALL, ROD, ANGLE, GAP, DT_CRADLE = 0.05, 0.1, 0.5, math.radians(60), 1e-6, 1 / 240
V0 = math.sqrt(2 * G * ROD * (1 - math.cos(ANGLE)))       # the released balls' speed at the bottom
AFTER = 0.05                                              # s after the impact at which velocities are read


def _start_angle(full: bool) -> float:
    """Where the released balls start: 60 degrees at rest (full), or 2 degrees before the bottom already at
    the speed the swing from 60 degrees gives there (reduced: the impact in the second step)."""
    return ANGLE if full else math.radians(2)


def _cradle_scene(balls_in: int, full: bool):
    piv = np.array([[(2 * R_BALL + GAP) * i, 0.0] for i in range(5)])
    balls = piv + [0.0, -ROD]
    vel = np.zeros((10, 2))
    a = _start_angle(full)
    speed = 0.0 if full else math.sqrt(2 * G * ROD * (math.cos(a) - math.cos(ANGLE)))
    for b in range(balls_in):
        balls[b] = piv[b] + ROD * np.array([-math.sin(a), -math.cos(a)])
        vel[5 + b] = speed * np.array([math.cos(a), -math.sin(a)])
    return piv, balls, vel


def _cradle(solver_name: str, balls_in: int, full: bool):
    """(signed speeds / V0 of the five balls AFTER s after the last ball moves, the change of the total energy
    (kinetic + gravity) over the step in which it starts to move, over the incoming kinetic energy). The energy
    is compared over that step alone: the swing itself changes it by the integrator's error (symplectic Euler's
    pendulum gains up to 5e-3 of it on the way up, and loses it again)."""
    piv, balls, vel = _cradle_scene(balls_in, full)
    model, state = jc.build(np.concatenate([piv, balls]), np.r_[np.ones(5), np.full(5, M_BALL)],
                            rods=[(i, 5 + i) for i in range(5)], fixed=list(range(5)),
                            radius=np.r_[np.zeros(5), np.full(5, R_BALL)],
                            collide=[(5 + i, 5 + j) for i in range(5) for j in range(i + 1, 5)],
                            restitution=1.0, restitution_threshold=0.01, velocities=vel)
    steps = round((0.45 if full else 0.03) / DT_CRADLE) + round(AFTER / DT_CRADLE) + 2
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), DT_CRADLE, steps)
    x, v = np.asarray(traj.x)[:, 5:], np.asarray(traj.v)[:, 5:]
    moved = np.abs(v[:, 4, 0]) > 0.3 * V0
    if not moved.any():
        return np.full(5, np.nan), np.nan
    k = int(np.argmax(moved)) + round(AFTER / DT_CRADLE)
    speeds = np.sign(v[k, :, 0]) * np.linalg.norm(v[k], axis=1) / V0
    energy = 0.5 * M_BALL * np.sum(v ** 2, (1, 2)) + M_BALL * G * np.sum(x[:, :, 1], 1)
    k0 = int(np.argmax(moved))
    before = energy[k0 - 1] if k0 else 0.5 * M_BALL * np.sum(vel ** 2) + M_BALL * G * np.sum(balls[:, 1])
    return speeds, (energy[k0] - before) / (0.5 * M_BALL * V0 ** 2 * balls_in)


def _cradle_outcome(solver_name: str, balls_in: int, full: bool) -> Outcome:
    speeds, gain = _cradle(solver_name, balls_in, full)
    out, rest = speeds[5 - balls_in:], speeds[: 5 - balls_in]
    value = float(np.min(out))
    ok = value >= 0.95 and np.all(np.abs(rest) <= 0.05) and gain <= 1e-3
    return Outcome(value, bool(ok), f"balls / v0 {np.round(speeds, 3).tolist()}; out >= 0.95, others <= 0.05; "
                                    f"energy gain {gain:.1e} <= 1e-3 of the incoming")


def _box2d_cradle(balls_in: int, full: bool) -> float:
    """Box2D 2.3 (pybox2d), the same set-up: distance joints to static pivots, restitution 1, 8/3 iterations."""
    from Box2D import b2CircleShape, b2FixtureDef, b2World

    piv, balls, vel = _cradle_scene(balls_in, full)
    world = b2World(gravity=(0, -G))
    ground = world.CreateStaticBody(position=(0, 0))
    bodies = []
    for i in range(5):
        b = world.CreateDynamicBody(position=tuple(balls[i]), fixedRotation=True)
        b.CreateFixture(b2FixtureDef(shape=b2CircleShape(radius=R_BALL), density=M_BALL / (math.pi * R_BALL ** 2),
                                     friction=0.0, restitution=1.0))
        b.linearVelocity = tuple(vel[5 + i])
        world.CreateDistanceJoint(bodyA=ground, bodyB=b, anchorA=tuple(piv[i]), anchorB=tuple(balls[i]))
        bodies.append(b)
    return _peer_speed(lambda: world.Step(DT_CRADLE, 8, 3), lambda: [b.linearVelocity for b in bodies], balls_in,
                       full)


def _pymunk_cradle(balls_in: int, full: bool) -> float:
    """pymunk 7 (Chipmunk), the same set-up: pin joints to the static body, elasticity 1, default iterations."""
    import pymunk

    piv, balls, vel = _cradle_scene(balls_in, full)
    space = pymunk.Space()
    space.gravity = (0, -G)
    bodies = []
    for i in range(5):
        b = pymunk.Body(M_BALL, math.inf)
        b.position, b.velocity = tuple(balls[i]), tuple(vel[5 + i])
        s = pymunk.Circle(b, R_BALL)
        s.elasticity, s.friction = 1.0, 0.0
        space.add(b, s, pymunk.PinJoint(space.static_body, b, tuple(piv[i]), (0, 0)))
        bodies.append(b)
    return _peer_speed(lambda: space.step(DT_CRADLE), lambda: [b.velocity for b in bodies], balls_in, full)


def _peer_speed(step, velocities, balls_in: int, full: bool) -> float:
    """The slowest outgoing ball's signed speed / V0, AFTER s after the last ball moves, of a peer engine."""
    vs = []
    for _ in range(round((0.45 if full else 0.03) / DT_CRADLE) + round(AFTER / DT_CRADLE) + 2):
        step()
        vs.append([math.copysign(math.hypot(u[0], u[1]), u[0]) for u in velocities()])
    vs = np.array(vs)
    k = int(np.argmax(np.abs(vs[:, 4]) > 0.3 * V0)) + round(AFTER / DT_CRADLE)
    return float(np.min(vs[k, 5 - balls_in:]) / V0)


@case("newton's cradle",
      """Five touching balls (R 0.05 m, 0.1 kg, 1 um apart) on 0.5 m rods from fixed pivots, restitution 1
      (threshold 0.01 m/s), no friction, dt 1/240; ball 0 released from 60 degrees (full; reduced: 2 degrees
      before the bottom at the swing's speed). The number: the last ball's speed / v0, 0.05 s after it moves.
      Bound: >= 0.95, the others <= 0.05, and the impact's step adds no more than 1e-3 of the incoming
      kinetic energy to the total (kinetic + gravity). The classic result; Box2D 2.3 and pymunk 7 in the
      same set-up.""",
      "momentum and energy of sequential impacts; Box2D, pymunk",
      peers={"Box2D": lambda full: _box2d_cradle(1, full), "pymunk": lambda full: _pymunk_cradle(1, full)})
def cradle_one(solver_name: str, full: bool) -> Outcome:
    return _cradle_outcome(solver_name, 1, full)


@case("newton's cradle, two balls in",
      """The cradle of `newton's cradle` with balls 0 and 1 released together. The number: the slower of the
      last two balls' speeds / v0, 0.05 s after the last one moves. Bound: both >= 0.95, the other three <=
      0.05, no energy gained (as the single cradle).""",
      "momentum and energy of sequential impacts; Box2D, pymunk",
      peers={"Box2D": lambda full: _box2d_cradle(2, full), "pymunk": lambda full: _pymunk_cradle(2, full)})
def cradle_two(solver_name: str, full: bool) -> Outcome:
    return _cradle_outcome(solver_name, 2, full)


# ---- piles ----------------------------------------------------------------------------------------------------
R_DISC, FRICTION, DT_PILE = 0.5, 0.6, 1 / 60


def _pyramid(base: int):
    """Centres of a hexagonal pyramid of touching discs of radius R_DISC on the floor y = 0, `base` in the
    bottom row."""
    return np.array([[2 * R_DISC * (i + r / 2), R_DISC + r * math.sqrt(3) * R_DISC]
                     for r in range(base) for i in range(base - r)])


@case("pyramid holds",
      """A hexagonal pyramid of touching discs (R 0.5 m, 1 kg, friction 0.6) on a floor, all pairs colliding,
      dt 1/60: 55 discs (base 10) for 5 s (full), 15 discs (base 5) for 2 s (reduced). The number: the largest
      horizontal displacement of any disc over the run / R. Bound: 0.01 (a pyramid of frictional discs at rest
      stays at rest; PGS and Direct keep it to rounding). Penalty's discs are springs that give way by their load
      over the stiffness, so it runs at stiffness 1e6 N/m with 100 substeps (its stability limit asks for 76);
      at its matrix settings (1e5, 30 substeps) the reduced pyramid spreads 2.3% of R.""",
      "statics: the pyramid at rest")
def pyramid_holds(solver_name: str, full: bool) -> Outcome:
    base, seconds = (10, 5.0) if full else (5, 2.0)
    pos = _pyramid(base)
    model, state = jc.build(pos, np.ones(len(pos)), radius=R_DISC, collide=True, planes=[((0.0, 1.0), 0.0)],
                            friction=FRICTION)
    stiff = {"stiffness": 1e6, "substeps": 100} if solver_name == "Penalty" else {}
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](**stiff), DT_PILE, round(seconds / DT_PILE))
    spread = float(np.max(np.abs(np.asarray(traj.x)[:, :, 0] - pos[:, 0])) / R_DISC)
    return Outcome(spread, spread <= 0.01, "max horizontal displacement / R <= 0.01")


@case("static column at rest",
      """A column of touching discs (R 0.5 m, 1 kg) standing on a floor, neighbours colliding, no friction
      needed, dt 1/60: 10 discs for 5 s (full), 5 discs for 2 s (reduced). The number: the largest reported
      speed |v| of any disc at the end. Bound: 1e-3 m/s (the column is in equilibrium from the start).""",
      "statics: the column at rest")
def column_at_rest(solver_name: str, full: bool) -> Outcome:
    n, seconds = (10, 5.0) if full else (5, 2.0)
    col = np.array([[0.0, R_DISC + 2 * R_DISC * k] for k in range(n)])
    model, state = jc.build(col, np.ones(n), radius=R_DISC, collide=[(k, k + 1) for k in range(n - 1)],
                            planes=[((0.0, 1.0), 0.0)])
    final, _ = jc.rollout(model, state, SOLVERS[solver_name](), DT_PILE, round(seconds / DT_PILE))
    speed = float(np.max(np.linalg.norm(np.asarray(final.v), axis=-1)))
    return Outcome(speed, speed < 1e-3, "max |v| at the end < 1e-3 m/s")
