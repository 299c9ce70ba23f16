"""The neighbour grid (a model built with ``collide="grid"``, or ``collide=True`` above 256 particles): the
candidate pairs of a step from a spatial hash of the positions, kept in K slots per particle, the check that a
step's paths touched no unlisted pair, and merging two lists. No gradient flows through it: it only picks
indices (docs/contacts.md, "The neighbour grid")."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.contact import ContactSystem, ContactTopology, Reuse
from jaxcon.core.contact_rows import dot as _dot, magnitude as _magnitude, tolerance as _tolerance


# ---- the neighbour grid -----------------------------------------------------------------------------------------
#: The grid's candidate distance is (1 + GRID_SKIN) (r_i + r_j) + h |v_j - v_i|: every pair that can touch
#: within the step on straight paths, plus a skin for velocities that change during the solve.
GRID_SKIN = 0.25


#: A rollout's search also keeps the pairs within a wider distance, (1 + GRID_SKIN + GRID_REUSE_SKIN)(r_i + r_j)
#: + h |v_j - v_i| (a Verlet list), and later steps pick their candidates from that list instead of searching,
#: while it provably holds every candidate (`reused_search`). Wider: fewer searches while a pile moves, but
#: longer lists and wider cells (more bucket entries to scan, more overflow of the list). The 1024-disc box
#: took the list in 107, 158 and 207 of 240 steps with 0.1, 0.25 and 0.5, at the same cost within the host's
#: noise (docs/contacts.md, the neighbour grid).
GRID_REUSE_SKIN = 0.25


#: Entries of each neighbouring cell's bucket a particle scans, per slot: GRID_SCAN * K. A bucket holding more
#: counts its extra entries as overflow (they might have been candidates). At 1 a dense pack of equal discs
#: overflowed as soon as the cells grew with the relative speed (K = 8 discs per cell, a cell side of about
#: 1.4 diameters); at 2 a cell may be twice as wide.
GRID_SCAN = 2


_HASH = np.array([73856093, 19349663, 83492791], np.uint32)


def _cell_hash(c, table):
    """Bucket of integer cell coordinates c [dim, ...] in a table of `table` (a power of two) buckets."""
    h = jnp.zeros(c.shape[1:], jnp.uint32)
    for a in range(c.shape[0]):
        h = h ^ (c[a].astype(jnp.uint32) * jnp.uint32(_HASH[a]))
    return (h & jnp.uint32(table - 1)).astype(jnp.int32)


def neighbours(cs: ContactSystem, x, v, h):
    """Candidate pairs of a grid model at positions x and velocities v [dim, *view] for a step of length h:
    (partners [n, K] int32, internal indices, -1 for empty slots; overflow, int32 scalar).

    The particles are hashed into cells of side 2 (1 + GRID_SKIN) max(r) + 2 h max|v - mean(v)| (so every
    candidate of a particle lies in its own cell or one of the 3^dim - 1 around it), sorted by bucket, and each
    particle scans up to GRID_SCAN * K entries of each of those cells' buckets (`_scan`). A scanned j is kept
    if it is in that cell, j's user index is above i's (each pair once), they are not a skipped pair
    (`core.contact.joined_at_rest`: one rod, rope or constraint row, or touching at build within one piece), and
    |x_j - x_i| is below the candidate distance (1 + GRID_SKIN)(r_i + r_j) + h |v_j - v_i|; the first K are
    kept (`_select`). The overflow counts the candidates that found no slot plus the bucket entries beyond
    those scanned (those may or may not have been candidates: it is an upper bound, and 0 means no candidate
    was missed). No gradient flows through the search (it only picks indices). `grid_search` also returns
    the scan, and `common.grid_step` checks that the pairs of a step's actual paths were found."""
    return grid_search(cs, x, v, h)[0]


def _spread(vf):
    """max |v - mean(v)| of velocities vf [dim, n]: |v_j - v_i| <= 2 spread (relative to the mean velocity, a
    pile falling as one keeps small cells)."""
    d = vf - jnp.mean(vf, axis=1, keepdims=True)
    return jnp.sqrt(jnp.max(_dot(d, d)))


def _closer(xf, vf, r, h, skin):
    """close(jc) -> [n, M] bool: is particle jc [n, M] (-1 as 0) within (1 + skin)(r_i + r_j) + h |v_j - v_i| of
    each particle i, at positions xf and velocities vf [dim, n] (radii r [n])."""
    def close(jc):
        d, dv = xf[:, jc] - xf[:, :, None], vf[:, jc] - vf[:, :, None]
        cut = (1 + skin) * (r[:, None] + r[jc]) + h * jnp.sqrt(_dot(dv, dv))
        return jnp.sqrt(_dot(d, d)) < cut
    return close


def _flat(cs: ContactSystem, x, v):
    dim = x.shape[0]
    return (lax.stop_gradient(x.reshape(dim, -1)), lax.stop_gradient(v.reshape(dim, -1)),
            lax.stop_gradient(cs.radius_flat))


def grid_search(cs: ContactSystem, x, v, h):
    """`neighbours`, and its scan (`_scan`'s scanned entries j [n, M], bucket entries left unscanned [n], and
    the cell side), which `path_search` can pick from again."""
    xf, vf, r = _flat(cs, x, v)
    scan = _scan(cs.ct, xf, _reach(r, h, _spread(vf), GRID_SKIN))
    return _select(cs, scan, _closer(xf, vf, r, h, GRID_SKIN)), scan


def _reach(r, h, spread, skin):
    """The cell side for candidates within (1 + skin)(r_i + r_j) + h |v_j - v_i|: 2 (1 + skin) max(r) + 2 h s."""
    return 2 * (1 + skin) * jnp.max(r) + 2 * h * spread


def reused_search(cs: ContactSystem, x, v, h, prev: Reuse):
    """`grid_search` for a step of a rollout, which keeps a wider list across steps (a Verlet list):
    ((partners, overflow), reuse, reach), reach the usual cell side (`_reach`), at which `path_search` scans
    when it runs after this step (its `floor`).

    A search lists the pairs within (1 + GRID_SKIN + E)(r_i + r_j) + h |v_j - v_i| (E = GRID_REUSE_SKIN) with
    the positions it was made at, `reuse` (`core.contact.Reuse`). A later step takes its candidates (the pairs
    within the grid's usual distance, `neighbours`) from that list, without a search, while the list was
    complete and D + h s <= E min(r), where D is the largest displacement of a particle since the search (less
    a common offset, the middle of their range) and s the velocities' spread (`_spread`, |v_j - v_i| <= 2 s):
    a pair left out of the list was at least (1 + GRID_SKIN + E)(r_i + r_j) apart, has come at most 2 D closer,
    and its usual distance has grown by at most 2 h s, so it is no candidate now. Otherwise (and always under
    `vmap`, where the `lax.cond` runs both branches) it searches again. Where the wider list is incomplete
    (more than K candidates in a row, or bucket entries its wider cells left unscanned) the step's candidates
    come from the usual search (`grid_search`), as without a kept list. A step's candidates are put in the order
    the usual search gives them (`_scan_order`), so they are the same arrays, and the results the same, as
    with the usual search at every step."""
    xf, vf, r = _flat(cs, x, v)
    close = _closer(xf, vf, r, h, GRID_SKIN)
    spread = _spread(vf)
    reach = _reach(r, h, spread, GRID_SKIN)
    dev = xf - prev.anchor
    dev = dev - (jnp.max(dev, 1, keepdims=True) + jnp.min(dev, 1, keepdims=True)) / 2
    moved = jnp.sqrt(jnp.max(_dot(dev, dev)))
    reuse = prev.ok & (moved + h * spread <= GRID_REUSE_SKIN * jnp.min(r))

    def search(_):
        scan = _scan(cs.ct, xf, _reach(r, h, spread, GRID_SKIN + GRID_REUSE_SKIN))
        wide, over = _select(cs, scan, _closer(xf, vf, r, h, GRID_SKIN + GRID_REUSE_SKIN))
        found = lax.cond(over == 0, lambda _: _pick(wide, close),
                         lambda _: _select(cs, _scan(cs.ct, xf, reach), close), None)
        return found, Reuse(wide, xf, over == 0)

    (partners, overflow), reuse = lax.cond(reuse, lambda _: (_pick(prev.partners, close), prev), search, None)
    return (_scan_order(partners, xf, reach), overflow), reuse, reach


def _scan_order(partners, xf, reach):
    """Each row of partners [n, K] in the order `grid_search` lists them: by the offset of the partner's cell
    (cells of side `reach`, `_scan`'s) in `itertools.product((-1, 0, 1), repeat=dim)` order, then by index
    (a bucket's entries are sorted stably). The order is the sweep's (slot by slot, Gauss-Seidel between
    slots), and it matters for a pile's coming to rest: the 2048-, 3072- and 4096-disc boxes with
    PGS(10, substeps=2) moved at 0.007, 0.012 and 0.033 m/s at 8 s in this order, 0.052, 0.048 and 0.080 with
    each row sorted by index (float32, 2026-11-25)."""
    n, dim = partners.shape[0], xf.shape[0]
    c = _cells(xf, reach)
    jc = jnp.maximum(partners, 0)
    off = c[:, jc] - c[:, :, None] + 1                                              # [dim, n, K], 0 to 2
    key = sum(off[a] * 3 ** (dim - 1 - a) for a in range(dim)) * n + jc
    end = 3 ** dim * n
    key = L.sort_rows(jnp.where(partners >= 0, jnp.clip(key, 0, end - 1), end))
    return jnp.where(key < end, key % n, -1).astype(jnp.int32)


def _pick(partners, close):
    """The entries of a candidate list partners [n, K] that `close` keeps, in order, first: (partners [n, K],
    overflow 0)."""
    keep = (partners >= 0) & close(jnp.maximum(partners, 0))
    out, _ = _compact(partners, keep, partners.shape[1])
    return out, jnp.zeros((), jnp.int32)


def _compact(j, keep, K):
    """The first K entries of each row of j [n, M] where keep [n, M]: ([n, K], -1 after the last; the number of
    kept entries beyond K, int32 scalar)."""
    out, _ = L.first_true(j, keep, K)
    return out, jnp.sum(jnp.maximum(jnp.sum(keep, 1) - K, 0)).astype(jnp.int32)


def _cells(xf, reach):
    """Integer cell coordinates [dim, n] of particles xf [dim, n] in cells of side `reach` (a little more)."""
    cell = jnp.maximum(reach, jnp.finfo(xf.dtype).tiny) * (1 + 1e-6)
    big = 2 ** 28                                                  # cell coordinates stay far from int32's end
    return jnp.clip(jnp.floor(xf / cell), -big, big).astype(jnp.int32)


def _scan(ct: ContactTopology, xf, reach):
    """Hash particles xf [dim, n] into cells of side `reach` and list, per particle, up to GRID_SCAN * K
    entries of its own and each surrounding cell's bucket: (j [n, 3^dim GRID_SCAN K], -1 where none, the
    bucket entries beyond those scanned [n], reach)."""
    K, table = ct.grid_k, ct.grid_table
    scan = GRID_SCAN * K
    dim, n = xf.shape
    c = _cells(xf, reach)
    key = _cell_hash(c, table)
    order = jnp.argsort(key)
    count = jnp.zeros((table,), jnp.int32).at[key].add(1)
    # each bucket's first position in the sorted order (a scatter-min: XLA CPU's cumsum of the counts is a
    # reduce-window as long as the table, 0.13 ms at 8192 buckets)
    start = jnp.full((table,), n, jnp.int32).at[key[order]].min(jnp.arange(n, dtype=jnp.int32))
    # A bucket's entries are consecutive in the sorted order: each particle reads `scan` of them as one slice
    # (a gather of windows, not of scan single entries), from the sorted indices and cell coordinates padded
    # with `scan` entries past the end (an empty bucket starts at n).
    sorted_j = jnp.concatenate([order.astype(jnp.int32), jnp.full((scan,), -1, jnp.int32)])
    sorted_c = jnp.concatenate([c[:, order], jnp.zeros((dim, scan), jnp.int32)], 1)
    window = jax.vmap(lambda lo: (lax.dynamic_slice(sorted_j, (lo,), (scan,)),
                                  lax.dynamic_slice(sorted_c, (jnp.zeros_like(lo), lo), (dim, scan))))
    # one offset at a time: gathering every surrounding cell at once ([3^dim, n, scan]) cut a grid gradient's
    # program by a fifth but ran the search 1.4x (1024 discs) to 2x (4096) slower, measured 2026-11-25
    cands, missed = [], jnp.zeros((n,), jnp.int32)
    for off in itertools.product((-1, 0, 1), repeat=dim):
        qc = c + jnp.asarray(off, jnp.int32)[:, None]
        qk = _cell_hash(qc, table)
        j, cj = window(start[qk])                                    # [n, scan], [n, dim, scan]
        size = count[qk]
        ok = (jnp.arange(scan)[None] < size[:, None]) & jnp.all(cj == qc.T[:, :, None], axis=1)
        cands.append(jnp.where(ok, j, -1))
        missed = missed + jnp.maximum(size - scan, 0).astype(jnp.int32)
    return jnp.concatenate(cands, 1), missed, reach


def _select(cs: ContactSystem, scan, close):
    """The first K scanned entries (`_scan`) j of each particle i with a higher user index, not skipped
    (`joined_at_rest`), and `close(jc)` [n, M] (jc the entries, -1 as 0): (partners [n, K], overflow: the entries
    kept beyond K plus the bucket entries left unscanned)."""
    ct = cs.ct
    K, (j, missed, _) = ct.grid_k, scan
    uid = jnp.asarray(ct.grid_uid.array)
    excl = jnp.asarray(ct.grid_exclude.array)
    jc = jnp.maximum(j, 0)
    keep = (j >= 0) & (uid[jc] > uid[:, None]) & close(jc)
    keep = keep & ~jnp.any(jc[:, :, None] == excl[:, None, :], axis=-1)
    out, extra = _compact(j, keep, K)
    return out, extra + jnp.sum(missed).astype(jnp.int32)


def path_search(cs: ContactSystem, x, x_end, h, scan, margin=None, floor=None):
    """The pairs that touch on the way from x to x_end [dim, *view] (each particle on the straight line between
    them: the nearest the pair comes is below r_i + r_j, less rounding; with `margin` [n], a per-particle
    widening, below r_i + r_j + margin_i + margin_j), as `neighbours` lists them (partners [n, K], overflow).
    The earlier search's `scan` is used again where its cells are wide enough for these displacements, else the
    particles are scanned again (`lax.cond`); with `scan` None (a step of `reused_search`) they are scanned in
    cells of the larger of the side these displacements need and `floor`, the step's usual side (so the scan
    is the one `grid_search` would have made and left for this check, where its cells were wide enough)."""
    dim = x.shape[0]
    xf, xe = (lax.stop_gradient(a.reshape(dim, -1)) for a in (x, x_end))
    r = lax.stop_gradient(cs.radius_flat)
    if margin is not None:
        r = r + lax.stop_gradient(margin)
    reach = _reach(r, 1, _spread(xe - xf), GRID_SKIN)           # the spread of whole displacements: h = 1
    if scan is None:
        scan = _scan(cs.ct, xf, jnp.maximum(reach, floor))
    else:
        scan = lax.cond(reach <= scan[2], lambda _: scan, lambda _: _scan(cs.ct, xf, reach), None)

    def close(jc):
        d0 = xf[:, jc] - xf[:, :, None]
        e = (xe[:, jc] - xe[:, :, None]) - d0
        s = jnp.clip(-_dot(d0, e) * L.safe_reciprocal(_dot(e, e)), 0, 1)
        closest = jnp.sqrt(_dot(d0 + s * e, d0 + s * e))
        R = r[:, None] + r[jc]
        return closest < R - _tolerance(_magnitude(xf[:, jc]) + _magnitude(xf)[:, None] + R)

    return _select(cs, scan, close)


def merge_partners(a, b):
    """The partners [n, K] of `a` followed by those of `b` that `a` lacks, the first K of each row (a pair
    sits in the row of its lower-numbered particle in both): (partners, how many did not fit, int32)."""
    K = a.shape[1]
    both = jnp.concatenate([a, jnp.where(jnp.any(b[:, :, None] == a[:, None, :], -1), -1, b)], 1)
    return _compact(both, both >= 0, K)


def unsolved(touching, solved):
    """How many pairs of `touching` [n, K] (`path_search`) are not in `solved` [n, K]: int32 scalar (a pair sits
    in the row of its lower-numbered particle in both)."""
    new = (touching >= 0) & ~jnp.any(touching[:, :, None] == solved[:, None, :], -1)
    return jnp.sum(new).astype(jnp.int32)
