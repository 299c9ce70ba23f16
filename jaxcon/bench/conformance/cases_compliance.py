"""Compliance: a compliant constraint is the same spring, potential C^2 / (2 alpha), in every solver."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import G, Outcome, case, crossing_frequency, for_compliance


def _link(x, p):
    return p["L"] - jnp.linalg.norm(x[1] - x[0])


def _stretch_error(solver_name, n, alpha, dt, seconds, m=0.01, length=0.1):
    """A hanging chain's worst |mean stretch over the second half / (alpha T_k) - 1| (`static_stretch`)."""
    steps = int(round(seconds / dt))
    tension = G * m * (n - np.arange(n))
    y = -np.concatenate([[0.0], np.cumsum(length + alpha * tension)])
    pos = np.stack([np.zeros(n + 1), y], 1)
    link = jc.Constraint(_link, particles=[(k, k + 1) for k in range(n)], params={"L": np.full(n, length)},
                         compliance=alpha, name="link")
    model, state = jc.build(pos, np.full(n + 1, m), fixed=[0], constraints=[link])
    state = state.replace(lam=jnp.asarray(tension * dt))
    _, traj = jc.rollout(model, state, for_compliance(solver_name), dt, steps)
    d = np.linalg.norm(np.diff(np.asarray(traj.x), axis=1), axis=2)[steps // 2:] - length
    return float(np.max(np.abs(d.mean(0) / (alpha * tension) - 1)))


@case("compliant static stretch",
      """A vertical chain: a fixed pivot and N bobs of 0.01 kg on 0.1 m links, each link a `jc.Constraint`
      distance of compliance alpha, started at the analytic equilibrium (link k stretched by alpha T_k) with the
      analytic impulses. Reduced: N = 5, alpha 1e-4 and 1e-2 m/N, dt 1/240, 1 s; full: N = 10, alpha 1e-4, 1e-3
      and 1e-2, dt 1/60, 1/240 and 1/480, 4 s. XPBD with 16 iterations (docs/solvers.md: the iterations its
      static stretch needs; the default 1 iteration is 35% off at dt 1/240). The number: the worst link's mean stretch over the
      second half divided by alpha T_k, minus 1, worst over the runs. Bound: 1%.""",
      "analytic alpha T")
def static_stretch(solver_name: str, full: bool) -> Outcome:
    if full:
        runs = [(10, a, dt, 4.0) for a in (1e-4, 1e-3, 1e-2) for dt in (1 / 60, 1 / 240, 1 / 480)]
    else:
        runs = [(5, a, 1 / 240, 1.0) for a in (1e-4, 1e-2)]
    err = max(_stretch_error(solver_name, *r) for r in runs)
    return Outcome(err, err <= 0.01, "worst |stretch / (alpha T) - 1| <= 0.01")


def _frequency(solver_name, alpha, dt, m=0.1, length=0.5, periods=4):
    """The measured angular frequency of a bob on a compliant link along the link, no gravity (`frequency`)."""
    omega = np.sqrt(1 / (alpha * m))
    steps = int(np.ceil(periods * 2 * np.pi / omega / dt))
    amp = 1e-3 * length
    pos = np.array([[0.0, 0.0], [length + amp, 0.0]])
    link = jc.Constraint(_link, particles=[(0, 1)], params={"L": np.array([length])}, compliance=alpha,
                         name="link")
    model, state = jc.build(pos, np.array([1.0, m]), fixed=[0], constraints=[link], gravity=0.0)
    _, traj = jc.rollout(model, state, for_compliance(solver_name), dt, steps)
    x = np.asarray(traj.x)
    s = np.concatenate([[amp], np.linalg.norm(x[:, 1] - x[:, 0], axis=-1) - length])
    return 2 * np.pi * crossing_frequency(s, dt, centre=0.0), omega


@case("compliant frequency",
      """A bob of 0.1 kg on a 0.5 m link of compliance alpha (a `jc.Constraint` distance) to a fixed pivot, no
      gravity, started stretched by 0.5 mm at rest: its small-oscillation frequency along the link against the
      analytic sqrt(k / m), k = 1 / alpha, from the zero crossings over 4 periods. Reduced: alpha 1e-2 m/N at dt
      1/240 (h omega = 0.13); full: alpha 1e-1, 1e-2 and 1e-3 at dt 1/120, 1/240 and 1/960 (h omega at most
      0.13, where the implicit spring's own frequency error, 1 - atan(h omega) / (h omega), is at most 0.6%).
      XPBD with 16 iterations, as in the static case. Bound: 1%, worst run.""",
      "analytic sqrt(k / m)")
def frequency(solver_name: str, full: bool) -> Outcome:
    runs = [(1e-1, 1 / 120), (1e-2, 1 / 240), (1e-3, 1 / 960)] if full else [(1e-2, 1 / 240)]
    errs = []
    for alpha, dt in runs:
        got, want = _frequency(solver_name, alpha, dt)
        errs.append(abs(got / want - 1))
    err = max(errs)
    return Outcome(err, err <= 0.01, "worst |omega / sqrt(k / m) - 1| <= 0.01")
