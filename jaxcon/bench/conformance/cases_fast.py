"""Float32 small accelerations, fast particles against thin obstacles, and start overlaps, in every solver.

References: analytic free fall and Coulomb sliding; geometry (where an obstacle's face is); the documented
push-out speed (`contact_rows.PUSH_OUT_SPEED`, 3 m/s) and energy.
"""
from __future__ import annotations

import warnings

import numpy as np

from jaxcon.core.model import build
from jaxcon.core.sim import rollout
from jaxcon.scenes import cloth_edges
from jaxcon.bench.conformance import G, CONTACT_SOLVERS, SOLVERS, Outcome, case

PUSH = 3.0


def _run(model, state, solver_name, dt, steps):
    """A rollout with the solver at its documented settings; Penalty with at least the substeps its
    `stability_limit` asks for (its springs diverge otherwise: the cloth's 0.01 kg particles need 280)."""
    solver = SOLVERS[solver_name]()
    if solver_name == "Penalty":
        need = int(np.ceil(dt / solver.stability_limit(model)))
        if need > solver.substeps:
            solver = SOLVERS[solver_name](substeps=need)
    with warnings.catch_warnings():          # Penalty's stability warning: the cell's bound judges the run
        warnings.simplefilter("ignore", RuntimeWarning)
        return rollout(model, state, solver, dt, steps)


def _grid(n, spacing):
    g = np.stack(np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing, indexing="ij"), -1)
    return g.reshape(-1, 2)


@case("free fall float32",
      """A free cloth (n x n particles, 1 kg in all, structural and shear rods, nothing fixed) released at rest
      10 m up, float32, dt 1/240, 0.5 s. The number: the centre of mass's drop over g t^2 / 2, minus 1. Bound:
      1% (symplectic Euler's first-order error is 1 / steps = 0.83%). n = 6 (16 at full size).""",
      "analytic g t^2 / 2")
def free_fall(solver_name: str, full: bool) -> Outcome:
    n, steps, dt = (16 if full else 6), 120, 1 / 240
    x = np.concatenate([_grid(n, 1 / (n - 1)), np.full((n * n, 1), 10.0)], 1)
    edges, _ = cloth_edges(n, n)
    model, state = build(x, 1.0 / (n * n), rods=[tuple(e) for e in np.asarray(edges)], dtype=np.float32)
    final, _ = _run(model, state, solver_name, dt, steps)
    drop = 10.0 - float(np.mean(np.asarray(final.x, np.float64)[:, 2]))
    err = drop / (0.5 * G * (steps * dt) ** 2) - 1
    return Outcome(err, abs(err) <= 0.01, "|drop / (g t^2 / 2) - 1| <= 0.01")


@case("small forces float32",
      """A free dumbbell (two 1 kg particles at (3, 4) and (4, 4) m, one rod) pulled down by 0.49, 0.50 and
      0.51 N per particle (gravity F / m), float32,
      dt 1/240, 0.5 s (1 s at full size). The number: the worst of the three displacements' and of the two
      differences' relative errors against F t^2 / (2 m). Bound: 2 / steps (first order: symplectic Euler's
      error is 1 / steps), so the three forces are told apart to within 2 / steps of their 2% difference.""",
      "analytic F t^2 / (2 m)")
def small_forces(solver_name: str, full: bool) -> Outcome:
    steps, dt = (240 if full else 120), 1 / 240
    t = steps * dt
    drops = []
    for f in (0.49, 0.50, 0.51):
        model, state = build(np.array([[3.0, 4.0], [4.0, 4.0]]), 1.0, rods=[(0, 1)], gravity=np.array([0.0, -f]),
                                dtype=np.float32)
        final, _ = _run(model, state, solver_name, dt, steps)
        drops.append(4.0 - float(np.mean(np.asarray(final.x, np.float64)[:, 1])))
    ref = [0.5 * f * t * t for f in (0.49, 0.50, 0.51)]
    errs = [d / r - 1 for d, r in zip(drops, ref)]
    errs += [(drops[k + 1] - drops[k]) / (ref[k + 1] - ref[k]) - 1 for k in range(2)]
    worst = max(errs, key=abs)
    return Outcome(worst, abs(worst) <= 2 / steps, f"worst relative error <= 2 / steps = {2 / steps:.4f}")


def _incline(solver_name, ratio, steps, mu=0.5, r=0.05, dt=1 / 240):
    th = np.arctan(ratio * mu)
    n, down = np.array([-np.sin(th), 0, np.cos(th)]), np.array([-np.cos(th), 0, -np.sin(th)])
    model, state = build((r * n)[None], [1.0], radius=r, planes=[(n, 0.0)], friction=mu, dtype=np.float32)
    _, traj = _run(model, state, solver_name, dt, steps)
    s = (np.asarray(traj.x[:, 0], np.float64) - r * n) @ down
    return s, dt * np.arange(1, steps + 1), G * (np.sin(th) - mu * np.cos(th))


@case("incline float32",
      """A 1 kg particle (R 0.05 m) at rest on a plane through the origin, mu 0.5, float32, dt 1/240, 1 s
      (0.5 s reduced). Slip: tan = 1.1 mu; the acceleration fitted (quadratic) over the second half, against
      g (sin - mu cos), bound 1%. Stick: tan = 0.9 mu, the distance slid, bound 1e-5 m (Penalty: its documented
      creep, slip_velocity t). The number: the slip
      case's relative error (the stick distance in the detail).""",
      "analytic g (sin - mu cos); 0 when it sticks", solvers=CONTACT_SOLVERS)
def incline(solver_name: str, full: bool) -> Outcome:
    steps = 240 if full else 120
    s, t, a_ref = _incline(solver_name, 1.1, steps)
    a = 2 * np.polyfit(t[steps // 2:], s[steps // 2:], 2)[0]
    err = a / a_ref - 1
    stick, t, _ = _incline(solver_name, 0.9, steps)
    slid = float(np.max(np.abs(stick)))
    # Penalty's friction is regularised: a contact that should stick creeps at up to its slip_velocity
    creep = float(SOLVERS["Penalty"]().slip_velocity) * t[-1] if solver_name == "Penalty" else 1e-5
    return Outcome(err, abs(err) <= 0.01 and slid <= creep,
                   f"|a / a_ref - 1| <= 0.01 and stick slid {slid:.2e} m <= {creep:.1e} m")


@case("ball through cloth",
      """A ball (r 5 cm, 1 kg; 0.01 kg at reduced size) falling at 50 m/s onto the middle of a corner-pinned
      n x n cloth of touching particles (r 2 cm, spacing 4 cm, 0.01 kg, collide=True), dt 1/120, from 0.5 m
      above it for 0.25 s; n = 12 (6, from 0.1 m above for 10 steps, at reduced size). The number: the most the ball's centre got below the lowest cloth particle
      within 8 cm of it horizontally (m; negative: it stayed above). Bound: it never passes the cloth, the
      number below 0. Penalty with the substeps its `stability_limit` asks for.""",
      "geometry", solvers=CONTACT_SOLVERS)
def ball_through_cloth(solver_name: str, full: bool) -> Outcome:
    n, ball_mass, z, steps = (12, 1.0, 1.5, 30) if full else (6, 0.01, 1.1, 10)
    sp = 0.04
    c = (n - 1) * sp / 2
    cloth = np.concatenate([_grid(n, sp), np.full((n * n, 1), 1.0)], 1)
    x = np.concatenate([cloth, [[c, c, z]]])
    radius = np.full(len(x), 0.02)
    radius[-1] = 0.05
    v = np.zeros_like(x)
    v[-1, 2] = -50.0
    mass = np.full(len(x), 0.01)
    mass[-1] = ball_mass
    edges, _ = cloth_edges(n, n)
    model, state = build(x, mass, rods=[tuple(e) for e in np.asarray(edges)], fixed=[0, n - 1, n * (n - 1), n * n - 1],
                            velocities=v, radius=radius, collide=True)
    _, traj = _run(model, state, solver_name, 1 / 120, steps)
    xs = np.asarray(traj.x)
    ball, cl = xs[:, -1], xs[:, : n * n]
    near = np.linalg.norm(cl[:, :, :2] - ball[:, None, :2], axis=-1) < 0.08
    below = np.where(near, cl[:, :, 2], np.inf).min(1) - ball[:, 2]
    worst = float(np.max(np.where(near.any(1), below, -np.inf)))
    return Outcome(worst, worst < 0, "the ball's centre never below the cloth around it")


def _wall(solver_name, collide):
    wall = np.array([[0.5, 0.02 * i] for i in range(-5, 5)])
    x = np.concatenate([[[-1.0, 0.0]], wall])
    v = np.zeros_like(x)
    v[0, 0] = 200.0
    model, state = build(x, 1.0, fixed=list(range(1, 11)), velocities=v, radius=0.01, collide=collide,
                            gravity=np.zeros(2))
    _, traj = _run(model, state, solver_name, 1 / 60, 5)
    return float(np.max(np.asarray(traj.x)[:, 0, 0]))


@case("disc through wall",
      """A 1 cm disc at 200 m/s (3.3 m per step at dt 1/60) toward a wall of ten touching fixed discs (r 1 cm,
      centres at x = 0.5), no gravity, 5 steps, all pairs (and the neighbour grid at full size). The number: the
      disc's largest x. Bound: at most 0.49, half a radius past the wall's face at 0.48.""",
      "geometry", solvers=CONTACT_SOLVERS)
def disc_through_wall(solver_name: str, full: bool) -> Outcome:
    worst = max(_wall(solver_name, col) for col in ((True, "grid") if full else (True,)))
    return Outcome(worst, worst <= 0.49, "x <= 0.49 (the wall's face is at 0.48)")


@case("particle through sphere",
      """A 1 cm particle at 100 m/s (1.7 m per step at dt 1/60) toward a static sphere (R 5 cm at x = 0.5), no
      gravity, 5 steps. The number: the particle's largest x. Bound: at most 0.47, half the contact distance past
      the sphere's face at 0.44.""",
      "geometry", solvers=CONTACT_SOLVERS)
def particle_through_sphere(solver_name: str, full: bool) -> Outcome:
    model, state = build(np.array([[-1.0, 0.0]]), 1.0, velocities=np.array([[100.0, 0.0]]), radius=0.01,
                            spheres=[((0.5, 0.0), 0.05)], gravity=np.zeros(2))
    _, traj = _run(model, state, solver_name, 1 / 60, 5)
    worst = float(np.max(np.asarray(traj.x)[:, 0, 0]))
    return Outcome(worst, worst <= 0.47, "x <= 0.47 (the sphere's face is at 0.44)")


def _energy(traj, mass):
    v, y = np.asarray(traj.v, np.float64), np.asarray(traj.x, np.float64)[..., -1]
    return 0.5 * np.sum(mass * np.sum(v * v, -1), -1) + G * np.sum(mass * y, -1)


@case("start overlap push-out",
      """Start overlaps: (a) a column of N 1 kg discs (r 5 cm) started 1 cm apart (90% overlapped) on a floor,
      N = 4 (10 at full size), dt 1/240, 0.25 s (2 s at full size); (b) a 1 kg particle (r 1 cm) started inside
      two overlapping static spheres (R 0.5 m at x = -0.3 and 0.3), dt 1/240, 0.25 s (0.5 s at full size). The number: the largest
      speed less what gravity alone gives by then (g t), m/s. Bound: at most 3 m/s (the documented push-out
      speed), and the energy (kinetic plus potential) never above its start by more than N (1 kg / 2)(3 m/s)^2.""",
      "PUSH_OUT_SPEED = 3 m/s; energy", solvers=CONTACT_SOLVERS)
def start_overlap(solver_name: str, full: bool) -> Outcome:
    n, steps, dt = (10, 480, 1 / 240) if full else (4, 60, 1 / 240)
    t = dt * np.arange(1, steps + 1)
    x = np.array([[0.0, 0.5 + 0.01 * i] for i in range(n)])
    model, state = build(x, 1.0, radius=0.05, collide=True, planes=[((0.0, 1.0), 0.0)])
    _, traj = _run(model, state, solver_name, dt, steps)
    speed = np.linalg.norm(np.asarray(traj.v, np.float64), axis=-1).max(1)
    fast = float(np.max(speed - G * t))
    gain = float(np.max(_energy(traj, 1.0)) - G * np.sum(x[:, 1]))
    model, state = build(np.array([[0.0, 0.0]]), 1.0, radius=0.01, spheres=[((-0.3, 0.0), 0.5), ((0.3, 0.0), 0.5)])
    _, traj = _run(model, state, solver_name, dt, min(steps, 120))
    speed = np.linalg.norm(np.asarray(traj.v, np.float64), axis=-1).max(1)
    fast = max(fast, float(np.max(speed - G * t[:min(steps, 120)])))
    gain2 = float(np.max(_energy(traj, 1.0)))
    ok = fast <= PUSH and gain <= n * 0.5 * PUSH ** 2 and gain2 <= 0.5 * PUSH ** 2
    return Outcome(fast, ok, f"speed - g t <= 3 m/s; energy gain {gain:.3g} J (column), {gain2:.3g} J (spheres)")
