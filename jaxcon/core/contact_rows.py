"""The contact kind's rows (docs/contacts.md): planes, spheres and particle pairs made into unilateral rows
with friction, a time of impact and restitution targets, at velocity level (`rows`) and at position level
(`obstacle_gap`, `velocity_rows`). Solvers consume them (`jaxcon.solvers.contact`); the
neighbour grid that lists a grid model's pairs is `jaxcon.core.grid`.

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
found at the start of every step by `grid.neighbours` (a spatial hash of the positions) and kept in K slots per
particle; their rows are those above, with `Rows.i`/`Rows.j` [n, K] naming the particles (j = -1: empty slot,
k = 0). A PGS sweep solves them after the obstacles slot by slot, the rows of one slot together with mass
splitting (`SlotBlock`; a slot of few rows on those rows gathered, `SparseSlots`); the position safety pass
projects them the same way, and the warm start matches last step's impulses by partner (a slot's impulse is
carried over only if the same pair is listed again).
`Impulses.partners` [n, K] and `Impulses.overflow` (the candidates that did not fit) travel with the impulses.
The time-of-impact correction applies to grid pairs as to listed ones. After the solve, `common.grid_step`
checks that no unlisted pair touched on the paths the solve gave (`grid.path_search`, `grid.unsolved`),
solving the step again with those pairs if one did.

Start overlaps (a particle inside an obstacle or another particle) are pushed out at no more than
`PUSH_OUT_SPEED`, along `direction` (the last axis where the centres coincide). Gaps within rounding of 0
(`_gap`) are classified the same way by every program that computes them, so that forward and reverse mode
agree. `ContactSystem.from_model` makes every leaf NaN when one holds a value `Model` refuses.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.contact import ContactSystem, ContactTopology, Impulses

Array = Any


class Rows(NamedTuple):
    """Contact rows of one (sub)step: normal n, target velocity `target`, effective mass k, inverse-mass sum
    winv, time of impact `toi` (0 unless an impact happens within the step), gap, and `target_c`: the target
    without restitution (the compression phase; None for solvers that do not split the solve). Grid pair rows
    also carry their particles i, j [n, K] (internal indices, j = -1 for an empty slot); None otherwise. `near`:
    touching or within rounding of it (an impact of such a contact is one of a touching contact, `_gap`).
    `warm`: the rows the warm start applies last step's impulse to (touching, an impact, or a pair within the
    solver's slop of touching). `slots`: a grid's `SparseSlots` (the rows of each slot, for the slots that
    hold few), or None."""

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
    sel: Any = None
    slots: Any = None


class Selection(NamedTuple):
    """Obstacle rows worth sweeping (`select_obstacles`): per obstacle the flat indices of the rows within reach,
    `idx` [Q, cap] (the particle count where unused), and `inside` [Q, n] (bool), the same rows as a mask.
    `planes`: inside a velocity solve (`obstacles_in_solve`), per obstacle its rows (flat, `sel` None), its
    picked rows gathered in `idx`'s order and the inverse masses at them, made once per solve instead of in every
    sweep; None otherwise. `late`: the solve's phase (`phase`), which those rows' targets follow where they are
    read (`phase_target`), or None (their own targets)."""

    idx: Array
    inside: Array
    planes: Any = None
    late: Any = None


def dot(a, b):
    """Sum of a * b over the leading (dim) axis, written out component by component (`layout.dot0`). On XLA's
    CPU backend `jnp.sum(a * b, 0)` of gathered operands ([dim, n, M] from x[:, j]) becomes a reduction kernel
    that gathers again for every element: the grid search's distance test of the 1024-disc box took 6.5 ms
    that way and 0.26 ms written out."""
    return L.dot0(a, b)


def length(d):
    """`layout.safe_length` with `dot`: (length, 1 / length) along the leading axis, both 0 at zero length."""
    d2 = dot(d, d)
    ok = d2 > L.min_length2(d.dtype)
    inv = jnp.where(ok, lax.rsqrt(jnp.where(ok, d2, 1)), 0)
    return d2 * inv, inv


def _norm(d):
    """`layout.safe_norm` along the leading axis with `dot`: (length, unit direction, 0 at zero length)."""
    dist, inv = length(d)
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


def overlap_normal(d0, disp, R, ahead=None, hold=None):
    """(unit normal, gap, floor) of contacts at distance vectors d0 [dim, ...] at the start of a position-level
    substep (XPBD, RATTLE; touching at |d| = R), displaced by `disp` since (d = d0 + disp, `disp`
    kept apart so that it stays in full precision: `contact.position_pass`).

    Every row keeps one normal through the sweeps of a substep, and its gap is measured along it, n . d - R
    (the linearised gap of a speculative row; n . d >= R implies |d| >= R): the predicted end's, d0 + `ahead`
    (`direction`), except
    * for a contact that already overlapped at the start (a particle started inside a sphere or another
      particle), which keeps the start's normal and the gap along it, n0 . d - R, so that it leaves by the
      nearest surface of where it was (upwards from the exact centre), not by the side that gravity's
      prediction happened to move it towards;
    * for a contact separated at the start whose straight path over the substep's predicted displacement
      `ahead` (the free one, h v; default `disp`) passes the other body, coming out again or ending beyond its
      centre (`_swept`, the speculative contact of the velocity rows, at position level): the normal at that
      time of impact, with the gap along it. A particle that moves further than the other body's size in one
      substep is stopped at the surface it hit, instead of being projected out of the side it ended nearest.
      Decided on the prediction, not on the current displacement, so that the row keeps one normal through
      the sweeps of a substep (with the current one it switched between the two normals from sweep to sweep,
      and RATTLE's break at dt 1/60 ended with balls 23% of a diameter into each other).

    On the current direction, which every sweep's corrections turn, a contact's position impulses summed to a
    vector off the normal at the end, and the velocity rows (`velocity_rows`), which can take back only the part
    along their normal, left the rest: RATTLE's billiards break gained 4e-4 of its kinetic energy in the step
    after the break, at any number of sweeps.

    `floor` (<= 0): the gap the contact is projected onto: 0, or for a start overlap deeper than `hold` (at
    least `CONTACT_SLOP` R; the position-level solvers pass PUSH_OUT_SPEED h) the start's gap C0: the position pass keeps such an overlap from getting deeper but does not
    push it out (that would become velocity, v = dp / h); `solvers.contact.push_out` does, at position level, at
    most PUSH_OUT_SPEED h per substep. Shallower overlaps (what a substep's sweeps left of the last one's
    contacts) are projected out as before: held too, a landing pile kept them (XPBD's grid pile overlapped 0.75%
    of a diameter instead of 0.29%)."""
    dist0, n0 = direction(d0)
    tol = tolerance(magnitude(d0) + R)
    C0 = dist0 - R
    deep = C0 < -tol
    ahead = disp if ahead is None else ahead
    n_hit, _, _, hit, _, _ = _swept(d0, ahead, R, 1.0, tol)
    end = d0 + ahead
    # the path passed the other body: out again, or beyond its centre (projecting along the end's own normal
    # would push it out of the far side)
    hit = hit & ((dot(end, end) > R * R) | (dot(n_hit, end) < 0))
    d = d0 + disp
    dist, n = direction(d)
    # a path that stays outside: the normal where it comes closest (a half-plane there holds it outside, and one
    # at the end of a path that ran past the other body would push it forward)
    aa = dot(ahead, ahead)
    t = jnp.clip(-dot(d0, ahead) / jnp.where(aa > 0, aa, 1), 0, 1)
    fixed = deep | hit | (dot(end, end) > R * R)
    n = jnp.where(fixed, jnp.where(deep | hit, jnp.where(deep, n0, n_hit), direction(d0 + t * ahead)[1]), n)
    hold = CONTACT_SLOP * R if hold is None else jnp.maximum(hold, CONTACT_SLOP * R)
    return n, jnp.where(fixed, dot(n, d), dist) - R, jnp.where(C0 < -hold, C0, 0)


def pair_slots(ct: ContactTopology, n: int, partners=None):
    """The pair contacts' particles: (ia, ja, valid, index). Listed pairs: the static rounds (ct.i, ct.j
    [R, S]), their `valid` mask, index None. A grid model's `partners` [n, K]: ia each slot's particle, ja its
    partner (0 for an empty slot), valid the slots in use, index the flat (ia, ja) (`pair_index`)."""
    if partners is None:
        return ct.i.array, ct.j.array, ct.valid.array, None
    ia = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], partners.shape)
    ja = jnp.maximum(partners, 0)
    return ia, ja, partners >= 0, (ia.reshape(-1), ja.reshape(-1))


def pair_partners(pairs: Optional[Rows]):
    """A grid model's partners [n, K] of the pair rows (`pair_total`'s `partners`), None for listed pairs."""
    return pairs.j if pairs is not None and pairs.i is not None else None


def pair_index(ct: ContactTopology, pairs: Rows):
    """The pair rows' particles, flat: (i, j) [P] internal indices (grid rows: empty slots point at 0 and have
    k = 0)."""
    if pair_partners(pairs) is not None:
        return pairs.i.reshape(-1), jnp.maximum(pairs.j, 0).reshape(-1)
    return ct.i.array.reshape(-1), ct.j.array.reshape(-1)


# ---- how a sweep visits the contact rows (`layout.each_colour`) -------------------------------------------------
# The contact rows come in three layouts, each a block whose colours `layout.each_colour` runs one after another
# (`ObstacleBlock`, `pair_block`: `RoundBlock`, `SlotBlock`): obstacle q's rows (one per particle), a round of listed
# pairs (disjoint pairs), and a grid slot (one row per particle, whose partners may repeat, so its rows share
# particles). A colour gives the update the relative values of its rows' particles (`rel`, `both`) and writes an
# impulse back (`apply`); a slot also splits masses between the rows it shares a particle with (`split_mass`). `rows`
# is a pair (data, multipliers): a slot with no rows is skipped and keeps its multipliers (`lax.cond`: the same values
# and derivatives).


class Unilateral:
    """What the row update (`rows.solve`, `rows.accumulate`) asks of a colour of contact rows: every row is
    unilateral (lam_n >= 0) and solved on its own."""

    all_rope, rope, star = True, None, False


#: Every contact row at once (Jacobi's update, which has no colours).
UNILATERAL = Unilateral()


class ObstacleColour(Unilateral):
    """Obstacle q's rows inside a sweep: one per particle, on the [dim, *view] arrays. `q` is an int, or traced
    inside `each_obstacle`'s scan; `sphere` (static) says whether it is a sphere (else a plane)."""

    split = False

    def __init__(self, q, sphere: Optional[bool] = None):
        self.q, self.sphere = q, sphere

    @staticmethod
    def rel(a):
        return a

    @staticmethod
    def apply(w, a, P):
        return a + w * P


class RoundColour(Unilateral):
    """A round of listed pairs inside a sweep: particles i, j [S] (flat internal indices) of disjoint pairs,
    `valid` [S] (padding), and `src` [n], where each particle's change comes from (a gather writes the round
    back: no scatter)."""

    split = False

    def __init__(self, i, j, src, valid):
        self.i, self.j, self.src, self.valid = i, j, src, valid

    def rel(self, a):
        """a_j - a_i of per-particle values a [dim, n]."""
        return a[:, self.j] - a[:, self.i]

    def both(self, a):
        """a_i + a_j of per-particle values a [n]."""
        return a[self.i] + a[self.j]

    def apply(self, w, a, P):
        """a [dim, n] plus the changes of impulses P [dim, S] on the second particles (-w_i P, +w_j P)."""
        zero = jnp.zeros((a.shape[0], 1), a.dtype)
        return a + jnp.take(jnp.concatenate([-w[self.i] * P, w[self.j] * P, zero], -1), self.src, axis=-1)


class SlotColour(Unilateral):
    """A grid slot inside a sweep: particle i's row with its partner j[i] [n] (-1: none), for every i at once."""

    split = True

    def __init__(self, j):
        self.partner = j
        self.j = jnp.maximum(j, 0)

    def rel(self, a):
        return a[:, self.j] - a

    def both(self, a):
        return a + a[self.j]

    def apply(self, w, a, P):
        return a.at[:, self.j].add(w[self.j] * P) - w * P

    def split_mass(self, w, act):
        """Mass splitting's effective masses 1 / (c_i w_i + c_j w_j), c the slot's rows `act` [n] (1 or 0) at
        each particle (`jaxcon.solvers.contact.jacobi_pass`)."""
        c = act + jnp.zeros_like(act).at[self.j].add(act)
        return L.safe_reciprocal(c * w + c[self.j] * w[self.j])


class GatheredSlotColour(Unilateral):
    """A sparse grid slot's rows gathered (`SparseSlots`): rows of particles i [C] with partners `partner` [C]
    (-1 where a row is padding; its particle is then out of range, and its gathered data is 0, so it changes
    nothing). The same updates as `SlotColour` on those rows, in the same order."""

    split = True

    def __init__(self, i, partner, n: int):
        self.partner, self.n = partner, n
        self.i, self.j = jnp.minimum(i, n - 1), jnp.maximum(partner, 0)

    def rel(self, a):
        return a[:, self.j] - a[:, self.i]

    def both(self, a):
        return a[self.i] + a[self.j]

    def apply(self, w, a, P):
        return a.at[:, self.j].add(w[self.j] * P).at[:, self.i].add(-(w[self.i] * P))

    def split_mass(self, w, act):
        c = jnp.zeros((self.n,), act.dtype).at[self.i].add(act).at[self.j].add(act)
        return L.safe_reciprocal(c[self.i] * w[self.i] + c[self.j] * w[self.j])


class SparseSlots(NamedTuple):
    """Where a grid's slots hold few rows: per slot, its rows' particles `idx` [K, C] (in order, n after the
    last) and their count [K]. A slot of at most C rows is swept on those rows gathered (`GatheredSlotColour`)
    instead of on all n (`SlotBlock`): at rest the 1024-disc box's fourth slot holds 38 rows (docs/contacts.md)."""

    idx: Array
    count: Array


#: A slot of at most n / SPARSE_SLOT rows is swept on its rows gathered (`SparseSlots`); 0: never.
SPARSE_SLOT = 8


def sparse_slots(partners) -> Optional[SparseSlots]:
    """`SparseSlots` of a grid's partners [n, K] (None below 2 SPARSE_SLOT particles, or with SPARSE_SLOT 0)."""
    n, K = partners.shape
    if not SPARSE_SLOT or n < 2 * SPARSE_SLOT:
        return None
    cap = int(np.ceil(n / SPARSE_SLOT))
    live = _slots_first(partners) >= 0
    idx, _ = L.first_true(jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (K, n)), live, cap, fill=n)
    return SparseSlots(idx, jnp.sum(live, 1, dtype=jnp.int32))


#: Up to this many obstacles, a loop over them (`each_obstacle`) is written out; above, it is a `lax.scan` over the
#: planes and one over the spheres, so that the program's size, and XLA's compile time, do not grow with their
#: number (docs/contacts.md: a 100-plane box).
UNROLL_OBSTACLES = 8


def each_obstacle(ct: ContactTopology, fn, carry, rows=None):
    """``carry, out = fn(carry, q, sphere, row)`` for every obstacle q, in order (planes, then spheres): `row` is
    `rows`' (a pytree of [Q, ...] leaves, or None) entry q, `sphere` (static) whether q is a sphere, and `q` an
    int, or a traced index above UNROLL_OBSTACLES obstacles. The outs are stacked, [Q, ...]."""
    Q, P = ct.n_obstacles, ct.n_planes
    if Q <= UNROLL_OBSTACLES:
        outs = []
        for q in range(Q):
            carry, out = fn(carry, q, q >= P, jax.tree.map(lambda a: a[q], rows))
            outs.append(out)
        return carry, jax.tree.map(lambda *a: jnp.stack(a), *outs)
    outs = []
    for sphere, lo, count in ((False, 0, P), (True, P, ct.n_spheres)):
        if not count:
            continue

        def body(c, xs, lo=lo, sphere=sphere):
            k, row = xs
            return fn(c, lo + k, sphere, row)
        carry, out = lax.scan(body, carry, (jnp.arange(count, dtype=jnp.int32),
                                            jax.tree.map(lambda a, lo=lo, count=count: a[lo:lo + count], rows)))
        outs.append(out)
    return carry, jax.tree.map(lambda *a: jnp.concatenate(a), *outs)


class ObstacleBlock:
    """Every obstacle's rows, [Q, ...] leaves: obstacle by obstacle (planes, then spheres; `each_obstacle`)."""

    def __init__(self, ct: ContactTopology):
        self.ct = ct

    def each(self, fn, carry, rows):
        return each_obstacle(self.ct, lambda c, q, sphere, row: fn(c, ObstacleColour(q, sphere), row), carry, rows)


class RoundBlock:
    """Listed pairs' rows, [..., R, S] leaves: round by round in a `lax.scan`."""

    def __init__(self, ct: ContactTopology):
        self.ct = ct

    def each(self, fn, carry, rows):
        ct = self.ct
        rows = jax.tree.map(lambda a: jnp.moveaxis(a, -2, 0), rows)
        xs = (ct.i.array, ct.j.array, ct.src.array, ct.valid.array, rows)

        def body(carry, x):
            i, j, src, valid, row = x
            return fn(carry, RoundColour(i, j, src, valid), row)

        carry, out = lax.scan(body, carry, xs)
        return carry, jax.tree.map(lambda a: jnp.moveaxis(a, 0, -2), out)


class SlotBlock:
    """A grid model's pair rows, [..., n, K] leaves, with their `partners` [n, K]: slot by slot in a `lax.scan`;
    a slot no particle uses (the grid fills each particle's slots from the first, so the last ones are often empty
    everywhere) is skipped. `major`: the multipliers (the second half of the rows) are slot-major already,
    [K, ..., n] (`in_solve`), and come back that way. `rows_major`: so are the partners ([K, n]) and the rows'
    data, moved once by a caller that runs many passes over the same rows (`slot_rows`)."""

    def __init__(self, partners, major: bool = False, rows_major: bool = False, sparse: Optional[SparseSlots] = None):
        self.partners, self.major, self.rows_major, self.sparse = partners, major, rows_major, sparse

    def each(self, fn, carry, rows):
        def body(carry, x):
            j, (data, lam), sp = x

            def whole(c):
                return fn(c, SlotColour(j), (data, lam))

            if sp is None:
                return lax.cond(jnp.any(j >= 0), whole, lambda c: (c, lam), carry)
            idx, count = sp

            def gathered(c):
                def take(a):
                    return jnp.take(a, idx, axis=-1, mode="fill", fill_value=0)
                colour = GatheredSlotColour(idx, jnp.take(j, idx, mode="fill", fill_value=-1), j.shape[-1])
                c, out = fn(c, colour, (jax.tree.map(take, data), jax.tree.map(take, lam)))
                return c, jax.tree.map(lambda a, o: a.at[..., idx].set(o, mode="drop"), lam, out)

            return lax.switch(_slot_branch(count, idx.shape[-1]), (lambda c: (c, lam), gathered, whole), carry)

        data, lam = rows
        partners = self.partners
        if not self.rows_major:
            partners, data = _slots_first(partners), jax.tree.map(_slots_first, data)
        if not self.major:
            lam = jax.tree.map(_slots_first, lam)
        sparse = None if self.sparse is None else tuple(self.sparse)
        carry, out = lax.scan(body, carry, (partners, (data, lam), sparse))
        return carry, out if self.major else jax.tree.map(_slots_last, out)


def _slot_branch(count, cap: int):
    """Which way `SlotBlock` sweeps a slot of `count` rows: 0 skipped (empty), 1 gathered (at most `cap` rows,
    `GatheredSlotColour`), 2 whole. Under `jax.vmap` one way for every copy, unbatched, so that `lax.switch`
    (or `lax.cond`) runs one branch rather than every branch (a batched index makes it a select of every
    branch's result): skipped where the slot is empty in every copy, else whole. A batch of 4 256-disc boxes
    (PGS(10), 120 steps from the drop) took 2.1 s so, 3.9 s with a batched index and no gathered branch (every
    slot swept whole in every sweep, the empty ones too), and 4.7 s with the gathered branch as well. (A model
    without `SparseSlots` keeps its `lax.cond` on `jnp.any`: the same rule there changed the rounding of the
    compiled programs under the suite's XLA flags.)"""
    @jax.custom_batching.custom_vmap
    def branch(count):
        return jnp.where(count == 0, 0, jnp.where(count <= cap, 1, 2)).astype(jnp.int32)

    @branch.def_vmap
    def _batched(axis_size, in_batched, count):
        if not in_batched[0]:
            return branch(count), False
        return jnp.where(jnp.all(count == 0), 0, 2).astype(jnp.int32), False

    return branch(count)


def _slots_first(a):
    """A grid's [..., n, K] leaf slot-major, [K, ..., n]."""
    return jnp.moveaxis(a, -1, 0)


def _slots_last(a):
    """`_slots_first` undone: [K, ..., n] -> [..., n, K]."""
    return jnp.moveaxis(a, 0, -1)


def slot_rows(partners, data, sparse: Optional[SparseSlots] = None):
    """A grid's `partners` [n, K] and rows' data [..., n, K] moved slot-major once, with the block that reads
    them so (`SlotBlock(rows_major=True)`): for the position pass, whose up to `GRID_OVERLAP_PASSES` passes read
    the same rows. Moving them in each pass made a pass of the 4096-disc box about a fifth dearer (0.24 against
    0.19 ms; docs/contacts.md)."""
    return SlotBlock(_slots_first(partners), rows_major=True, sparse=sparse), jax.tree.map(_slots_first, data)


def pair_block(ct: ContactTopology, partners=None, major: bool = False, sparse: Optional[SparseSlots] = None):
    """The pair rows' block: a grid model's slots (its `partners` [n, K]; `major`, `sparse`: `SlotBlock`), else
    the listed pairs' rounds."""
    return SlotBlock(partners, major, sparse=sparse) if partners is not None else RoundBlock(ct)


# ---- a grid's pair impulses inside a velocity solve -------------------------------------------------------------
# A grid model's pair impulses are [..., n, K] (a particle's K slots side by side), the layout of its rows and
# partners, which the search, the warm start and the position pass use. A sweep updates them slot by slot, and
# moving them slot-major and back in every sweep cost more than moving them once per solve: `solve_phases` does
# that (`in_solve`, `impulses_slot_major`) and moves them back after (`impulses_slot_minor`). The rows, which do
# not change within the solve, stay as they are: moving them once too made the sweeps cheaper but the step no
# faster, as the rows and the warm start took longer (probably XLA's layout assignment; docs/contacts.md).


def obstacles_in_solve(obs: Rows, w) -> Rows:
    """Obstacle rows inside a velocity solve whose obstacle impulses are split by obstacle
    (`obstacle_impulses_split`), where a sweep picks rows (`obs.sel`): each obstacle's rows split off, flat, and
    its picked rows and the inverse masses `w` [1, *view] at them gathered, once here (`Selection.planes`)
    instead of in every sweep. The sweeps compute the same updates (`solvers.contact._selected_obstacles`)."""
    nview = obs.gap.ndim - 1
    n = int(np.prod(obs.gap.shape[1:]))
    wf = w.reshape(-1)
    planes = []
    for q in range(obs.gap.shape[0]):
        f = jax.tree.map(lambda a: a[q].reshape(a[q].shape[:a[q].ndim - nview] + (-1,)), obs._replace(sel=None))
        at = jnp.minimum(obs.sel.idx[q], n - 1)
        fs = jax.tree.map(lambda a: jnp.take(a, at, axis=-1), f)
        fs = fs._replace(k=fs.k * (obs.sel.idx[q] < n).astype(fs.k.dtype))      # an unused entry: no row
        planes.append((f, fs, jnp.take(wf, at)[None]))
    return obs._replace(sel=obs.sel._replace(planes=tuple(planes)))


def obstacle_impulses_split(imp: Impulses) -> Impulses:
    """The obstacle impulses as a tuple per obstacle, flat: obs_n ([n], ...), obs_t ([dim, n], ...)."""
    Q, dim = imp.obs_n.shape[0], imp.obs_t.shape[1]
    return imp._replace(obs_n=tuple(imp.obs_n[q].reshape(-1) for q in range(Q)),
                        obs_t=tuple(imp.obs_t[q].reshape(dim, -1) for q in range(Q)))


def obstacle_impulses_joined(imp: Impulses, view) -> Impulses:
    """`obstacle_impulses_split` undone, `view` the particles' view shape: obs_n [Q, *view], obs_t [Q, dim, *view]."""
    return imp._replace(obs_n=jnp.stack([a.reshape(view) for a in imp.obs_n]),
                        obs_t=jnp.stack([a.reshape((a.shape[0],) + tuple(view)) for a in imp.obs_t]))


def phase(f: Optional[Rows], late) -> Optional[Rows]:
    """Rows with the target of the solve's phase (`common.solve_phases`): `target` where `late`, else the
    compression target `target_c`, in the obstacles' split-off and gathered rows too (`obstacles_in_solve`)."""
    if f is None:
        return None

    if f.sel is not None and f.sel.planes is not None:     # the split-off rows switch where they are read
        return f._replace(sel=f.sel._replace(late=late))
    return phase_target(f, late)


def phase_target(r: Rows, late) -> Rows:
    """`r` with the target of the phase `late` (`phase`): `target` where `late`, else `target_c`; `r` itself
    where `late` is None."""
    return r if late is None else r._replace(target=jnp.where(late, r.target, r.target_c))


def in_solve(pairs: Rows) -> Rows:
    """A grid's pair rows inside a velocity solve whose pair impulses are slot-major (`impulses_slot_major`): `i`
    None, which `is_in_solve` tests, and `j` as it is."""
    return pairs._replace(i=None)


def is_in_solve(pairs: Rows) -> bool:
    """Whether these are a grid's pair rows marked by `in_solve`."""
    return pairs.i is None and pairs.j is not None


def impulses_slot_major(imp: Impulses) -> Impulses:
    """A grid model's pair impulses with the slot axis first (pair_n [K, n], pair_t [K, dim, n])."""
    return imp._replace(pair_n=_slots_first(imp.pair_n), pair_t=_slots_first(imp.pair_t))


def impulses_slot_minor(imp: Impulses) -> Impulses:
    """`impulses_slot_major` undone: pair_n [n, K], pair_t [dim, n, K]."""
    return imp._replace(pair_n=_slots_last(imp.pair_n), pair_t=_slots_last(imp.pair_t))


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
#: pass projects onto one slop: the position pass removes overlap without making velocity, and what it leaves (within
#: its stopping tolerance, `solvers.contact.GRID_PASS_STOP`, or in a column too tall for its passes) is turned into
#: velocity only beyond PUSH_SLOPS. Both removing the same overlap kept piles moving (docs/contacts.md, piles at
#: rest): beyond one slop the 1024-disc box moved at 1.1 m/s; beyond two the 4096-disc box still flowed at 2.3 m/s
#: after 8 s, 97% of its discs faster than 0.05 m/s; beyond six it comes to rest (0.03 m/s at 8 s with 2 substeps).
PUSH_SLOPS = 6.0


def _targets(C, C_spec, vn0, vn1, impact, toi, cs: ContactSystem, beta, h, bounce, slop=0.0):
    """Target velocity of contacts with gap C (`_gap`: > 0 separated, <= 0 touching), normal velocity vn0 at
    the start of the step and vn1 after the external forces, and an impact at `toi` where `impact` (module
    docstring; a contact within rounding of touching, C = 0, may be an impact at toi ~ 0). `bounce` = (the
    separation speed restitution asks of each row, whether the row collided elastically): `chain_bounces`.

    Within an impact step the approach velocity is taken to change linearly, vn0 + (vn1 - vn0) t / h, so the
    impact speed u depends on the time of impact, and the forces keep acting for the rest of the step after the
    bounce: target = max(b + (vn1 - vn0) (h - toi) / h, 0), b the bounce (e u for a lone impact). This keeps
    the map from one state to the next continuous where the impact moves from one step to the next (at toi = h
    and toi = 0 both sides give the same state), and gives the time-of-impact dependence of u its right
    derivative (du/dC = a / |vn1|).
    A separated contact that is not an impact gets the speculative target -max(C_spec, 0) / h, C_spec its gap
    along the row's normal: it may close that gap within the step, and never pushes; in the restitution phase a
    separated contact that the impact propagation made collide elastically gets its bounce instead. C_spec < 0
    where a contact overlaps by less than the rounding tolerance (separated by `_gap`, 1.2 mm at 40 m in
    float32): -C_spec / h pushed that overlap out within one step, past the Baumgarte threshold, and kicked
    single discs deep in the 4096-disc box at 0.1 to 0.2 m/s (docs/contacts.md, piles at rest). A touching one
    pushes its overlap beyond `slop` (m) out at -beta (C + slop) / h, at most `PUSH_OUT_SPEED`.
    Returns (target, target without restitution)."""
    bounce, elastic = bounce
    rest = (vn1 - vn0) * (h - toi) / h
    push = jnp.minimum(-beta * jnp.minimum(C + slop, 0) / h, PUSH_OUT_SPEED)

    def target(after, hit):
        return jnp.where(hit, after, jnp.where(C > 0, -jnp.maximum(C_spec, 0) / h, jnp.maximum(after, push)))

    return target(jnp.maximum(bounce + rest, 0), impact | elastic), target(jnp.maximum(rest, 0), impact)


#: Gauss-Seidel passes of the impact propagation (`chain_bounces`): an impact is passed on through up to about
#: this many touching contacts in a row within one step (two per pass along a chain of listed pairs).
BOUNCE_PASSES = 8


def chain_bounces(cs: ContactSystem, w, v, obs, pairs, partners=None):
    """Restitution targets of every contact row from sequential impacts, per step: ((obstacle bounce, elastic)
    or None, (pair bounce, elastic) or None), each [rows' shape].

    `obs`, `pairs`: per row (n, k, reach, off): normal, effective mass (0: no row), the approach speed the row
    must exceed to collide within the step (its gap over h for a separated row that is no impact, else 0) and
    a speed added to its normal velocity (the external forces' share up to its time of impact). Starting from
    the velocities `v` before any impulse (particles [dim, *view]), `BOUNCE_PASSES` Gauss-Seidel passes
    (obstacles, then the pairs round by round or slot by slot, as `solvers.contact.sweep`) treat each row
    that approaches faster than its reach as a collision of its two bodies alone: the impulse (1 + e) k u
    for an approach u, e = 0 at or below the restitution threshold (Newton's restitution applied pair by
    pair, Box2D's per-contact rule on the velocity the contact meets). A rack or a row of touching balls
    then passes a hit on ball by ball, as separate impacts in the order of the chain: the end ball of a
    Newton's cradle leaves with the hit ball's velocity and the others stay, two in give two out. A pair
    collision never raises the kinetic energy (e <= 1), so neither does the sequence.

    A row that collided elastically (e > 0) gets as bounce its final separation speed of the sequence,
    max(vn + off, 0); every other row 0 (no restitution). The solvers then solve for those separation speeds
    with every row and constraint at once, so other constraints (rods, a floor) still hold. A lone impact's
    bounce is e u, as Newton's rule; with no row approaching faster than the threshold (or e = 0) the passes
    are skipped and every bounce is 0."""
    dim, shape = v.shape[0], v.shape
    e, threshold = cs.restitution, cs.threshold
    wf = w.reshape(-1)

    def colour(wc):
        def update(vc, c, rows):
            (n, k, reach, off), elastic = rows
            u = -(dot(c.rel(vc), n) + off)
            hit = (k > 0) & (u > reach) & (u > 0)
            if c.split:           # a grid slot's rows share particles: mass splitting over those that collide
                k = c.split_mass(wc, hit.astype(vc.dtype)) * (k > 0).astype(vc.dtype)
            ee = jnp.where(u > threshold, e, 0)
            P = n * jnp.where(hit, (1 + ee) * u * k, 0)
            return c.apply(wc, vc, P), elastic | (hit & (ee > 0))
        return update

    def one_pass(_, carry):
        vc, el_o, el_p = carry
        if obs is not None:
            vc, el_o = ObstacleBlock(cs.ct).each(colour(w), vc, (obs, el_o))
        if pairs is not None:
            vf, el_p = L.each_colour(pair_block(cs.ct, partners), colour(wf), vc.reshape(dim, -1), (pairs, el_p))
            vc = vf.reshape(shape)
        return vc, el_o, el_p

    def normal_speeds(vc):
        out = [None, None]
        if obs is not None:
            out[0] = dot(jnp.moveaxis(obs[0], 1, 0), vc[:, None]) + obs[3]
        if pairs is not None:
            vf = vc.reshape(dim, -1)
            ia, ja, _, _ = pair_slots(cs.ct, vf.shape[1], partners)
            out[1] = dot(pairs[0], vf[:, ja] - vf[:, ia]) + pairs[3]
        return out

    no = tuple(None if f is None else jnp.zeros(f[1].shape, bool) for f in (obs, pairs))
    start = normal_speeds(v)
    fast = jnp.zeros((), bool)
    for f, vn in zip((obs, pairs), start):
        if f is not None:
            fast = fast | jnp.any((f[1] > 0) & (-vn > jnp.maximum(f[2], threshold)))

    def propagate(v):
        vc, el_o, el_p = lax.fori_loop(0, BOUNCE_PASSES, one_pass, (v,) + no)
        return vc, (el_o, el_p)

    vc, elastic = lax.cond(fast & (e > 0), propagate, lambda v: (v, no), v)
    return tuple(None if f is None else (jnp.where(el, jnp.maximum(vn, 0), 0), el)
                 for f, vn, el in zip((obs, pairs), normal_speeds(vc), elastic))


def tolerance(scale):
    """Rounding tolerance of a gap computed from numbers of size `scale`: `ROUNDING` eps scale (`_gap`)."""
    return ROUNDING * jnp.finfo(scale.dtype).eps * scale


def _gap(C, tol):
    """The gap a row uses: C + tol (`tolerance`), so that a contact touches (gap <= 0) only once it overlaps
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
    uu = dot(u, u)
    du = dot(d, u)
    disc = du * du - uu * (Ci * (dist + Ri))
    hit = (Ci > 0) & (du < 0) & (disc > 0)
    root = jnp.sqrt(jnp.where(hit, disc, 1))
    t = Ci * (dist + Ri) / jnp.where(hit, root - du, 1)
    hit = hit & (t < h)
    toi = jnp.where(hit, t, 0)
    _, n_hit = _norm(d + toi * u)
    n = jnp.where(hit, n_hit, n0)
    return n, C, dot(n, d) - R, hit, hit, toi


def magnitude(a):
    """Sum of |a| over the leading (dim) axis: the size of the coordinates a gap is computed from. Written out
    component by component, as `dot`: XLA's CPU backend sends `jnp.sum(jnp.abs(a), 0)` to a reduction kernel of
    its own."""
    out = jnp.abs(a[0])
    for k in range(1, a.shape[0]):
        out = out + jnp.abs(a[k])
    return out


def _obstacle_geometry(cs: ContactSystem, x, v, h):
    """(n [Q, dim, *view], C, C_n, hit, impact, toi, tol [Q, *view]) of every particle against every plane,
    then every sphere, for particles moving at `v` over the step; tol is `_gap`'s rounding tolerance."""
    dim, nview = x.shape[0], x.ndim - 1
    r = cs.radius[0]
    size = magnitude(x) + r

    def one(_, q, sphere, row):
        if not sphere:
            nrm = jnp.broadcast_to(cs.plane_normal[q].reshape((dim,) + (1,) * nview), x.shape)
            C = dot(nrm, x) - cs.plane_offset[q] - r
            tol = tolerance(size + jnp.abs(cs.plane_offset[q]))
            vn = dot(nrm, v)
            Ci = _gap(C, tol)                  # as in `_swept`: the impact is when the gap reaches -tol
            impact = (Ci > 0) & (Ci + h * vn < 0)
            return None, (nrm, C, C, impact, impact, jnp.where(impact, Ci / jnp.where(impact, -vn, 1), 0), tol)
        s = q - cs.ct.n_planes
        c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
        R = cs.sphere_radius[s] + r
        tol = tolerance(size + magnitude(c) + R)
        return None, _swept(x - c, v, R, h, tol) + (tol,)
    return each_obstacle(cs.ct, one, None)[1]


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
    passes its `partners` [n, K] (from `grid.neighbours`). `slop`: the solver's contact slop, a fraction of the
    contact distance (`CONTACT_SLOP`; 0: none)."""
    ct, dim = cs.ct, x.shape[0]
    xf, vf, v0f, wf = x.reshape(dim, -1), v.reshape(dim, -1), v0.reshape(dim, -1), w.reshape(-1)
    obs = _obstacle_geometry(cs, x, v, h) if ct.n_obstacles else None
    pairs, index = None, None
    if ct.n_pairs or ct.has_grid:
        ia, ja, valid, index = pair_slots(ct, xf.shape[1], partners)
        xi, xj, R = xf[:, ia], xf[:, ja], cs.radius_flat[ia] + cs.radius_flat[ja]
        tol = tolerance(magnitude(xi) + magnitude(xj) + R)
        pairs = _swept(xj - xi, vf[:, ja] - vf[:, ia], R, h, tol)
        live = jnp.asarray(valid)          # a padding or empty slot is no impact (it would hide a real one)
        pairs = pairs[:3] + (pairs[3] & live, pairs[4] & live, pairs[5], tol)
    obs, pairs = _first_impacts(ct, obs, pairs, xf.shape[1], index)

    def prepare(geometry, vn0, vn1, winv, k, distance, window):
        n, C, C_n, _, impact, toi, tol = geometry
        toi = jnp.where(impact, toi, 0)
        gap = _gap(C, tol)
        s = slop * distance
        # Warm-started: touching, impacts, and pairs within the slop of touching either way (a disc of a pile that
        # lifts off its neighbour by less than the slop keeps the impulse it leant on it with; measured in
        # docs/contacts.md). Obstacles keep gap <= 0: warm-starting those within the slop as well brought the pile
        # to rest sooner (0.003 against 0.018 m/s at 8 s) but the float32 drape's gradients 1.9% off float64.
        warm = impact | (gap <= (s if window else 0))
        f = Rows(n, None, k, winv, toi, gap, None, near=C <= tol, warm=warm)
        # the impact propagation's view of the row (`chain_bounces`): the approach speed it must exceed to close the
        # gap within the step (0 for impacts and rows touching within rounding; none for a separated row that
        # approaches and closes it already but is no impact: one that touches only at the end of the step, or a
        # later impact `_first_impacts` cleared), and the external forces' share up to the impact
        reach = jnp.maximum(C_n, 0) / h
        reach = jnp.where(impact | (C <= tol), 0, jnp.where((vn0 >= 0) | (-vn0 < reach), reach, jnp.inf))
        return f, (C_n, vn0, vn1, impact, PUSH_SLOPS * s), (n, k, reach, (vn1 - vn0) * toi / h)

    def finish(prep, bounce):
        f, (C_n, vn0, vn1, impact, push_slop) = prep
        target, target_c = _targets(f.gap, C_n, vn0, vn1, impact, f.toi, cs, beta, h, bounce, push_slop)
        return f._replace(target=target, target_c=target_c)

    if obs is not None:
        n = obs[0]
        winv = jnp.broadcast_to(w[0], obs[1].shape)
        nd = jnp.moveaxis(n, 1, 0)                     # [dim, Q, *view]
        obs = prepare(obs, dot(nd, v0[:, None]), dot(nd, v[:, None]), winv, L.safe_reciprocal(winv), cs.radius, False)
    if pairs is not None:
        n = pairs[0]
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype)
        vn0, vn1 = (dot(n, a[:, ja] - a[:, ia]) for a in (v0f, vf))
        pairs = prepare(pairs, vn0, vn1, winv, k, cs.radius_flat[ia] + cs.radius_flat[ja], True)
    bounces = chain_bounces(cs, w, v0, *(None if f is None else f[2] for f in (obs, pairs)), partners=partners)
    obs, pairs = (None if f is None else finish(f[:2], b) for f, b in zip((obs, pairs), bounces))
    if obs is not None and xf.shape[1] >= SELECT_FROM:
        obs = obs._replace(sel=select_obstacles(obs, vf, h))
    if pairs is not None and index is not None:
        pairs = pairs._replace(i=ia, j=partners, slots=sparse_slots(partners))
    return obs, pairs


#: How deep a speculative row (`speculative_rows`) lets a contact go, as a fraction of its contact distance.
SPECULATIVE_DEPTH = 0.5


def speculative_rows(cs: ContactSystem, w, x, v, h, partners=None, depth=SPECULATIVE_DEPTH):
    """Speculative rows for a solver whose contacts are springs (Penalty): (obstacle Rows or None, pair Rows or
    None) whose target vn' >= -max(C_n + depth R, 0) / h lets each contact close its gap and go at most `depth`
    of its contact distance R deep within the (sub)step, never further, along the normal at the time of impact
    of the straight paths at the velocities `v` (`_swept`, as the velocity rows' speculative contacts; C_n the
    gap along it). A contact already that deep gets the target 0: it goes no deeper, and its spring pushes it out.
    Spheres and pairs only (a plane is a half-space: nothing passes it); no restitution, no friction (the
    spring's). A spring contact stopped this way loses the approach speed the row takes; a contact the spring
    holds within `depth` on its own is untouched."""
    ct, dim = cs.ct, x.shape[0]
    obs = pairs = None
    if ct.n_spheres:
        geo = _obstacle_geometry(cs, x, v, h)
        n, C_n = geo[0], geo[2]
        r = cs.radius[0]
        reach = jnp.concatenate([jnp.zeros((ct.n_planes,) + r.shape, r.dtype),
                                 cs.sphere_radius.reshape((-1,) + (1,) * r.ndim) + r])      # planes, then spheres
        winv = jnp.broadcast_to(w[0], C_n.shape)
        sphere = (jnp.arange(ct.n_obstacles) >= ct.n_planes).reshape((-1,) + (1,) * (C_n.ndim - 1))
        k = L.safe_reciprocal(winv) * sphere.astype(winv.dtype)
        obs = Rows(n, -jnp.maximum(C_n + depth * reach, 0) / h, k, winv, jnp.zeros_like(C_n), C_n)
    if ct.n_pairs or ct.has_grid:
        xf, vf, wf = x.reshape(dim, -1), v.reshape(dim, -1), w.reshape(-1)
        ia, ja, valid, _ = pair_slots(ct, xf.shape[1], partners)
        R = cs.radius_flat[ia] + cs.radius_flat[ja]
        xi, xj = xf[:, ia], xf[:, ja]
        geo = _swept(xj - xi, vf[:, ja] - vf[:, ia], R, h, tolerance(magnitude(xi) + magnitude(xj) + R))
        n, C_n = geo[0], geo[2]
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype)
        pairs = Rows(n, -jnp.maximum(C_n + depth * R, 0) / h, k, winv, jnp.zeros_like(C_n), C_n)
        if partners is not None:
            pairs = pairs._replace(i=ia, j=partners)
    return obs, pairs


#: Models of at least this many particles sweep an obstacle's rows only where a particle is within reach of it
#: (`select_obstacles`, `solvers.contact.sweep`): the 1024-disc box has 3072 plane rows, of which about 100 touch.
SELECT_FROM = 256


def select_obstacles(obs: Rows, vf, h) -> Selection:
    """The obstacle rows a sweep is likely to change (`Selection`): those within h * 2 max|v| of touching (vf
    [dim, n]: the velocities after the external forces), which includes every touching and warm-started row; at
    most a quarter of the particles per obstacle (the rest are left out of both `idx` and `inside`, so a sweep in
    which one of them would change solves the whole obstacle). Only indices: no gradient flows through it. The
    sweep checks, every time, that the rows it leaves out would not change (`solvers.contact.sweep`)."""
    gap = lax.stop_gradient(obs.gap)
    Q, n = gap.shape[0], vf.shape[1]
    cap = max(32, -(-n // 4))
    speed = jnp.sqrt(jnp.max(L.dot0(vf, vf)))
    inside = (gap <= 2 * h * lax.stop_gradient(speed)) | obs.warm
    inside = inside.reshape(Q, n)
    idx, rank = L.first_true(jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (Q, n)), inside, cap, fill=n)
    return Selection(idx, inside & (rank < cap))


# ---- the restitution phases' rows -------------------------------------------------------------------------------
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


def pair_total(ct, w, P, sign_i, index=None, partners=None):  # noqa: D401
    """Sum over every pair slot of +w_j P on j and sign_i * w_i P on i: [dim, n] (a scatter-add). `index`:
    the slots' flat (i, j) (`pair_index`; default the static rounds'). `partners` [n, K]: a grid's slots, whose i
    is each row's own particle, so the i part is a sum over its K slots (written out), not a scatter."""
    dim = P.shape[0]
    wf = w.reshape(-1)
    ia, ja = (ct.i.array.reshape(-1), ct.j.array.reshape(-1)) if index is None else index
    Pf = P.reshape(dim, -1)
    if partners is not None:
        Ps = P.reshape(dim, -1, partners.shape[-1])
        own = Ps[..., 0]
        for k in range(1, Ps.shape[-1]):
            own = own + Ps[..., k]
        return (sign_i * wf * own).at[:, ja].add(wf[ja] * Pf)
    out = jnp.zeros((dim, wf.shape[0]), P.dtype)
    return out.at[:, ja].add(wf[ja] * Pf).at[:, ia].add(sign_i * wf[ia] * Pf)


# ---- rows at position level (XPBD, Penalty) and of XPBD's velocity pass ---------------------------------
def obstacle_gap(cs: ContactSystem, q, p, sphere: Optional[bool] = None):
    """(unit normal [dim, *view], gap [*view]) of every particle at `p` against obstacle q (planes first).
    A traced q (`each_obstacle`) comes with `sphere`, whether it is a sphere."""
    dim, nview = p.shape[0], p.ndim - 1
    r = cs.radius[0]
    if not (q >= cs.ct.n_planes if sphere is None else sphere):
        nrm = jnp.broadcast_to(cs.plane_normal[q].reshape((dim,) + (1,) * nview), p.shape)
        return nrm, dot(nrm, p) - cs.plane_offset[q] - r
    s = q - cs.ct.n_planes
    c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
    dist, nrm = direction(p - c)
    return nrm, dist - cs.sphere_radius[s] - r


def obstacle_moved_gap(cs: ContactSystem, q, x, dp, ahead=None, hold=0.0, sphere: Optional[bool] = None):
    """(unit normal, gap, floor) of every particle against obstacle q at positions x + dp, x the start of a
    position-level substep and dp the displacement since (`overlap_normal`, with the predicted one `ahead`,
    holding start overlaps deeper than `hold`, at least CONTACT_SLOP r; a plane's normal is its own). The gap is
    computed as (gap at x) + n . dp, so a displacement below an ulp of x still counts. q and `sphere` as for
    `obstacle_gap`."""
    dim, nview = x.shape[0], x.ndim - 1
    r = cs.radius[0]
    if not (q >= cs.ct.n_planes if sphere is None else sphere):
        nrm = jnp.broadcast_to(cs.plane_normal[q].reshape((dim,) + (1,) * nview), x.shape)
        C0 = dot(nrm, x) - cs.plane_offset[q] - r
        return nrm, C0 + dot(nrm, dp), jnp.where(C0 < -jnp.maximum(hold, CONTACT_SLOP * r), C0, 0)
    s = q - cs.ct.n_planes
    c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
    return overlap_normal(x - c, dp, cs.sphere_radius[s] + r, ahead, jnp.maximum(hold, CONTACT_SLOP * r))


def obstacle_reach(cs: ContactSystem, q, sphere: Optional[bool] = None):
    """The contact distance of a particle (of the model's contact radius) from obstacle q: the radius for a
    plane, the radius plus the sphere's for a sphere (q and `sphere` as for `obstacle_gap`)."""
    r = cs.radius[0]
    if not (q >= cs.ct.n_planes if sphere is None else sphere):
        return r
    return r + cs.sphere_radius[q - cs.ct.n_planes]


def obstacle_size(cs: ContactSystem, q, sphere: Optional[bool] = None):
    """A size of obstacle q's parameters for a rounding tolerance (`tolerance`) at position level: the sum of
    the absolute components of a plane's normal, or of a sphere's centre (q and `sphere` as for `obstacle_gap`)."""
    if not (q >= cs.ct.n_planes if sphere is None else sphere):
        return jnp.sum(jnp.abs(cs.plane_normal[q]))
    return jnp.sum(jnp.abs(cs.sphere_centre[q - cs.ct.n_planes]))


def velocity_rows(cs: ContactSystem, w, p, v_before, imp: Impulses, partners=None, moved=None):
    """Velocity rows (obstacle Rows or None, pair Rows or None) at the end of the position solve: normals and
    gaps at `p`, restitution targets from `v_before` (start of the substep, after gravity) by the impact
    propagation of every solver (`chain_bounces`), and effective masses only for contacts that pushed in this
    substep (lam_n > 0; the others get k = 0, no impulse). A grid model's pair rows are its `partners`' slots
    [n, K].

    `moved` = (x, dp, ahead): p = x + dp came from the position pass's start x, displacement dp and predicted
    displacement `ahead`; the rows then take the position pass's own normals (`overlap_normal`: a start overlap's
    start normal, a swept contact's normal at its time of impact), so that the velocity rows, which may take
    back the position impulses (their accumulated impulse starts from them), act along the normals those were
    applied along. On the end's own normals, taking a swept pair's position impulse back along another
    direction left an impulse across the pair that gained energy (RATTLE's break at dt 1/60: +7e-4 of its
    kinetic energy in one step)."""
    ct, dim = cs.ct, p.shape[0]
    obs = pairs = None
    x0, dp, ahead = (None, None, None) if moved is None else moved
    if ct.n_obstacles:
        def gap(c, q, sphere, row):
            if moved is None:
                return c, obstacle_gap(cs, q, p, sphere=sphere)
            return c, obstacle_moved_gap(cs, q, x0, dp, ahead, sphere=sphere)[:2]
        n, C = each_obstacle(ct, gap, None)[1]
        winv = jnp.broadcast_to(w[0], C.shape)
        k = L.safe_reciprocal(winv) * (imp.obs_n > 0).astype(C.dtype)
        obs = Rows(n, None, k, winv, jnp.zeros_like(C), C)
    if ct.n_pairs or ct.has_grid:
        pf, wf = p.reshape(dim, -1), w.reshape(-1)
        ia, ja, valid, _ = pair_slots(ct, pf.shape[1], partners)
        R = cs.radius_flat[ia] + cs.radius_flat[ja]
        if moved is None:
            dist, n = direction(pf[:, ja] - pf[:, ia])
            C = dist - R
        else:
            x0f, df, af = (a.reshape(dim, -1) for a in (x0, dp, dp if ahead is None else ahead))
            n, C, _ = overlap_normal(x0f[:, ja] - x0f[:, ia], df[:, ja] - df[:, ia], R, af[:, ja] - af[:, ia])
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype) * (imp.pair_n > 0).astype(C.dtype)
        pairs = Rows(n, None, k, winv, jnp.zeros_like(C), C)
        if partners is not None:
            pairs = pairs._replace(i=ia, j=partners)
    bounces = chain_bounces(cs, w, v_before, *(None if f is None else (f.n, f.k, 0 * f.k, 0 * f.k)
                                               for f in (obs, pairs)), partners=partners)
    return tuple(None if f is None else f._replace(target=b[0]) for f, b in zip((obs, pairs), bounces))
