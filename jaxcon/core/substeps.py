"""Shared substep loop for solvers whose per-substep warm start is the previous substep's impulse."""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def substepped(substep, substeps: int, x, v, lam, dt, watch=None):
    """Run `substep(x, v, lam_ws, h) -> (x, v, lam_h)` `substeps` times with h = dt / substeps.

    The step's warm start `lam` (an impulse over dt) is split evenly over the substeps; the returned impulse
    is the sum over the substeps, so it stays an impulse over dt (N s). Static trip count (reverse mode works).
    Integer leaves (a neighbour grid's contact partners and overflow, the same in every substep of a step) are
    passed through: the returned ones are the last substep's.

    `watch(k, x_k) -> array`: also return its elementwise maximum over the positions after each substep k = 1 ..
    substeps (a neighbour grid's check of the paths, `common.grid_step`), as a fourth output.
    """
    h = dt / substeps
    if substeps == 1:
        out = substep(x, v, lam, h)
        return out if watch is None else out + (watch(1, out[0]),)
    ws = jax.tree.map(lambda l: l / substeps if _real(l) else l, lam)
    zero = jax.tree.map(lambda l: jnp.zeros_like(l) if _real(l) else l, lam)
    worst = None if watch is None else watch(0, x)

    def body(k, carry):
        x, v, ws, total, worst = carry
        x, v, ws = substep(x, v, ws, h)
        if watch is not None:
            worst = jnp.maximum(worst, watch(k + 1, x))
        return x, v, ws, jax.tree.map(lambda t, w: t + w if _real(w) else w, total, ws), worst

    x, v, _, total, worst = lax.fori_loop(0, substeps, body, (x, v, ws, zero, worst))
    return (x, v, total) if watch is None else (x, v, total, worst)


def _real(a):
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)
