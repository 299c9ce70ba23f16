"""Batch-minor layout: a batch of B copies of one model solved as one system of B disjoint copies.

A batched rollout of many small systems is fastest when every array carries the batch as its last, contiguous
axis: particles ``[dim, *view, B]`` and each colour block's constraints ``[*block.shape, B]``. Every slice,
pad and elementwise update of a colour then runs over contiguous runs of B values, and XLA fuses a step into
a few kernels over the whole batch. With the batch leading (what ``jax.vmap`` of a rollout gives), each of
those operations is a strided access over small ``[dim, *view]`` arrays, one kernel each.

This layout needs no solver code of its own: the B copies form a topology whose view is ``(*view, B)``, whose
strided colour boxes gain a full-range box on the batch axis and whose gather blocks index ``p * B + b``.
Solvers that only use the internal layout (everything except `Direct`, which assembles matrices in user
order) run on it unchanged.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, PartitionSpec

from jaxcon.core import layout as L
from jaxcon.core import sim as _sim
from jaxcon.core.checks import check_int, check_values, describe_shape
from jaxcon.core.model import Model, State, Trajectory, check_partners
from jaxcon.core.pytree import StaticArray
from jaxcon.core.system import Solver, System
from jaxcon.core.topology import Block, Topology


def batch_minor_topology(t: Topology, batch: int, packed: bool = False, unroll: bool = False) -> Topology:
    """The topology of `batch` disjoint copies of `t`, copy b of particle p at flat position p * batch + b of
    the view ``(*t.view, batch)``. Constraint k of copy b is ``k * batch + b`` within its block. Built from
    `t`'s unrolled layout (one block per colour; a compact table's rows would each be a batch of gathers).
    `packed`: PGS sweeps it with `jaxcon.solvers.pgs.packed_sweeps` (one kernel per colour and sweep) where
    `packing_pays`. `unroll`: the solvers unroll their loop over sweeps (`Topology.unroll`)."""
    t, B = t.unrolled, int(batch)
    out = object.__new__(Topology)
    out.batch, out.packed, out.unroll = B, bool(packed) and packing_pays(t), bool(unroll)
    ar = np.arange(B)

    def rep(idx):           # per-constraint or per-particle indices of one copy -> all copies, batch-minor
        return (np.asarray(idx, np.int64)[:, None] * B + ar).reshape(-1)

    out.n, out.dim, out.m = t.n * B, t.dim, t.m * B
    out.m_pairs, out.sets, out.set_hubs = t.m_pairs * B, (), []     # models with constraint sets are batched with vmap
    out.i, out.j = rep(t.i), rep(t.j)
    out.is_rope, out.colour = np.repeat(t.is_rope, B), np.repeat(t.colour, B)
    out.fixed = np.repeat(t.fixed, B)                   # copy b of particle p is p * B + b
    out.star, out.has_stars = np.full(out.m, -1, np.int64), False     # star models are batched with vmap
    out.view = t.view + (B,)
    out.has_ropes, out.has_rods = t.has_ropes, t.has_rods
    out.pos = None if t.pos is None else rep(t.pos).astype(np.int32)
    out.order = None if t.order is None else rep(t.order).astype(np.int32)
    out.perm = out.inv_perm = None           # constraint order conversions go through the unbatched topology
    blocks = []
    for b in t.blocks:
        if b.strided:
            ext = lambda box: (box[0] + (0,), box[1] + (1,), box[2] + (B,))   # noqa: E731
            rope = None if b.rope is None else StaticArray(np.broadcast_to(b.rope.array[..., None], b.shape + (B,)))
            blocks.append(Block(b.offset * B, b.size * B, b.shape + (B,), ext(b.i_box), ext(b.j_box), None, None,
                                None, rope, b.all_rope))
        else:
            src = b.src.array.astype(np.int64)
            src_b = np.where(src[:, None] < 2 * b.size, src[:, None] * B + ar, 2 * b.size * B).reshape(-1)
            rope = None if b.rope is None else StaticArray(np.repeat(b.rope.array, B))
            blocks.append(Block(b.offset * B, b.size * B, (b.size * B,), None, None,
                                StaticArray(rep(b.i_idx.array).astype(np.int32)),
                                StaticArray(rep(b.j_idx.array).astype(np.int32)),
                                StaticArray(src_b.astype(np.int32)), rope, b.all_rope))
    out.blocks = tuple(blocks)
    for a in (out.i, out.j, out.is_rope, out.colour, out.fixed, out.star):
        a.setflags(write=False)
    out._key = ("batch-minor", B, out.packed, out.unroll, t._key)
    out._hash = hash(out._key)
    return out


def _box_positions(box):
    """The flat positions, in its view, that a strided box covers (as a set)."""
    start, step, count = box
    axes = [s + st * np.arange(c) for s, st, c in zip(start, step, count)]
    return set(map(tuple, np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes)).tolist()))


def packing_pays(t: Topology) -> bool:
    """Whether PGS's packed sweeps (`jaxcon.solvers.pgs.packed_sweeps`) suit the copies of `t`: every colour
    strided, each colour's endpoint boxes either equal to or disjoint from those of the colour after it (and of
    the first colour, for the warm start), so the next colour reads the impulses without padding
    (`layout.gather_after`), and the impulse rows at most double what a colour rewrites (m + the largest colour
    <= dim * n). Elsewhere the padded terms are stored apart and the packed array grows with the model: chains of
    7 and 8 links packed to 57 and 58 kernels per step against 74, and ran 2.6 and 4.4x slower on CPU; the 4x4
    cloth to 323 against 293."""
    t = t.unrolled
    blocks = t.blocks
    if not blocks or not all(b.strided and getattr(b, "generic", None) is None for b in blocks):
        return False        # packed_sweeps solves rod and rope rows (a constraint set's block is not strided)
    if t.m + max(b.size for b in blocks) > t.dim * t.n:
        return False
    sets = [(_box_positions(b.i_box), _box_positions(b.j_box)) for b in blocks]
    pairs = [(c, (c + 1) % len(blocks)) for c in range(len(blocks))] + [(c, 0) for c in range(len(blocks))]
    return all(a == g or not (a & g) for c, n in pairs for a in sets[c] for g in sets[n])


def particles_in(t: Topology, x):
    """[..., B, n, dim] in user order -> [..., dim, *view, B]."""
    if t.order is not None:
        x = jnp.take(x, t.order, axis=-2)
    x = jnp.moveaxis(x, (-3, -2, -1), (-1, -2, -3))                 # [..., dim, n, B]
    return x.reshape(x.shape[:-2] + t.view + x.shape[-1:])


def particles_out(t: Topology, x):
    """[..., dim, *view, B] -> [..., B, n, dim] in user order."""
    lead = x.shape[: x.ndim - len(t.view) - 2]
    x = x.reshape(lead + (t.dim, t.n, x.shape[-1]))
    if t.order is not None:
        x = jnp.take(x, t.pos, axis=-2)
    return jnp.moveaxis(x, (-3, -2, -1), (-1, -2, -3))


def _to_block(b: Block, seg, B):
    """[..., B, size] -> the block's batch-minor array: [..., *shape, B] (strided) or [..., size * B] (gather)."""
    seg = jnp.moveaxis(seg, -2, -1)                                   # [..., size, B]
    if b.strided:
        return seg.reshape(seg.shape[:-2] + b.shape + (B,))
    return seg.reshape(seg.shape[:-2] + (b.size * B,))


def constraints_in(t: Topology, a, batch: int):
    """[..., B, m] (or [m], shared by the batch) in the user's constraint order -> tuple of per-block
    batch-minor arrays."""
    a = jnp.asarray(a)
    if a.ndim == 1:
        a = jnp.broadcast_to(a, (batch, t.m))
    a = jnp.take(a, t.perm, axis=-1) if t.m else a
    return tuple(_to_block(b, a[..., b.offset: b.offset + b.size], batch) for b in t.blocks)


def constraints_out(t: Topology, blocks, batch: int):
    """Inverse of `constraints_in`: per-block batch-minor arrays -> [..., B, m] in the user's order."""
    segs = []
    for b, a in zip(t.blocks, blocks):
        lead = a.shape[: a.ndim - (len(b.shape) + 1 if b.strided else 1)]
        segs.append(jnp.moveaxis(a.reshape(lead + (b.size, batch)), -1, -2))     # [..., B, size]
    return jnp.take(jnp.concatenate(segs, axis=-1), t.inv_perm, axis=-1)


def flat_blocks_out(t: Topology, flat, batch: int):
    """[..., m * B] as recorded by the time loop (`layout.constraints_concat` of the batch-minor blocks) ->
    [..., B, m] in the user's constraint order."""
    blocks, start = [], 0
    for b in t.blocks:
        n = b.size * batch
        blocks.append(flat[..., start: start + n].reshape(flat.shape[:-1] + (b.shape + (batch,) if b.strided
                                                                             else (n,))))
        start += n
    return constraints_out(t, blocks, batch)


def system(model, tb: Topology, dtype, batch: int) -> System:
    """The model's System on the batch-minor topology `tb`: inverse masses [1, *view, B], per-block rest
    lengths [*shape, B] (or [size * B]), shared by every copy."""
    t = model.topology.unrolled
    w = L.per_particle_in(t, jnp.asarray(model.inv_mass, dtype))
    w = jnp.broadcast_to(w[..., None], w.shape + (batch,))
    rest = constraints_in(t, jnp.asarray(model.rest_length, dtype), batch)
    return System(w, rest, jnp.asarray(model.gravity, dtype), tb)


# ---- batched rollouts ---------------------------------------------------------------------------------------
#: Systems per chunk on CPU: the batch-minor arrays of a chunk stay in cache (16384 double pendulums, PGS(10),
#: 2-core AMD EPYC: 3.1e7 pendulum-steps/s in pieces of 1024 against 2.1e7 in one piece, docs/batching.md).
CPU_CHUNK = 1024


def layout_generic(solver, model=None) -> bool:
    """Whether `solver` only uses the internal layout, so it runs on the batch-minor topology. `Direct`
    assembles its matrices in user order, contacts gather pairs over the particle axis, a hub's star
    (`topology.star_colouring`) sums over its spokes, and a `jc.Constraint` set's rows have no batch-minor
    blocks; all four are batched with `jax.vmap` instead."""
    return getattr(solver, "batch_minor", True) and (model is None or (model.contact is None
                                                                       and not model.topology.has_stars
                                                                       and not model.topology.has_sets))


def drive_in(t: Topology, forces, targets, dtype):
    """A batch's inputs -> batch-minor: forces [B, steps, n, dim] -> [steps, dim, *view, B]; targets
    [B, steps, n_fixed, dim] -> [steps, dim, n_fixed * B] (copy b of the k-th fixed particle at k * B + b,
    the order of `sim.fixed_slots` on the batch-minor topology). Either may be None."""
    f = None if forces is None else particles_in(t, jnp.moveaxis(jnp.asarray(forces, dtype), 0, 1))
    if targets is not None:
        a = jnp.transpose(jnp.asarray(targets, dtype), (1, 3, 2, 0))            # [steps, dim, n_fixed, B]
        targets = a.reshape(a.shape[:2] + (-1,))
    return f, targets


def _minor(model, states, solver, dt, steps, save_every, drive=(None, None), packed=False, unroll=False):
    """One batch-minor rollout of every state in `states` ([b, ...] leaves), under `drive` = (forces, targets)
    with the same leading axis b (or None); `packed`, `unroll`: see `batch_minor_topology`."""
    t, dtype, B = model.topology.unrolled, jnp.result_type(states.x), states.x.shape[0]
    tb = batch_minor_topology(t, B, packed, unroll)
    sys = system(model, tb, dtype, B)
    x = particles_in(t, jnp.asarray(states.x, dtype))
    v = _sim.hold_fixed(tb, particles_in(t, jnp.asarray(states.v, dtype)))
    lam = constraints_in(t, jnp.asarray(states.lam, dtype), B)
    (x, v, lam), (xs, vs, lams) = _sim._time_loop(sys, solver, (x, v, lam), jnp.asarray(dt, dtype), steps,
                                                  save_every, drive=drive_in(t, *drive, dtype))
    final = State(particles_out(t, x), particles_out(t, v), constraints_out(t, lam, B))
    lead = lambda a: jnp.moveaxis(a, 0, 1)          # noqa: E731  records come out [T, B, ...]; the batch leads
    return final, Trajectory(lead(particles_out(t, xs)), lead(particles_out(t, vs)), lead(flat_blocks_out(t, lams, B)))


def _map(f, xs, batch_size):
    """`lax.map(f, xs, batch_size=...)` that also takes and returns zero-size leaves (a model with contacts and
    no rods has lam [B, 0], which lax.map's reshape cannot split into pieces)."""
    leaves, tree = jax.tree.flatten(xs)
    empty = [a.size == 0 for a in leaves]
    if not any(empty):
        return lax.map(f, xs, batch_size=batch_size)
    b = leaves[0].shape[0]
    kept = [a for a, e in zip(leaves, empty) if not e]
    out_tree = []

    def g(ks):
        it = iter(ks)
        full = [jnp.zeros(a.shape[1:], a.dtype) if e else next(it) for a, e in zip(leaves, empty)]
        out = jax.tree.flatten(f(jax.tree.unflatten(tree, full)))
        out_tree.append((out[1], [o.shape for o in out[0]], [o.dtype for o in out[0]]))
        return [o for o in out[0] if o.size]

    res = iter(lax.map(g, kept, batch_size=batch_size))
    otree, shapes, dtypes = out_tree[0]
    return jax.tree.unflatten(otree, [jnp.zeros((b,) + sh, dt) if int(np.prod(sh)) == 0 else next(res)
                                      for sh, dt in zip(shapes, dtypes)])


def _pad(tree, multiple):
    """Pad the leading (batch) axis of every leaf to a multiple of `multiple` with copies of the last entry."""
    b = jax.tree.leaves(tree)[0].shape[0]
    extra = (-b) % multiple
    if not extra:
        return tree
    return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]), tree)


def _local(model, batch, solver, dt, steps, save_every, chunk, sweeps="plain"):
    """The batch held by one device, `batch` = (states, (forces, targets)) with leading batch axes: batch-minor in
    chunks of `chunk` (None: one piece), or `jax.vmap` over chunks for solvers that are not layout-generic.
    `sweeps` (`sweep_mode`): "packed" packs PGS's sweeps in a batch run in one piece (`batch_minor_topology`;
    pieces never pack), "unrolled" unrolls the solvers' loops over sweeps."""
    b = batch[0].x.shape[0]
    if not layout_generic(solver, model):
        one = lambda a: _sim._rollout_jit(model, a[0], solver, dt, steps, save_every, None, True,  # noqa: E731
                                          *a[1])
        return _map(one, batch, min(chunk or b, b))
    if chunk is None or chunk >= b:
        return _minor(model, batch[0], solver, dt, steps, save_every, batch[1], sweeps == "packed",
                      sweeps == "unrolled")
    padded = _pad(batch, chunk)
    n = padded[0].x.shape[0] // chunk
    parts = jax.tree.map(lambda a: a.reshape((n, chunk) + a.shape[1:]), padded)
    out = lax.map(lambda a: _minor(model, a[0], solver, dt, steps, save_every, a[1], unroll=sweeps == "unrolled"),
                  parts)
    return jax.tree.map(lambda a: a.reshape((n * chunk,) + a.shape[2:])[:b], out)


def _per_copy(a, b):
    """forces / targets with a leading batch axis of b: [b, steps, ., dim] as given, or an array without the
    batch axis ([steps, ., dim], shared by every copy) repeated b times; None stays None."""
    return a if a is None or jnp.ndim(a) == 4 else jnp.broadcast_to(a, (b,) + jnp.shape(a))


@functools.partial(jax.jit, static_argnames=("steps", "save_every", "chunk", "mesh", "sweeps"))
def _batched_jit(model, states, solver, dt, steps, save_every, chunk, mesh=None, forces=None, targets=None,
                 sweeps="plain"):
    b = states.x.shape[0]
    batch = (states, tuple(_per_copy(a, b) for a in (forces, targets)))
    if mesh is None or mesh.size == 1:
        return _local(model, batch, solver, dt, steps, save_every, chunk, sweeps)
    axis = mesh.axis_names
    spec, rep = PartitionSpec(axis), PartitionSpec()
    local = jax.shard_map(lambda m, a, so, h: _local(m, a, so, h, steps, save_every, chunk, sweeps), mesh=mesh,
                          in_specs=(rep, spec, rep, rep), out_specs=spec, check_vma=False)
    out = local(model, _pad(batch, mesh.size), solver, jnp.asarray(dt))
    return out if out[0].x.shape[0] == b else jax.tree.map(lambda a: a[:b], out)


def _mesh(devices, mesh):
    if mesh is not None and devices is not None:
        raise ValueError("batched_rollout: pass `devices` or `mesh`, not both")
    if mesh is not None:
        if not isinstance(mesh, Mesh):
            raise TypeError(f"batched_rollout: `mesh` must be a jax.sharding.Mesh, got {type(mesh).__name__}")
        return mesh
    devices = jax.local_devices() if devices is None else _devices(devices)
    return Mesh(np.array(devices), ("batch",))


def _devices(devices) -> list:
    """`devices` as a list of distinct jax Devices (what jax.devices() and jax.local_devices() return)."""
    hint = "a list of jax devices, such as jax.local_devices() or jax.devices('cpu')[:2]"
    if isinstance(devices, (str, bytes, jax.Device)) or not hasattr(devices, "__iter__"):
        raise TypeError(f"batched_rollout: `devices` must be {hint}, got {devices!r}")
    devices = list(devices)
    if not devices:
        raise ValueError("batched_rollout: `devices` is empty")
    for k, d in enumerate(devices):
        if not isinstance(d, jax.Device):
            raise TypeError(f"batched_rollout: `devices` must be {hint}; `devices[{k}]` is {d!r} "
                            f"({type(d).__name__})")
    if len(set(devices)) != len(devices):
        raise ValueError(f"batched_rollout: `devices` lists a device twice: {devices}")
    return devices


def default_chunk(devices) -> int | None:
    """Chunk size by backend: CPU_CHUNK on CPU (cache), none on accelerators (one piece is fastest there; a
    batch that does not fit is refused by the memory check before compiling)."""
    return CPU_CHUNK if all(d.platform == "cpu" for d in devices) else None


def sweep_mode(chunk, devices) -> str:
    """How a batch-minor rollout runs PGS's sweeps (and every solver's loop over sweeps), by backend:

    - on a GPU or TPU, "unrolled": plain sweeps with the loop over them unrolled (`Topology.unroll`). On an
      H200 (jax 0.11.2, double pendulums, PGS(10), one piece) that ran 1.6 to 6x the packed sweeps and 1.2 to
      2.7x the plain loop: a loop ends XLA's fusions at every trip, and XLA's GPU fusion (which has multi-output
      fusions) merges the plain sweep's two kernels per colour by itself, so packing only adds its
      optimization barriers (docs/batching.md);
    - on the CPU, "packed" for a batch run in one piece (`chunk` given; `jaxcon.solvers.pgs.packed_sweeps`: one
      kernel per colour and sweep instead of two plus a copy, XLA's CPU backend having no multi-output fusion),
      and "plain" under the CPU default (pieces of CPU_CHUNK), whose plain sweeps ran 1.3 to 1.5x faster there.
      Pieces smaller than the batch never pack."""
    if default_chunk(devices) is None:
        return "unrolled"
    return "packed" if chunk is not None else "plain"


def batched_rollout(model: Model, states: State, solver: Solver, dt, steps: int, *, chunk: int | None = None,
                    save_every: int = 1, devices=None, mesh=None, forces=None, targets=None):
    """`rollout` of a batch of initial states (x, v [B, n, dim], lam [B, m]) with one model and solver.

    The batch runs in the batch-minor layout (module docstring): one system of B disjoint copies, every array
    with the batch as its last axis, so each step compiles to a few kernels over the whole batch. Results
    equal a `jax.vmap` of `rollout` (bitwise for PGS, to rounding for XPBD and Penalty); `Direct` is batched
    with `jax.vmap`. Works under `jax.grad` and `jax.jit`.

    Args:
      chunk: systems per piece on each device. None (default): CPU_CHUNK (1024) on CPU, where pieces that fit
        in cache ran 1.5x faster than one large piece, and no chunking on GPU or TPU. A batch run in one piece
        on the CPU (`chunk` >= the batch) carries PGS's sweeps in one packed array: about half the kernels per
        step; on an accelerator the loop over sweeps is unrolled instead (`sweep_mode`).
      save_every: as for `rollout`.
      devices: the devices to shard the batch over (default: all local devices); a batch that does not divide
        evenly is padded with copies of its last state, which are dropped from the results.
      mesh: instead of `devices`, a `jax.sharding.Mesh` whose axes together shard the batch (for example a
        global mesh after `jax.distributed.initialize()`; docs/batching.md).
      forces, targets: as for `rollout`, per copy with a leading batch axis ([B, steps, n, dim],
        [B, steps, n_fixed, dim]), or without it ([steps, n, dim], [steps, n_fixed, dim]): shared by every copy.

    Returns (finals, trajs) with a leading batch axis, sharded over the devices like the input batch.
    """
    forces, targets = _check_batch(model, states, solver, dt, steps, save_every, chunk, forces, targets)
    mesh = _mesh(devices, mesh)
    sweeps = sweep_mode(chunk, mesh.devices.flat)
    if chunk is None:
        chunk = default_chunk(mesh.devices.flat)
    return _batched_jit(model, states, solver, dt, steps, save_every, chunk, mesh if mesh.size > 1 else None,
                        forces, targets, sweeps)


def _check_batch(model, states, solver, dt, steps, save_every, chunk, forces=None, targets=None):
    if not isinstance(states, State):
        raise TypeError(f"batched_rollout: `states` must be a jaxcon State, got {type(states).__name__}")
    if np.ndim(states.x) != 3:
        raise ValueError(f"batched_rollout: `states.x` must have shape [batch, n, dim], got {np.shape(states.x)}")
    if np.shape(states.x)[0] == 0:
        raise ValueError("batched_rollout: `states` holds an empty batch (0 initial states)")
    if chunk is not None:
        check_int("batched_rollout", "chunk", chunk, 1)
    check_int("batched_rollout", "save_every", save_every, 1)
    _sim.check_x64("batched_rollout", model, states)
    B = np.shape(states.x)[0]
    for name in ("x", "v", "lam", "contact_n", "contact_t", "contact_partners"):
        a = getattr(states, name)
        if a is not None and (np.ndim(a) == 0 or np.shape(a)[0] != B):
            raise ValueError(f"batched_rollout: `states.{name}` must have the batch of `states.x` ({B} initial "
                             f"states) as its leading axis, got {describe_shape(np.shape(a))}")
    first = jax.tree.map(lambda a: a[0], states)
    _sim._check_call("batched_rollout", model, first, solver, dt, steps)
    for name in ("x", "v", "lam", "contact_n", "contact_t"):
        if getattr(states, name) is not None:
            check_values("batched_rollout", f"states.{name}", getattr(states, name))
    if states.contact_partners is not None:
        check_partners("batched_rollout", "states.contact_partners", states.contact_partners)
    if steps % save_every:
        raise ValueError(f"batched_rollout: `steps` ({steps}) must be a multiple of `save_every` ({save_every})")
    forces, targets = _sim.check_drive("batched_rollout", model, forces, targets, steps, batch=B)
    _sim.check_record_memory("batched_rollout", model, first, steps, save_every, batch=B,
                             inputs=_sim.drive_bytes(model, first, steps, forces, targets, B))
    return forces, targets
