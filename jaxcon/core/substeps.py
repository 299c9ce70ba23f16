"""Shared substep loop for solvers whose per-substep warm start is the previous substep's impulse."""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def substepped(substep, substeps: int, x, v, lam, dt, path: bool = False, unroll: bool = False):
    """Run `substep(x, v, lam_ws, h) -> (x, v, lam_h)` `substeps` times with h = dt / substeps.

    The step's warm start `lam` (an impulse over dt) is split evenly over the substeps; the returned impulse
    is the sum over the substeps, so it stays an impulse over dt (N s). Static trip count (reverse mode works).
    Integer leaves (a neighbour grid's contact partners and overflow, the same in every substep of a step) are
    passed through: the returned ones are the last substep's.

    `path`: also return the positions after each substep k = 1 .. substeps, [substeps, *x.shape] without gradient
    (a neighbour grid's check of the paths, `common.grid_step`), as a fourth output. `unroll`: unroll the loop over
    substeps (`Topology.unroll`).
    """
    h = dt / substeps
    if substeps == 1:
        out = substep(x, v, lam, h)
        return out if not path else out + (lax.stop_gradient(out[0])[None],)
    ws = jax.tree.map(lambda l: l / substeps if _real(l) else l, lam)
    zero = jax.tree.map(lambda l: jnp.zeros_like(l) if _real(l) else l, lam)
    trail = jnp.zeros((substeps,) + x.shape, x.dtype) if path else None

    def body(k, carry):
        x, v, ws, total, trail = carry
        x, v, ws = substep(x, v, ws, h)
        if path:
            trail = trail.at[k].set(lax.stop_gradient(x))
        return x, v, ws, jax.tree.map(lambda t, w: t + w if _real(w) else w, total, ws), trail

    x, v, _, total, trail = lax.fori_loop(0, substeps, body, (x, v, ws, zero, trail), unroll=unroll)
    return (x, v, total) if not path else (x, v, total, trail)


def _real(a):
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)
