"""Motion with an analytic or SciPy reference: compliant angle and bending springs' frequencies, friction on an
incline (2-D and 3-D, stick and slip), and a driven 3-D pendulum's order of accuracy."""
from __future__ import annotations

import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import G, SOLVERS, Outcome, case, crossing_frequency


def _oscillator(solver_name, full, bending: bool):
    """(measured / analytic frequency - 1) of a unit-mass bob on a compliant angle (2-D) or bending (3-D) spring,
    the worst over the case's compliances; the bob's distance d from the spring's axis is held by rods, so
    omega = 1 / sqrt(alpha m d^2)."""
    d, m = 0.5, 1.0
    hertz = (2.0, 8.0) if full else (2.0,)
    dt = 1 / 240
    worst = 0.0
    for f in hertz:
        alpha = 1.0 / ((2 * np.pi * f) ** 2 * m * d * d)
        th0 = 0.05
        if bending:
            x = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-d, 0.5, 0.0], [d, 0.5, 0.0]])
            kind = jc.constraints.bending([[0, 1, 2, 3]], positions=x, compliance=alpha)
            x[3] = [d * np.cos(th0), 0.5, d * np.sin(th0)]
            model, state = jc.build(x, [1.0, 1.0, 1.0, m], rods=[(0, 3), (1, 3)], fixed=[0, 1, 2],
                                    constraints=kind, gravity=np.zeros(3))
        else:
            x = np.array([[0.0, 1.0], [0.0, 0.0], [d, 0.0]])
            kind = jc.constraints.angle([[0, 1, 2]], positions=x, compliance=alpha)
            x[2] = [d * np.cos(th0), d * np.sin(th0)]
            model, state = jc.build(x, [1.0, 1.0, m], rods=[(1, 2)], fixed=[0, 1], constraints=kind,
                                    gravity=np.zeros(2))
        steps = int(round((6.0 if full else 2.0) / dt))
        _, traj = jc.rollout(model, state, SOLVERS[solver_name](), dt, steps)
        s = np.asarray(traj.x[:, -1, -1])
        worst = max(worst, abs(crossing_frequency(s, dt) / f - 1))
    return Outcome(worst, worst <= 0.01, "|f / f_analytic - 1| <= 0.01, f = sqrt(1 / (alpha m d^2)) / 2 pi")


@case("compliant angle frequency",
      """A bob of 1 kg held 0.5 m from a fixed pivot by a rod, with a compliant `angle` spring at the pivot
      (2-D, no gravity), released 0.05 rad from its rest angle, dt 1/240; compliances for 2 Hz (and 8 Hz at full
      size). The number: the worst |f / f_analytic - 1| over them, f from the crossings. Bound: 1%.""",
      "analytic 1 / (2 pi sqrt(alpha m d^2))")
def angle_frequency(solver_name: str, full: bool) -> Outcome:
    return _oscillator(solver_name, full, bending=False)


@case("compliant bending frequency",
      """A hinge of two triangles (3-D, no gravity): the edge and one wing fixed, the other wing a 1 kg particle
      0.5 m from the edge held on its circle by two rods, with a compliant `bending` spring; released 0.05 rad
      from flat, dt 1/240; compliances for 2 Hz (and 8 Hz at full size). The number: the worst
      |f / f_analytic - 1|. Bound: 1%.""",
      "analytic 1 / (2 pi sqrt(alpha m d^2))")
def bending_frequency(solver_name: str, full: bool) -> Outcome:
    return _oscillator(solver_name, full, bending=True)


def _incline(solver_name, dim, ratio, seconds, dtype=None):
    """(distance slid along the slope [steps], analytic acceleration, time [steps]) of a 1 kg particle of radius
    5 cm resting on a plane inclined at atan(ratio mu), mu 0.5, dt 1/240."""
    mu, r, dt = 0.5, 0.05, 1 / 240
    th = np.arctan(ratio * mu)
    if dim == 3:
        n, down = np.array([-np.sin(th), 0.0, np.cos(th)]), np.array([-np.cos(th), 0.0, -np.sin(th)])
    else:
        n, down = np.array([-np.sin(th), np.cos(th)]), np.array([-np.cos(th), -np.sin(th)])
    model, state = jc.build((r * n)[None], [1.0], radius=r, planes=[(n, 0.0)], friction=mu, dtype=dtype)
    steps = int(round(seconds / dt))
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), dt, steps)
    s = (np.asarray(traj.x[:, 0], np.float64) - r * n) @ down
    return s, G * (np.sin(th) - mu * np.cos(th)), dt * np.arange(1, steps + 1)


@case("incline slip",
      """A 1 kg particle (radius 5 cm) on a plane at tan = 1.1 mu (mu 0.5), 2-D and 3-D, dt 1/240, 1 s (0.5 s
      reduced). The number: the worst |a / a_analytic - 1|, a from a quadratic fit over the second half;
      a_analytic = g (sin - mu cos). Bound: 1%.""",
      "analytic g (sin - mu cos)")
def incline_slip(solver_name: str, full: bool) -> Outcome:
    worst = 0.0
    for dim in (2, 3):
        s, a_ref, t = _incline(solver_name, dim, 1.1, 1.0 if full else 0.5)
        h = len(t) // 2
        worst = max(worst, abs(2 * np.polyfit(t[h:], s[h:], 2)[0] / a_ref - 1))
    return Outcome(worst, worst <= 0.01, "|a / (g (sin - mu cos)) - 1| <= 0.01")


@case("incline stick",
      """The same particle on a plane at tan = 0.9 mu: static friction holds it. The number: the largest distance
      slid (m), 2-D and 3-D, over 1 s (0.5 s reduced). Bound: 1e-6 m; Penalty's friction is regularised
      Coulomb, documented to creep at up to its `slip_velocity`, so its bound is slip_velocity times the
      time.""",
      "analytic: no motion")
def incline_stick(solver_name: str, full: bool) -> Outcome:
    seconds = 1.0 if full else 0.5
    slid = max(float(np.abs(_incline(solver_name, dim, 0.9, seconds)[0]).max()) for dim in (2, 3))
    solver = SOLVERS[solver_name]()
    bound = float(solver.slip_velocity) * seconds if isinstance(solver, jc.Penalty) else 1e-6
    return Outcome(slid, slid <= bound, f"distance slid <= {bound:.1e} m")


def _spherical_reference(ts, L, A, w, r0, u0, stiffness=None):
    """Bob positions [len(ts), 3] of a spherical pendulum of length L (unit mass) whose pivot moves as
    (A sin(w t), 0, 0), from bob offset r0 and relative velocity u0: SciPy's DOP853 on r'' = g - p'' + lam r,
    with lam keeping |r| = L (lam = -(r . (g - p'') + |r'|^2) / L^2), or for a spring of `stiffness` (Penalty's
    rod) lam = -stiffness (|r| - L) / |r|."""
    from scipy.integrate import solve_ivp

    g = np.array([0.0, 0.0, -G])

    def rhs(t, y):
        r, u = y[:3], y[3:]
        a = g - np.array([-A * w * w * np.sin(w * t), 0.0, 0.0])
        if stiffness is None:
            lam = -(r @ a + u @ u) / (r @ r)
        else:
            lam = -stiffness * (1 - L / np.sqrt(r @ r))
        return np.concatenate([u, a + lam * r])

    sol = solve_ivp(rhs, (0.0, ts[-1]), np.concatenate([r0, u0]), method="DOP853", rtol=1e-12, atol=1e-12,
                    dense_output=True)
    return sol.sol(ts)[:3].T + np.stack([A * np.sin(w * ts), 0 * ts, 0 * ts], -1)


#: The order of accuracy each solver documents for constrained motion (RATTLE is second order, the others first).
ORDER = {"RATTLE": 2}


@case("driven 3-D pendulum order",
      """A 3-D pendulum (1 m, 1 kg) whose pivot is driven along x as 0.1 sin(5 t) through `targets`, started 0.5
      rad out with a sideways velocity, over 2 s (1 s reduced) at dt 1/240 and 1/480 (1/120 and 1/240 reduced).
      The number: the observed order log2(err(dt) / err(dt / 2)), err the largest distance from SciPy's solution.
      Bound: at least the solver's order (RATTLE 2, the others 1) less 0.3. Penalty's rod is a spring, so its
      reference is SciPy's pendulum on that spring.""",
      "SciPy DOP853, rtol 1e-12")
def driven_pendulum_order(solver_name: str, full: bool) -> Outcome:
    L, A, w, th0, T = 1.0, 0.1, 5.0, 0.5, (2.0 if full else 1.0)
    r0 = np.array([L * np.sin(th0), 0.0, -L * np.cos(th0)])
    u0 = np.array([0.0, 1.0, 0.0])
    solver = SOLVERS[solver_name]()
    stiffness = float(solver.stiffness) if isinstance(solver, jc.Penalty) else None
    errs = []
    for hz in ((240, 480) if full else (120, 240)):
        n = int(round(T * hz))
        ts = np.arange(1, n + 1) / hz
        pivot = np.stack([A * np.sin(w * ts), 0 * ts, 0 * ts], -1)
        model, state = jc.build(np.stack([np.zeros(3), r0]), [1.0, 1.0], rods=[(0, 1)], fixed=[0],
                                velocities=np.stack([np.zeros(3), u0 + [A * w, 0.0, 0.0]]))
        _, traj = jc.rollout(model, state, solver, 1 / hz, n, targets=pivot[:, None, :])
        ref = _spherical_reference(ts, L, A, w, r0, u0, stiffness)
        errs.append(np.abs(np.asarray(traj.x[:, 1]) - ref).max())
    order = float(np.log2(errs[0] / errs[1]))
    want = ORDER.get(solver_name, 1)
    return Outcome(order, order >= want - 0.3,
                   f"observed order >= {want} - 0.3 (errors {errs[0]:.2e}, {errs[1]:.2e} m)")
