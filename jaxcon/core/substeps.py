"""Shared substep loop for solvers whose per-substep warm start is the previous substep's impulse."""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def substepped(substep, substeps: int, x, v, lam, dt):
    """Run `substep(x, v, lam_ws, h) -> (x, v, lam_h)` `substeps` times with h = dt / substeps.

    The step's warm start `lam` (an impulse over dt) is split evenly over the substeps; the returned impulse
    is the sum over the substeps, so it stays an impulse over dt (N s). Static trip count (reverse mode works).
    Integer leaves (a neighbour grid's contact partners and overflow, the same in every substep of a step) are
    passed through: the returned ones are the last substep's.
    """
    h = dt / substeps
    if substeps == 1:
        return substep(x, v, lam, h)
    ws = jax.tree.map(lambda l: l / substeps if _real(l) else l, lam)
    zero = jax.tree.map(lambda l: jnp.zeros_like(l) if _real(l) else l, lam)

    def body(_, carry):
        x, v, ws, total = carry
        x, v, ws = substep(x, v, ws, h)
        return x, v, ws, jax.tree.map(lambda t, w: t + w if _real(w) else w, total, ws)

    x, v, _, total = lax.fori_loop(0, substeps, body, (x, v, ws, zero))
    return x, v, total


def _real(a):
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)
