"""The contact kind (docs/contacts.md): its rows as unilateral velocity constraints with friction, their update
in every solver that takes contacts (Gauss-Seidel `sweep`, SoftStep's `soft_rows`, Jacobi's `jacobi_pass`, the
position-level `position_pass` of XPBD), warm start, time of impact, the neighbour grid's search and the position
safety pass.

Each contact has a unit normal n (from the obstacle, or from the pair's first particle, towards the particle
that is pushed), a gap C (< 0: overlap) and an accumulated normal impulse lam_n >= 0 with a friction impulse
lam_t in the tangent plane, |lam_t| <= mu lam_n. Per (sub)step of length h, with vn the approach velocity
measured before the solve (after gravity):

* Speculative contact (Box2D): a separated contact (C > 0) that does not close within the step only asks
  vn' >= -C / h: it may close the gap, never more, so nothing tunnels.
* Impact: a separated contact that would close within the step (C + h vn < 0) hits at time of impact
  toi = C / -vn. Its target is the bounce velocity e u (0 when the impact speed u is below
  `restitution_threshold`) plus what the external forces add after the impact (`_targets`), and after
  the solve the positions are corrected as if the impulse had acted at toi instead of at the start of the
  step: x += -toi * (velocity change from that contact's impulse) (DiffTaichi's time-of-impact correction).
  This makes positions and their gradients those of an impact at the right time: an elastic ball dropped on
  the ground has d y_T / d y_0 = -1 instead of +1.
* Touching or overlapping (C <= 0): vn' >= max(bounce, -beta C / h) (Baumgarte push-out of the overlap).

Friction is solved after each contact's normal row, as a 2-D or 3-D vector clamped to the Coulomb disc.

Neighbour grid (a model built with ``collide="grid"``, or ``collide=True`` above 256 particles; one search per
step, shared by its substeps, `common.grid_substepped`): the pairs are
found at the start of every step by `neighbours` (a spatial hash of the positions) and kept in K slots per
particle; their rows are those above, with `Rows.i`/`Rows.j` [n, K] naming the particles (j = -1: empty slot,
k = 0). A PGS sweep solves them after the obstacles slot by slot, the rows of one slot together with mass
splitting (`grid_pass`); the position safety pass projects them the same way, and the warm start matches last
step's impulses by partner (a slot's impulse is carried over only if the same pair is listed again).
`Impulses.partners` [n, K] and `Impulses.overflow` (the candidates that did not fit) travel with the impulses.
The time-of-impact correction applies to grid pairs as to listed ones. After the solve, `common.grid_step`
checks that no unlisted pair touched on the paths the solve gave (`path_search`, `unsolved`), solving the
step again with those pairs if one did.

Start overlaps (a particle inside an obstacle or another particle) are pushed out at no more than
`PUSH_OUT_SPEED`, along `direction` (the last axis where the centres coincide). Gaps within rounding of 0
(`_gap`) are classified the same way by every program that computes them, so that forward and reverse mode
agree. `ContactSystem.from_model` makes every leaf NaN when one holds a value `Model` refuses.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import itertools

import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.contact import (  # noqa: F401  (the contact data types the solvers use, re-exported here)
    ContactSystem,
    ContactTopology,
    Impulses,
    zero_impulses,
)

Array = Any


class Rows(NamedTuple):
    """Contact rows of one (sub)step: normal n, target velocity `target`, effective mass k, inverse-mass sum
    winv, time of impact `toi` (0 unless an impact happens within the step), gap, and `target_c`: the target
    without restitution (the compression phase; None for solvers that do not split the solve). Grid pair rows
    also carry their particles i, j [n, K] (internal indices, j = -1 for an empty slot); None otherwise. `near`:
    touching or within rounding of it (an impact of such a contact is one of a touching contact, `_gap`).
    `warm`: the rows the warm start applies last step's impulse to (touching, an impact, or a pair within the
    solver's slop of touching)."""

    n: Array
    target: Array
    k: Array
    winv: Array
    toi: Array
    gap: Array
    target_c: Array = None
    i: Array = None
    j: Array = None
    near: Array = None
    warm: Array = None


def _dot(a, b):
    """Sum of a * b over the leading (dim) axis, written out component by component (`layout.dot0`). On XLA's
    CPU backend `jnp.sum(a * b, 0)` of gathered operands ([dim, n, M] from x[:, j]) becomes a reduction kernel
    that gathers again for every element: the grid search's distance test of the 1024-disc box took 6.5 ms
    that way and 0.26 ms written out."""
    return L.dot0(a, b)


def _length(d):
    """`layout.safe_length` with `_dot`: (length, 1 / length) along the leading axis, both 0 at zero length."""
    d2 = _dot(d, d)
    ok = d2 > L.min_length2(d.dtype)
    inv = jnp.where(ok, lax.rsqrt(jnp.where(ok, d2, 1)), 0)
    return d2 * inv, inv


def _norm(d):
    """`layout.safe_norm` along the leading axis with `_dot`: (length, unit direction, 0 at zero length)."""
    dist, inv = _length(d)
    return dist, d * inv


def direction(d):
    """(length [...], unit direction [dim, ...]) of contact vectors d [dim, ...] (from the first body to the
    second) as `layout.safe_norm`, except that where d is 0 (coincident centres: a particle started at a
    sphere's centre, or on another particle) the direction is +e_last, the last axis (y in 2-D, z in 3-D: up
    for the default gravity), so that the overlap is still pushed out: the second body upwards. Its derivative
    there is 0."""
    dist, n = _norm(d)
    up = jnp.zeros((d.shape[0],) + (1,) * (d.ndim - 1), d.dtype).at[-1].set(1)
    return dist, jnp.where(dist > 0, n, up)


def overlap_normal(d0, d, R):
    """(unit normal, gap) of contacts at distance vectors d [dim, ...] (touching at |d| = R) for a position
    level solver (XPBD) whose contacts also had d0 at the start of the substep: the normal of d
    (`direction`), except for a contact that already overlapped at the start (a particle started inside a
    sphere or another particle), which keeps the start's normal and the gap along it, n0 . d - R, so that it
    leaves by the nearest surface of where it was (upwards from the exact centre), not by the side that
    gravity's prediction happened to move it towards."""
    dist0, n0 = direction(d0)
    dist, n = direction(d)
    deep = dist0 - R < -_tolerance(_magnitude(d0) + R)
    return jnp.where(deep, n0, n), jnp.where(deep, _dot(n0, d), dist) - R


# ---- the neighbour grid -----------------------------------------------------------------------------------------
#: The grid's candidate distance is (1 + GRID_SKIN) (r_i + r_j) + h |v_j - v_i|: every pair that can touch
#: within the step on straight paths, plus a skin for velocities that change during the solve.
GRID_SKIN = 0.25

#: Entries of each neighbouring cell's bucket a particle scans, per slot: GRID_SCAN * K. A bucket holding more
#: counts its extra entries as overflow (they might have been candidates). At 1 a dense pack of equal discs
#: overflowed as soon as the cells grew with the relative speed (K = 8 discs per cell, a cell side of about
#: 1.4 diameters); at 2 a cell may be twice as wide.
GRID_SCAN = 2

#: PGS's position safety passes for a grid model. Its slot-by-slot passes converge more slowly than the rounds'
#: Gauss-Seidel ones: on 18 discs in 4 staggered rows landing on a floor (PGS(10), dt 1/120) the deepest overlap
#: was 0.86% of a diameter with 8 passes, 0.30% with 16 and 0.12% with 32 (all pairs: 0.03% with 8); a pass
#: costs K small steps over n particles, against n - 1 rounds for all pairs. `PGS(contact_passes=k)` overrides
#: it: with substeps, the passes' lifts kept a deep pile flowing, and one pass lets it rest (docs/contacts.md).
GRID_OVERLAP_PASSES = 32

#: A grid model's position passes stop after one that moved no particle by more than this fraction of the slop
#: times the smallest radius (`project_overlaps`). Measured on the 1024-disc box (docs/contacts.md): 0.1 with
#: the push-out beyond two slops (`PUSH_SLOPS`) rests by 5 s at 12 ms per step; 0.1 with the push-out beyond one
#: slop did not rest in 8 s (1.1 m/s); 0.001 rested at 28 ms per step (most steps ran all 32 passes). With the
#: push-out beyond six slops, 0.5 and 1.0 saved no time (6.5 and 6.6 ms per step against 6.4) and left deeper
#: overlaps (3.9% and 4.5% of R at 8 s against 1.9%).
GRID_PASS_STOP = 0.1

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


def grid_search(cs: ContactSystem, x, v, h):
    """`neighbours`, and its scan (`_scan`'s scanned entries j [n, M], bucket entries left unscanned [n], and
    the cell side), which `path_search` can pick from again."""
    dim = x.shape[0]
    xf = lax.stop_gradient(x.reshape(dim, -1))
    vf = lax.stop_gradient(v.reshape(dim, -1))
    r = lax.stop_gradient(cs.radius_flat)
    reach = 2 * (1 + GRID_SKIN) * jnp.max(r) + 2 * h * _spread(vf)
    scan = _scan(cs.ct, xf, reach)

    def close(jc):              # within the candidate distance (1 + GRID_SKIN)(r_i + r_j) + h |v_j - v_i|
        d, dv = xf[:, jc] - xf[:, :, None], vf[:, jc] - vf[:, :, None]
        cut = (1 + GRID_SKIN) * (r[:, None] + r[jc]) + h * jnp.sqrt(_dot(dv, dv))
        return jnp.sqrt(_dot(d, d)) < cut

    return _select(cs, scan, close), scan


def _scan(ct: ContactTopology, xf, reach):
    """Hash particles xf [dim, n] into cells of side `reach` and list, per particle, up to GRID_SCAN * K
    entries of its own and each surrounding cell's bucket: (j [n, 3^dim GRID_SCAN K], -1 where none, the
    bucket entries beyond those scanned [n], reach)."""
    K, table = ct.grid_k, ct.grid_table
    scan = GRID_SCAN * K
    dim, n = xf.shape
    cell = jnp.maximum(reach, jnp.finfo(xf.dtype).tiny) * (1 + 1e-6)
    big = 2 ** 28                                                  # cell coordinates stay far from int32's end
    c = jnp.clip(jnp.floor(xf / cell), -big, big).astype(jnp.int32)
    key = _cell_hash(c, table)
    order = jnp.argsort(key)
    count = jnp.zeros((table,), jnp.int32).at[key].add(1)
    start = jnp.cumsum(count) - count                 # each bucket's first position in the sorted order
    # one offset at a time: gathering every surrounding cell at once ([3^dim, n, scan]) cut a grid gradient's
    # program by a fifth but ran the search 1.4x (1024 discs) to 2x (4096) slower, measured 2026-11-25
    cands, missed = [], jnp.zeros((n,), jnp.int32)
    for off in itertools.product((-1, 0, 1), repeat=dim):
        qc = c + jnp.asarray(off, jnp.int32)[:, None]
        qk = _cell_hash(qc, table)
        lo = start[qk]
        hi = lo + count[qk]
        idx = lo[:, None] + jnp.arange(scan)[None]                   # [n, scan] positions in the sorted order
        j = order[jnp.minimum(idx, n - 1)]
        ok = (idx < hi[:, None]) & jnp.all(c[:, j] == qc[:, :, None], axis=0)
        cands.append(jnp.where(ok, j, -1))
        missed = missed + jnp.maximum(hi - lo - scan, 0).astype(jnp.int32)
    return jnp.concatenate(cands, 1), missed, reach


def _select(cs: ContactSystem, scan, close):
    """The first K scanned entries (`_scan`) j of each particle i with a higher user index, not skipped
    (`joined_at_rest`), and `close(jc)` [n, M] (jc the entries, -1 as 0): (partners [n, K], overflow: the entries
    kept beyond K plus the bucket entries left unscanned)."""
    ct = cs.ct
    K, (j, missed, _) = ct.grid_k, scan
    n = j.shape[0]
    uid = jnp.asarray(ct.grid_uid.array)
    excl = jnp.asarray(ct.grid_exclude.array)
    jc = jnp.maximum(j, 0)
    keep = (j >= 0) & (uid[jc] > uid[:, None]) & close(jc)
    keep = keep & ~jnp.any(jc[:, :, None] == excl[:, None, :], axis=-1)
    rank = jnp.cumsum(keep, axis=1) - 1
    count = jnp.sum(keep, axis=1)
    slot = jnp.where(keep & (rank < K), rank, K)
    out = jnp.full((n, K + 1), -1, jnp.int32).at[jnp.arange(n)[:, None], slot].set(j.astype(jnp.int32))
    overflow = jnp.sum(jnp.maximum(count - K, 0) + missed).astype(jnp.int32)
    return out[:, :K], overflow


def path_search(cs: ContactSystem, x, x_end, h, scan, margin=None):
    """The pairs that touch on the way from x to x_end [dim, *view] (each particle on the straight line between
    them: the nearest the pair comes is below r_i + r_j, less rounding; with `margin` [n], a per-particle
    widening, below r_i + r_j + margin_i + margin_j), as `neighbours` lists them (partners [n, K], overflow).
    The earlier search's `scan` is used again where its cells are wide enough for these displacements, else the
    particles are scanned again (`lax.cond`)."""
    dim = x.shape[0]
    xf, xe = (lax.stop_gradient(a.reshape(dim, -1)) for a in (x, x_end))
    r = lax.stop_gradient(cs.radius_flat)
    if margin is not None:
        r = r + lax.stop_gradient(margin)
    reach = 2 * (1 + GRID_SKIN) * jnp.max(r) + 2 * _spread(xe - xf)
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
    n, K = a.shape
    both = jnp.concatenate([a, jnp.where(jnp.any(b[:, :, None] == a[:, None, :], -1), -1, b)], 1)
    keep = both >= 0
    rank = jnp.cumsum(keep, axis=1) - 1
    slot = jnp.where(keep & (rank < K), rank, K)
    out = jnp.full((n, K + 1), -1, jnp.int32).at[jnp.arange(n)[:, None], slot].set(both)
    return out[:, :K], jnp.sum(jnp.maximum(jnp.sum(keep, 1) - K, 0)).astype(jnp.int32)


def unsolved(touching, solved):
    """How many pairs of `touching` [n, K] (`path_search`) are not in `solved` [n, K]: int32 scalar (a pair sits
    in the row of its lower-numbered particle in both)."""
    new = (touching >= 0) & ~jnp.any(touching[:, :, None] == solved[:, None, :], -1)
    return jnp.sum(new).astype(jnp.int32)


def pair_slots(ct: ContactTopology, n: int, partners=None):
    """The pair contacts' particles: (ia, ja, valid, index). Listed pairs: the static rounds (ct.i, ct.j
    [R, S]), their `valid` mask, index None. A grid model's `partners` [n, K]: ia each slot's particle, ja its
    partner (0 for an empty slot), valid the slots in use, index the flat (ia, ja) (`pair_index`)."""
    if partners is None:
        return ct.i.array, ct.j.array, ct.valid.array, None
    ia = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], partners.shape)
    ja = jnp.maximum(partners, 0)
    return ia, ja, partners >= 0, (ia.reshape(-1), ja.reshape(-1))


def pair_index(ct: ContactTopology, pairs: Rows):
    """The pair rows' particles, flat: (i, j) [P] internal indices (grid rows: empty slots point at 0 and have
    k = 0)."""
    if pairs is not None and pairs.i is not None:
        return pairs.i.reshape(-1), jnp.maximum(pairs.j, 0).reshape(-1)
    return ct.i.array.reshape(-1), ct.j.array.reshape(-1)


# ---- rows ------------------------------------------------------------------------------------------------------
#: Gaps within ROUNDING * eps * (the size of the coordinates they come from) of 0 count as touching (`_gap`).
ROUNDING = 64

#: The fastest a touching contact's Baumgarte term pushes an overlap out (m/s), Box2D's
#: `contactPushMaxVelocity` (b2_contactPushMaxVelocity, 3 m/s). Without it a particle that starts deep inside
#: an obstacle leaves at beta C / h: 0.2 * 0.8 m at h = 1/240 s is 38 m/s, and the position pass then removes
#: the overlap, so nothing takes that velocity back (a particle started 0.3 R off a 1 m sphere's centre
#: reached z = 58 m after 2 s with PGS(10, substeps=4)).
PUSH_OUT_SPEED = 3.0

#: PGS's default contact slop (`PGS.contact_slop`), a fraction of the contact distance (r_i + r_j for a pair, r
#: for an obstacle): Box2D's linear slop (b2_linearSlop, 5 mm for bodies of about a metre). Overlaps up to the
#: slop are left to the contact: the Baumgarte term pushes out only the overlap beyond `PUSH_SLOPS` of it, the
#: position safety pass projects onto it (not onto C = 0), and a pair whose gap is within it either way is
#: warm-started. Without
#: it a pile never rests (docs/contacts.md, piles at rest): the position pass left resting contacts at C = 0,
#: within rounding of touching, so that the next step took 40% of the disc box's pushing pairs as separated and
#: solved them cold (no warm start, hence no friction either), while the Baumgarte term pushed every overlap
#: out at velocity level that the position pass removed as well.
CONTACT_SLOP = 0.005

#: The Baumgarte term of a touching contact pushes out only the overlap beyond PUSH_SLOPS slops, while the position
#: pass projects onto one slop: the position pass removes overlap without making velocity, and what it leaves
#: (within its stopping tolerance, `GRID_PASS_STOP`, or in a column too tall for its passes) is turned into
#: velocity only beyond PUSH_SLOPS. Both removing the same overlap kept piles moving (docs/contacts.md, piles at
#: rest): beyond one slop the 1024-disc box moved at 1.1 m/s; beyond two the 4096-disc box still flowed at 2.3 m/s
#: after 8 s, 97% of its discs faster than 0.05 m/s; beyond six it comes to rest (0.03 m/s at 8 s with 2 substeps).
PUSH_SLOPS = 6.0


def _targets(C, C_spec, vn0, vn1, impact, toi, cs: ContactSystem, beta, h, slop=0.0):
    """Target velocity of contacts with gap C (`_gap`: > 0 separated, <= 0 touching), normal velocity vn0 at
    the start of the step and vn1 after the external forces, and an impact at `toi` where `impact` (module
    docstring; a contact within rounding of touching, C = 0, may be an impact at toi ~ 0).

    Within an impact step the approach velocity is taken to change linearly, vn0 + (vn1 - vn0) t / h, so the
    impact speed u depends on the time of impact, and the forces keep acting for the rest of the step after the
    bounce: target = max(e u + (vn1 - vn0) (h - toi) / h, 0). This keeps the map from one state to the next
    continuous where the impact moves from one step to the next (at toi = h and toi = 0 both sides give the
    same state), and gives the time-of-impact dependence of u its right derivative (du/dC = a / |vn1|).
    A separated contact that is not an impact gets the speculative target -C_spec / h, C_spec its gap along
    the row's normal. A touching one pushes its overlap beyond `slop` (m) out at -beta (C + slop) / h, at most
    `PUSH_OUT_SPEED`.
    Returns (target, target without restitution)."""
    dv = vn1 - vn0
    u = -(vn0 + dv * toi / h)
    bounce = jnp.where(u > cs.threshold, cs.restitution * u, 0)
    rest = dv * (h - toi) / h
    push = jnp.minimum(-beta * jnp.minimum(C + slop, 0) / h, PUSH_OUT_SPEED)

    def target(after):
        return jnp.where(impact, after, jnp.where(C > 0, -C_spec / h, jnp.maximum(after, push)))

    return target(jnp.maximum(bounce + rest, 0)), target(jnp.maximum(rest, 0))


def _tolerance(scale):
    """Rounding tolerance of a gap computed from numbers of size `scale`: `ROUNDING` eps scale (`_gap`)."""
    return ROUNDING * jnp.finfo(scale.dtype).eps * scale


def _gap(C, tol):
    """The gap a row uses: C + tol (`_tolerance`), so that a contact touches (gap <= 0) only once it overlaps
    by more than rounding.

    The position pass leaves the contacts it corrects at C = 0 up to rounding, so that the next step's C is
    +-1e-17 (float64). Whether such a contact is separated or touching (warm-started, its Baumgarte term
    active), and whether an approaching one is an impact at toi = C / |vn| (whose derivative, 1 / |vn|, the
    touching branch does not have) would be decided by the rounding of the program that computes it, and the
    forward-mode and reverse-mode programs round differently: the drape's jax.grad was 2% off jax.jacfwd.
    Within the tolerance a contact is separated whatever the sign of its rounding: speculative, or an impact
    at toi ~ tol / |vn| if it approaches (`_swept`)."""
    return C + tol


def _swept(d, u, R, h, tol):
    """Contact of two spheres (or a sphere and a point) whose centres are `d` apart ([dim, ...], from the first
    to the second) and move apart at the constant relative velocity `u` over the step, touching at distance R.

    Returns (n, C, C_n, hit, impact, toi): C = |d| - R; `hit` where the straight-line paths come within R - tol
    inside the step (`_gap`'s tolerance: a contact left at C = 0 +- rounding by the position pass that
    approaches is an impact at toi ~ tol / speed, whatever the sign of its rounding), at time toi (the smaller
    root of |d + t u| = R - tol, in a cancellation-free form); n the unit normal at the time of impact where
    `hit`, else at the start (`direction`: the last axis where d = 0), and C_n = n . d - R the gap along it.
    `impact` starts equal to `hit` (`_first_impacts` may clear it). Using the normal at impact, not a
    linearised gap along the start normal, is what catches glancing impacts of balls that move several
    diameters per step."""
    dist, n0 = direction(d)
    C = dist - R
    Ci, Ri = _gap(C, tol), R - tol
    uu = _dot(u, u)
    du = _dot(d, u)
    disc = du * du - uu * (Ci * (dist + Ri))
    hit = (Ci > 0) & (du < 0) & (disc > 0)
    root = jnp.sqrt(jnp.where(hit, disc, 1))
    t = Ci * (dist + Ri) / jnp.where(hit, root - du, 1)
    hit = hit & (t < h)
    toi = jnp.where(hit, t, 0)
    _, n_hit = _norm(d + toi * u)
    n = jnp.where(hit, n_hit, n0)
    return n, C, _dot(n, d) - R, hit, hit, toi


def _magnitude(a):
    """Sum of |a| over the leading (dim) axis: the size of the coordinates a gap is computed from."""
    return jnp.sum(jnp.abs(a), 0)


def _obstacle_geometry(cs: ContactSystem, x, v, h):
    """(n [Q, dim, *view], C, C_n, hit, impact, toi, tol [Q, *view]) of every particle against every plane,
    then every sphere, for particles moving at `v` over the step; tol is `_gap`'s rounding tolerance."""
    ct, dim, nview = cs.ct, x.shape[0], x.ndim - 1
    out = []
    r = cs.radius[0]
    size = _magnitude(x) + r
    for p in range(ct.n_planes):
        nrm = jnp.broadcast_to(cs.plane_normal[p].reshape((dim,) + (1,) * nview), x.shape)
        C = jnp.sum(nrm * x, 0) - cs.plane_offset[p] - r
        tol = _tolerance(size + jnp.abs(cs.plane_offset[p]))
        vn = jnp.sum(nrm * v, 0)
        Ci = _gap(C, tol)                  # as in `_swept`: the impact is when the gap reaches -tol
        impact = (Ci > 0) & (Ci + h * vn < 0)
        out.append((nrm, C, C, impact, impact, jnp.where(impact, Ci / jnp.where(impact, -vn, 1), 0), tol))
    for s in range(ct.n_spheres):
        c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
        R = cs.sphere_radius[s] + r
        tol = _tolerance(size + _magnitude(c) + R)
        out.append(_swept(x - c, v, R, h, tol) + (tol,))
    return tuple(jnp.stack(a) for a in zip(*out))


def _first_impacts(ct, obs, pairs, n_particles, index=None):
    """Keep an impact only if it is the first, within the step, of each particle it involves: a ball that hits
    another cannot also hit, on its unobstructed path, the ball behind it or the cushion beyond. The later
    ones stay speculative contacts along their normal at impact (no bounce, no time of impact). `obs`/`pairs`:
    (n, C, C_n, hit, impact, toi, tol) or None. Returns them with `impact` updated. An impact of a contact that
    already touches (C <= tol, `_swept`) is a touching contact, given its time of impact only for its
    derivative: it is always kept, and it hides no other impact."""
    inf = jnp.inf

    def real(g):
        return g[3] & (g[1] > g[6])

    ref = (obs if obs is not None else pairs)[5]
    first = jnp.full((n_particles,), inf, ref.dtype)
    if obs is not None:
        first = jnp.min(jnp.where(real(obs), obs[5], inf).reshape(obs[5].shape[0], -1), axis=0)
    if pairs is not None:
        ia, ja = (ct.i.array.reshape(-1), ct.j.array.reshape(-1)) if index is None else index
        t = jnp.where(real(pairs), pairs[5], inf).reshape(-1)
        first = first.at[ia].min(t).at[ja].min(t)
        keep = ((t <= first[ia]) & (t <= first[ja])).reshape(pairs[3].shape)
        pairs = pairs[:4] + (pairs[3] & (keep | ~real(pairs)),) + pairs[5:]
    if obs is not None:
        keep = obs[5] <= first.reshape((1,) + obs[5].shape[1:])
        obs = obs[:4] + (obs[3] & (keep | ~real(obs)),) + obs[5:]
    return obs, pairs


def rows(cs: ContactSystem, w, x, v0, v, beta, h, partners=None, slop=0.0):
    """Contact rows at the start of a (sub)step: (obstacle Rows or None, pair Rows or None). `v0` is the
    velocity at the start of the step, `v` after the external forces and before any impulse. A grid model
    passes its `partners` [n, K] (from `neighbours`). `slop`: the solver's contact slop, a fraction of the
    contact distance (`CONTACT_SLOP`; 0: none)."""
    ct, dim = cs.ct, x.shape[0]
    xf, vf, v0f, wf = x.reshape(dim, -1), v.reshape(dim, -1), v0.reshape(dim, -1), w.reshape(-1)
    obs = _obstacle_geometry(cs, x, v, h) if ct.n_obstacles else None
    pairs, index = None, None
    if ct.n_pairs or ct.has_grid:
        ia, ja, valid, index = pair_slots(ct, xf.shape[1], partners)
        xi, xj, R = xf[:, ia], xf[:, ja], cs.radius_flat[ia] + cs.radius_flat[ja]
        tol = _tolerance(_magnitude(xi) + _magnitude(xj) + R)
        pairs = _swept(xj - xi, vf[:, ja] - vf[:, ia], R, h, tol)
        live = jnp.asarray(valid)          # a padding or empty slot is no impact (it would hide a real one)
        pairs = pairs[:3] + (pairs[3] & live, pairs[4] & live, pairs[5], tol)
    obs, pairs = _first_impacts(ct, obs, pairs, xf.shape[1], index)

    def finish(geometry, vn0, vn1, winv, k, distance, window):
        n, C, C_n, _, impact, toi, tol = geometry
        toi = jnp.where(impact, toi, 0)
        gap = _gap(C, tol)
        s = slop * distance
        target, target_c = _targets(gap, C_n, vn0, vn1, impact, toi, cs, beta, h, PUSH_SLOPS * s)
        # Warm-started: touching, impacts, and pairs within the slop of touching either way (a disc of a pile that
        # lifts off its neighbour by less than the slop keeps the impulse it leant on it with; measured in
        # docs/contacts.md). Obstacles keep gap <= 0: warm-starting those within the slop as well brought the pile
        # to rest sooner (0.003 against 0.018 m/s at 8 s) but the float32 drape's gradients 1.9% off float64.
        warm = impact | (gap <= (s if window else 0))
        return Rows(n, target, k, winv, toi, gap, target_c, near=C <= tol, warm=warm)

    if obs is not None:
        n = obs[0]
        winv = jnp.broadcast_to(w[0], obs[1].shape)
        obs = finish(obs, jnp.sum(n * v0[None], 1), jnp.sum(n * v[None], 1), winv, L.safe_reciprocal(winv),
                     cs.radius, False)
    if pairs is not None:
        n = pairs[0]
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype)
        vn0, vn1 = (_dot(n, a[:, ja] - a[:, ia]) for a in (v0f, vf))
        pairs = finish(pairs, vn0, vn1, winv, k, cs.radius_flat[ia] + cs.radius_flat[ja], True)
        if index is not None:
            pairs = pairs._replace(i=ia, j=partners)
    return obs, pairs


def _solve_row(vrel, f: Rows, mu, ln, lt, soft=None):
    """One contact row, the velocity-level update every sequential-impulse solver uses: normal impulse
    lam_n += k (target - vn), clamped >= 0, then friction (clamped to the disc mu lam_n). `soft` =
    (mass_scale, impulse_scale), each of the rows' shape, makes it a soft row (SoftStep, `soft_rows`):
    lam_n += mass_scale k (target - vn) - impulse_scale lam_n. Returns (impulse change P [dim, ...] on the
    second body, new lam_n, new lam_t)."""
    if soft is None:
        vn = _dot(vrel, f.n)
        new_n = jnp.maximum(ln + (f.target - vn) * f.k, 0)
    else:
        mass_scale, impulse_scale = soft
        vn = jnp.sum(vrel * f.n, 0)
        new_n = jnp.maximum(ln + mass_scale * f.k * (f.target - vn) - impulse_scale * ln, 0)
    return finish_row(vrel, f, mu, ln, new_n, lt)


# SoftStep's contacts, Box2D v3 style (Erin Catto, "Solver2D", 2024; box2d/src/contact_solver.c).
#
# The rows are PGS's (`rows` with no Baumgarte term): speculative contacts, swept time of
# impact and restitution. Per substep of length h:
#
# * **Solve** (with bias, one Gauss-Seidel sweep after the rods): a separated contact (C > 0: speculative, or an
#   impact within the substep) is rigid, with its row's target. A touching or overlapping one (C <= 0) is a soft
#   constraint that pushes the overlap out like a spring-damper of `contact_hertz` and `contact_damping_ratio`:
#   target min(-bias_rate C, push_velocity), the update scaled by mass_scale and softened by
#   -impulse_scale lam_n (Box2D's b2MakeSoft coefficients; obstacles, Box2D's static bodies, at twice the
#   hertz), with no restitution, as Box2D. One difference from Box2D: an impact within the substep keeps its
#   row's bounce target here already (Box2D bounces only after relaxing), so that the time-of-impact correction
#   moves the particle on its bounced velocity for the rest of the substep, as PGS does.
# * positions x += h v, with PGS's time-of-impact correction.
# * **Relax** (without bias): every row rigid with its row's target, which for touching contacts is
#   max(e u + dv, 0): the push-out velocity is removed and restitution is applied here (Box2D applies it after
#   the relax iterations, to contacts whose approach speed exceeded the threshold; a row with a positive target
#   does the same within the relax sweeps).
#
# Friction is rigid in both stages (as Box2D's), clamped to mu lam_n.


def soft_rows(rows: Optional[Rows], soft, push_velocity):
    """SoftStep's solve-stage rows and their softness (Box2D v3's soft contacts): (rows, (mass_scale,
    impulse_scale)), each of the rows' shape. Touching or overlapping rows (gap <= 0, or within rounding of
    touching and no impact: `_gap`) get the push-out target min(-bias_rate C, push_velocity) and the soft
    coefficients `soft` = (bias_rate, mass_scale, impulse_scale); separated rows, and impacts, stay rigid."""
    if rows is None:
        return None, None
    bias_rate, mass_scale, impulse_scale = soft
    touching = (rows.gap <= 0) | (rows.near & (rows.toi == 0))
    target = jnp.where(touching, jnp.minimum(-bias_rate * rows.gap, push_velocity), rows.target)
    one = jnp.ones_like(rows.gap)
    return rows._replace(target=target), (jnp.where(touching, mass_scale * one, one),
                                          jnp.where(touching, impulse_scale * one, 0 * one))


def finish_row(vrel, f: Rows, mu, ln, new_n, lt):
    """The rest of a contact row once its new normal impulse `new_n` is known: friction on the relative
    velocity after that impulse, clamped to the disc mu new_n. Returns (P, new_n, new_t) as `_solve_row`."""
    dn = new_n - ln
    vrel = vrel + (f.winv * dn) * f.n
    vt = vrel - f.n * _dot(vrel, f.n)
    new_t = lt - vt * f.k
    length, inv = _length(new_t)
    limit = mu * new_n
    new_t = new_t * jnp.where(length >= limit, limit * inv, 1)
    return f.n * dn + (new_t - lt), new_n, new_t


def _pair_apply(ct, v, r, wi, wj, P):
    """v [dim, n] plus the velocity changes of round r's impulses P [dim, S] (-wi P on i, +wj P on j)."""
    zero = jnp.zeros((v.shape[0], 1), v.dtype)
    src = jnp.asarray(ct.src.array)[r]
    return v + jnp.take(jnp.concatenate([-wi * P, wj * P, zero], -1), src, axis=-1)


def sweep(cs: Optional[ContactSystem], w, v, obs: Rows, pairs: Rows, imp: Impulses, soft=(None, None)):
    """One Gauss-Seidel pass over every contact: obstacles one after another (each over all particles at
    once), then the pair rounds in a loop (a grid model's slots: `grid_pass`). Returns (v, imp); a model
    without contacts (`cs` None) returns them unchanged.

    `soft` = (obstacle softness, pair softness): SoftStep's (mass_scale, impulse_scale) per row
    (`soft_rows`), each None for rigid rows (`_solve_row`)."""
    if cs is None:
        return v, imp
    pick = lambda group, k: None if group is None else tuple(None if a is None else a[k] for a in group)  # noqa
    ct, mu = cs.ct, cs.friction
    on, ot = imp.obs_n, imp.obs_t
    if obs is not None:
        on, ot = list(on), list(ot)
        for q in range(ct.n_obstacles):
            f = Rows(*pick(obs, q))
            P, on[q], ot[q] = _solve_row(v, f, mu, on[q], ot[q], pick(soft[0], q))
            v = v + w * P
        on, ot = jnp.stack(on), jnp.stack(ot)
    pn, pt = imp.pair_n, imp.pair_t
    if pairs is not None and pairs.i is not None:
        v, pn, pt = grid_pass(cs, w, v, pairs, pn, pt, soft[1])
    elif pairs is not None:
        dim, shape = v.shape[0], v.shape
        ia, ja = jnp.asarray(ct.i.array), jnp.asarray(ct.j.array)
        wf = w.reshape(-1)

        def one_round(r, carry):
            vf, pn, pt = carry
            i, j = ia[r], ja[r]
            f = Rows(pairs.n[:, r], *pick(pairs[1:], r))
            P, ln, lt = _solve_row(vf[:, j] - vf[:, i], f, mu, pn[r], pt[:, r], pick(soft[1], r))
            vf = _pair_apply(ct, vf, r, wf[i], wf[j], P)
            return vf, pn.at[r].set(ln), pt.at[:, r].set(lt)

        vf, pn, pt = lax.fori_loop(0, ct.rounds, one_round, (v.reshape(dim, -1), pn, pt))
        v = vf.reshape(shape)
    return v, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def _slot(a, s):
    """Slot s of a grid array [..., n, K] (None stays None)."""
    return None if a is None else jnp.take(a, s, axis=-1)


def slot_major(a):
    """A grid array [..., n, K] as [K, ..., n] (None stays None): what `lax.scan` over the slots takes."""
    return None if a is None else jnp.moveaxis(a, -1, 0)


def grid_pass(cs: ContactSystem, w, v, pairs: Rows, pn, pt, soft=None):
    """One pass over a grid model's pair rows, slot by slot: the rows of one slot (one per particle, whose
    partners may repeat) are solved together from the same v, relaxed by mass splitting (each takes the
    effective mass 1 / (c_i w_i + c_j w_j), c the slot's rows that push at each particle, as
    `jacobi_pass` does), and the slots follow one another Gauss-Seidel-style, a `lax.scan`
    over the slots (slot-major copies of the rows, `slot_major`). A slot no row uses (the grid fills each
    particle's slots from the first, so the last ones are often empty everywhere) is skipped (`lax.cond`: the
    same values and derivatives). Returns (v, pair_n, pair_t)."""
    dim, shape = v.shape[0], v.shape
    wf = w.reshape(-1)

    def one_slot(vf, xs):
        f, ln, lt, ex = xs

        def solve(vf):
            j = jnp.maximum(f.j, 0)
            vrel = vf[:, j] - vf
            vn = _dot(vrel, f.n)
            act = (((ln > 0) | (ln + (f.target - vn) * f.k > 0)) & (f.k > 0)).astype(vf.dtype)
            c = act + jnp.zeros_like(act).at[j].add(act)
            g = f._replace(k=L.safe_reciprocal(c * wf + c[j] * wf[j]) * (f.k > 0).astype(vf.dtype))
            P, new_n, new_t = _solve_row(vrel, g, cs.friction, ln, lt, ex)
            return vf.at[:, j].add(wf[j] * P) - wf * P, (new_n, new_t)

        return lax.cond(jnp.any(f.k > 0), solve, lambda vf: (vf, (ln, lt)), vf)

    xs = (Rows(*(slot_major(a) for a in pairs)), slot_major(pn), slot_major(pt),
          None if soft is None else tuple(slot_major(a) for a in soft))
    vf, (pn, pt) = lax.scan(one_slot, v.reshape(dim, -1), xs)
    return vf.reshape(shape), jnp.moveaxis(pn, 0, -1), jnp.moveaxis(pt, 0, -1)


def _obstacle_frame(obs: Rows):
    """Obstacle rows with the dim axis first ([dim, Q, *view]), as `_solve_row` wants."""
    return obs._replace(n=jnp.moveaxis(obs.n, 1, 0))


def jacobi_counts(cs: ContactSystem, v, obs: Rows, pairs: Rows, imp: Impulses, base):
    """Mass splitting's counts (`jacobi_pass`): `base` [1, *view] (the other rows at each particle) plus, per
    particle, the contact rows that push on it in this iteration: those that hold an impulse, or whose
    unrelaxed update from the velocities `v` would give one."""
    ct, c = cs.ct, base
    if obs is not None:
        f = _obstacle_frame(obs)
        vn = jnp.sum(v[:, None] * f.n, 0)
        act = ((imp.obs_n > 0) | (imp.obs_n + (obs.target - vn) * obs.k > 0)) & (obs.k > 0)
        c = c + jnp.sum(act.astype(c.dtype), 0)[None]
    if pairs is not None:
        ia, ja = pair_index(ct, pairs)
        vf = v.reshape(v.shape[0], -1)
        vn = jnp.sum((vf[:, ja] - vf[:, ia]).reshape(pairs.n.shape) * pairs.n, 0)
        act = ((imp.pair_n > 0) | (imp.pair_n + (pairs.target - vn) * pairs.k > 0)) & (pairs.k > 0)
        act = act.astype(c.dtype).reshape(-1)
        flat = c.reshape(-1).at[ia].add(act).at[ja].add(act)
        c = flat.reshape(c.shape)
    return c


def jacobi_pass(cs: ContactSystem, w, v, obs: Rows, pairs: Rows, imp: Impulses, count, relax):
    """Every contact row updated from the same `v` (Jacobi), each by `_solve_row`: (dv, imp). A row between
    particles i and j takes the effective mass 1 / (c_i w_i + c_j w_j) with the per-particle counts `count`
    [1, *view] (mass splitting, `jacobi_counts`; an obstacle has no inverse mass: 1 / (c_i w_i)), or relax * k
    with a fixed relaxation (`count` None).

    Mass splitting (Tonge, Benevolenski and Voroshilov 2012, "Mass splitting for jitter-free parallel rigid body
    simulation") is the momentum-conserving form of the constraint averaging of Macklin et al. 2014. A particle
    touched by c rows in this iteration (its constraint rows, plus its contacts that push or are about to) lends
    each of them 1 / c of its mass, and the impulse is applied with the true masses. Every row's impulse acts
    equally and oppositely on its two particles, so momentum is conserved exactly (per-particle averaging of the
    velocity changes is not: c_i != c_j). Since the Delassus matrix is bounded by this diagonal
    (A = J W J^T <= diag(c_i w_i + c_j w_j), each particle's rows forming a Gram matrix of unit normals), the
    iteration converges for any fixed active set. The counts are recomputed in every iteration, so a particle
    free of contacts keeps its full mass and a ball wedged in a rack splits it six ways."""
    dv = jnp.zeros_like(v)
    ct, mu = cs.ct, cs.friction
    on, ot, pn, pt = imp[:4]
    if obs is not None:
        f = _obstacle_frame(obs)
        k = relax * obs.k if count is None else L.safe_reciprocal(count * obs.winv) * (obs.k > 0).astype(v.dtype)
        vrel = jnp.broadcast_to(v[:, None], f.n.shape)
        P, on, ot = _solve_row(vrel, f._replace(k=k), mu, on, jnp.moveaxis(ot, 1, 0))
        ot = jnp.moveaxis(ot, 0, 1)
        dv = dv + w * jnp.sum(P, 1)
    if pairs is not None:
        index = pair_index(ct, pairs)
        ia, ja = index
        vf = v.reshape(v.shape[0], -1)
        shape = pairs.k.shape
        if count is None:
            k = relax * pairs.k
        else:
            cf, wf = count.reshape(-1), w.reshape(-1)
            k = L.safe_reciprocal(cf[ia] * wf[ia] + cf[ja] * wf[ja]).reshape(shape) * (pairs.k > 0).astype(v.dtype)
        vrel = (vf[:, ja] - vf[:, ia]).reshape(pairs.n.shape)
        P, pn, pt = _solve_row(vrel, pairs._replace(k=k), mu, pn, pt)
        dv = dv + _pair_total(ct, w, P, -1.0, index).reshape(v.shape)
    return dv, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def carry_slots(prev: Impulses, partners):
    """A grid model's pair impulses `prev` (made with prev.partners) moved to the slots of `partners` [n, K]:
    (pair_n [n, K], pair_t [dim, n, K]). A slot keeps an impulse only if it lists the same partner again (each
    pair always sits in the row of its lower-numbered particle, so a pair that stays a candidate stays in the
    same row); a new pair starts from 0."""
    same = (partners[:, :, None] == prev.partners[:, None, :]) & (partners >= 0)[:, :, None]
    pn = jnp.sum(jnp.where(same, prev.pair_n[:, None, :], 0), -1)
    pt = jnp.sum(jnp.where(same[None], prev.pair_t[:, :, None, :], 0), -1)
    return pn, pt


def warm_start(cs: ContactSystem, w, v, obs: Rows, pairs: Rows, prev: Impulses, factor=1.0):
    """Apply last step's contact impulses to contacts that touch or will touch within this step, re-projected
    on the new normals (lam_n >= 0, friction inside the new cone). Returns (v, imp)."""
    ct, mu = cs.ct, cs.friction

    def project(f: Rows, ln, lt):
        active = f.warm & (f.k > 0)
        ln = jnp.maximum(ln, 0) * factor * active.astype(ln.dtype)
        lt = (lt - f.n * _dot(lt, f.n)) * factor
        length, inv = _length(lt)
        limit = mu * ln
        return ln, lt * jnp.where(length >= limit, limit * inv, 1) * active.astype(ln.dtype)

    on, ot = prev.obs_n, prev.obs_t
    if obs is not None:
        on, ot = project(_obstacle_frame(obs), on, jnp.moveaxis(ot, 1, 0))
        ot = jnp.moveaxis(ot, 0, 1)          # back to [Q, dim, *view]
        v = v + w * jnp.sum(obs.n * on[:, None] + ot, 0)
    pn, pt = prev.pair_n, prev.pair_t
    if pairs is not None and pairs.i is not None:
        pn, pt = carry_slots(prev, pairs.j)
    if pairs is not None:
        pn, pt = project(pairs, pn, pt)
        P = pairs.n * pn + pt
        v = v + _pair_total(ct, w, P, -1.0, pair_index(ct, pairs)).reshape(v.shape)
    return v, prev._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


# ---- restitution that never creates energy ---------------------------------------------------------------------
def compression(f: Optional[Rows]) -> Optional[Rows]:
    """The rows of the compression phase: every target without its restitution part."""
    return None if f is None else f._replace(target=f.target_c)


def bouncing(obs: Optional[Rows], pairs: Optional[Rows]):
    """Whether any row asks for a bounce (its target is above its compression target)."""
    out = jnp.zeros((), bool)
    for f in (obs, pairs):
        if f is not None:
            out = out | jnp.any(f.target > f.target_c)
    return out


def restitution_scale(w, v_free, v_c, v_n, bounce):
    """The largest s in [0, 1] for which v_c + s (v_n - v_c) has no more kinetic energy than the larger of the
    velocity before any impulse (`v_free`) and the compression phase's (`v_c`); 1 where no row bounces.

    Newton's restitution applied to several coupled impacts at once (a ball that hits a cluster which is also
    hitting a cushion) can end with more kinetic energy than before the impacts; a single impact, or one into a
    cluster whose other contacts are inelastic, cannot. The compression phase (every contact inelastic) only
    removes energy (or adds what Baumgarte push-out adds), so scaling the restitution phase's change back to
    that bound keeps the non-penetration targets of the compression phase, the cone, lam_n >= 0 (a convex
    combination of two solutions that satisfy them) and the momentum, and never raises the kinetic energy."""
    m = L.safe_reciprocal(w)
    d = v_n - v_c
    kc, b, c = jnp.sum(m * v_c * v_c), jnp.sum(m * v_c * d), jnp.sum(m * d * d)
    e = jnp.maximum(jnp.sum(m * v_free * v_free), kc)
    e = e * (1 + 16 * jnp.finfo(e.dtype).eps)
    within = ~bounce | (kc + 2 * b + c <= e)
    # Where `within`, the root below is not used, but reverse mode still multiplies its (zero) cotangent by its
    # partial derivatives: with the phases' velocities a rounding error apart, c ~ 1e-27 and d s / d c ~ 1 / c^2
    # overflows float32, and 0 * inf is NaN (the falling chain's friction gradient). So the root only ever sees
    # safe values there (b = 0, c = slack = 1), and its square root never sees 0.
    b, c = jnp.where(within, 0, b), jnp.where(within, 1, c)
    slack = jnp.where(within, 1, jnp.maximum(e - kc, 0))
    disc = b * b + c * slack
    root = jnp.where(disc > 0, jnp.sqrt(jnp.where(disc > 0, disc, 1)), 0)
    den = b + root                        # two cancellation-free forms of the larger root of K(s) = e
    # For b < 0 the root is (|b| + root) / c, at most 1 when not `within` (K(1) > e), i.e. c >= |b| + root: the
    # maximum changes nothing there and keeps the quotient and its derivatives bounded when c underflows.
    s = jnp.where(b >= 0, slack / jnp.where(den > 0, den, 1),
                  (root - b) / jnp.where(b < 0, jnp.maximum(c, root - b), 1))
    return jnp.where(within, 1, jnp.clip(s, 0, 1))


def _pair_total(ct, w, P, sign_i, index=None):  # noqa: D401
    """Sum over every pair slot of +w_j P on j and sign_i * w_i P on i: [dim, n] (a scatter-add). `index`:
    the slots' flat (i, j) (`pair_index`; default the static rounds')."""
    dim = P.shape[0]
    wf = w.reshape(-1)
    ia, ja = (ct.i.array.reshape(-1), ct.j.array.reshape(-1)) if index is None else index
    Pf = P.reshape(dim, -1)
    out = jnp.zeros((dim, wf.shape[0]), P.dtype)
    return out.at[:, ja].add(wf[ja] * Pf).at[:, ia].add(sign_i * wf[ia] * Pf)


#: Passes that carry a time of impact across touching contacts (a ball hit in a rack passes the impulse on
#: through up to this many touching neighbours within the same step).
TOI_PASSES = 8


def impact_times(cs: ContactSystem, obs: Rows, pairs: Rows, imp: Impulses, shape):
    """Per-particle time [1, *view] at which its velocity changed within the step: the time of impact of the
    impacts it takes part in (with an impulse), carried on through contacts that touch at the start of the step
    and push (a rack hit by the cue ball: the whole cluster's velocities change at the cue ball's impact), 0 for
    particles no impact reaches."""
    tau = jnp.zeros(shape[1:], obs.toi.dtype if obs is not None else pairs.toi.dtype)
    if obs is not None:
        hit = (obs.toi > 0) & (imp.obs_n > 0)
        tau = jnp.max(jnp.where(hit, obs.toi, 0), axis=0)
    if pairs is None:
        return tau[None]
    ia, ja = pair_index(cs.ct, pairs)
    push = (imp.pair_n > 0).reshape(-1)
    toi = jnp.where(push, pairs.toi.reshape(-1), 0)
    flat = tau.reshape(-1)
    flat = flat.at[ia].max(toi).at[ja].max(toi)
    touching = push & ((pairs.toi == 0) | pairs.near).reshape(-1)       # not an impact of separated balls

    def carry(_, t):
        across = jnp.where(touching, jnp.maximum(t[ia], t[ja]), 0)
        return t.at[ia].max(across).at[ja].max(across)

    # Without an impact nothing is carried (the same values and derivatives): a pile at rest skips the passes.
    flat = lax.cond(jnp.any(flat > 0), lambda t: lax.fori_loop(0, TOI_PASSES, carry, t), lambda t: t, flat)
    return flat.reshape((1,) + shape[1:])


#: PGS's passes of the position safety pass when particles collide with each other (one pass leaves half of an
#: overlap between a ball and one it is pressed against on a cushion; 8 bring the worst off-axis billiards
#: break from 12% of a diameter to 0.14%). Obstacles alone need one. Jacobi keeps one: its under-converged
#: stacks leave overlap every step, and removing all of it at position level, with no velocity change, makes
#: a resting column jitter (0.05 m/s).
OVERLAP_PASSES = 8


def project_overlaps(cs: ContactSystem, w, x, passes: Optional[int] = None, pairs: Optional[Rows] = None, slop=0.0):
    """Move overlapping contacts apart at position level (non-linear Gauss-Seidel, as Box2D v2's position
    solver), `passes` times (default: `OVERLAP_PASSES` with pairs, `GRID_OVERLAP_PASSES` with a grid, else 1):
    pair rounds, then obstacles (which cannot move, so they have the last word; a heavy ball on light ones
    is then pushed out of them without pushing the bottom one into the floor). Velocities
    are not touched, so no kinetic energy or momentum is added; it only acts where the velocity solve left an
    overlap (an under-converged cluster, or the time-of-impact correction of a particle whose velocity was
    also changed by a later contact). A grid model's pairs (the rows `pairs` of this step) are projected
    slot by slot instead (the overlaps of one slot together, each split between the overlaps at its particles).
    `slop`: the overlaps are projected onto `slop` times the contact distance, not onto 0 (`CONTACT_SLOP`)."""
    ct = cs.ct
    dim, shape = x.shape[0], x.shape
    r = cs.radius[0]
    k = L.safe_reciprocal(w[0])

    def obstacles(x):
        for p in range(ct.n_planes):
            nrm = cs.plane_normal[p].reshape((dim,) + (1,) * (x.ndim - 1))
            C = jnp.sum(nrm * x, 0) - cs.plane_offset[p] - r
            x = x + nrm * (jnp.maximum(-C - slop * r, 0) * (k > 0))
        for q in range(ct.n_spheres):
            d = x - cs.sphere_centre[q].reshape((dim,) + (1,) * (x.ndim - 1))
            dist, n = direction(d)
            C = dist - cs.sphere_radius[q] - r
            x = x + n * (jnp.maximum(-C - slop * r, 0) * (k > 0))
        return x

    def pair_rounds(x):
        ia, ja = jnp.asarray(ct.i.array), jnp.asarray(ct.j.array)
        valid = jnp.asarray(ct.valid.array)
        wf, rf = w.reshape(-1), cs.radius_flat

        def one_round(q, xf):
            i, j = ia[q], ja[q]
            dist, n = direction(xf[:, j] - xf[:, i])
            winv = wf[i] + wf[j]
            push = jnp.maximum((1 - slop) * (rf[i] + rf[j]) - dist, 0) * L.safe_reciprocal(winv) * valid[q]
            return _pair_apply(ct, xf, q, wf[i], wf[j], n * push)

        return lax.fori_loop(0, ct.rounds, one_round, x.reshape(dim, -1)).reshape(shape)

    def grid_pairs(x):
        wf, rf = w.reshape(-1), cs.radius_flat

        def one_slot(xf, xs):                     # slot by slot, as grid_pass (empty slots skipped)
            jj, kk = xs

            def project(xf):
                j = jnp.maximum(jj, 0)
                dist, n = direction(xf[:, j] - xf)
                over = jnp.maximum((1 - slop) * (rf + rf[j]) - dist, 0) * (kk > 0)
                hit = (over > 0).astype(xf.dtype)
                c = hit + jnp.zeros_like(hit).at[j].add(hit)
                P = n * (over * L.safe_reciprocal(c * wf + c[j] * wf[j]))
                return xf.at[:, j].add(wf[j] * P) - wf * P

            return lax.cond(jnp.any(kk > 0), project, lambda xf: xf, xf), None

        return lax.scan(one_slot, x.reshape(dim, -1), (slot_major(pairs.j), slot_major(pairs.k)))[0].reshape(shape)

    def one_pass(_, x):
        if ct.n_pairs:
            x = pair_rounds(x)
        elif ct.has_grid:
            x = grid_pairs(x)
        return obstacles(x) if ct.n_obstacles else x

    if passes is None:
        passes = GRID_OVERLAP_PASSES if ct.has_grid else OVERLAP_PASSES if ct.n_pairs else 1
    if passes == 1:
        return one_pass(0, x)
    if not ct.has_grid:
        return lax.fori_loop(0, passes, one_pass, x)
    # A grid model's passes stop once one moves no particle by more than GRID_PASS_STOP of the slop (of the
    # smallest radius; with no slop, once one moves nothing): a pile at rest, whose velocity solve leaves no
    # overlap beyond the slop, takes one pass instead of GRID_OVERLAP_PASSES.
    limit = lax.stop_gradient(GRID_PASS_STOP * slop * jnp.min(cs.radius_flat))

    def gated(_, carry):
        def run(x):
            y = one_pass(0, x)
            return y, lax.stop_gradient(jnp.max(jnp.abs(y - x))) > limit
        return lax.cond(carry[1], run, lambda x: (x, carry[1]), carry[0])

    return lax.fori_loop(0, passes, gated, (x, jnp.ones((), bool)))[0]


# ---- contacts at position level (XPBD, Penalty) ------------------------------------------------------------
# Contacts at position level, for XPBD (Mueller et al. 2020, "Detailed rigid body simulation with extended
# position based dynamics"; Macklin et al. 2019, "Small steps in physics simulation").
#
# Per substep of length h, from positions x and predicted positions p = x + h (v + h g):
#
# * `position_pass` (once per solver iteration, after the rod and rope colours): every contact with gap C(p) is a
#   rigid (compliance 0) unilateral constraint. Its position multiplier lam_n (kg m, accumulated over the
#   iterations, clamped >= 0) changes by -C / (w_i + w_j): an overlap is pushed out, and a contact pushed out
#   too far by an earlier row gives some of it back. Then **static friction**: the relative tangential
#   displacement of the two bodies over the substep, dx_t, is cancelled (lam_t -= dx_t / (w_i + w_j)) when the
#   resulting |lam_t| <= mu lam_n; otherwise nothing is added (the kinetic part is the velocity pass's), and a
#   lam_t left above a cone that shrank is scaled back onto it. Obstacles are solved one after another, each
#   for all particles at once; pairs round by round (a loop over the rounds, as `sweep`), a grid
#   model's pairs slot by slot (`_grid_project`).
# * `position_velocity_pass` (once, after v = (p - x) / h): each contact with lam_n > 0 gets one velocity row, solved by
#   `sweep` starting from the position impulses lam / h: the normal velocity is set to
#   max(-e vn_before, 0) (restitution; vn_before is the normal relative velocity at the start of the substep
#   after gravity, e = 0 when |vn_before| <= the restitution threshold), with the total normal impulse of the
#   substep kept >= 0, then **dynamic friction** removes the tangential relative velocity with a total friction
#   impulse clamped to the Coulomb disc mu * (total normal impulse). Where the velocity row adds no normal impulse
#   and static friction did not hold, that is Mueller et al.'s eq. 30, |dv_t| = min(mu lam_n / h (w_i + w_j),
#   |v_t|); the clamp on the total makes every reported impulse satisfy |lam_t| <= mu lam_n.
#
# The substep's reported impulses (N s) are the velocity pass's totals: lam / h plus the velocity rows.


def obstacle_gap(cs: ContactSystem, q: int, p, x=None):
    """(unit normal [dim, *view], gap [*view]) of every particle at `p` against obstacle q (planes first).
    With the substep's start positions `x`, a particle that started inside a sphere keeps the normal it had
    there (`overlap_normal`)."""
    dim, nview = p.shape[0], p.ndim - 1
    r = cs.radius[0]
    if q < cs.ct.n_planes:
        nrm = jnp.broadcast_to(cs.plane_normal[q].reshape((dim,) + (1,) * nview), p.shape)
        return nrm, jnp.sum(nrm * p, 0) - cs.plane_offset[q] - r
    s = q - cs.ct.n_planes
    c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
    if x is not None:
        return overlap_normal(x - c, p - c, cs.sphere_radius[s] + r)
    dist, nrm = direction(p - c)
    return nrm, dist - cs.sphere_radius[s] - r


def _pair_gap(cs: ContactSystem, pf, r, xf):
    """(unit normal [dim, S] from i to j, gap [S]) of pair round r at flat positions pf [dim, n], the substep
    having started at xf (`overlap_normal`)."""
    ct = cs.ct
    i, j = jnp.asarray(ct.i.array)[r], jnp.asarray(ct.j.array)[r]
    return overlap_normal(xf[:, j] - xf[:, i], pf[:, j] - pf[:, i], cs.radius_flat[i] + cs.radius_flat[j])


def _position_row(disp, n, C, k, mu, ln, lt):
    """One contact at position level: normal multiplier (accumulated, >= 0), then static friction. `disp` is
    the second body's displacement over the substep relative to the first, k = 1 / (w_i + w_j) (0: no row).
    Returns (position impulse change P [dim, ...] on the second body, new lam_n, new lam_t)."""
    new_n = jnp.maximum(ln - C * k, 0)
    disp_t = disp - n * jnp.sum(disp * n, 0)
    stick = lt - disp_t * k
    limit = mu * new_n
    length, _ = L.safe_length(stick)
    held, inv = L.safe_length(lt)
    kept = lt * jnp.where(held > limit, limit * inv, 1)
    new_t = jnp.where(length <= limit, stick, kept)
    return n * (new_n - ln) + (new_t - lt), new_n, new_t


def position_pass(cs: ContactSystem, w, x, p, imp: Impulses, partners=None):
    """One position-level pass over every contact (the section's comment above): obstacles, then the pair rounds (a grid
    model's `partners` [n, K]: its slots, `_grid_project`). x: positions at the start of the substep, p:
    current positions [dim, *view]; imp: position multipliers (kg m) accumulated in this substep. Returns
    (p, imp)."""
    ct, mu = cs.ct, cs.friction
    on, ot = imp.obs_n, imp.obs_t
    if ct.n_obstacles:
        on, ot = list(on), list(ot)
        k = L.safe_reciprocal(w[0])
        for q in range(ct.n_obstacles):
            n, C = obstacle_gap(cs, q, p, x)
            P, on[q], ot[q] = _position_row(p - x, n, C, k, mu, on[q], ot[q])
            p = p + w * P
        on, ot = jnp.stack(on), jnp.stack(ot)
    pn, pt = imp.pair_n, imp.pair_t
    if ct.n_pairs:
        dim, shape = p.shape[0], p.shape
        ia, ja = jnp.asarray(ct.i.array), jnp.asarray(ct.j.array)
        valid = jnp.asarray(ct.valid.array, p.dtype)
        wf, xf = w.reshape(-1), x.reshape(dim, -1)

        def one_round(r, carry):
            pf, pn, pt = carry
            i, j = ia[r], ja[r]
            n, C = _pair_gap(cs, pf, r, xf)
            disp = (pf[:, j] - xf[:, j]) - (pf[:, i] - xf[:, i])
            k = L.safe_reciprocal(wf[i] + wf[j]) * valid[r]
            P, ln, lt = _position_row(disp, n, C, k, mu, pn[r], pt[:, r])
            pf = _pair_apply(ct, pf, r, wf[i], wf[j], P)
            return pf, pn.at[r].set(ln), pt.at[:, r].set(lt)

        pf, pn, pt = lax.fori_loop(0, ct.rounds, one_round, (p.reshape(dim, -1), pn, pt))
        p = pf.reshape(shape)
    elif ct.has_grid:
        p, pn, pt = _grid_project(cs, w, x, p, partners, pn, pt)
    return p, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def _grid_project(cs: ContactSystem, w, x, p, partners, pn, pt):
    """`position_pass`'s pass over a grid model's pairs, slot by slot as `contact.grid_pass`: the rows of one slot
    (one per particle, whose partners may repeat) are projected together from the same positions, relaxed by
    mass splitting (k = 1 / (c_i w_i + c_j w_j), c the slot's rows at each particle that push or overlap), and
    the slots follow one another in a `lax.scan`; a slot no particle uses is skipped. Returns (p, pair_n
    [n, K], pair_t [dim, n, K])."""
    dim, shape = p.shape[0], p.shape
    wf, xf, r = w.reshape(-1), x.reshape(dim, -1), cs.radius_flat

    def one_slot(pf, xs):
        j, ln, lt = xs

        def solve(pf):
            jc = jnp.maximum(j, 0)
            n, C = overlap_normal(xf[:, jc] - xf, pf[:, jc] - pf, r + r[jc])
            disp = (pf[:, jc] - xf[:, jc]) - (pf - xf)
            act = ((j >= 0) & ((C < 0) | (ln > 0))).astype(pf.dtype)
            c = act + jnp.zeros_like(act).at[jc].add(act)
            k = L.safe_reciprocal(c * wf + c[jc] * wf[jc]) * act
            P, new_n, new_t = _position_row(disp, n, C, k, cs.friction, ln, lt)
            return pf.at[:, jc].add(wf[jc] * P) - wf * P, (new_n, new_t)

        return lax.cond(jnp.any(j >= 0), solve, lambda pf: (pf, (ln, lt)), pf)

    xs = (slot_major(partners), slot_major(pn), slot_major(pt))
    pf, (pn, pt) = lax.scan(one_slot, p.reshape(dim, -1), xs)
    return pf.reshape(shape), jnp.moveaxis(pn, 0, -1), jnp.moveaxis(pt, 0, -1)


def _bounce_target(cs: ContactSystem, vn_before):
    """Restitution target of the velocity pass: max(-e vn_before, 0), e = 0 at or below the threshold."""
    e = jnp.where(jnp.abs(vn_before) > cs.threshold, cs.restitution, 0)
    return jnp.maximum(-e * vn_before, 0)


def velocity_rows(cs: ContactSystem, w, p, v_before, imp: Impulses, partners=None):
    """Velocity rows (obstacle Rows or None, pair Rows or None) at the end of the position solve: normals and
    gaps at `p`, restitution targets from `v_before` (start of the substep, after gravity), and effective
    masses only for contacts that pushed in this substep (lam_n > 0; the others get k = 0, no impulse). A grid
    model's pair rows are its `partners`' slots [n, K]."""
    ct, dim = cs.ct, p.shape[0]
    obs = pairs = None
    if ct.n_obstacles:
        ns, Cs = zip(*(obstacle_gap(cs, q, p) for q in range(ct.n_obstacles)))
        n, C = jnp.stack(ns), jnp.stack(Cs)
        winv = jnp.broadcast_to(w[0], C.shape)
        k = L.safe_reciprocal(winv) * (imp.obs_n > 0).astype(C.dtype)
        obs = Rows(n, _bounce_target(cs, jnp.sum(n * v_before[None], 1)), k, winv, jnp.zeros_like(C), C)
    if ct.n_pairs or ct.has_grid:
        pf, vf, wf = p.reshape(dim, -1), v_before.reshape(dim, -1), w.reshape(-1)
        ia, ja, valid, _ = pair_slots(ct, pf.shape[1], partners)
        dist, n = direction(pf[:, ja] - pf[:, ia])
        C = dist - cs.radius_flat[ia] - cs.radius_flat[ja]
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype) * (imp.pair_n > 0).astype(C.dtype)
        vn = jnp.sum(n * (vf[:, ja] - vf[:, ia]), 0)
        pairs = Rows(n, _bounce_target(cs, vn), k, winv, jnp.zeros_like(C), C)
        if partners is not None:
            pairs = pairs._replace(i=ia, j=partners)
    return obs, pairs


def position_velocity_pass(cs: ContactSystem, w, p, v_before, v, imp: Impulses, h, partners=None):
    """Restitution and dynamic friction (the section's comment above) on v = (p - x) / h. `imp` holds the substep's
    position multipliers (kg m). Returns (v, the substep's contact impulses in N s)."""
    obs, pairs = velocity_rows(cs, w, p, v_before, imp, partners)
    start = imp._replace(**{f: getattr(imp, f) / h for f in ("obs_n", "obs_t", "pair_n", "pair_t")})
    return sweep(cs, w, v, obs, pairs, start)
