"""Synthetic identification experiments shared by the demo and the tests."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcon.core.model import build
from jaxcon.core.sim import rollout
from jaxcon.solvers.pgs import PGS


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


def violated_chain_identification(n: int = 8, link: float = 0.25, seed: int = 0, beta: float = 0.35,
                                  angle: float = 1.0, dt: float = 1 / 240, steps: int = 240, every: int = 2,
                                  noise: float = 1e-3, mass: float = 0.1, dtype=None):
    """A chain released from a violated start: n links of nominal length `link` m (`mass` kg per bob), their
    true rest lengths each perturbed by up to 10%, the initial positions laid out straight at `angle` rad with
    the NOMINAL lengths, so every link starts up to 10% off its rest length and the first steps are a
    Baumgarte correction at rate beta (which makes beta identifiable). Data: PGS(10, beta) with its default
    warm start for `steps` steps, every `every`-th step observed with `noise` m of Gaussian noise on every
    particle.

    Returns (guess model with the nominal rest lengths, state, true rest lengths, observed [S, n + 1, 2],
    sample_steps [S])."""
    from jaxcon.scenes import chain
    rng = np.random.default_rng(seed)
    model, state = chain(n, n * link, mass * n, angle=angle, dtype=dtype)
    true_L = link * (1 + rng.uniform(-0.1, 0.1, n))
    truth = model.replace(rest_length=jnp.asarray(true_L, model.rest_length.dtype))
    _, tr = rollout(truth, state, PGS(iterations=10, beta=beta), dt, steps)
    ss = np.arange(every, steps + 1, every)
    obs = np.asarray(tr.x)[ss - 1] + noise * rng.standard_normal((len(ss),) + tr.x.shape[1:])
    return model, state, true_L, obs.astype(np.asarray(tr.x).dtype), ss
