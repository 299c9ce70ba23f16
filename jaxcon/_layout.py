"""Array operations on the internal layout: particles ``[dim, *view]``, constraints as one array per block.

These are the building blocks every solver uses; none of them loops over particles or constraints.
"""
from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from ._topology import Block, Topology


# ---- particles ---------------------------------------------------------------------------------------------
def particles_in(topo: Topology, x):
    """[..., n, dim] user layout -> [..., dim, *view] internal layout."""
    x = jnp.swapaxes(x, -1, -2)
    return x.reshape(x.shape[:-1] + topo.view)


def particles_out(topo: Topology, x):
    """[..., dim, *view] internal layout -> [..., n, dim] user layout."""
    lead = x.ndim - 1 - len(topo.view)
    x = x.reshape(x.shape[: lead + 1] + (topo.n,))
    return jnp.swapaxes(x, -1, -2)


def per_particle_in(topo: Topology, a):
    """[n] per-particle scalars -> [1, *view], broadcastable against internal particle arrays."""
    return a.reshape((1,) + topo.view)


# ---- constraints -------------------------------------------------------------------------------------------
def constraints_in(topo: Topology, a):
    """[..., m] in the user's constraint order -> tuple of [..., *block.shape], one per block."""
    a = jnp.take(a, topo.perm, axis=-1) if topo.m else a
    lead = a.shape[:-1]
    return tuple(a[..., b.offset: b.offset + b.size].reshape(lead + b.shape) for b in topo.blocks)


def constraints_out(topo: Topology, blocks):
    """Inverse of `constraints_in`."""
    if not blocks:
        raise ValueError("model has no constraints")
    flat = [x.reshape(x.shape[: x.ndim - len(b.shape)] + (b.size,)) for x, b in zip(blocks, topo.blocks)]
    a = jnp.concatenate(flat, axis=-1)
    return jnp.take(a, topo.inv_perm, axis=-1)


def _box_slice(x, box):
    start, step, count = box
    limit = tuple(s + st * (c - 1) + 1 for s, st, c in zip(start, step, count))
    lead = x.ndim - len(start)
    return lax.slice(x, (0,) * lead + start, x.shape[:lead] + limit, (1,) * lead + step)


def _box_pad(p, box, view):
    start, step, count = box
    lead = p.ndim - len(start)
    cfg = [(0, 0, 0)] * lead
    for s, st, c, size in zip(start, step, count, view):
        cfg.append((s, size - (s + st * (c - 1) + 1), st - 1))
    return lax.pad(p, jnp.zeros((), p.dtype), cfg)


def gather_pair(topo: Topology, block: Block, x):
    """Endpoint values of a block: x[..., *view] -> (x_i, x_j), each [..., *block.shape]."""
    if block.strided:
        return _box_slice(x, block.i_box), _box_slice(x, block.j_box)
    lead = x.ndim - len(topo.view)
    flat = x.reshape(x.shape[:lead] + (topo.n,))
    return jnp.take(flat, block.i_idx.array, axis=-1), jnp.take(flat, block.j_idx.array, axis=-1)


def scatter_pair(topo: Topology, block: Block, p_i, p_j):
    """Per-particle array that holds p_i at the block's first endpoints, p_j at its second, zero elsewhere.

    Each particle is an endpoint of at most one constraint of a block, so this is a pad (strided blocks) or a
    gather (general blocks); it never needs a scatter-add.
    """
    if block.strided:
        return _box_pad(p_i, block.i_box, topo.view) + _box_pad(p_j, block.j_box, topo.view)
    lead = p_i.shape[:-1]
    zero = jnp.zeros(lead + (1,), p_i.dtype)
    flat = jnp.take(jnp.concatenate([p_i, p_j, zero], axis=-1), block.src.array, axis=-1)
    return flat.reshape(lead + topo.view)


# ---- guarded geometry --------------------------------------------------------------------------------------
def safe_norm(d, axis=0):
    """(length, unit direction) of vectors along `axis`; at zero length the direction is 0 and every
    derivative is finite (the square root and the division only see a positive argument)."""
    d2 = jnp.sum(d * d, axis=axis)
    ok = d2 > jnp.finfo(d.dtype).tiny
    dist = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2, 1)), 0)
    inv = jnp.where(ok, 1 / jnp.where(ok, dist, 1), 0)
    return dist, d * jnp.expand_dims(inv, axis)


def safe_reciprocal(a):
    """1/a where a > 0, else 0 (and a zero derivative there)."""
    ok = a > 0
    return jnp.where(ok, 1 / jnp.where(ok, a, 1), 0)


