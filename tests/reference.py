"""Independent references for the tests: planar pendulum chains in reduced (angle) coordinates, scipy DOP853.

The implementation lives in `jaxcon.bench.references.scipy_ode` (shared with the speed-vs-error bench). Beside
it, `pendulum_setup`: how a user fits the SciPy `RECORDING` with `jc.fit(setup=...)` (shared with
benchmarks/fit_recording.py)."""
from __future__ import annotations

import jax.numpy as jnp

from jaxcon.bench.references.scipy_ode import (  # noqa: F401
    RECORDING, _chain_rhs, chain_positions, double_pendulum_positions, double_pendulum_recording, driven_pendulum)


def pendulum_setup(theta, model, state, solver):
    """`jc.fit`'s `setup` for the double pendulum of `RECORDING`: reduced coordinates for the start (angles,
    angular velocities), both lengths and the mass ratio m2 / m1 (m1 = 1 kg: with positions alone only the ratio
    is identifiable)."""
    a, w, L = theta["angles"], theta["omegas"], theta["lengths"]
    x = jnp.cumsum(jnp.stack([L * jnp.sin(a), -L * jnp.cos(a)], -1), 0)
    v = jnp.cumsum(jnp.stack([jnp.cos(a), jnp.sin(a)], -1) * (L * w)[:, None], 0)
    inv_mass = jnp.stack([jnp.zeros(()), jnp.ones(()), 1 / theta["ratio"]])
    return (model.replace(rest_length=L, inv_mass=inv_mass),
            state.replace(x=state.x.at[1:].set(x), v=state.v.at[1:].set(v)), solver)

