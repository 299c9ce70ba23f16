"""Contacts: the static contact topology and the checks of `jc.build`'s contact arguments.

A model may have three kinds of contact, each a unilateral constraint on a gap C >= 0:

* plane p:  C = n_p . x - offset_p - r        (one contact per particle and plane)
* sphere s: C = |x - c_s| - R_s - r           (one per particle and static sphere)
* pair:     C = |x_j - x_i| - r_i - r_j       (candidate pairs, all of them when ``collide=True``)

Pairs come from one of two places. A static list (``collide=True`` up to `MAX_ALL_PAIRS_PARTICLES`
particles, or the user's own pairs) is split into rounds at build time, as below. A neighbour grid
(``collide="grid"``, or ``collide=True`` above that size) finds the pairs inside every (sub)step instead:
each particle keeps up to K = ``max_neighbours`` partners (`jaxcon.core.grid.neighbours`), and the
pairs are solved slot by slot (the rows of one slot together, with mass splitting).

Obstacle contacts need no broad phase: each obstacle's contacts are solved together, vectorised over every
particle. Candidate pairs are split into rounds of disjoint pairs (a round-robin schedule for all pairs: n
particles in n - 1 rounds, or n rounds when n is odd), padded to one width, so a sweep is one loop over rounds
whose body does not depend on n: the program's size is the same for 16 balls and for 1000.

Contact impulses are reported in one order: plane contacts (plane-major: index p * n + particle), then sphere
contacts (s * n + particle), then pairs in the order of `ContactTopology.pairs`. A grid model has no static
pairs: its pair slots come last instead, particle-major (index Q * n + particle * K + slot), slot s of particle
i holding the contact with `State.contact_partners[i, s]` (-1: an empty slot, impulse 0). Each pair sits in
one slot only, in the row of its lower-numbered particle.
"""
from __future__ import annotations

import itertools
from typing import Any, NamedTuple, Optional

import jax.numpy as jnp
import numpy as np

from jaxcon.core import layout as L
from jaxcon.core.pytree import StaticArray, pytree_dataclass, static_field
from jaxcon.core.topology import Topology, greedy_colouring, parse_pairs

Array = Any

# collide=True solves every pair in every sweep: O(n^2) work per sweep, in n - 1 rounds. Above this many
# particles it uses the neighbour grid instead. Measured (docs/contacts.md, PGS(10), 2 CPU cores) the grid is
# cheaper per step at every size from 32 particles on (1.0 against 1.3 ms at 32, 6.8 against 89 ms at 256,
# 22 ms against 2.6 s at 1024). The all-pairs rounds are Gauss-Seidel over every pair: they converge better,
# need no capacity and work with every solver and with substeps, so they stay the default while a step costs
# tens of milliseconds; above that, all pairs is an explicit list (any solver) and the grid the default.
MAX_ALL_PAIRS_PARTICLES = 256

#: Default capacity of the neighbour grid (partners kept per particle), by dimension: a disc of equal discs
#: touches at most 6, a ball of equal balls 12, plus room for the ones about to touch.
DEFAULT_MAX_NEIGHBOURS = {2: 8, 3: 16}


def grid_table_size(n: int) -> int:
    """Buckets of the neighbour grid's spatial hash: the power of two at or above 8 n (at least 64). Each step
    counts the particles per bucket (a table of that size) and finds a bucket's range of the particles sorted by
    bucket from the counts' running sum: one gather per looked-up cell, where a binary search over the sorted
    particles (the table of 2^30 buckets this replaced) took 18 searches of log2(n) rounds each in 2-D, 11 of
    the 17.5 ms of the 1024-disc box's step. Equal discs fill about one cell in two particles, so one bucket in
    16 is occupied and two occupied cells seldom share one (such a bucket is still handled: each entry's cell is
    checked, and its extra entries count towards the overflow)."""
    return 1 << max(6, int(np.ceil(np.log2(8 * max(n, 1)))))


def round_robin(n: int) -> list:
    """Rounds of disjoint pairs covering every pair of n particles exactly once (the circle method): n - 1
    rounds of n / 2 pairs when n is even, n rounds of (n - 1) / 2 when odd. Returns a list of [k, 2] arrays."""
    m = n + (n % 2)                     # a dummy particle m - 1 when n is odd: its partner sits out the round
    ring = list(range(m))
    rounds = []
    for _ in range(m - 1):
        pairs = [(ring[k], ring[m - 1 - k]) for k in range(m // 2)]
        pairs = [(min(a, b), max(a, b)) for a, b in pairs if a < n and b < n]
        rounds.append(np.asarray(pairs, np.int64).reshape(-1, 2))
        ring = [ring[0], ring[-1]] + ring[1:-1]
    return rounds


def _greedy_rounds(pairs: np.ndarray, n: int) -> list:
    """Rounds of disjoint pairs for an arbitrary pair list (greedy edge colouring in the given order)."""
    colour = greedy_colouring(pairs[:, 0], pairs[:, 1], n)
    return [pairs[colour == c] for c in range(int(colour.max(initial=-1)) + 1)]


def _rounds(pairs: np.ndarray, n: int) -> list:
    """Dense pair sets (at least half of all pairs, e.g. `collide=True` less the constrained pairs) use the
    round-robin schedule with the missing pairs left out, so there are at most n rounds; sparse ones a greedy
    colouring."""
    if 2 * len(pairs) < n * (n - 1) // 2:
        return _greedy_rounds(pairs, n)
    want = set(map(tuple, np.sort(pairs, axis=1).tolist()))
    rounds = [r[np.array([(int(a), int(b)) in want for a, b in r], bool)] if len(r) else r
              for r in round_robin(n)]
    return [r for r in rounds if len(r)]


class ContactTopology:
    """Everything static about a model's contacts: obstacle counts and the rounds of candidate pairs.

    Pair rounds are [R, S] index arrays into the internal (flat) particle order, padded with invalid slots;
    `src` [R, n] says, per round, where each particle's velocity change comes from in
    concat(p_i [S], p_j [S], 0) (a particle is in at most one pair per round, so no scatter-add is needed).
    Hashes and compares by content, so it can be jit metadata.
    """

    def __init__(self, n: int, n_planes: int, n_spheres: int, pairs: np.ndarray, pos=None, grid_k: int = 0,
                 exclude=None):
        self.n = int(n)
        self.grid_k = int(grid_k)
        self._grid(exclude, pos)
        self.n_planes = int(n_planes)
        self.n_spheres = int(n_spheres)
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
        self.pairs = StaticArray(pairs)              # user particle indices, user order
        self.n_pairs = len(pairs)
        if self.n_pairs:
            rounds = _rounds(pairs, self.n)
            width = max(len(r) for r in rounds)
            R = len(rounds)
            ii = np.zeros((R, width), np.int32)
            jj = np.zeros((R, width), np.int32)
            valid = np.zeros((R, width), bool)
            src = np.full((R, self.n), 2 * width, np.int32)
            lookup = {(int(a), int(b)): k for k, (a, b) in enumerate(np.sort(pairs, axis=1))}
            slot = np.zeros(self.n_pairs, np.int64)
            to_internal = np.arange(self.n) if pos is None else np.asarray(pos)
            for r, rp in enumerate(rounds):
                for s, (a, b) in enumerate(rp):
                    k = lookup[(min(a, b), max(a, b))]
                    a, b = pairs[k]                  # keep the user's orientation: i -> j
                    ia, ib = to_internal[a], to_internal[b]
                    ii[r, s], jj[r, s], valid[r, s] = ia, ib, True
                    src[r, ia], src[r, ib] = s, width + s
                    slot[k] = r * width + s
            self.i, self.j, self.valid, self.src = (StaticArray(a) for a in (ii, jj, valid, src))
            self.slot = StaticArray(slot)            # user pair k sits at flat round slot slot[k]
            self.rounds, self.width = R, width
        else:
            self.i = self.j = self.valid = self.src = self.slot = None
            self.rounds, self.width = 0, 0
        self._key = (self.n, self.n_planes, self.n_spheres, pairs.tobytes(), None if pos is None else
                     np.asarray(pos).tobytes(), self.grid_k, None if self.grid_exclude is None else
                     self.grid_exclude.array.tobytes())
        self._hash = hash(self._key)

    def _grid(self, exclude, pos):
        """The neighbour grid's static parts: the hash table size, each internal particle's user index `uid`,
        and `exclude` [n, D]: per internal particle, the internal indices of the particles it never collides
        with (-1 padding): the pairs `joined_at_rest` skips, given as `exclude` [m, 2] in user indices."""
        self.grid_table = self.grid_uid = self.grid_exclude = None
        if not self.grid_k:
            return
        n = self.n
        to_internal = np.arange(n) if pos is None else np.asarray(pos)
        uid = np.empty(n, np.int32)
        uid[to_internal] = np.arange(n)
        ex = np.zeros((0, 2), np.int64) if exclude is None else np.asarray(exclude, np.int64).reshape(-1, 2)
        ex = to_internal[ex]
        deg = np.bincount(ex.reshape(-1), minlength=n)
        table = np.full((n, max(int(deg.max(initial=0)), 1)), -1, np.int32)
        a, b = np.concatenate([ex[:, 0], ex[:, 1]]), np.concatenate([ex[:, 1], ex[:, 0]])
        order = np.argsort(a, kind="stable")
        a, b = a[order], b[order]
        table[a, np.arange(len(a)) - (np.cumsum(deg) - deg)[a]] = b
        self.grid_table = grid_table_size(n)
        self.grid_uid, self.grid_exclude = StaticArray(uid), StaticArray(table)

    @property
    def has_grid(self) -> bool:
        return self.grid_k > 0

    @property
    def n_obstacles(self) -> int:
        return self.n_planes + self.n_spheres

    @property
    def k(self) -> int:
        """Number of contact slots (the length of a state's contact impulses)."""
        return self.n_obstacles * self.n + self.n_pairs + self.n * self.grid_k

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return self is other or (isinstance(other, ContactTopology) and self._hash == other._hash
                                 and self._key == other._key)

    def __repr__(self):
        pairs = (f"a neighbour grid of {self.grid_k} per particle" if self.grid_k else
                 f"{self.n_pairs} pairs in {self.rounds} rounds")
        return f"ContactTopology({self.n_planes} planes, {self.n_spheres} spheres, {pairs})"


def _pieces(n: int, edges: np.ndarray) -> np.ndarray:
    """Connected pieces of n particles joined by `edges` [m, 2]: a label per particle (the smallest index of its
    piece), by hooking each edge's larger label onto its smaller one and pointer jumping until nothing changes
    (a few rounds of array work, no Python loop over particles)."""
    label = np.arange(n)
    if not len(edges):
        return label
    a, b = edges[:, 0], edges[:, 1]
    while True:
        la, lb = label[a], label[b]
        if np.array_equal(la, lb):
            return label
        np.minimum.at(label, np.maximum(la, lb), np.minimum(la, lb))
        while True:
            jumped = label[label]
            if np.array_equal(jumped, label):
                break
            label = jumped


def _near_pairs(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Pairs (i < j) [k, 2] with |x_j - x_i| <= (r_i + r_j)(1 + 1e-9) (in float64, from the model's positions):
    particles hashed into cells a little wider than 2 max(r), sorted by cell, and each one's own and
    neighbouring cells looked up with `searchsorted`. Its cost grows with the particles per cell: one particle
    far larger than the others puts many in one cell."""
    n, dim = x.shape
    cut = 2 * float(r.max(initial=0.0))
    if n < 2 or not cut > 0:
        return np.zeros((0, 2), np.int64)
    c = np.floor((x - x.min(0)) / (cut * (1 + 1e-6))).astype(np.int64)
    span = c.max(0) + 3
    def key(cells):
        k = np.zeros(len(cells), np.int64)
        for a in range(dim):
            k = k * span[a] + cells[:, a] + 1
        return k
    own = key(c)
    order = np.argsort(own, kind="stable")
    sorted_keys = own[order]
    out = []
    for off in itertools.product((-1, 0, 1), repeat=dim):
        q = key(c + np.asarray(off))
        lo, hi = np.searchsorted(sorted_keys, q, "left"), np.searchsorted(sorted_keys, q, "right")
        count = hi - lo
        i = np.repeat(np.arange(n), count)
        first = np.repeat(lo - (np.cumsum(count) - count), count)
        j = order[first + np.arange(len(i))]
        keep = i < j
        i, j = i[keep], j[keep]
        d = np.linalg.norm(x[j] - x[i], axis=1)
        within = d <= (r[i] + r[j]) * (1 + 1e-9)
        out.append(np.stack([i[within], j[within]], -1))
    return np.concatenate(out)


#: A constraint row of at most this many particles (a rod, a bending hinge, an angle) makes its particles
#: neighbours that never collide; a larger row (the polygon of an `area`, the mesh of a `volume`) spans a whole
#: body, whose far sides must still collide, so it only joins them into one piece.
ROW_NEIGHBOURS_MAX = 4


def joined_at_rest(n: int, groups, x, radius, fixed=None) -> np.ndarray:
    """The pairs that `collide=True` skips, [m, 2] with i < j, unique: two particles of one constraint (a rod, a
    rope, or one row of at most ROW_NEIGHBOURS_MAX particles of a constraint set), and two particles of one
    connected piece already within contact distance, |x_j - x_i| <= r_i + r_j, at build (a cloth's or a chain's
    neighbours when the radius is large). A piece is the particles joined through constraints, not through a
    fixed particle: two pendulums on one pivot are two pieces. Particles of different pieces always collide
    (a rack of touching balls, two cloths stacked), however close they start. `groups`: [m, a] particle index
    arrays (a >= 2), `x` [n, dim] and `radius` [n] NumPy arrays (`radius` None: no size, so nothing is within
    contact), `fixed` [n] bool or None."""
    groups = [np.asarray(g, np.int64).reshape(len(g), -1) for g in groups if len(g) and np.shape(g)[-1] >= 2]
    if not groups:
        return np.zeros((0, 2), np.int64)
    own = [np.stack([g[:, p], g[:, q]], -1).reshape(-1, 2) for g in groups if g.shape[1] <= ROW_NEIGHBOURS_MAX
           for p, q in itertools.combinations(range(g.shape[1]), 2)]
    pairs = own + [np.zeros((0, 2), np.int64)]
    if radius is not None:
        free = np.ones(n, bool) if fixed is None else ~np.asarray(fixed, bool)
        edges = []
        for g in groups:                       # each row's free particles, joined to its first free one
            ok = free[g]
            anchor = g[np.arange(len(g)), np.argmax(ok, axis=1)]
            for k in range(g.shape[1]):
                keep = ok[:, k] & ok.any(axis=1)
                edges.append(np.stack([anchor[keep], g[keep, k]], -1))
        label = _pieces(n, np.concatenate(edges))
        shared = np.flatnonzero(np.bincount(label, minlength=n)[label] > 1)   # particles of pieces of 2 or more
        near = shared[_near_pairs(np.asarray(x, np.float64)[shared], np.asarray(radius, np.float64)[shared])]
        pairs.append(near[label[near[:, 0]] == label[near[:, 1]]])
    pairs = np.sort(np.concatenate(pairs), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0).reshape(-1, 2)


def check_max_neighbours(value, collide, dim: int) -> int:
    """`build`'s `max_neighbours` (None: `DEFAULT_MAX_NEIGHBOURS`): a Python int >= 1, only with
    ``collide=True`` or ``"grid"``."""
    if value is None:
        return DEFAULT_MAX_NEIGHBOURS[dim]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"build: `max_neighbours` must be a Python int >= 1 (it is static), got {value!r}")
    if value < 1:
        raise ValueError(f"build: `max_neighbours` must be >= 1, got {value}")
    if not ((isinstance(collide, (bool, np.bool_)) and bool(collide)) or (isinstance(collide, str)
                                                                          and collide == "grid")):
        raise ValueError("build: `max_neighbours` sets the neighbour grid's capacity and needs collide=True or "
                         f"collide='grid', got collide={collide!r}")
    return int(value)


def uses_grid(collide, n: int) -> bool:
    """Whether `collide` asks for the neighbour grid: ``"grid"``, or True above `MAX_ALL_PAIRS_PARTICLES`."""
    if isinstance(collide, str):
        if collide != "grid":
            raise ValueError(f"build: `collide` must be True, False, 'grid' or a list of (i, j) pairs, got {collide!r}")
        return True
    return isinstance(collide, (bool, np.bool_)) and bool(collide) and n > MAX_ALL_PAIRS_PARTICLES


def contact_pairs(collide, n: int, exclude: np.ndarray) -> np.ndarray:
    """Candidate pairs from `collide`: False/None (none), True (every pair not in `exclude` [m, 2], the pairs
    `joined_at_rest` skips), or a list of (i, j) pairs (checked). A grid (`uses_grid`) has no static pairs."""
    if collide is None or collide is False or uses_grid(collide, n):
        return np.zeros((0, 2), np.int64)
    if collide is True:
        a, b = np.triu_indices(n, 1)
        pairs = np.stack([a, b], -1)
        if len(exclude):
            ex = np.sort(np.asarray(exclude, np.int64), axis=1)
            pairs = pairs[~np.isin(pairs[:, 0] * n + pairs[:, 1], ex[:, 0] * n + ex[:, 1])]
        return pairs
    if isinstance(collide, (bool, np.bool_)):
        return contact_pairs(bool(collide), n, exclude)
    pairs = parse_pairs("collide", collide, n)
    key = np.sort(pairs, axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    if len(first) != len(pairs):
        dup = sorted(set(range(len(pairs))) - set(first.tolist()))[0]
        raise ValueError(f"build: `collide[{dup}]` = {tuple(pairs[dup].tolist())} repeats an earlier pair")
    return pairs


# ---- the contact data every solver shares: leaves and impulses in the internal layout ---------------------
# (jaxcon.solvers.contact computes with them; `core` keeps them so that it never imports a solver.)
@pytree_dataclass
class ContactSystem:
    """A model's contact leaves in the internal layout: radius [1, *view] and [n] (internal order)."""

    radius: Array
    radius_flat: Array
    friction: Array
    restitution: Array
    threshold: Array
    plane_normal: Array
    plane_offset: Array
    sphere_centre: Array
    sphere_radius: Array
    ct: ContactTopology = static_field()

    @classmethod
    def from_model(cls, model, dtype) -> Optional["ContactSystem"]:
        if model.contact is None:
            return None
        t = model.topology
        leaves = {k: jnp.asarray(getattr(model, k), dtype) for k in _LEAVES}
        bad = _invalid(leaves)
        # A value that `Model` refuses when it is concrete (NaN, negative friction, restitution outside [0, 1],
        # ...) can still arrive traced: an optimiser step with a NaN gradient inside jit. Every solver then
        # computes with NaN leaves, so that the rollout's outputs are NaN and the bad value is seen (a NaN
        # friction alone only made PGS's friction clamp `|lam_t| >= NaN` false: a finite, frictionless run).
        leaves = {k: jnp.where(bad, jnp.nan, v) for k, v in leaves.items()}
        r = L.per_particle_in(t, leaves["radius"])
        normal = L.safe_norm(leaves["plane_normal"], axis=-1)[1]     # unit, also for fitted or traced normals
        return cls(r, r.reshape(t.n), leaves["friction"], leaves["restitution"], leaves["restitution_threshold"],
                   normal, leaves["plane_offset"], leaves["sphere_centre"], leaves["sphere_radius"], model.contact)


_LEAVES = ("radius", "friction", "restitution", "restitution_threshold", "plane_normal", "plane_offset",
           "sphere_centre", "sphere_radius")
_NONNEGATIVE = ("radius", "friction", "restitution", "restitution_threshold", "sphere_radius")


def _invalid(leaves: dict):
    """Whether any contact leaf holds a value `Model` refuses (jaxcon.core.model's contact checks): a
    non-finite value, a negative radius, friction, restitution, threshold or sphere radius, or restitution
    above 1. A scalar bool (traced under jit)."""
    bad = jnp.zeros((), bool)
    for k, v in leaves.items():
        bad = bad | ~jnp.all(jnp.isfinite(v))
        if k in _NONNEGATIVE:
            bad = bad | jnp.any(v < 0)
    return bad | jnp.any(leaves["restitution"] > 1)


class Reuse(NamedTuple):
    """A grid model's wider candidate list, kept across steps (`grid.reused_search`): `partners` [n, K] (int32,
    internal indices, -1 empty) within the wider distance of the search at positions `anchor` [dim, n], and
    `ok` (bool scalar): the list is complete (no candidate of the wider distance was left out), so a later
    step may pick its pairs from it."""

    partners: Array
    anchor: Array
    ok: Array


def no_reuse(topo: Topology, ct: ContactTopology, dtype) -> Reuse:
    """A `Reuse` that no step may use (the first step of a rollout searches)."""
    return Reuse(jnp.full((topo.n, ct.grid_k), -1, jnp.int32), jnp.zeros((topo.dim, topo.n), dtype),
                 jnp.zeros((), bool))


class Impulses(NamedTuple):
    """Accumulated contact impulses, internal layout: obstacles n [Q, *view], t [Q, dim, *view]; pairs
    n [R, S], t [dim, R, S], or for a grid model n [n, K], t [dim, n, K] with `partners` [n, K] (int32, internal
    indices, -1 empty) and `overflow` (int32 scalar) of the (sub)step that made them (None without a grid).
    Between the steps of a rollout a grid model also carries its wider candidate list `reuse` (a `Reuse`;
    None within a step, and for a state entering a rollout: `sim._enter` gives it `no_reuse`)."""

    obs_n: Array
    obs_t: Array
    pair_n: Array
    pair_t: Array
    partners: Array = None
    overflow: Array = None
    reuse: Any = None


# ---- layout: user order <-> internal --------------------------------------------------------------------------------------------------
def contacts_in(topo: Topology, ct: ContactTopology, cn, ctan) -> Impulses:
    """User order (cn [k], ctan [k, dim]) -> internal `Impulses`."""
    n, q, dim = topo.n, ct.n_obstacles, topo.dim
    obs_n = cn[: q * n].reshape(q, n)
    obs_t = jnp.swapaxes(ctan[: q * n].reshape(q, n, dim), 1, 2)
    if topo.order is not None:
        obs_n, obs_t = jnp.take(obs_n, topo.order, axis=-1), jnp.take(obs_t, topo.order, axis=-1)
    obs_n, obs_t = obs_n.reshape((q,) + topo.view), obs_t.reshape((q, dim) + topo.view)
    if ct.has_grid:
        K, uid = ct.grid_k, ct.grid_uid.array
        gn = cn[q * n:].reshape(n, K)[uid]
        gt = jnp.moveaxis(ctan[q * n:].reshape(n, K, dim)[uid], -1, 0)
        return Impulses(obs_n, obs_t, gn, gt, None, jnp.zeros((), jnp.int32))
    R, S = ct.rounds, ct.width
    pn = jnp.zeros((R * S,), cn.dtype)
    pt = jnp.zeros((dim, R * S), cn.dtype)
    if ct.n_pairs:
        pn = pn.at[ct.slot.array].set(cn[q * n:])
        pt = pt.at[:, ct.slot.array].set(ctan[q * n:].T)
    return Impulses(obs_n, obs_t, pn.reshape(R, S), pt.reshape(dim, R, S))


def contacts_out(topo: Topology, ct: ContactTopology, imp: Impulses):
    """Internal `Impulses` (any leading axes) -> user order (cn [..., k], ctan [..., k, dim])."""
    q, dim = ct.n_obstacles, topo.dim
    lead = imp.obs_n.shape[: imp.obs_n.ndim - 1 - len(topo.view)]
    on = imp.obs_n.reshape(lead + (q, topo.n))
    ot = imp.obs_t.reshape(lead + (q, dim, topo.n))
    if topo.order is not None:
        on, ot = jnp.take(on, topo.pos, axis=-1), jnp.take(ot, topo.pos, axis=-1)
    ns = [on.reshape(lead + (q * topo.n,))]
    ts = [jnp.swapaxes(ot, -1, -2).reshape(lead + (q * topo.n, dim))]
    if ct.n_pairs:
        pn = imp.pair_n.reshape(lead + (-1,))
        pt = imp.pair_t.reshape(lead + (dim, -1))
        ns.append(jnp.take(pn, ct.slot.array, axis=-1))
        ts.append(jnp.swapaxes(jnp.take(pt, ct.slot.array, axis=-1), -1, -2))
    if ct.has_grid:
        pos = topo.pos if topo.order is not None else np.arange(topo.n)     # user particle -> internal row
        n, K = topo.n, ct.grid_k
        ns.append(jnp.take(imp.pair_n, pos, axis=-2).reshape(lead + (n * K,)))
        pt = jnp.moveaxis(jnp.take(imp.pair_t, pos, axis=-2), -3, -1)        # [..., n, K, dim]
        ts.append(pt.reshape(lead + (n * K, dim)))
    return jnp.concatenate(ns, -1), jnp.concatenate(ts, -2)


def partners_in(ct: ContactTopology, partners):
    """A state's contact_partners (user order, [n, K]; None: unknown) -> internal rows and indices."""
    n, K = ct.n, ct.grid_k
    if partners is None:
        return jnp.full((n, K), -1, jnp.int32)
    uid = ct.grid_uid.array
    internal = np.empty(n, np.int32)
    internal[uid] = np.arange(n)
    p = jnp.asarray(partners, jnp.int32)[uid]
    return jnp.where(p >= 0, jnp.asarray(internal)[jnp.clip(p, 0, n - 1)], -1).astype(jnp.int32)


def partners_out(ct: ContactTopology, partners):
    """Internal partners [..., n, K] -> user order (rows by user particle, user indices, -1 kept)."""
    uid = jnp.asarray(ct.grid_uid.array)
    internal = np.empty(ct.n, np.int64)
    internal[ct.grid_uid.array] = np.arange(ct.n)
    p = jnp.take(partners, internal, axis=-2)
    return jnp.where(p >= 0, uid[jnp.maximum(p, 0)], -1).astype(jnp.int32)


def zero_impulses(topo: Topology, ct: ContactTopology, dtype) -> Impulses:
    q, dim = ct.n_obstacles, topo.dim
    if ct.has_grid:
        n, K = topo.n, ct.grid_k
        return Impulses(jnp.zeros((q,) + topo.view, dtype), jnp.zeros((q, dim) + topo.view, dtype),
                        jnp.zeros((n, K), dtype), jnp.zeros((dim, n, K), dtype), jnp.full((n, K), -1, jnp.int32),
                        jnp.zeros((), jnp.int32))
    return Impulses(jnp.zeros((q,) + topo.view, dtype), jnp.zeros((q, dim) + topo.view, dtype),
                    jnp.zeros((ct.rounds, ct.width), dtype), jnp.zeros((dim, ct.rounds, ct.width), dtype))
