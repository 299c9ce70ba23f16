"""Static constraint topology, fixed in NumPy when a model is built.

Constraints are distance constraints between particle pairs (i, j). They are grouped into colours such that
no two constraints of one colour share a particle, so a whole colour can be solved at once and Gauss-Seidel
order holds between colours. Internally particles are stored struct-of-arrays as ``[dim, *view]`` (``view`` is
``(n,)`` or a grid shape such as ``(ny, nx)``) and each colour is a *block*:

* a strided block, when the colour's first and second endpoints each form a strided box of the view (chains,
  structured cloth colourings). Reading is a strided slice, writing back is a pad: no gather, no scatter.
* a gather block otherwise. Reading is a gather; writing back is also a gather, from the block's impulses into
  particle order (each particle appears at most once per colour, so no scatter-add is needed).

* a table block (the *compact* layout), which holds every colour at once as a ``[colours, width]`` table of
  index pairs, padded with an out-of-range particle index. Per-constraint quantities (frames, biases, warm
  starts) are computed for the whole table in one pass; Gauss-Seidel sweeps visit its rows in a `lax.scan`
  (`layout.each_colour`), so one colour's code is traced and compiled once instead of once per colour.

Small models with several colours get the compact layout by default: it compiles their gradients 3 to 4x
faster and costs run time, which grows with the colour size (docs/performance.md has the trade measured).
Larger models keep one block per colour. ``jc.build(..., layout=...)`` chooses explicitly.

The internal particle order may differ from the user's. When a colour steps by 2 along the last (contiguous)
axis of a grid view, e.g. a cloth's horizontal edges split by column parity, each row of that axis is stored
as its even entries, then its odd ones (a permutation; the view keeps the grid's shape): every such colour
then reads and writes unit-step runs of a row. On CPU the column-parity colours of a 64x64 cloth ran 4 to 7x
slower than the row-parity ones in the plain layout, and as fast in the permuted one. ``order`` (internal
position -> user particle) and ``pos`` (its inverse) convert.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Optional

import numpy as np

from jaxcon.core.pytree import StaticArray


def greedy_colouring(i: np.ndarray, j: np.ndarray, n: int, fixed=None) -> np.ndarray:
    """Greedy edge colouring in the given order: smallest colour not used at either endpoint. Endpoints marked
    in `fixed` ([n] bool, default none) never conflict: a fixed particle does not move, so any number of
    constraints of one colour may share it."""
    colour = np.empty(len(i), dtype=np.int64)
    used = [set() for _ in range(n)]
    free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
    for k, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
        c = 0
        while (free[a] and c in used[a]) or (free[b] and c in used[b]):
            c += 1
        colour[k] = c
        used[a].add(c)
        used[b].add(c)
    return colour


#: A particle with at least this many constraints is a hub: its constraints are solved together as a *star*
#: (`star_colouring`). Below it Gauss-Seidel over single constraints is stable (a cloth particle has at most 8).
STAR_MIN_DEGREE = 9


def star_colouring(i: np.ndarray, j: np.ndarray, n: int, fixed=None) -> tuple[np.ndarray, np.ndarray]:
    """The default colouring: (star [m], colour [m]). `fixed` ([n] bool): particles that never move, which no
    two constraints of a colour conflict over and which are never hubs (their constraints do not couple).

    Hubs (free particles with at least `STAR_MIN_DEGREE` constraints), most constraints first, each take the
    constraints at them that no earlier hub took, one per other particle (a duplicated rod stays outside): a
    *star*, whose constraints share only the hub and are solved together, exactly (`layout.block_solve`).
    star[k] is constraint k's star (stars numbered from 0), or -1. Stars are coloured greedily (two stars that
    share a particle get different colours) and the other constraints greedily among themselves
    (`greedy_colouring`, in the given order); the two colour sets are numbered independently.

    Why: Gauss-Seidel one constraint at a time around a hub has an error operator with large complex
    eigenvalues. XPBD's v = (p - x) / h feeds the unconverged part of each substep into the next one's
    prediction (the constraint error follows e' = G (2 e - e_prev)), and PGS's warm start feeds it through
    the next step's impulses: from about 9 spokes (XPBD) and 32 (PGS(10)) that recurrence grows, and a hub of
    spokes at rest length, released under gravity, turned rounding error into 1e49 m (XPBD, 16 spokes). A star
    solved exactly has no such error: the recurrence decays at the Baumgarte rate (docs/hard-cases.md)."""
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    m = len(i)
    free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
    star = np.full(m, -1, np.int64)
    deg = np.bincount(np.concatenate([i, j]), minlength=n)
    hubs = [int(p) for p in np.argsort(-deg, kind="stable") if deg[p] >= STAR_MIN_DEGREE and free[p]]
    members = []
    for p in hubs:
        ks = np.nonzero(((i == p) | (j == p)) & (star < 0))[0]
        other = np.where(i[ks] == p, j[ks], i[ks])
        _, first = np.unique(other, return_index=True)          # one constraint per other particle
        ks = ks[np.sort(first)]
        if len(ks) >= 2:
            star[ks] = len(members)
            members.append((p, ks))
    colour = np.full(m, -1, np.int64)
    groups = [np.unique(np.concatenate([i[ks], j[ks]])) for _, ks in members]
    for (_, ks), c in zip(members, _first_fit(groups, free)):
        colour[ks] = c
    rest = star < 0
    colour[rest] = greedy_colouring(i[rest], j[rest], n, fixed)
    return star, colour


def set_stars(particles: np.ndarray, n: int, fixed=None) -> list:
    """The hubs of a constraint set (rows `particles` [m, k]): [(hub, its rows)], the set's stars. As for rods
    (`star_colouring`): free particles in at least `STAR_MIN_DEGREE` rows, most rows first, each take the rows at
    them that no earlier hub took and that share no free particle but the hub with the rows taken before (a row
    that holds the hub twice stays outside), and are a star where they are at least `STAR_MIN_DEGREE` rows. A
    star's rows share only the hub, so their J M^-1 J^T is a diagonal plus the hub's rank-dim term and is solved
    exactly by one dim x dim system (`layout.block_solve`). Rows that share other particles as well (a cloth's
    bending hinges: up to 12 at a particle, but never 9 that share only it) stay rows of the set's colours."""
    rows = np.asarray(particles, np.int64)
    m = len(rows)
    free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
    if m < STAR_MIN_DEGREE:
        return []
    srt = np.sort(rows, axis=1)
    first = np.ones(srt.shape, bool)
    first[:, 1:] = srt[:, 1:] != srt[:, :-1]
    at = np.bincount(srt[first], minlength=n)                   # rows at each particle
    hubs = [int(p) for p in np.argsort(-at, kind="stable") if at[p] >= STAR_MIN_DEGREE and free[p]]
    taken = np.zeros(m, bool)
    out = []
    for p in hubs:
        chosen, used = [], set()
        for r in np.flatnonzero(np.any(rows == p, axis=1) & ~taken).tolist():
            others = {int(q) for q in rows[r] if q != p and free[q]}
            if int(np.sum(rows[r] == p)) != 1 or others & used:
                continue
            chosen.append(r)
            used |= others
        if len(chosen) >= STAR_MIN_DEGREE:
            taken[chosen] = True
            out.append((p, np.asarray(chosen, np.int64)))
    return out


def check_colouring(i: np.ndarray, j: np.ndarray, colour: np.ndarray, n: int, fixed=None) -> None:
    """Raise ValueError unless no two constraints of the same colour share a particle that is not `fixed`."""
    free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
    for c in np.unique(colour):
        sel = colour == c
        ends = np.concatenate([i[sel], j[sel]])
        counts = np.bincount(ends, minlength=n) * free
        if counts.max(initial=0) > 1:
            p = int(np.argmax(counts))
            ks = np.nonzero(sel & ((i == p) | (j == p)))[0][:2].tolist()
            raise ValueError(
                f"colouring: constraints {ks} both have colour {int(c)} and share particle {p}; "
                "constraints of one colour must not share a particle that is not fixed"
            )


def parse_pairs(name: str, pairs, n: int) -> np.ndarray:
    """`build`'s (i, j) index pairs argument `name` as an [k, 2] int64 array, checked against n particles."""
    if pairs is None:
        return np.zeros((0, 2), np.int64)
    try:
        a = np.asarray(pairs)
    except ValueError:
        raise ValueError(f"build: `{name}` must be a list of (i, j) particle index pairs; some entries are not "
                         "pairs (ragged list)") from None
    if a.size == 0:
        return np.zeros((0, 2), np.int64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"build: `{name}` must be a list of (i, j) particle index pairs, got shape {a.shape}")
    if a.dtype.kind not in "iu":
        if a.dtype.kind == "f" and np.all(a == np.round(a)):
            a = a.astype(np.int64)
        else:
            raise ValueError(f"build: `{name}` must hold integer particle indices, got dtype {a.dtype}")
    a = a.astype(np.int64)
    bad = (a < 0) | (a >= n)
    if bad.any():
        k = int(np.argwhere(bad)[0][0])
        raise ValueError(
            f"build: `{name}[{k}]` = {tuple(a[k].tolist())} has a particle index out of range "
            f"(there are {n} particles, indices 0..{n - 1})"
        )
    same = a[:, 0] == a[:, 1]
    if same.any():
        k = int(np.argmax(same))
        raise ValueError(f"build: `{name}[{k}]` joins particle {int(a[k, 0])} to itself")
    return a


def _strided_box(coords: np.ndarray) -> Optional[tuple]:
    """If `coords` ([k, ndim], in row-major order) is exactly a strided box, return (start, step, count)."""
    start, step, count = [], [], []
    for ax in range(coords.shape[1]):
        vals = np.unique(coords[:, ax])
        s = int(vals[1] - vals[0]) if len(vals) > 1 else 1
        if len(vals) > 1 and not np.all(np.diff(vals) == s):
            return None
        start.append(int(vals[0]))
        step.append(s)
        count.append(len(vals))
    if int(np.prod(count)) != len(coords):
        return None
    grid = np.stack(
        np.meshgrid(*[st + sp * np.arange(c) for st, sp, c in zip(start, step, count)], indexing="ij"), -1
    ).reshape(-1, coords.shape[1])
    if not np.array_equal(grid, coords):
        return None
    return tuple(start), tuple(step), tuple(count)


LAYOUTS = ("auto", "compact", "unrolled")
#: 'auto' picks the compact layout when the model has at least this many colours ...
COMPACT_MIN_COLOURS = 4
#: ... and none of them has more constraints than this (docs/performance.md, "Compact and unrolled layouts"),
COMPACT_MAX_WIDTH = 256
#: ... or, whatever their width, more colours than this: the unrolled layout compiles every colour's code
#: again, so its compile time grows with the colours (24x24 cloth split into 16 / 32 / 64 colours, PGS(10):
#: 3.1 / 4.1 / 9.9 s unrolled against 0.9 / 0.6 / 1.1 s compact, and 1.2 / 1.8 / 4.8 ms a step against
#: 1.0 / 1.2 / 1.0; with 252 colours the unrolled rollout took 327 s to compile). Stars (`star_colouring`) are
#: one scanned block in either layout and are not counted.
UNROLLED_MAX_COLOURS = 12


@dataclasses.dataclass(frozen=True)
class Block:
    """One colour of constraints, solved together. Shapes are static; arrays are read-only NumPy."""

    offset: int                  # position of this block in the colour-ordered constraint vector
    size: int                    # number of constraints
    shape: tuple                 # per-constraint array shape inside the solver: box shape or (size,)
    i_box: Optional[tuple]       # strided: (start, step, count) per view axis of the first endpoints
    j_box: Optional[tuple]       # strided: same for the second endpoints
    i_idx: Optional[StaticArray]  # gather: flat particle indices [size]
    j_idx: Optional[StaticArray]
    src: Optional[StaticArray]    # gather: [n] index into concat(p_i, p_j, 0) for the write-back
    rope: Optional[StaticArray]   # bool [*shape] where mixed; None when all rods or all ropes
    all_rope: bool
    table: bool = False           # compact layout: i_idx, j_idx, src (user constraint index, m where
    #                               padding) are [colours, width], the indices padded with particle index n
    flat: Optional[StaticArray] = None   # table, star: [size] flat positions of the real entries, in block order
    star: bool = False            # every star: hub [C, H] and j_idx, src [C, H, S] (colour, star, spoke: the other
    hub: Optional[StaticArray] = None    # particles and user constraint indices, padded with n and m)
    generic: Optional[int] = None # a constraint set's block: the set's index; i_idx [k, C, W] its particles (internal
    real: Optional[StaticArray] = None   # flat), src [C, W] user constraint indices (m: padding), real [C, W]
    unrolled: Optional["SetColour"] = None   # a set's colour of its own (shape (size,), i_idx [k, size], src [size])
    set_block: Optional[int] = None      # a set's block: its index among the set blocks (`System.sets`)
    hub_slot: Optional[StaticArray] = None   # a set's stars (`Topology._set_star_block`): bool [k, C, H * S], the
    spokes: int = 0                      # slot of each row that holds its star's hub; S, the spokes of a star

    @property
    def strided(self) -> bool:
        return self.i_box is not None

    @property
    def has_rope(self) -> bool:
        return self.all_rope or self.rope is not None


@dataclasses.dataclass(frozen=True)
class SetInfo:
    """The static part of a `jc.Constraint` set: its particles [m, k] (user indices), kind and name."""

    particles: np.ndarray
    unilateral: bool
    name: str
    fn: Any = None      # the set's `fn`: `Model.replace` refuses a set of another kind

    @property
    def m(self) -> int:
        return int(self.particles.shape[0])

    @property
    def k(self) -> int:
        return int(self.particles.shape[1])

    @property
    def key(self):
        return (self.particles.tobytes(), self.particles.shape, self.unilateral, self.name)


@dataclasses.dataclass(frozen=True, eq=False)
class SetColour:
    """One colour of a constraint set that is a block of its own (`Block.unrolled`, `Topology._set_blocks`):
    `size` rows, ordered by their first particle. `idx` [k, size]: their particles (internal flat indices).
    `boxes`: per slot, the strided box of the view its particles form, in row order, or None (then rows are read
    with a gather). `src` [n]: for each particle the position of its row entry in the slot-major
    [k * size] contributions, k * size where it has none (or is fixed: its contributions are 0), so the write-back
    is a gather."""

    size: int
    idx: StaticArray
    boxes: Optional[tuple]
    src: StaticArray


def _set_colour(rows: np.ndarray, view: tuple, fixed: np.ndarray) -> SetColour:
    """The `SetColour` of rows [size, k] (internal flat particle indices, sorted by their first particle)."""
    size, k = rows.shape
    boxes = tuple(_strided_box(np.stack(np.unravel_index(rows[:, s], view), -1)) for s in range(k))
    if any(b is None for b in boxes) or len({b[2] for b in boxes}) != 1:
        boxes = None
    flat = rows.T.reshape(-1)                                    # slot-major
    free = ~fixed[flat]
    # a colour never holds a free particle twice: rows name distinct particles, and the colourings keep rows
    # that share a free particle apart
    if len(np.unique(flat[free])) != int(free.sum()):      # the write-back gather would drop a contribution
        raise RuntimeError("topology: a constraint set's colour holds a free particle twice (an internal error; "
                           "please report it with the set's particles)")
    src = np.full(len(fixed), k * size, np.int32)
    src[flat[free]] = np.flatnonzero(free)
    return SetColour(size, StaticArray(rows.T.astype(np.int32)), boxes, StaticArray(src))


#: The most colours `lattice_colouring` may give one group of translated rows before it gives up.
_LATTICE_MAX = 64


def lattice_colouring(rows: np.ndarray, view: tuple, most: Optional[int] = None) -> Optional[np.ndarray]:
    """A colouring of constraints of any arity (rows [m, k], flat particle indices of the grid `view`, row-major)
    whose colours are strided boxes where the rows are translates of a few stencils (a cloth's edges, its hinges,
    a lattice's cells): rows with the same offsets between their particles form a group, and a group's row at
    grid position p gets the class of p modulo q, with q the smallest vector (by the number of classes) such that
    no two rows of one class share a particle (no difference of two of the stencil's offsets is 0 modulo q).
    Each class is a colour, groups one after another. Returns None when a row repeats a particle, two rows are the
    same, a group would need more than `_LATTICE_MAX` classes, or the colours would be more than `most`."""
    import itertools

    m, k = rows.shape
    coords = np.stack(np.unravel_index(rows, view), -1)                    # [m, k, ndim]
    off = (coords - coords[:, :1]).reshape(m, -1)
    sigs, group = np.unique(off, axis=0, return_inverse=True)
    if most is not None and len(sigs) > most:             # every stencil needs a colour of its own
        return None
    group = group.reshape(-1)
    colour, base = np.empty(m, np.int64), 0
    for g, sig in enumerate(sigs):
        o = sig.reshape(k, -1)
        d = (o[:, None] - o[None]).reshape(-1, o.shape[1])
        d = d[np.any(d != 0, axis=1)]
        if len(d) != k * (k - 1):                                        # a row repeats a particle
            return None
        ext = o.max(0) - o.min(0)
        if int(np.prod(ext + 1)) > _LATTICE_MAX:
            return None
        q = min((q for q in itertools.product(*[range(1, e + 2) for e in ext])
                 if np.all(np.any(d % np.asarray(q) != 0, axis=1))), key=lambda q: (int(np.prod(q)), q))
        sel = np.flatnonzero(group == g)
        if len(np.unique(rows[sel, 0])) != len(sel):                    # the same row twice: no class keeps
            return None                                                  # the two apart
        cls = np.ravel_multi_index(tuple((coords[sel, 0] % np.asarray(q)).T), q)
        used, inv = np.unique(cls, return_inverse=True)
        colour[sel] = base + inv.reshape(-1)
        base += len(used)
        if most is not None and base > most:
            return None
    return colour


def greedy_colouring_any(particles: np.ndarray, n: int, fixed=None) -> np.ndarray:
    """Greedy colouring of constraints of any arity ([m, k] particle indices), in the given order: the smallest
    colour not used at any of the constraint's particles that are not `fixed` (a fixed particle never moves, so
    any number of constraints of one colour may share it)."""
    free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
    return _first_fit(np.asarray(particles).tolist(), free)


def _first_fit(groups, free) -> np.ndarray:
    """First-fit colouring of `groups` (each a sequence of particle indices), in order: each group gets the
    smallest colour not yet used at any of its particles that are `free` (fixed ones may be shared)."""
    used = [set() for _ in range(len(free))]
    colour = np.empty(len(groups), np.int64)
    for r, group in enumerate(groups):
        ps = [int(p) for p in group if free[p]]
        c = 0
        while any(c in used[p] for p in ps):
            c += 1
        colour[r] = c
        for p in ps:
            used[p].add(c)
    return colour


def _splits(view) -> bool:
    """Whether the parity split (`Topology._choose_layout`) applies to a view: its last axis even and >= 4."""
    return view[-1] % 2 == 0 and view[-1] >= 4


def _minor_step2(box) -> bool:
    """Whether a strided box (or None) steps by 2 along the last axis, more than once."""
    return box is not None and box[1][-1] == 2 and box[2][-1] > 1


def _parity_pos(n: int, last: int) -> np.ndarray:
    """The parity split's internal position of each particle: each row of the last axis evens first."""
    lead, col = np.divmod(np.arange(n), last)
    return lead * last + (col % 2) * (last // 2) + col // 2


class Topology:
    """Everything static about a model: sizes, index pairs, kinds, colouring and the internal layout.

    Hashes and compares by content (computed once), so it can be jit metadata. `layout` is 'auto' (compact for
    small models with several colours: `COMPACT_MIN_COLOURS`, `COMPACT_MAX_WIDTH`), 'compact' or 'unrolled'.
    """

    def __init__(self, n, dim, i, j, is_rope, colour, view, layout="auto", star=None, fixed=None, sets=()):
        self.n = int(n)
        self.dim = int(dim)
        self.i = np.asarray(i, np.int64)
        self.j = np.asarray(j, np.int64)
        self.is_rope = np.asarray(is_rope, bool)
        self.colour = np.asarray(colour, np.int64)
        self.view = tuple(int(s) for s in view)    # the particle grid's shape (internal order: see pos / order)
        # rods and ropes are the pair constraints 0..m_pairs-1; `sets` (`SetInfo`, one per jc.Constraint set)
        # follow in order, so m counts every constraint (the length of a state's lam)
        self.sets = tuple(sets)
        self.m_pairs = len(self.i)
        self.m = self.m_pairs + sum(s.m for s in self.sets)
        # star[k]: constraint k's star (`star_colouring`), -1 if it has none; a star's colour is its own colour set
        self.star = np.full(self.m_pairs, -1, np.int64) if star is None else np.asarray(star, np.int64)
        self.has_stars = bool((self.star >= 0).any())
        # the particles fixed when the model was built: the colouring may put constraints that share one of them
        # in one colour, so they must stay fixed (`Model` checks their inverse mass stays 0)
        self.fixed = np.zeros(self.n, bool) if fixed is None else np.asarray(fixed, bool)
        for a in (self.i, self.j, self.is_rope, self.colour, self.star, self.fixed):
            a.setflags(write=False)
        self.has_ropes = bool(self.is_rope.any())
        self.has_rods = bool((~self.is_rope).any())
        if layout not in LAYOUTS:
            raise ValueError(f"build: `layout` must be one of {LAYOUTS}, got {layout!r}")
        self._layout = layout
        # a model without rods or ropes has no colours to put in a table: it keeps the (empty) unrolled layout
        if self.m_pairs and (layout == "compact" or (layout == "auto" and self._small())):
            self._compact()
        else:
            self._choose_layout()
        self._set_blocks()
        if not self.compact:
            self._split_for_sets()
        self.layout = "compact" if self.compact else "unrolled"
        self._key = (
            self.n, self.dim, self.view, self.i.tobytes(), self.j.tobytes(), self.is_rope.tobytes(),
            self.colour.tobytes(), self.layout, self.star.tobytes(), self.fixed.tobytes(),
            tuple(s.key for s in self.sets), tuple(b.size for b in self.blocks if b.unrolled is not None),
        )
        self._hash = hash(self._key)

    compact = False
    #: Copies in a batch-minor topology (`jaxcon.core.batch.batch_minor_topology`): the view's last axis; None
    #: for a single system.
    batch = None
    #: Whether a batch-minor topology's solvers carry each sweep's velocities and impulses in one packed array
    #: (`jaxcon.solvers.pgs.packed_sweeps`): what a batch run in one piece uses.
    packed = False
    #: Whether the solvers unroll their loops over sweeps and substeps (a batch-minor topology on an accelerator,
    #: `jaxcon.core.batch.sweep_mode`): XLA's GPU fusion then fuses across sweeps, as in the hand-written
    #: reference; a loop ends every fusion at each trip.
    unroll = False

    @property
    def n_colours(self) -> int:
        return sum(int(b.shape[0]) if b.table or b.star or (b.generic is not None and b.unrolled is None) else 1
                   for b in self.blocks)

    def _small(self) -> bool:
        plain = self.colour[self.star < 0]
        if not len(plain):
            return False
        sizes = np.bincount(np.unique(plain, return_inverse=True)[1])
        return len(sizes) >= COMPACT_MIN_COLOURS and (int(sizes.max()) <= COMPACT_MAX_WIDTH
                                                      or len(sizes) > UNROLLED_MAX_COLOURS)

    def _compact(self):
        """Replace the colours' blocks by one table block (stars keep theirs, before it): row c holds colour c's
        constraints in the order of the unrolled layout without the parity split, padded to the widest colour
        with particle index n."""
        self.pos = self.order = None
        all_blocks, self.perm, self.inv_perm = self._build_blocks(None)
        stars = tuple(b for b in all_blocks if b.star)
        blocks = [b for b in all_blocks if not b.star]
        if not blocks:                       # stars only: nothing to put in a table
            self.blocks = stars
            return
        width = max(b.size for b in blocks)
        lo, hi = np.minimum(self.i, self.j)[self.perm], np.maximum(self.i, self.j)[self.perm]
        I = np.full((len(blocks), width), self.n, np.int32)
        J = np.full((len(blocks), width), self.n, np.int32)
        src = np.full((len(blocks), width), self.m, np.int32)      # user constraint index, m where padding
        rope = np.zeros((len(blocks), width), bool)
        for c, b in enumerate(blocks):
            seg = slice(b.offset, b.offset + b.size)
            I[c, :b.size], J[c, :b.size] = lo[seg], hi[seg]
            src[c, :b.size] = self.perm[seg]
            rope[c, :b.size] = self.is_rope[self.perm[seg]]
        flat = np.concatenate([c * width + np.arange(b.size) for c, b in enumerate(blocks)]).astype(np.int32)
        plain = self.is_rope[self.star < 0]
        all_rope = bool(plain.all())
        mixed = StaticArray(rope) if plain.any() and not all_rope else None
        offset = blocks[0].offset
        self.blocks = stars + (Block(offset, self.m_pairs - offset, I.shape, None, None, StaticArray(I), StaticArray(J),
                                     StaticArray(src), mixed, all_rope, table=True, flat=StaticArray(flat)),)
        self.compact = True

    @property
    def unrolled(self) -> "Topology":
        """This topology in the unrolled layout (one block per colour): itself unless it is compact."""
        if not self.compact:
            return self
        if getattr(self, "_unrolled", None) is None:
            self._unrolled = Topology(self.n, self.dim, self.i, self.j, self.is_rope, self.colour, self.view,
                                      layout="unrolled", star=self.star, fixed=self.fixed, sets=self.sets)
        return self._unrolled

    def _choose_layout(self):
        """User order, or each row of the last axis stored evens first (parity split) when that keeps every
        strided colour strided and some colour steps by 2 along that axis (see the module docstring). The view
        is the grid's shape either way."""
        plain = self._build_blocks(None)
        minor_step2 = any(_minor_step2(b.i_box) for b in plain[0])
        if _splits(self.view) and minor_step2:
            pos = _parity_pos(self.n, self.view[-1])
            split = self._build_blocks(pos)
            if sum(b.strided for b in split[0]) >= sum(b.strided for b in plain[0]):
                self._set_order(pos)
                self.blocks, self.perm, self.inv_perm = split
                return
        self.pos, self.order = None, None
        self.blocks, self.perm, self.inv_perm = plain

    def _set_order(self, pos):
        self.pos, self.order = pos.astype(np.int32), np.argsort(pos).astype(np.int32)
        self.pos.setflags(write=False)
        self.order.setflags(write=False)

    def _boxes(self):
        """(strided pair blocks, set colours read through boxes) of the current blocks."""
        return (sum(b.strided for b in self.blocks),
                sum(b.unrolled is not None and b.unrolled.boxes is not None for b in self.blocks))

    def _split_for_sets(self):
        """The parity split (`_choose_layout`) where the pairs did not ask for it but a constraint set's colour
        steps by 2 along the last axis (a cloth's edges as a `jc.Constraint` set: its column-parity colours),
        kept where no pair block and no set colour loses its boxes. The set colours then read and write unit-step
        runs instead of every other entry (PGS(10) on the 32x32 cloth's edges as a distance set: about 20% less
        time per step, measured alternately with the plain layout)."""
        if self.pos is not None or not self.sets or not _splits(self.view) or not any(
                _minor_step2(box) for b in self.blocks if b.unrolled is not None for box in b.unrolled.boxes or ()):
            return
        before, counts = (self.blocks, self.perm, self.inv_perm), self._boxes()
        pos = _parity_pos(self.n, self.view[-1])
        self._set_order(pos)
        self.blocks, self.perm, self.inv_perm = self._build_blocks(pos)
        self._set_blocks()
        if any(a < b for a, b in zip(self._boxes(), counts)):
            self.pos, self.order = None, None
            self.blocks, self.perm, self.inv_perm = before

    def _build_blocks(self, pos):
        """Blocks for particles laid out in `self.view`, user particle p at flat position pos[p] (identity if
        None). Returns (blocks, perm, inv_perm)."""
        n = self.n
        # Orient every constraint with i < j (a distance constraint is symmetric), so regular structures
        # give a constant endpoint offset and hence strided boxes.
        lo = np.minimum(self.i, self.j)
        hi = np.maximum(self.i, self.j)
        if pos is not None:
            lo, hi = pos[lo], pos[hi]
        order, blocks, offset = [], [], 0
        for blk, ks in self._star_blocks(pos):
            blocks.append(dataclasses.replace(blk, offset=offset))
            order.append(ks)
            offset += len(ks)
        plain = self.star < 0
        for c in np.unique(self.colour[plain]):
            ks = np.nonzero((self.colour == c) & plain)[0]
            ks = ks[np.argsort(lo[ks], kind="stable")]
            ci = np.stack(np.unravel_index(lo[ks], self.view), -1)
            cj = np.stack(np.unravel_index(hi[ks], self.view), -1)
            ibox = _strided_box(ci)
            jbox = None
            if ibox is not None:
                delta = cj - ci
                if np.all(delta == delta[0]):
                    jstart = tuple(int(s + d) for s, d in zip(ibox[0], delta[0]))
                    jbox = (jstart, ibox[1], ibox[2])
            rope = self.is_rope[ks]
            all_rope = bool(rope.all())
            if jbox is not None:
                shape = tuple(ibox[2])
                mixed = StaticArray(rope.reshape(shape)) if rope.any() and not all_rope else None
                blk = Block(offset, len(ks), shape, ibox, jbox, None, None, None, mixed, all_rope)
            else:
                size = len(ks)
                src = np.full(n, 2 * size, np.int32)
                src[lo[ks]] = np.arange(size)
                src[hi[ks]] = size + np.arange(size)
                mixed = StaticArray(rope) if rope.any() and not all_rope else None
                blk = Block(offset, size, (size,), None, None, StaticArray(lo[ks].astype(np.int32)),
                            StaticArray(hi[ks].astype(np.int32)), StaticArray(src), mixed, all_rope)
            blocks.append(blk)
            order.append(ks)
            offset += len(ks)
        perm = np.concatenate(order) if order else np.zeros(0, np.int64)
        # perm[q] = user index of the constraint at colour-ordered position q; inv_perm is its inverse.
        perm, inv_perm = perm.astype(np.int32), np.argsort(perm).astype(np.int32)
        perm.setflags(write=False)
        inv_perm.setflags(write=False)
        return tuple(blocks), perm, inv_perm

    def _star_blocks(self, pos):
        """The stars as one block (user particle p at internal flat position pos[p]): [(Block with offset 0, the
        user constraint indices of its spokes in block order)], or [] without stars. Its arrays are [C, H, S]:
        star colour, star, spoke; hub [C, H] and the other particles j_idx [C, H, S] are padded with n, src (user
        constraint index) with m. Spokes run from the hub to the other particle, in order of that particle. The
        colours are swept one after another in a scan (`layout.each_colour`), so the star code is traced once."""
        if not self.has_stars:
            return []
        to_internal = np.arange(self.n) if pos is None else np.asarray(pos)
        stars = np.unique(self.star[self.star >= 0])
        colour_of = {int(k): int(self.colour[np.argmax(self.star == k)]) for k in stars}
        colours = sorted(set(colour_of.values()))
        by_colour = [[int(k) for k in stars if colour_of[int(k)] == c] for c in colours]
        spokes = {}
        for k in stars:
            ks = np.nonzero(self.star == k)[0]
            hub = int(np.bincount(np.concatenate([self.i[ks], self.j[ks]])).argmax())   # the shared particle
            other = np.where(self.i[ks] == hub, self.j[ks], self.i[ks])
            o = np.argsort(other, kind="stable")
            spokes[int(k)] = (hub, ks[o], other[o])
        C, H = len(colours), max(len(g) for g in by_colour)
        S = max(len(v[1]) for v in spokes.values())
        hubs = np.full((C, H), self.n, np.int32)
        J = np.full((C, H, S), self.n, np.int32)
        src = np.full((C, H, S), self.m, np.int32)
        rope = np.zeros((C, H, S), bool)
        for c, group in enumerate(by_colour):
            for r, k in enumerate(group):
                hub, ks, other = spokes[k]
                hubs[c, r] = to_internal[hub]
                J[c, r, :len(ks)], src[c, r, :len(ks)], rope[c, r, :len(ks)] = to_internal[other], ks, self.is_rope[ks]
        flat = np.flatnonzero(src < self.m).astype(np.int32)
        r_real = rope.reshape(-1)[flat]
        all_rope = bool(r_real.all())
        mixed = StaticArray(rope) if r_real.any() and not all_rope else None
        blk = Block(0, len(flat), (C, H, S), None, None, None, StaticArray(J), StaticArray(src), mixed, all_rope,
                    flat=StaticArray(flat), star=True, hub=StaticArray(hubs))
        return [(blk, src.reshape(-1)[flat].astype(np.int64))]

    has_sets = property(lambda self: bool(self.sets))

    def _set_blocks(self):
        """Append the constraint sets' blocks (`SetInfo`), after the pairs' blocks, and extend perm / inv_perm to
        every constraint. Each set has its own colouring (greedy over the free particles). Small sets with
        several colours (the rule of the compact layout: `_unrolls`) are one table block [colours, width], swept
        colour by colour in a scan (`layout.each_colour`); the others get a block per colour (`Block.unrolled`),
        read and written through strided boxes where its rows form them (`SetColour`), else gathers. Such a set
        takes `lattice_colouring` where every one of its colours is then a box and it needs no more colours than
        the greedy one. A set's hubs (`set_stars`) come first, as one more table of their own (`_set_star_block`),
        and the set's other rows are laid out as above."""
        self.set_hubs = []                       # (set index, hub (user index), its rows) per star of a set
        if not self.sets:
            return
        to_internal = np.arange(self.n) if self.pos is None else np.asarray(self.pos)
        fixed = np.zeros(self.n, bool)
        fixed[to_internal] = self.fixed
        blocks, perm = list(self.blocks), [np.asarray(self.perm, np.int64)]
        first, offset, n_set_blocks = self.m_pairs, self.m_pairs, 0
        for s_id, info in enumerate(self.sets):
            internal = to_internal[info.particles]
            rest = np.arange(info.m)
            stars = set_stars(info.particles, self.n, self.fixed)
            if stars:                       # the set's stars first: one block, swept star colour by star colour
                blk, rows = self._set_star_block(info, internal, stars, offset, first, s_id, n_set_blocks)
                blocks.append(blk)
                perm.append(rows.astype(np.int64))
                offset, n_set_blocks = offset + blk.size, n_set_blocks + 1
                self.set_hubs += [(s_id, p, ks) for p, ks in stars]
                rest = np.setdiff1d(rest, np.concatenate([ks for _, ks in stars]))
            if not len(rest):
                first += info.m
                continue
            parts, internal = info.particles[rest], internal[rest]
            colour = greedy_colouring_any(parts, self.n, self.fixed)
            groups = None
            if self._unrolls(np.bincount(colour)):
                # on the user's grid positions: the parity split (`pos`) permutes a row, so translates there are
                # not translates internally; the boxes are checked on the internal positions
                lattice = (lattice_colouring(parts, self.view, int(colour.max()) + 1) if info.k > 1
                           else None)
                tried = None if lattice is None else self._set_colours(internal, lattice, fixed)
                if tried is not None and all(c.boxes is not None for c, _ in tried):
                    colour, groups = lattice, tried
                else:
                    groups = self._set_colours(internal, colour, fixed)
            if groups is not None:                          # one block per colour, read and written directly
                for sc, rows in groups:
                    src = (first + rest[rows]).astype(np.int32)
                    blocks.append(Block(offset, sc.size, (sc.size,), None, None, sc.idx, None, StaticArray(src),
                                        None, info.unilateral, flat=StaticArray(np.arange(sc.size, dtype=np.int32)),
                                        generic=s_id, real=StaticArray(np.ones(sc.size, bool)), unrolled=sc,
                                        set_block=n_set_blocks))
                    perm.append(src.astype(np.int64))
                    offset += sc.size
                    n_set_blocks += 1
                first += info.m
                continue
            C, W = int(colour.max()) + 1, int(np.bincount(colour).max())
            idx = np.zeros((C, W, info.k), np.int32)
            src = np.full((C, W), self.m, np.int32)
            for c in range(C):
                rows = np.flatnonzero(colour == c)
                idx[c, :len(rows)] = internal[rows]
                idx[c, len(rows):] = internal[rows[0]]      # padding: a real row, masked
                src[c, :len(rows)] = first + rest[rows]
            real = src < self.m
            flat = np.flatnonzero(real.reshape(-1)).astype(np.int32)
            blocks.append(Block(offset, len(rest), (C, W), None, None, StaticArray(np.moveaxis(idx, -1, 0)), None,
                                StaticArray(src), None,
                                info.unilateral, flat=StaticArray(flat), generic=s_id, real=StaticArray(real),
                                set_block=n_set_blocks))
            n_set_blocks += 1
            perm.append(src.reshape(-1)[flat].astype(np.int64))
            first += info.m
            offset += len(rest)
        perm = np.concatenate(perm).astype(np.int32)
        inv_perm = np.argsort(perm).astype(np.int32)
        perm.setflags(write=False)
        inv_perm.setflags(write=False)
        self.blocks, self.perm, self.inv_perm = tuple(blocks), perm, inv_perm

    def _set_star_block(self, info, internal, stars, offset, first, s_id, set_block):
        """A set's stars (`set_stars`) as one block (Block, the user constraint indices of its rows in block order),
        laid out as a set's table [C, H * S] (star colour; star by star, S spokes each, padded with a masked copy of
        a real row): a colour's stars share no free particle (first fit, as the rods' stars). `hub_slot` [k, C,
        H * S] marks each row's hub, false on padding; `layout.block_solve` solves each star's rows together."""
        groups = [np.unique(info.particles[ks]) for _, ks in stars]
        colour = _first_fit(groups, ~self.fixed)
        C, H = int(colour.max()) + 1, int(np.bincount(colour).max())
        S = max(len(ks) for _, ks in stars)
        idx = np.zeros((C, H * S, info.k), np.int32)
        src = np.full((C, H * S), self.m, np.int32)
        hub = np.zeros((C, H * S, info.k), bool)
        for c in range(C):
            mine = [st for st, cc in zip(stars, colour) if cc == c]
            idx[c] = internal[mine[0][1][0]]                         # padding: a real row, masked
            for h, (p, ks) in enumerate(mine):
                at = slice(h * S, h * S + len(ks))
                idx[c, at], src[c, at], hub[c, at] = internal[ks], first + ks, info.particles[ks] == p
        real = src < self.m
        flat = np.flatnonzero(real.reshape(-1)).astype(np.int32)
        blk = Block(offset, len(flat), (C, H * S), None, None, StaticArray(np.moveaxis(idx, -1, 0)), None,
                    StaticArray(src), None, info.unilateral, flat=StaticArray(flat), generic=s_id,
                    real=StaticArray(real), set_block=set_block, hub_slot=StaticArray(np.moveaxis(hub, -1, 0)),
                    spokes=S)
        return blk, src.reshape(-1)[flat]

    def block_degree(self) -> np.ndarray:
        """[n] (user order) how many blocks solved together meet at each particle: a constraint counts at each of
        its particles, a star (rods' or a set's: `star_colouring`, `set_stars`) once at its hub."""
        deg = np.bincount(np.concatenate([self.i, self.j] + [s.particles.reshape(-1) for s in self.sets]),
                          minlength=self.n)
        for k in np.unique(self.star[self.star >= 0]):
            ks = np.flatnonzero(self.star == k)
            deg[np.bincount(np.concatenate([self.i[ks], self.j[ks]])).argmax()] -= len(ks) - 1
        for _, p, ks in self.set_hubs:
            deg[p] -= len(ks) - 1
        return deg

    def _unrolls(self, sizes) -> bool:
        """Whether a constraint set with colours of these sizes gets a block per colour: never in the compact
        layout, nor with more than `UNROLLED_MAX_COLOURS` colours (each colour's code is compiled apart); else
        always in the unrolled layout, and by default unless it is small with several colours
        (`COMPACT_MIN_COLOURS`, `COMPACT_MAX_WIDTH`), as for rods."""
        if self._layout == "compact" or len(sizes) > UNROLLED_MAX_COLOURS:
            return False
        return self._layout == "unrolled" or not (len(sizes) >= COMPACT_MIN_COLOURS
                                                   and int(sizes.max()) <= COMPACT_MAX_WIDTH)

    def _set_colours(self, internal, colour, fixed) -> list:
        """[(SetColour, its rows: set row indices sorted by their first particle's internal position)] per
        colour."""
        out = []
        for c in range(int(colour.max()) + 1):
            rows = np.flatnonzero(colour == c)
            rows = rows[np.argsort(internal[rows, 0], kind="stable")]
            out.append((_set_colour(internal[rows], self.view, fixed), rows))
        return out

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return self is other or (
            isinstance(other, Topology) and self._hash == other._hash and self._key == other._key
        )

    def __repr__(self):
        kinds = f"{int((~self.is_rope).sum())} rods, {int(self.is_rope.sum())} ropes"
        if self.has_stars:
            kinds += f", {int(self.star.max()) + 1} hub stars"
        for info in self.sets:
            kinds += f", {info.m} {info.name}"
        if self.set_hubs:
            kinds += f", {len(self.set_hubs)} set hub stars"
        strided = sum(b.strided or (b.unrolled is not None and b.unrolled.boxes is not None) for b in self.blocks)
        if self.compact:
            tab = next(b for b in self.blocks if b.table)
            return (f"Topology(n={self.n}, dim={self.dim}, {kinds}, {self.n_colours} colours (compact: one "
                    f"[{tab.shape[0]}, {tab.shape[1]}] table), view={self.view})")
        return (f"Topology(n={self.n}, dim={self.dim}, {kinds}, {self.n_colours} colours "
                f"({strided} strided), view={self.view}{'' if self.order is None else ', parity-split'})")
