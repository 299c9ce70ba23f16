"""Synthetic identification experiments shared by the demo and the tests."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._model import build
from ._sim import rollout
from ._solver import PGS


def chain_identification(n: int = 20, seed: int = 0, beta: float = 0.2, dt: float = 1 / 240, steps: int = 240,
                         noise: float = 1e-3, dtype=np.float64):
    """A chain whose hidden rest lengths are the nominal 2/n m each perturbed by up to 10%, simulated with
    PGS(10, beta) for `steps` steps and observed with `noise` m of Gaussian noise on every position.

    The initial positions are the true geometry jittered by 3 mm per particle, so the first steps are a
    Baumgarte correction of a constraint error at rate beta: beta is not identifiable from motion that already
    satisfies the constraints.

    Returns (guess_model with the nominal rest lengths, state, true rest lengths, observed positions).
    """
    rng = np.random.default_rng(seed)
    nominal = np.full(n, 2.0 / n)
    true_L = nominal * (1 + rng.uniform(-0.1, 0.1, n))
    a = 0.3
    x = np.concatenate([[np.zeros(2)], np.cumsum(true_L[:, None] * np.array([np.sin(a), -np.cos(a)]), 0)])
    x[1:] += 0.003 * rng.standard_normal(x[1:].shape)
    model, state = build(x.astype(dtype), np.r_[1.0, np.full(n, 1.0 / n)], rods=[(k, k + 1) for k in range(n)],
                         fixed=[0], rest_lengths=true_L.astype(dtype))
    _, tr = rollout(model, state, PGS(iterations=10, beta=beta), dt, steps)
    obs = np.asarray(tr.x) + noise * rng.standard_normal(tr.x.shape)
    return model.replace(rest_length=jnp.asarray(nominal, dtype)), state, true_L, obs.astype(dtype)
