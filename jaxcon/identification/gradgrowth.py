"""Gradient growth with horizon: the norm of d loss(x_T) / d rest_length for several horizons T.

Reverse mode through a rollout multiplies the per-step Jacobians d(x, v, lam)_{t+1} / d(x, v, lam)_t. When
their product grows (an under-converged PGS sweep coupled to the next step through its warm-start impulses,
or chaotic physics), the gradient grows geometrically with T. `gradient_norms` measures that growth.

Implementation: the rollout runs in chunks of K steps (K = gcd of the horizons, at most `chunk`). Two
functions are compiled once per (model, solver, dt): a chunk forward and the VJP of a chunk. The forward pass
stores the state at each chunk boundary; each horizon is then one reverse sweep over its chunks, each chunk
recomputed by its VJP (the same memory bound as `rollout(checkpoint=K)`). The gradient is exact: the same as
`jax.grad` of `loss(rollout(...)[0].x)`.
"""
from __future__ import annotations

import functools
import math
from typing import Callable, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core.model import Model, State
from jaxcon.core.sim import _check_call, _rollout_jit
from jaxcon.core.system import Solver

LOSSES = {
    "mean_x2": lambda x: jnp.mean(x ** 2),
}


@functools.partial(jax.jit, static_argnames=("k",))
def _chunk_forward(model, state, solver, dt, k):
    return _rollout_jit(model, state, solver, dt, k, 1)[0]


@functools.partial(jax.jit, static_argnames=("k",))
def _chunk_vjp(model, state, solver, dt, k, ct_state):
    """Pull the cotangent of the state after k steps back to (model, state before)."""
    _, pull = jax.vjp(lambda m, s: _rollout_jit(m, s, solver, dt, k, 1)[0], model, state)
    return pull(ct_state)


@functools.partial(jax.jit, static_argnames=("loss",))
def _loss_grad(state, loss):
    return jax.grad(lambda s: loss(s.x))(state)


def gradient_norms(model: Model, state: State, solver: Solver, dt, horizons: Sequence[int],
                   loss: Union[str, Callable] = "mean_x2", *, chunk: int = 50, return_grads: bool = False):
    """Norms of the gradient of loss(x_T) w.r.t. `model.rest_length`, for each horizon T in `horizons`.

    Args:
      model, state, solver, dt: as for `jc.rollout` (dtype from `state.x`).
      horizons: increasing step counts T >= 1.
      loss: "mean_x2" (mean of x_T^2 over particles and coordinates, m^2) or a function of x_T [n, dim] to a
        scalar.
      chunk: the largest chunk length K (steps recomputed per reverse chunk); the chunk is gcd(horizons, K).
      return_grads: also return the gradients themselves.

    Returns: np.ndarray [len(horizons)] of 2-norms (float64), or (norms, [grad per horizon]) when
      return_grads. A non-finite norm means the gradient overflowed.
    """
    horizons = [int(h) for h in horizons]
    if not horizons or any(h < 1 for h in horizons) or sorted(horizons) != horizons:
        raise ValueError(f"gradient_norms: `horizons` must be increasing ints >= 1, got {horizons}")
    _check_call("gradient_norms", model, state, solver, dt, horizons[-1])
    if isinstance(loss, str):
        if loss not in LOSSES:
            raise ValueError(f"gradient_norms: unknown loss {loss!r}; known: {sorted(LOSSES)} or a callable")
        loss = LOSSES[loss]
    k = functools.reduce(math.gcd, horizons + [int(chunk)])
    dtype = jnp.result_type(state.x)
    dt = jnp.asarray(dt, dtype)
    # Forward: the state at every chunk boundary up to the longest horizon.
    boundaries = [state]
    for _ in range(horizons[-1] // k):
        boundaries.append(_chunk_forward(model, boundaries[-1], solver, dt, k))
    norms, grads = [], []
    for h in horizons:
        n = h // k
        ct = _loss_grad(boundaries[n], loss)
        g = jnp.zeros_like(model.rest_length)
        for c in range(n - 1, -1, -1):
            ct_model, ct = _chunk_vjp(model, boundaries[c], solver, dt, k, ct)
            g = g + ct_model.rest_length
        g = np.asarray(g, np.float64)
        norms.append(float(np.linalg.norm(g)) if np.all(np.isfinite(g)) else float("inf"))
        grads.append(g)
    norms = np.asarray(norms)
    return (norms, grads) if return_grads else norms


def growth_rate(horizons: Sequence[int], norms, dt) -> dict:
    """Lyapunov-like growth rates from `gradient_norms`: per step, log(norm_T) / T for each horizon, and the
    slope d log(norm) / dT between the last two finite horizons (1/step and 1/s)."""
    h = np.asarray(horizons, np.float64)
    g = np.asarray(norms, np.float64)
    per_step = np.where(np.isfinite(g) & (g > 0), np.log(np.where(g > 0, g, 1.0)) / h, np.nan)
    ok = np.isfinite(g) & (g > 0)
    slope = np.nan
    if ok.sum() >= 2:
        i, j = np.flatnonzero(ok)[-2:]
        slope = (np.log(g[j]) - np.log(g[i])) / (h[j] - h[i])
    return {"log_norm_over_T": per_step, "slope_per_step": slope, "slope_per_second": slope / float(dt)}
