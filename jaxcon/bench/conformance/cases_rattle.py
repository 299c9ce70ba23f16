"""RATTLE's cells, run for every solver: a stiff compliant set, a compliant cantilever at its potential minimum, the
energy of a 3-link pendulum over a long run, and the velocity a static column of discs reports."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy import optimize

import jaxcon as jc
from jaxcon.bench.conformance import G, SOLVERS, Outcome, case, for_compliance


def _user_length(x, p):
    return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))


@case("implicit stiff set",
      """A pendulum whose link is a `jc.Constraint` distance of compliance alpha = 1e-12 m/N (1 kg bob, 1 m, fixed
      pivot), released from horizontal, dt 1/240, 1 s (reduced: 0.5 s). The tension is at most 3 m g, so the
      link stretches by at most 3e-11 m. The number: the largest | |d| - L | / L over the run. Bound: 1e-3 and
      every position finite and within 1.01 L of the pivot. An explicit spring of this stiffness is unstable at
      any usable step (RATTLE's old springs reached 1e24 m). Penalty is left out: it integrates compliant rows as
      explicit springs by design, documented stable only below a substep of 2 sqrt(alpha / s) (docs/constraints.md),
      and warns above it.""",
      "analytic: alpha T <= 3e-11 m", solvers=[s for s in SOLVERS if s != "Penalty"])
def stiff_set(solver_name: str, full: bool) -> Outcome:
    link = jc.Constraint(_user_length, [[0, 1]], {"L": [1.0]}, compliance=1e-12, name="link")
    model, state = jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0, fixed=[0], constraints=link)
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), 1 / 240, 240 if full else 120)
    x = np.asarray(traj.x)
    d = np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
    err = float(np.max(np.abs(d - 1.0))) if np.all(np.isfinite(x)) else np.inf
    return Outcome(err, err <= 1e-3 and float(np.max(d)) <= 1.01, "max | |d| - L | / L <= 1e-3")


def _bend(x, p):
    """The bend at x[1] of the polyline x[0], x[1], x[2] (rad; 0 straight, counter-clockwise positive)."""
    e1, e2 = x[1] - x[0], x[2] - x[1]
    return jnp.arctan2(e1[0] * e2[1] - e1[1] * e2[0], jnp.dot(e1, e2))


def _cantilever(n: int, mass: float, link: float, alpha: float):
    """The potential minimum of a 2-D cantilever: particles 0 (at -link, 0) and 1 (the origin) fixed, n free
    particles joined by rigid links of `link` m, a bending spring of compliance alpha (rad / (N m)) at each of
    particles 1 .. n. SciPy in the links' angles theta_k (theta_0 = 0): minimise sum m g y + sum phi_k^2 /
    (2 alpha), phi_k = theta_k - theta_{k-1}, to a gradient of 1e-13. Returns (positions [n + 2, 2], bends
    [n], the links' tensions [n + 1] (N; the fixed link's is 0 and unused))."""
    k = np.arange(1, n + 1)

    def energy(th):
        phi = np.diff(np.concatenate([[0.0], th]))
        y = np.cumsum(link * np.sin(th))
        return mass * G * np.sum(y) + np.sum(phi ** 2) / (2 * alpha)

    def grad(th):
        phi = np.diff(np.concatenate([[0.0], th]))
        return mass * G * link * np.cos(th) * (n - k + 1) + (phi - np.append(phi[1:], 0.0)) / alpha

    th = optimize.minimize(energy, np.zeros(n), jac=grad, method="BFGS", options={"gtol": 1e-13}).x
    th = optimize.root(grad, th, jac=lambda t: optimize.approx_fprime(t, grad, 1e-8), tol=1e-15).x
    assert np.max(np.abs(grad(th))) < 1e-10, "the cantilever's minimum did not converge"
    pos = np.vstack([[-link, 0.0], [0.0, 0.0], np.cumsum(link * np.stack([np.cos(th), np.sin(th)], 1), 0)])
    phi = np.diff(np.concatenate([[0.0], th]))
    # the links' tensions from the free particles' force balance: gravity, the springs' forces J^T (-phi / alpha)
    # and the links' (tension T pulls the link's ends together)
    J = np.asarray(jax.vmap(jax.grad(_bend), in_axes=(0, None))(
        jnp.asarray(np.stack([pos[i - 1:i + 2] for i in range(1, n + 1)])), {}))
    force = np.zeros_like(pos)
    force[:, 1] -= mass * G
    for i in range(n):
        force[i:i + 3] += J[i] * (-phi[i] / alpha)
    A = np.zeros((2 * n, n + 1))
    for r in range(n + 1):
        u = (pos[r + 1] - pos[r]) / link
        for p, sign in ((r, 1.0), (r + 1, -1.0)):
            if p >= 2:
                A[2 * (p - 2):2 * (p - 1), r] = sign * u
    tension = np.linalg.lstsq(A, -force[2:].reshape(-1), rcond=None)[0]
    return pos, phi, tension


@case("bending cantilever at rest",
      """A 2-D cantilever: two fixed particles clamp the first link horizontally, then 10 (reduced: 4) free
      particles of 0.01 kg on rigid rods of 0.05 m, with a bending spring (a `jc.Constraint` of the bend angle,
      compliance 0.1 rad / (N m)) at every joint. It starts at rest at its potential minimum (SciPy, in the links'
      angles, gradient 1e-13), with the analytic impulses as its warm start (rods' tensions from the force
      balance, the springs' -phi dt / alpha), and runs 1 s at dt 1/240. The springs are stiff for the step
      (h omega above 2 at the tip: explicit springs were unstable: RATTLE's moved 19 times the drop). The number:
      the largest distance of a particle from the minimum over the run, divided by the tip's drop. Bound: 2%: a
      solver whose static spring is off by 1% (the compliance cells' bound) rests 1% of the drop away and, started
      at the true minimum, swings about its own rest point up to twice that. Each solver at its settings for
      compliant constraints (`for_compliance`: XPBD with 16 iterations).""",
      "SciPy minimum of the potential")
def cantilever_at_rest(solver_name: str, full: bool) -> Outcome:
    n, mass, link, alpha, dt = (10 if full else 4), 0.01, 0.05, 0.1, 1 / 240
    pos, phi, tension = _cantilever(n, mass, link, alpha)
    bend = jc.Constraint(_bend, [(i - 1, i, i + 1) for i in range(1, n + 1)], {}, compliance=alpha, name="bend")
    model, state = jc.build(pos, np.full(n + 2, mass), rods=[(i, i + 1) for i in range(n + 1)], fixed=[0, 1],
                            constraints=[bend])
    state = state.replace(lam=jnp.asarray(np.concatenate([tension, -phi / alpha]) * dt))
    _, traj = jc.rollout(model, state, for_compliance(solver_name), dt, 240)
    x = np.asarray(traj.x)
    drop = abs(pos[-1, 1])
    moved = float(np.max(np.linalg.norm(x - pos, axis=2))) / drop if np.all(np.isfinite(x)) else np.inf
    return Outcome(moved, moved <= 0.02, f"max |x - x_min| / tip drop ({drop:.3g} m) <= 0.02")


@case("energy of a 3-link pendulum",
      """A 3-link pendulum (0.5 m rods, 1 kg bobs, fixed pivot) released at rest from 1.2, 0.6 and -0.4 rad,
      dt 1/240, 1e5 steps (reduced: 1e4), energy every 10 steps. The number: the energy error (E - E0) / (M g L),
      M g L = 3 x 9.81 x 1.5 J. RATTLE, symplectic: |E - E0| <= 1e-3 M g L over the run, and (reduced) the drift
      between the means of the first and the last fifth <= 1e-4 (a tenth of the full bound for a tenth of the
      steps). Every other solver is documented first order and dissipative: it must not gain energy, E - E0 <=
      1e-3 M g L.""",
      "energy conservation (analytic E0)")
def pendulum_energy(solver_name: str, full: bool) -> Outcome:
    th = np.array([1.2, 0.6, -0.4])
    pos = np.vstack([[0.0, 0.0], np.cumsum(np.stack([0.5 * np.sin(th), -0.5 * np.cos(th)], 1), 0)])
    model, state = jc.build(pos, np.ones(4), rods=[(0, 1), (1, 2), (2, 3)], fixed=[0])
    scale = 3 * G * 1.5
    e0 = float(jc.energy(model, state.x, state.v))
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), 1 / 240, 100_000 if full else 10_000, save_every=10)
    e = (np.asarray(jc.energy(model, traj.x, traj.v)) - e0) / scale
    if not np.all(np.isfinite(e)):
        return Outcome(np.inf, False, "non-finite energy")
    if solver_name != "RATTLE":
        gain = float(np.max(e))
        return Outcome(gain, gain <= 1e-3, "first order: no gain, max (E - E0) / (M g L) <= 1e-3")
    worst = float(np.max(np.abs(e)))
    fifth = len(e) // 5
    drift = abs(float(e[-fifth:].mean() - e[:fifth].mean()))
    ok = worst <= 1e-3 and (full or drift <= 1e-4)
    return Outcome(worst, ok, f"symplectic: max |E - E0| / (M g L) <= 1e-3; drift {drift:.2e}"
                   + ("" if full else " <= 1e-4"))


@case("static column velocity",
      """A column of 10 (reduced: 5) touching discs (R 0.5 m, 1 kg) standing on a floor, pairs colliding with
      their neighbours, dt 1/60, 5 s (reduced: 1 s). At rest the velocity every solver reports after a step is 0
      (the impulses hold the weight exactly: the floor's is N m g dt). The number: the largest |v| reported at
      the last step. Bound: 1e-3 m/s (RATTLE reported g dt / 2 = 0.082 m/s, the second half kick of gravity,
      while its positions stood still).""",
      "analytic: at rest")
def static_column(solver_name: str, full: bool) -> Outcome:
    n, radius = (10 if full else 5), 0.5
    col = np.array([[0.0, radius + 2 * radius * k] for k in range(n)])
    model, state = jc.build(col, np.ones(n), radius=radius, collide=[(k, k + 1) for k in range(n - 1)],
                            planes=[((0.0, 1.0), 0.0)])
    final, _ = jc.rollout(model, state, SOLVERS[solver_name](), 1 / 60, 300 if full else 60)
    v = float(np.max(np.abs(np.asarray(final.v)))) if np.all(np.isfinite(np.asarray(final.x))) else np.inf
    return Outcome(v, v <= 1e-3, "max |v| at the end <= 1e-3 m/s")
