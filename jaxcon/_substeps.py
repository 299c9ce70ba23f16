"""Shared helper: run a per-substep function `substeps` times and sum the per-substep impulses."""
from __future__ import annotations

import operator

import jax.numpy as jnp
from jax import lax


def substepped(substep, x, v, lam, dt, substeps):
    """Advance (x, v) by `substeps` calls of ``substep(x, v, lam_ws, h) -> (x, v, lam_sub)`` with h = dt /
    substeps. The warm start of the first substep is the step impulse `lam` / substeps, of each later one the
    previous substep's impulse. Returns (x, v, impulse summed over the step)."""
    h = dt / substeps
    if substeps == 1:
        return substep(x, v, lam, h)
    ws = tuple(l / substeps for l in lam)
    zero = tuple(jnp.zeros_like(l) for l in lam)

    def body(_, carry):
        x, v, ws, total = carry
        x, v, ws = substep(x, v, ws, h)
        return x, v, ws, tuple(map(operator.add, total, ws))

    x, v, _, total = lax.fori_loop(0, substeps, body, (x, v, ws, zero))
    return x, v, total
