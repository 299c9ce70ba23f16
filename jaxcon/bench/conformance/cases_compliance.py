"""Compliance: a compliant constraint is the same spring, potential C^2 / (2 alpha), in every solver."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import SOLVERS, Outcome, case

G = 9.81


def _link(x, p):
    return p["L"] - jnp.linalg.norm(x[1] - x[0])


@case("compliant static stretch",
      """A vertical chain: a fixed pivot and N bobs of 0.01 kg on 0.1 m links, each link a `jc.Constraint`
      distance of compliance alpha = 1e-4 m/N, started at the analytic equilibrium (link k stretched by alpha T_k)
      with the analytic impulses, dt 1/240. The number: the worst link's mean stretch over the second half
      divided by alpha T_k, minus 1. Bound: 1%.""",
      "analytic alpha T")
def static_stretch(solver_name: str, full: bool) -> Outcome:
    n, m, length, alpha, dt = (10, 0.01, 0.1, 1e-4, 1 / 240) if full else (5, 0.01, 0.1, 1e-4, 1 / 240)
    steps = 960 if full else 240
    tension = G * m * (n - np.arange(n))
    y = -np.concatenate([[0.0], np.cumsum(length + alpha * tension)])
    pos = np.stack([np.zeros(n + 1), y], 1)
    link = jc.Constraint(_link, particles=[(k, k + 1) for k in range(n)], params={"L": np.full(n, length)},
                         compliance=alpha, name="link")
    model, state = jc.build(pos, np.full(n + 1, m), fixed=[0], constraints=[link])
    state = state.replace(lam=jnp.asarray(tension * dt))
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), dt, steps)
    d = np.linalg.norm(np.diff(np.asarray(traj.x), axis=1), axis=2)[steps // 2:] - length
    err = np.max(np.abs(d.mean(0) / (alpha * tension) - 1))
    return Outcome(err, err <= 0.01, "worst |stretch / (alpha T) - 1| <= 0.01")
