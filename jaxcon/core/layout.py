"""Array operations on the internal layout: particles ``[dim, *view]``, constraints as one array per block.

These are the building blocks every solver uses; none of them loops over particles or constraints.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core.topology import Block, Topology


# ---- particles ---------------------------------------------------------------------------------------------
def particles_in(topo: Topology, x):
    """[..., n, dim] user layout -> [..., dim, *view] internal layout."""
    if topo.order is not None:
        x = jnp.take(x, topo.order, axis=-2)
    x = jnp.swapaxes(x, -1, -2)
    return x.reshape(x.shape[:-1] + topo.view)


def particles_out(topo: Topology, x):
    """[..., dim, *view] internal layout -> [..., n, dim] user layout."""
    lead = x.ndim - 1 - len(topo.view)
    x = x.reshape(x.shape[: lead + 1] + (topo.n,))
    if topo.order is not None:
        x = jnp.take(x, topo.pos, axis=-1)
    return jnp.swapaxes(x, -1, -2)


def per_particle_in(topo: Topology, a):
    """[n] per-particle scalars -> [1, *view], broadcastable against internal particle arrays."""
    if topo.order is not None:
        a = jnp.take(a, topo.order, axis=-1)
    return a.reshape((1,) + topo.view)


def per_particle_out(topo: Topology, a):
    """Inverse of `per_particle_in`: [1, *view] -> [n] in user particle order."""
    a = a.reshape(topo.n)
    return a if topo.order is None else jnp.take(a, topo.pos)


# ---- constraints -------------------------------------------------------------------------------------------
def constraints_in(topo: Topology, a):
    """[..., m] in the user's constraint order -> tuple of [..., *block.shape], one per block (a table's or a
    star block's padding is zero)."""
    if not (topo.compact or topo.has_stars or topo.has_sets):
        a = jnp.take(a, topo.perm, axis=-1) if topo.m else a
        lead = a.shape[:-1]
        return tuple(a[..., b.offset: b.offset + b.size].reshape(lead + b.shape) for b in topo.blocks)
    out = []
    for b in topo.blocks:
        if b.table or b.star or b.generic is not None:
            out.append(jnp.take(a, b.src.array, axis=-1, mode="fill", fill_value=0))
        else:
            seg = jnp.take(a, topo.perm[b.offset: b.offset + b.size], axis=-1)
            out.append(seg.reshape(seg.shape[:-1] + b.shape))
    return tuple(out)


def constraints_concat(topo: Topology, blocks, like=None):
    """Tuple of [..., *block.shape] -> one [..., m] array, still in block order (see `constraints_out`). A model
    without constraints gives [..., 0], its leading axes and dtype those of `like` ([..., dim, *view])."""
    if not blocks:
        if like is None:
            raise ValueError("model has no constraints")
        return jnp.zeros(like.shape[: like.ndim - 1 - len(topo.view)] + (0,), like.dtype)
    flat = []
    for x, b in zip(blocks, topo.blocks):
        if b.table or b.star or b.generic is not None:
            flat.append(jnp.take(x.reshape(x.shape[: x.ndim - len(b.shape)] + (-1,)), b.flat.array, axis=-1))
        else:
            flat.append(x.reshape(x.shape[: x.ndim - len(b.shape)] + (b.size,)))
    return flat[0] if len(flat) == 1 else jnp.concatenate(flat, axis=-1)


def constraints_unpermute(topo: Topology, a):
    """[..., m] in block order (`constraints_concat`) -> the user's constraint order."""
    return jnp.take(a, topo.inv_perm, axis=-1)


def constraints_out(topo: Topology, blocks, like=None):
    """Inverse of `constraints_in` (`like`: see `constraints_concat`)."""
    return constraints_unpermute(topo, constraints_concat(topo, blocks, like))


def _split_box(box, view):
    """Rewrite a strided box of `view` as a contiguous box of a finer view.

    An axis of size n read with step s > 1 is split into (n // s, s) when s divides n; the box's start a
    becomes (a // s, a % s) and its count (count, 1). Reshaping the array to the finer view is free (row-major),
    and the box then has unit steps: reads are plain slices and writes are edge pads, with no interior
    padding. On CPU this took PGS on the 64x64 cloth from 16-18 to 9-10 ns per constraint-iteration. Returns
    (finer view, start, count), or None when some step does not divide its axis (the box is then read with a
    strided slice)."""
    start, step, count = box
    shape, st, cnt = [], [], []
    for size, a, s, c in zip(view, start, step, count):
        if c == 1 or s == 1:
            shape.append(size), st.append(a), cnt.append(c)
        elif size % s == 0:
            shape += [size // s, s]
            st += [a // s, a % s]
            cnt += [c, 1]
        else:
            return None
    return tuple(shape), tuple(st), tuple(cnt)


def _box_slice(x, box, view):
    lead = x.shape[: x.ndim - len(view)]
    split = _split_box(box, view)
    if split is not None:
        shape, start, count = split
        y = lax.slice(x.reshape(lead + shape), (0,) * len(lead) + start,
                      lead + tuple(a + c for a, c in zip(start, count)))
        return y.reshape(lead + box[2])
    start, step, count = box
    limit = tuple(s + st * (c - 1) + 1 for s, st, c in zip(start, step, count))
    return lax.slice(x, (0,) * len(lead) + start, lead + limit, (1,) * len(lead) + step)


def _box_pad(p, box, view):
    lead = p.shape[: p.ndim - len(view)]
    zero = jnp.zeros((), p.dtype)
    split = _split_box(box, view)
    if split is not None:
        shape, start, count = split
        cfg = [(0, 0, 0)] * len(lead) + [(a, n - a - c, 0) for a, c, n in zip(start, count, shape)]
        return lax.pad(p.reshape(lead + count), zero, cfg).reshape(lead + view)
    start, step, count = box
    cfg = [(0, 0, 0)] * len(lead)
    for s, st, c, size in zip(start, step, count, view):
        cfg.append((s, size - (s + st * (c - 1) + 1), st - 1))
    return lax.pad(p, zero, cfg)


class _Mask:
    """A traced boolean mask where a `Block` holds a StaticArray (`Row.rope.array`)."""

    __slots__ = ("array",)

    def __init__(self, array):
        self.array = array


class Row:
    """One colour of a table block inside `each_colour`'s scan: traced endpoint indices [width] (padding is
    index n) and rope mask. Quacks like a gather `Block` for `gather_pair`, `add_pair` and the rope helpers."""

    strided = False
    table = False

    def __init__(self, ij, rope, all_rope):
        self.ij, self.all_rope = ij, all_rope          # [2 width]: the first endpoints, then the second
        self.rope = None if rope is None else _Mask(rope)

    @property
    def has_rope(self) -> bool:
        return self.all_rope or self.rope is not None


class StarRow:
    """One colour of a star block inside `each_colour`'s scan: traced hubs [H], other particles [H, S] (padding:
    index n) and rope mask."""

    strided = False
    table = False
    star = True

    def __init__(self, hub, j, rope, all_rope):
        self.hub, self.j_idx, self.all_rope = _Mask(hub), _Mask(j), all_rope
        self.rope = None if rope is None else _Mask(rope)

    @property
    def has_rope(self) -> bool:
        return self.all_rope or self.rope is not None


class SetRow:
    """One colour of a constraint set's block inside `each_colour`'s scan: traced particle indices [k, W] and
    real mask [W]; `generic` (the set's index) and `all_rope` (unilateral) as the block's. A set's per-row arrays
    keep their row axes last ([..., C, W] for the block, [..., W] for a row), like every table's."""

    strided = False
    table = False
    star = False
    rope = None
    unrolled = None

    def __init__(self, idx, real, block, hub=None):
        self.i_idx, self.real = _Mask(idx), _Mask(real)
        self.generic, self.all_rope, self.set_block = block.generic, block.all_rope, block.set_block
        self.hub_slot, self.spokes = (None if hub is None else _Mask(hub)), block.spokes

    @property
    def has_rope(self) -> bool:
        return self.all_rope


def gather_rows(topo: Topology, block, x):
    """A constraint set's particles' values: x [..., *view] -> [..., k, *block.shape] (or [..., k, W] for a
    `SetRow`); strided slices for a colour of its own whose rows form boxes (`topology.SetColour`)."""
    col = getattr(block, "unrolled", None)
    if col is not None and col.boxes is not None:
        lead = x.shape[: x.ndim - len(topo.view)]
        return jnp.stack([_box_slice(x, b, topo.view).reshape(lead + (-1,)) for b in col.boxes], axis=-2)
    return jnp.take(_flat(topo, x), block.i_idx.array, axis=-1)


def dot_rows(topo: Topology, block, J, v):
    """sum over dim and slot of J [dim, k, *block.shape] times the rows' particles' values of v [dim, *view]
    (`gather_rows`), per row. For a colour of its own the sum is written out term by term (slot by slot, each
    slot's components as `dot0`), read from each slot's box or gather without stacking them: on CPU the
    reduction over the stacked [dim, k, *rows] (a concatenate and a reduce in one loop kernel) made a PGS sweep
    of the 32x32 cloth's edges as a `jc.Constraint` set 2.4x the cost of its rods' sweep, 1.8x without it (then
    1.2x with the parity split, `topology.Topology._split_for_sets`). A table's `SetRow` keeps the reduction,
    which fuses with its gather (`dot`)."""
    col = getattr(block, "unrolled", None)
    if col is None:
        return jnp.sum(J * gather_rows(topo, block, v), axis=(0, 1))
    lead = v.shape[: v.ndim - len(topo.view)]
    if col.boxes is not None:
        slots = [_box_slice(v, b, topo.view).reshape(lead + (-1,)) for b in col.boxes]
    else:
        flat = _flat(topo, v)
        slots = [jnp.take(flat, idx, axis=-1) for idx in block.i_idx.array]
    out = dot0(J[:, 0], slots[0])
    for s in range(1, len(slots)):
        out = out + dot0(J[:, s], slots[s])
    return out


def add_rows(topo: Topology, block, v, p):
    """v + the contributions p [..., k, *block.shape] of a constraint set's rows, summed per particle. A colour of
    its own (`topology.SetColour`) writes through pads of its boxes, or a gather (each free particle is in one of
    its rows at most); a table or `SetRow`, with a scatter-add, padding rows masked."""
    col = getattr(block, "unrolled", None)
    if col is not None:
        lead = p.shape[:-2]
        if col.boxes is not None:
            pads = [_box_pad(p[..., s, :].reshape(lead + b[2]), b, topo.view) for s, b in enumerate(col.boxes)]
            return v + functools.reduce(jnp.add, pads)
        return v + _gather_back(topo, [p.reshape(lead + (-1,))], col.src.array)
    p = p * block.real.array.astype(p.dtype)
    return _flat(topo, v).at[..., block.i_idx.array].add(p).reshape(v.shape)


def each_colour(block, fn, carry, rows):
    """Gauss-Seidel over the colours of `block`: ``carry, out = fn(carry, colour, rows)``, colour by colour.

    `rows` is a pytree of per-constraint arrays [..., *block.shape]. A strided or gather block is one colour,
    so fn runs once on it; so is a constraint set's colour of its own (`Block.unrolled`). A table block (compact
    layout) runs fn on each of its rows, in order, in a `lax.scan`: `colour` is then a `Row` and every leaf of
    `rows` is that row, [..., width]; a constraint set's table the same way (`SetRow`). `out` (a pytree of
    per-constraint arrays of the colour) is stacked back to [..., *block.shape]. A contact block
    (`core.contact_rows`: obstacles, pair rounds, grid slots) runs its colours its own way (`block.each`)."""
    if hasattr(block, "each"):
        return block.each(fn, carry, rows)
    if getattr(block, "unrolled", None) is not None:
        return fn(carry, block, rows)
    if getattr(block, "generic", None) is not None:     # a constraint set: its colours [C, W], in order
        hub = None if block.hub_slot is None else np.moveaxis(block.hub_slot.array, -2, 0)
        xs = (np.moveaxis(block.i_idx.array, -2, 0), block.real.array, hub,
              jax.tree.map(lambda a: jnp.moveaxis(a, -2, 0), rows))

        def set_body(carry, x):
            idx, real, hub, row = x
            return fn(carry, SetRow(idx, real, block, hub), row)

        carry, out = lax.scan(set_body, carry, xs)
        return carry, jax.tree.map(lambda a: jnp.moveaxis(a, 0, -2), out)
    if getattr(block, "star", False):          # a star block: its colours [C, H, S], one after another
        rope = None if block.rope is None else block.rope.array
        xs = (block.hub.array, block.j_idx.array, rope, jax.tree.map(lambda a: jnp.moveaxis(a, -3, 0), rows))

        def star_body(carry, x):
            hub, j, r, row = x
            return fn(carry, StarRow(hub, j, r, block.all_rope), row)

        carry, out = lax.scan(star_body, carry, xs)
        return carry, jax.tree.map(lambda a: jnp.moveaxis(a, 0, -3), out)
    if not block.table:
        return fn(carry, block, rows)
    rope = None if block.rope is None else block.rope.array
    ij = np.concatenate([block.i_idx.array, block.j_idx.array], axis=1)      # [colours, 2 width]
    xs = (ij, rope, jax.tree.map(lambda a: jnp.moveaxis(a, -2, 0), rows))

    def body(carry, x):
        ij, r, row = x
        return fn(carry, Row(ij, r, block.all_rope), row)

    carry, out = lax.scan(body, carry, xs)
    return carry, jax.tree.map(lambda a: jnp.moveaxis(a, 0, -2), out)


def _flat(topo, x):
    lead = x.shape[: x.ndim - len(topo.view)]
    return x.reshape(lead + (topo.n,))


def _indices(block):
    """Both endpoints' indices of a table block or row, concatenated along the last axis."""
    if isinstance(block, Row):
        return block.ij
    return np.concatenate([block.i_idx.array, block.j_idx.array], axis=-1)


def _star_real(topo, block):
    """[(C,) H, S] bool: the spokes of a star block (or `StarRow`) that are constraints (not padding)."""
    return block.j_idx.array < topo.n


def gather_pair(topo: Topology, block: Block, x):
    """Endpoint values of a block: x[..., *view] -> (x_i, x_j), each [..., *block.shape]. A table block or a
    `Row` reads 0 at its padding; a star block gives its hubs as x_i, the other particles as x_j, both 0 at
    its padding (so a padding spoke has no direction, no mass and no effective mass)."""
    if getattr(block, "star", False):
        flat = _flat(topo, x)
        xj = jnp.take(flat, block.j_idx.array, axis=-1, mode="fill", fill_value=0)        # [..., (C,) H, S]
        xi = jnp.take(flat, block.hub.array, axis=-1, mode="fill", fill_value=0)[..., None]
        return jnp.where(_star_real(topo, block), xi, 0), xj
    if block.table or isinstance(block, Row):
        both = jnp.take(_flat(topo, x), _indices(block), axis=-1, mode="fill", fill_value=0)   # one gather
        return jnp.split(both, 2, axis=-1)
    if block.strided:
        return _box_slice(x, block.i_box, topo.view), _box_slice(x, block.j_box, topo.view)
    lead = x.ndim - len(topo.view)
    flat = x.reshape(x.shape[:lead] + (topo.n,))
    return jnp.take(flat, block.i_idx.array, axis=-1), jnp.take(flat, block.j_idx.array, axis=-1)


def scatter_pair(topo: Topology, block: Block, p_i, p_j):
    """Per-particle array that holds p_i at the block's first endpoints, p_j at its second, zero elsewhere.

    Each particle is an endpoint of at most one constraint of a strided or gather block, so this is a pad
    (strided blocks) or a gather (gather blocks). A table block (every colour at once) sums with a scatter-add.
    """
    if block.table or isinstance(block, Row) or getattr(block, "star", False):
        lead = p_i.shape[: p_i.ndim - (len(block.j_idx.array.shape) if getattr(block, "star", False) else
                                       2 if block.table else 1)]
        return add_pair(topo, block, jnp.zeros(lead + topo.view, p_i.dtype), p_i, p_j)
    if block.strided:
        return _box_pad(p_i, block.i_box, topo.view) + _box_pad(p_j, block.j_box, topo.view)
    return _gather_back(topo, [p_i, p_j], block.src.array)


def _gather_back(topo: Topology, parts, src):
    """Per-particle array [..., *view] from contributions `parts` (arrays [..., P_a], concatenated): particle q
    takes entry src[q] of them, or 0 where src[q] is past their end. The write-back of a colour whose particles
    each appear once (a gather block, a set's colour of its own), a gather instead of a scatter-add."""
    lead = parts[0].shape[:-1]
    flat = jnp.concatenate(list(parts) + [jnp.zeros(lead + (1,), parts[0].dtype)], axis=-1)
    return jnp.take(flat, src, axis=-1).reshape(lead + topo.view)


def _slice_of_pad(p, pad_box, read_box):
    """`_box_slice(_box_pad(p, pad_box, view), read_box, view)` for two strided boxes of one view, without the
    view-sized array: along each axis the positions the boxes share are every k-th of `read_box`'s and every
    l-th of `pad_box`'s, so this is a strided slice of p padded with zeros (interior padding between)."""
    lead = p.ndim - len(read_box[0])
    starts, limits, strides, cfg = [0] * lead, list(p.shape[:lead]), [1] * lead, [(0, 0, 0)] * lead
    for (sa, ta, ca), (sg, tg, cg) in zip(zip(*pad_box), zip(*read_box)):
        pos = sg + tg * np.arange(cg)                        # positions read
        ok = (pos >= sa) & ((pos - sa) % ta == 0) & ((pos - sa) // ta < ca)
        ks = np.flatnonzero(ok)
        if not len(ks):
            return jnp.zeros(p.shape[:lead] + tuple(read_box[2]), p.dtype)
        ls = (pos[ks] - sa) // ta                            # their entries of p
        dk = int(ks[1] - ks[0]) if len(ks) > 1 else 1
        dl = int(ls[1] - ls[0]) if len(ls) > 1 else 1
        starts.append(int(ls[0]))
        limits.append(int(ls[-1]) + 1)
        strides.append(dl)
        cfg.append((int(ks[0]), int(cg - 1 - ks[-1]), dk - 1))
    out = lax.slice(p, starts, limits, strides)
    return lax.pad(out, jnp.zeros((), p.dtype), cfg)


def gather_after(topo: Topology, block: Block, v, updates):
    """`gather_pair(topo, block, v2)` of v2 = v after ``add_pair(topo, b, ., p_i, p_j)`` for each (b, p_i, p_j)
    of `updates` in turn, without forming v2: the same additions, gathered term by term (a gather commutes with
    elementwise sums, so the values are those of v2's endpoints). Between strided blocks each term is
    `_slice_of_pad` of p_i or p_j, which reads the endpoints from p_i and p_j directly instead of from padded
    view-sized arrays that XLA would then store to share them with the v2 it also builds (packed sweeps,
    `jaxcon.solvers.pgs.packed_sweeps`). Table and star updates (scatter-adds) are applied to v first."""
    if any(b.table or isinstance(b, Row) or getattr(b, "star", False) for b, _, _ in updates):
        for b, p_i, p_j in updates:
            v = add_pair(topo, b, v, p_i, p_j)
        return gather_pair(topo, block, v)
    gi, gj = gather_pair(topo, block, v)
    for b, p_i, p_j in updates:
        if b.strided and block.strided:
            gi = gi + (_slice_of_pad(p_i, b.i_box, block.i_box) + _slice_of_pad(p_j, b.j_box, block.i_box))
            gj = gj + (_slice_of_pad(p_i, b.i_box, block.j_box) + _slice_of_pad(p_j, b.j_box, block.j_box))
        elif b.strided:
            ai, aj = gather_pair(topo, block, _box_pad(p_i, b.i_box, topo.view))
            bi, bj = gather_pair(topo, block, _box_pad(p_j, b.j_box, topo.view))
            gi, gj = gi + (ai + bi), gj + (aj + bj)
        else:
            ti, tj = gather_pair(topo, block, scatter_pair(topo, b, p_i, p_j))
            gi, gj = gi + ti, gj + tj
    return gi, gj


def add_pair(topo: Topology, block: Block, v, p_i, p_j):
    """v + `scatter_pair(topo, block, p_i, p_j)`. Table blocks and rows add in place (a scatter-add that drops
    the padding); a table block may hold a particle in several rows, and the contributions sum."""
    if getattr(block, "star", False):        # each hub takes the sum of its spokes, each other particle its own
        flat = _flat(topo, v).at[..., block.hub.array].add(jnp.sum(p_i, axis=-1), mode="drop")
        return flat.at[..., block.j_idx.array].add(p_j, mode="drop").reshape(v.shape)
    if not (block.table or isinstance(block, Row)):
        return v + scatter_pair(topo, block, p_i, p_j)
    flat = _flat(topo, v).at[..., _indices(block)].add(jnp.concatenate([p_i, p_j], axis=-1), mode="drop")
    return flat.reshape(v.shape)


def block_solve(topo: Topology, block, f, rhs, alpha=0.0):
    """The multiplier changes of one colour's rows whose right-hand side is `rhs` [*block.shape]: rhs * f.k,
    each row on its own, for every block but a star block, whose rows share their hub and are solved together.
    `f` has n [dim, *shape] (unit normals from the first particle to the second), wi, wj (inverse masses) and k;
    `alpha` is added to every row's diagonal (XPBD's compliance / h^2).

    A star's rows solve (D + w_p N N^T) dlam = rhs, D = diag(w_o + alpha) (w_o the other particles', w_p the
    hub's inverse mass, N the rows' normals): with u = w_p N^T dlam, the change of the hub's velocity (or
    position), (I + w_p N^T D^-1 N) u = w_p N^T D^-1 rhs is a dim x dim system per hub, and dlam = D^-1 (rhs -
    N u). D is regularised by max(1e-6, 1e3 eps) (w_p + w_o), which keeps a row to a fixed particle (w_o = 0)
    solvable; the sweeps converge to the unregularised solution all the same (an inexact block solve changes
    how fast Gauss-Seidel converges, not where to).

    A constraint set's stars (`Block.hub_slot`, `topology.set_stars`) are solved the same way from their rows'
    Jacobians (`_set_star_solve`); a set's other rows, rhs * f.k."""
    if getattr(block, "hub_slot", None) is not None:
        return _set_star_solve(block, f, rhs, alpha)
    if not getattr(block, "star", False):
        return rhs * f.k
    dim = f.n.shape[0]
    real = _star_real(topo, block)
    wp = f.wi[..., :1]                                       # the hub's inverse mass (spoke 0 is always real)
    reg = max(1e-6, 1e3 * float(jnp.finfo(rhs.dtype).eps))
    inv_d = jnp.where(real, safe_reciprocal(f.wj + alpha + reg * (wp + f.wj)), 0)
    a = f.n * inv_d                                          # [dim, H, S]
    g = jnp.sum(a * rhs, axis=-1)                            # [dim, H]
    M = [[(a_ == b_) + wp[..., 0] * jnp.sum(a[a_] * f.n[b_], axis=-1) for b_ in range(dim)] for a_ in range(dim)]
    u = wp[..., 0] * _small_solve(M, g)                     # [dim, H]
    return (rhs - jnp.sum(f.n * u[..., None], axis=0)) * inv_d


def _set_star_solve(block, f, rhs, alpha=0.0):
    """`block_solve` for a constraint set's stars: rows [..., H * S] (`topology.Topology._set_star_block`), f a
    `rows.SetFrame`. A star's rows share only their hub p, so J M^-1 J^T = D + w_p N N^T, N [S, dim] the rows'
    Jacobians at the hub and D = diag(sum over their other particles q of w_q |J_q|^2, + alpha): the rods' star
    solve with N for the unit normals. Rows with no effective mass (f.k = 0: padding, inactive) take no part and
    get 0."""
    S = block.spokes
    hub = block.hub_slot.array.astype(rhs.dtype)                        # [k, ..., H S]
    live = f.k > 0
    jj = jnp.sum(f.J * f.J, axis=0)                                     # [k, ..., H S]
    Jh = jnp.sum(f.J * hub, axis=1)                                     # [dim, ..., H S]
    wp = jnp.sum(f.w * hub, axis=0)
    reg = max(1e-6, 1e3 * float(jnp.finfo(rhs.dtype).eps))
    d = jnp.sum((1 - hub) * f.w * jj, axis=0) + alpha
    inv_d = jnp.where(live, safe_reciprocal(d + reg * f.s), 0)

    def stars(a):                                                       # [..., H S] -> [..., H, S]
        return a.reshape(a.shape[:-1] + (a.shape[-1] // S, S))
    N, inv_d, r = stars(Jh), stars(inv_d), stars(rhs)
    wh = stars(wp)[..., 0]                                              # the hub's (spoke 0: real, or padding)
    a = N * inv_d
    g = jnp.sum(a * r, axis=-1)
    dim = N.shape[0]
    M = [[(a_ == b_) + wh * jnp.sum(a[a_] * N[b_], axis=-1) for b_ in range(dim)] for a_ in range(dim)]
    u = wh * _small_solve(M, g)
    return ((r - jnp.sum(N * u[..., None], axis=0)) * inv_d).reshape(rhs.shape)


def _small_solve(M, g):
    """Solve M u = g for a symmetric positive definite 2 x 2 or 3 x 3 M given as nested lists of [H] arrays, g
    [dim, H], by Cramer's rule (elementwise, so it fuses; det M >= 1 here, M being I plus a PSD matrix)."""
    if len(M) == 1:
        return g / M[0][0]
    if len(M) == 2:
        (a, b), (_, d) = M
        det = a * d - b * b
        return jnp.stack([d * g[0] - b * g[1], a * g[1] - b * g[0]]) / det
    (a, b, c), (_, d, e), (_, _, f) = M
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    return jnp.stack([A * g[0] + B * g[1] + C * g[2], B * g[0] + D * g[1] + E * g[2],
                      C * g[0] + E * g[1] + F * g[2]]) / det


# ---- guarded geometry --------------------------------------------------------------------------------------
def dot(block, a, b):
    """Sum of a * b over the leading (dim) axis for one colour: `dot0` on strided and gather blocks, a
    reduction on a table's `Row` (there the reduction fuses with the row's gathers; `dot0`'s per-component
    slices made XLA store the gathered rows first, 1.5x slower on the 16x16 cloth)."""
    return jnp.sum(a * b, axis=0) if isinstance(block, Row) else dot0(a, b)


@jax.custom_jvp
def dot0(a, b):
    """Sum of a * b over the leading (dim) axis, written out component by component.

    Same value as ``jnp.sum(a * b, axis=0)``, but elementwise: on CPU, XLA sends a reduction to a separate
    library kernel and materialises its sliced operands, while this fuses with the slices that produce a, b
    and the update that consumes the result (one loop kernel per colour instead of four; measured on the
    64x64 cloth)."""
    out = a[0] * b[0]
    for k in range(1, a.shape[0]):
        out = out + a[k] * b[k]
    return out


@dot0.defjvp
def _dot0_jvp(primals, tangents):
    a, b = primals
    da, db = tangents
    return dot0(a, b), jnp.sum(da * b + a * db, axis=0)


def min_length2(dtype):
    """Squared lengths at or below this count as zero length: sqrt of the smallest normal number (1.1e-19 in
    float32, i.e. 3.3e-10 m). Any smaller and the derivative of 1/|d| (|d|^-3) overflows to inf and then NaN."""
    return float(np.sqrt(np.finfo(dtype).tiny))


def safe_length(d, elementwise: bool = False):
    """(length, 1 / length) of vectors along the leading axis; both 0 at zero length (see `min_length2`),
    with finite derivatives everywhere (the reciprocal square root only sees an argument above that).

    elementwise: sum the squares with `dot0` instead of a reduction. The batch-minor layout uses it: there XLA
    on CPU sent the reduction over [dim, ..., B] to a library kernel that took 3 to 6 ms per step for 131072
    double pendulums, against 0.1 ms for the elementwise sum (fused into its consumers). For dim 2 the two are
    the same sum; for dim 3 the order of the additions may differ (rounding)."""
    d2 = dot0(d, d) if elementwise else jnp.sum(d * d, axis=0)
    ok = d2 > min_length2(d.dtype)
    inv = jnp.where(ok, lax.rsqrt(jnp.where(ok, d2, 1)), 0)
    return d2 * inv, inv


def safe_norm(d, axis=0, elementwise: bool = False):
    """(length, unit direction) of vectors along `axis`; at zero length the direction is 0 and every
    derivative is finite. `elementwise`: see `safe_length`."""
    if axis != 0:
        dist, n = safe_norm(jnp.moveaxis(d, axis, 0), elementwise=elementwise)
        return dist, jnp.moveaxis(n, 0, axis)
    dist, inv = safe_length(d, elementwise)
    return dist, d * inv


def rank_true(keep):
    """How many entries of each row of keep [n, M] (bool) are True before each entry: [n, M] int32, what
    `cumsum(keep, 1) - keep` gives. XLA CPU computes a cumsum along an axis as a reduce-window as long as the
    axis (0.7 ms for the 1024-disc box's [1024, 144] candidates); here the rows are packed into 32-bit words
    and counted with popcounts, elementwise (0.18 ms)."""
    n, M = keep.shape
    W = -(-M // 32)
    bits = jnp.pad(keep, ((0, 0), (0, W * 32 - M))).reshape(n, W, 32).astype(jnp.uint32)
    shift = jnp.arange(32, dtype=jnp.uint32)
    words = jnp.sum(bits << shift, axis=-1, dtype=jnp.uint32)            # the bits are distinct: a sum is an or
    per_word = lax.population_count(words).astype(jnp.int32)
    # the words' running count: a cumsum (a reduce-window as long as the row) for the grid's few words per row
    # (5 in 2-D, 14 in 3-D), a log-depth scan for long rows (an obstacle's row over every particle)
    total = jnp.cumsum(per_word, axis=1) if W <= 64 else lax.associative_scan(jnp.add, per_word, axis=1)
    before = total - per_word
    within = lax.population_count(words[:, :, None] & ((jnp.uint32(1) << shift) - jnp.uint32(1)))
    return (before[:, :, None] + within.astype(jnp.int32)).reshape(n, W * 32)[:, :M]


def computed_once(fn, args, witness=None):
    """``fn(*args)``, with its arguments and its results each computed once: inside a `lax.cond` whose predicate
    is always true (`witness`: an integer array whose first entry is >= -1, such as partners with -1 for none)
    but not known to XLA (an index clipped at 0 is known: XLA folds the test, and the conditional with it).
    XLA's CPU backend fuses an elementwise producer into every fusion that reads it, so a row update whose
    results feed a scatter, a subtraction and the multipliers' update was computed again in each of them; a
    conditional's operands and results are buffers of their own. With `witness` None, under `vmap` with a
    batched witness (the conditional then runs as a select), or where JAX's default backend is not the CPU (XLA's
    GPU backend has multi-output fusions, and a GPU conditional waits for its predicate on the host), it is
    ``fn(*args)`` as written. The same values and derivatives either way (docs/contacts.md: the disc box's step
    in 0.90 to 0.94 of the time)."""
    if witness is None or jax.default_backend() != "cpu":
        return fn(*args)
    zero = jax.eval_shape(fn, *args)
    return lax.cond(witness.reshape(-1)[0] >= -1, lambda a: fn(*a),
                    lambda a: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), zero), args)


def sort_rows(key):
    """Each row of key [n, M] (integers) sorted ascending, as ``jnp.sort(key, axis=1)``. Rows of up to 32
    entries (a grid's K slots) are sorted elementwise: each entry's rank is the number of entries below it, or
    equal to it and before it, and each place takes the entry of its rank. XLA's CPU sort of a [1024, 8] took
    about 100 us, this about 35; on the settled 1024-disc box's step 0.97x (the grid orders each step's
    candidates so, `grid._scan_order`; 0.98x at 4096 discs, docs/contacts.md)."""
    n, M = key.shape
    if M > 32:
        return jnp.sort(key, axis=1)
    at = np.arange(M)
    rank = sum(((key[:, t:t + 1] < key) | ((key[:, t:t + 1] == key) & (t < at))).astype(jnp.int32)
               for t in range(M))
    return sum(jnp.where(rank[:, s:s + 1] == at, key[:, s:s + 1], 0) for s in range(M)).astype(key.dtype)


def first_true(j, keep, K: int, fill: int = -1):
    """The first K entries of each row of j [n, M] where keep [n, M] (bool), in order, `fill` after the last:
    ([n, K] int32, each entry's rank among its row's kept entries [n, M] (`rank_true`))."""
    n = j.shape[0]
    rank = rank_true(keep)
    slot = jnp.where(keep & (rank < K), rank, K)
    out = jnp.full((n, K + 1), fill, jnp.int32).at[jnp.arange(n)[:, None], slot].set(j.astype(jnp.int32))
    return out[:, :K], rank


def safe_reciprocal(a):
    """1/a where a > 0, else 0 (and a zero derivative there)."""
    ok = a > 0
    return jnp.where(ok, 1 / jnp.where(ok, a, 1), 0)
