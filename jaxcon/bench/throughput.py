"""Batched throughput: `jax.vmap` of rollouts over a batch of initial states, timed after compilation."""
from __future__ import annotations

from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon import scenes
from jaxcon.bench.timing import compile_and_time
from jaxcon.core.model import State
from jaxcon.core.sim import _batched_jit, _rollout_jit
from jaxcon.core.system import Solver
from jaxcon.solvers.pgs import PGS


def _batch(scene, batch, dtype):
    rng = np.random.default_rng(0)
    if scene == "double_pendulum":
        model, _ = scenes.double_pendulum(dtype=dtype)
        states = [scenes.double_pendulum(angles=a, dtype=dtype)[1] for a in rng.uniform(-2, 2, (min(batch, 64), 2))]
    elif scene == "cloth":
        model, state = scenes.cloth(16, 16, dtype=dtype)
        states = []
        for _ in range(min(batch, 64)):
            v = np.zeros_like(np.asarray(state.x))
            v[:, 2] = rng.uniform(-1, 1)
            states.append(State(state.x, v.astype(dtype), state.lam))
    else:
        raise ValueError(f"batched_throughput: unknown scene {scene!r} ('double_pendulum' or 'cloth')")
    stacked = jax.tree.map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *states)
    reps = -(-batch // len(states))
    state = jax.tree.map(lambda a: jnp.concatenate([a] * reps)[:batch], stacked)
    return model, state


def batched_throughput(batch_sizes: Sequence[int] = (1, 64, 1024, 16384), steps: int = 240,
                       scene: str = "double_pendulum", solver: Optional[Solver] = None, dt: float = 1 / 240,
                       dtype=np.float32, repeats: int = 5, chunk: Optional[int] = None):
    """Time `jax.jit(jax.vmap(rollout))` over batches of initial states (different initial angles for the
    double pendulum, different initial vertical velocities for the 16x16 cloth).

    chunk: None times one `jax.vmap` over the whole batch; an int times `jc.batched_rollout` (vmap over chunks
    of that many states, lax.map across chunks).

    Only the final state is returned by the timed function (no per-step trajectory), so memory is
    O(batch). Returns a list of dicts: batch, particles (moving, per system), compile_s (lower + compile),
    run_s (median of `repeats` runs after compilation), particle_steps_per_s = batch * particles * steps /
    run_s.
    """
    solver = PGS() if solver is None else solver
    rows = []
    for b in batch_sizes:
        model, state = _batch(scene, int(b), dtype)
        if chunk is None:
            f = jax.vmap(lambda s: _rollout_jit(model, s, solver, dt, steps, steps)[0])
        else:
            f = lambda s: _batched_jit(model, s, solver, dt, steps, steps, min(chunk, int(b)))[0]  # noqa: E731
        compile_s, run, _ = compile_and_time(f, state, repeats=repeats)
        n = int(np.sum(np.asarray(model.inv_mass) > 0))
        rows.append(dict(scene=scene, batch=int(b), mode="vmap" if chunk is None else f"chunks of {chunk}",
                         particles=n, steps=steps, compile_s=compile_s, run_s=run,
                         particle_steps_per_s=b * n * steps / run))
    return rows


if __name__ == "__main__":
    for r in batched_throughput():
        print(r)
    for r in batched_throughput((1, 64), scene="cloth"):
        print(r)
