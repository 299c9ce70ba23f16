"""A plain scatter-add PGS: the reference the bench compares jaxcon's gradient compile time with.

The same method as `jc.PGS` (gravity, warm start, Baumgarte bias, colours in sequence, symplectic Euler) written
the short way: particles [n, dim] in user order, each colour's endpoints gathered with index arrays and its
impulses applied with `.at[].add`. Rods only. Not part of the library's API.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import lax


def plain_pgs_rollout(x, v, lam, w, rest, i, j, colour, gravity, beta, dt, steps, iterations):
    """Final (x, v, lam) after `steps` steps. x, v [n, dim]; lam, rest [m]; w [n]; i, j, colour: NumPy [m]."""
    groups = [np.nonzero(colour == c)[0] for c in np.unique(colour)]

    def step(carry, _):
        x, v, lam = carry
        v = v + dt * gravity * (w > 0).astype(v.dtype)[:, None]
        d = x[j] - x[i]
        dist = jnp.sqrt(jnp.sum(d * d, -1))
        n = d / dist[:, None]
        k = 1 / (w[i] + w[j])
        bias = beta / dt * (dist - rest)
        v = v.at[i].add(w[i, None] * n * lam[:, None]).at[j].add(-w[j, None] * n * lam[:, None])

        def sweep(_, c):
            v, lam = c
            for g in groups:
                gi, gj, gn = i[g], j[g], n[g]
                rel = jnp.sum((v[gj] - v[gi]) * gn, -1)
                dl = (rel + bias[g]) * k[g]
                p = gn * dl[:, None]
                v = v.at[gi].add(w[gi, None] * p).at[gj].add(-w[gj, None] * p)
                lam = lam.at[g].add(dl)
            return v, lam

        v, lam = lax.fori_loop(0, iterations, sweep, (v, lam))
        return (x + dt * v, v, lam), None

    return lax.scan(step, (x, v, lam), length=steps)[0]
