"""A plain batch-minor PGS for a batch of pendulum chains: the reference line of the batched-throughput bench.

The same method as `jc.PGS` (gravity, warm start, Baumgarte bias, constraints in sequence, symplectic Euler)
written the way a batch of tiny systems is fastest in plain JAX: every coordinate of every particle is its own
[B] array, and the sweeps are unrolled, so XLA fuses a step into about one kernel over the batch. Chains only
(particle 0 a fixed pivot, constraint k joining particles k and k + 1, all rods). Not part of the library.
"""
from __future__ import annotations

import jax.numpy as jnp
from jax import lax


def chain_pgs_rollout(x, v, lam, w, rest, gravity, beta, dt, steps, iterations):
    """Final (x, v, lam) of a batch of chains after `steps` steps.

    x, v: [B, n, dim]; lam: [B, m] with m = n - 1; w: [n] inverse masses (NumPy: which particles are fixed is
    static); rest: [m]; gravity: [dim]."""
    n, dim = x.shape[1], x.shape[2]
    m = n - 1
    X = [[x[:, p, a] for a in range(dim)] for p in range(n)]      # X[p][a]: [B]
    V = [[v[:, p, a] * float(w[p] > 0) for a in range(dim)] for p in range(n)]   # fixed: never move (as jc.PGS)
    lam = [lam[:, k] for k in range(m)]
    # the constraint colours of a chain: even links, then odd links (what jc.PGS's colouring gives)
    order = list(range(0, m, 2)) + list(range(1, m, 2))

    def step(carry, _):
        X, V, lam = carry
        V = [[V[p][a] + dt * gravity[a] * float(w[p] > 0) for a in range(dim)] for p in range(n)]
        frames = []
        for k in range(m):
            d = [X[k + 1][a] - X[k][a] for a in range(dim)]
            dist = jnp.sqrt(sum(c * c for c in d))
            nrm = [c / dist for c in d]
            frames.append((nrm, 1 / (w[k] + w[k + 1]), beta / dt * (dist - rest[k])))
        V = [list(p) for p in V]
        for k in range(m):                                   # warm start
            nrm = frames[k][0]
            for a in range(dim):
                V[k][a] = V[k][a] + w[k] * nrm[a] * lam[k]
                V[k + 1][a] = V[k + 1][a] - w[k + 1] * nrm[a] * lam[k]
        lam = list(lam)
        for _ in range(iterations):                          # unrolled sweeps
            for k in order:
                nrm, kk, bias = frames[k]
                rel = sum((V[k + 1][a] - V[k][a]) * nrm[a] for a in range(dim))
                dl = (rel + bias) * kk
                lam[k] = lam[k] + dl
                for a in range(dim):
                    V[k][a] = V[k][a] + w[k] * nrm[a] * dl
                    V[k + 1][a] = V[k + 1][a] - w[k + 1] * nrm[a] * dl
        X = [[X[p][a] + dt * V[p][a] for a in range(dim)] for p in range(n)]
        return (X, V, lam), None

    (X, V, lam), _ = lax.scan(step, (X, V, lam), length=steps)
    stack = lambda P: jnp.stack([jnp.stack(p, -1) for p in P], 1)   # noqa: E731
    return stack(X), stack(V), jnp.stack(lam, -1)
