"""Time stepping: `step` and `rollout`, jit-compiled, differentiable and batchable."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _layout as L
from ._model import Model, State, Trajectory, _check_values, check_state
from ._pytree import concrete
from ._solver import Solver, System, _check_int


def _check_call(owner, model, state, solver, dt, steps=None):
    if not isinstance(model, Model):
        raise TypeError(f"{owner}: `model` must be a jaxcon Model, got {type(model).__name__}")
    if not isinstance(solver, Solver):
        raise TypeError(f"{owner}: `solver` must be a jaxcon solver (e.g. jc.PGS()), got {type(solver).__name__}")
    check_state(owner, model, state)
    if np.ndim(dt) != 0:
        raise ValueError(f"{owner}: `dt` must be a scalar, got shape {np.shape(dt)}")
    d = concrete(dt)
    if d is not None and not (np.isfinite(d) and d > 0):
        raise ValueError(f"{owner}: `dt` must be finite and > 0, got {float(d)}")
    if steps is not None:
        _check_int(owner, "steps", steps, 1)


def _dtype(state):
    return jnp.result_type(state.x)


def _enter(model, state):
    t = model.topology
    dtype = _dtype(state)
    sys = System.from_model(model, dtype)
    x = L.particles_in(t, jnp.asarray(state.x, dtype))
    v = L.particles_in(t, jnp.asarray(state.v, dtype))
    lam = L.constraints_in(t, jnp.asarray(state.lam, dtype))
    return sys, x, v, lam


@jax.jit
def _step_jit(model, state, solver, dt):
    sys, x, v, lam = _enter(model, state)
    x, v, lam = solver._step(sys, x, v, lam, jnp.asarray(dt, x.dtype))
    t = model.topology
    return State(L.particles_out(t, x), L.particles_out(t, v), L.constraints_out(t, lam))


def step(model: Model, state: State, solver: Solver, dt) -> State:
    """Advance `state` by one step of length `dt` seconds. Returns the new State (its lam: the step's
    constraint impulses, N s, > 0 pulling)."""
    _check_call("step", model, state, solver, dt)
    return _step_jit(model, state, solver, dt)


@functools.partial(jax.jit, static_argnames=("steps", "save_every", "checkpoint"))
def _rollout_jit(model, state, solver, dt, steps, save_every, checkpoint=None):
    sys, x, v, lam = _enter(model, state)
    dt = jnp.asarray(dt, x.dtype)
    t = model.topology

    def one(_, carry):
        return solver._step(sys, *carry, dt)

    def body(carry, _):
        if save_every == 1:
            carry = one(0, carry)
        else:
            carry = lax.fori_loop(0, save_every, one, carry)
        x, v, lam = carry
        # The step's impulses are recorded as one flat array (block order), not one stacked output per colour
        # block: with ten stacked outputs per step, XLA:CPU's two worker threads took turns running the time
        # loop, and recording cost XPBD on the 64x64 cloth about 30% per step, none of it on one thread
        # (NPROC=1 or taskset). Flat, the recording figure fell by 12% (docs/solvers-a.md).
        return carry, (x, v, L.constraints_concat(t, lam))

    def records(carry, n):
        return lax.scan(body, carry, length=n)

    carry = (x, v, lam)
    n_rec = steps // save_every
    if checkpoint is None:
        carry, recs = records(carry, n_rec)
    else:
        # Outer scan over chunks of `checkpoint` steps, each chunk rematerialised in the backward pass:
        # reverse mode keeps the carry at every chunk boundary plus one chunk's residuals.
        per = checkpoint // save_every
        n_chunks, rest = divmod(n_rec, per)
        chunk = jax.checkpoint(lambda c: records(c, per))
        parts = []
        if n_chunks:
            carry, recs = lax.scan(lambda c, _: chunk(c), carry, length=n_chunks)
            parts.append(jax.tree.map(lambda a: a.reshape((n_chunks * per,) + a.shape[2:]), recs))
        if rest:
            carry, recs = jax.checkpoint(lambda c: records(c, rest))(carry)
            parts.append(recs)
        recs = parts[0] if len(parts) == 1 else jax.tree.map(lambda *a: jnp.concatenate(a), *parts)
    (x, v, lam), (xs, vs, lams) = carry, recs
    final = State(L.particles_out(t, x), L.particles_out(t, v), L.constraints_out(t, lam))
    traj = Trajectory(L.particles_out(t, xs), L.particles_out(t, vs), L.constraints_unpermute(t, lams))
    return final, traj


def rollout(model: Model, state: State, solver: Solver, dt, steps: int, *, save_every: int = 1,
            checkpoint: int | None = None):
    """Run `steps` steps of length `dt` seconds.

    Returns (final_state, traj): traj.x, traj.v [steps // save_every, n, dim] and traj.lam
    [steps // save_every, m], recorded after every `save_every`-th step (default: every step; lam is the
    impulse of that step, N s, > 0 pulling). Works under jax.jit, jax.grad and jax.vmap.

    checkpoint: None (default) or a number of steps K, a multiple of `save_every`. The rollout then runs as
      an outer scan over chunks of K steps whose body is wrapped in `jax.checkpoint`, so reverse mode stores
      the state at every chunk boundary and one chunk's intermediates (O(steps / K + K) per-step residuals
      instead of O(steps)), at the price of recomputing each chunk once in the backward pass. Values and
      gradients are unchanged. sqrt(steps) is a good K. A last partial chunk is allowed.
    """
    _check_call("rollout", model, state, solver, dt, steps)
    _check_int("rollout", "save_every", save_every, 1)
    if steps % save_every:
        raise ValueError(f"rollout: `steps` ({steps}) must be a multiple of `save_every` ({save_every})")
    if checkpoint is not None:
        _check_int("rollout", "checkpoint", checkpoint, 1)
        if checkpoint % save_every:
            raise ValueError(
                f"rollout: `checkpoint` ({checkpoint}) must be a multiple of `save_every` ({save_every})")
        if checkpoint >= steps:
            checkpoint = steps
    return _rollout_jit(model, state, solver, dt, steps, save_every, checkpoint)


@functools.partial(jax.jit, static_argnames=("steps", "save_every", "chunk"))
def _batched_jit(model, states, solver, dt, steps, save_every, chunk):
    return lax.map(lambda one: _rollout_jit(model, one, solver, dt, steps, save_every), states, batch_size=chunk)


def batched_rollout(model: Model, states: State, solver: Solver, dt, steps: int, *, chunk: int = 1024,
                    save_every: int = 1):
    """`rollout` of a batch of initial states (x, v [B, n, dim], lam [B, m]) with one model and solver.

    Runs `jax.vmap` over chunks of `chunk` states and `lax.map` across chunks. On CPU this is much faster than
    one `jax.vmap` over a large batch: measured on a 2-core Xeon, vmap of PGS double pendulums runs at
    ~1e7 particle-steps/s up to about 2000 systems and drops ~13x above that, while chunks of 1024 keep
    ~1e7 at 16384 systems. Returns (finals, trajs) with a leading batch axis.
    """
    if not isinstance(states, State):
        raise TypeError(f"batched_rollout: `states` must be a jaxcon State, got {type(states).__name__}")
    if np.ndim(states.x) != 3:
        raise ValueError(f"batched_rollout: `states.x` must have shape [batch, n, dim], got {np.shape(states.x)}")
    _check_int("batched_rollout", "chunk", chunk, 1)
    _check_int("batched_rollout", "save_every", save_every, 1)
    first = jax.tree.map(lambda a: a[0], states)
    _check_call("batched_rollout", model, first, solver, dt, steps)
    for name in ("x", "v", "lam"):
        if np.shape(getattr(states, name))[0] != np.shape(states.x)[0]:
            raise ValueError(f"batched_rollout: `states.{name}` has a different batch size than `states.x`")
        _check_values("batched_rollout", f"states.{name}", getattr(states, name))
    if steps % save_every:
        raise ValueError(f"batched_rollout: `steps` ({steps}) must be a multiple of `save_every` ({save_every})")
    return _batched_jit(model, states, solver, dt, steps, save_every, min(chunk, int(np.shape(states.x)[0])))
