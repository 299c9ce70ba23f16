"""Batched throughput: `jax.vmap` of rollouts over a batch of initial states, timed after compilation, with the
kernels each program launches per time step (`jaxcon.bench.kernels`)."""
from __future__ import annotations

from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon import scenes
from jaxcon.bench.kernels import step_kernels
from jaxcon.bench.timing import compile_and_time
from jaxcon.core.model import State
from jaxcon.bench.references.batch_minor_pgs import chain_pgs_rollout
from jaxcon.core import batch
from jaxcon.core.sim import _rollout_jit
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
    elif scene == "billiards":
        model, _ = scenes.billiards(dtype=dtype)
        states = [scenes.billiards(speed=sp, angle=a, dtype=dtype)[1]
                  for sp, a in zip(rng.uniform(5, 12, min(batch, 64)), rng.uniform(-0.05, 0.05, min(batch, 64)))]
    else:
        raise ValueError(f"batched_throughput: unknown scene {scene!r} ('double_pendulum', 'cloth' or 'billiards')")
    stacked = jax.tree.map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *states)
    reps = -(-batch // len(states))             # tiled, not concatenated: at 1M copies that was 16384 operands
    state = jax.tree.map(lambda a: jnp.tile(a, (reps,) + (1,) * (a.ndim - 1))[:batch], stacked)
    return model, state


MODES = ("vmap", "batched_rollout", "one_piece", "reference")


def _timed_fn(mode, model, solver, dt, steps, chunk, devices):
    if mode == "vmap":
        return jax.vmap(lambda s: _rollout_jit(model, s, solver, dt, steps, steps)[0].x)
    if mode in ("batched_rollout", "one_piece"):
        return lambda s: batch.batched_rollout(model, s, solver, dt, steps, save_every=steps,
                                               chunk=s.x.shape[0] if mode == "one_piece" else chunk,
                                               devices=devices)[0].x
    if mode == "reference":
        w = np.asarray(model.inv_mass)
        return lambda s: chain_pgs_rollout(s.x, s.v, s.lam, w, model.rest_length, model.gravity, solver.beta, dt,
                                           steps, solver.iterations)[0]
    raise ValueError(f"batched_throughput: unknown mode {mode!r} (one of {MODES})")


def batched_throughput(batch_sizes: Sequence[int] = (1, 64, 1024, 16384), steps: int = 240,
                       scene: str = "double_pendulum", solver: Optional[Solver] = None, dt: float = 1 / 240,
                       dtype=np.float32, repeats: int = 5, modes: Sequence[str] = MODES, chunk: Optional[int] = None,
                       backend: Optional[str] = None):
    """Time batched rollouts over batches of initial states (different initial angles for the double
    pendulum, different initial vertical velocities for the 16x16 cloth, different break speeds and angles for
    the 16-ball billiards), final state only, after compilation.

    modes: "vmap" (`jax.jit(jax.vmap(rollout))`), "batched_rollout" (`jc.batched_rollout` with its defaults,
    or `chunk`), "one_piece" (`jc.batched_rollout(chunk=batch)`: the whole batch in one piece: packed
    sweeps on the CPU, unrolled ones on an accelerator (`batch.sweep_mode`); skipped where that is the default
    already, and for models batched with vmap),
    "reference" (the plain batch-minor PGS of `bench.references.batch_minor_pgs`, double pendulum and PGS only;
    skipped otherwise).

    backend: run on this backend's local devices ("cpu", "gpu", ...; default: JAX's default backend); vmap and
    the reference run on its first device, `batched_rollout` shards over all of them.

    Returns a list of dicts: scene, batch, mode, devices, backend, particles (moving, per system), compile_s
    (lower + compile), run_s (median of `repeats` runs), system_steps_per_s = batch * steps / run_s,
    particle_steps_per_s and kernels (`kernels.step_kernels` of the compiled program: fusions, copies, other and
    total per time step; None where the time loop is not found).
    """
    solver = PGS() if solver is None else solver
    devices = jax.local_devices(backend=backend)
    rows = []
    for b in batch_sizes:
        with jax.default_device(devices[0]):
            model, state = _batch(scene, int(b), dtype)
            n = int(np.sum(np.asarray(model.inv_mass) > 0))
            for mode in modes:
                if mode == "reference" and (scene != "double_pendulum" or type(solver) is not PGS):
                    continue
                if mode == "one_piece" and (batch.default_chunk(devices) is None or chunk is not None
                                            or not batch.layout_generic(solver, model)):
                    continue
                f = _timed_fn(mode, model, solver, dt, steps, chunk, devices)
                compile_s, run, compiled = compile_and_time(f, state, repeats=repeats)
                try:
                    kernels = step_kernels(compiled.as_text(), steps)
                except ValueError:
                    kernels = None
                rows.append(dict(scene=scene, batch=int(b), mode=mode, devices=len(devices) if mode in
                                 ("batched_rollout", "one_piece") else 1, backend=devices[0].platform, particles=n,
                                 steps=steps, compile_s=compile_s, run_s=run, system_steps_per_s=b * steps / run,
                                 particle_steps_per_s=b * n * steps / run, kernels=kernels))
    return rows


def backends() -> list:
    """The backends JAX can run on here (cpu always; gpu, tpu where present)."""
    found = []
    for name in ("cpu", "gpu", "tpu"):
        try:
            if jax.local_devices(backend=name):
                found.append(name)
        except RuntimeError:
            pass
    return found


if __name__ == "__main__":
    for r in batched_throughput():
        print(r)
