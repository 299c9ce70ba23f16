"""Contacts: the static contact topology and the checks of `jc.build`'s contact arguments.

A model may have three kinds of contact, each a unilateral constraint on a gap C >= 0:

* plane p:  C = n_p . x - offset_p - r        (one contact per particle and plane)
* sphere s: C = |x - c_s| - R_s - r           (one per particle and static sphere)
* pair:     C = |x_j - x_i| - r_i - r_j       (candidate pairs, all of them when ``collide=True``)

Obstacle contacts need no broad phase: each obstacle's contacts are solved together, vectorised over every
particle. Candidate pairs are split into rounds of disjoint pairs (a round-robin schedule for all pairs: n
particles in n - 1 rounds, or n rounds when n is odd), padded to one width, so a sweep is one loop over rounds
whose body does not depend on n: the program's size is the same for 16 balls and for 1000.

Contact impulses are reported in one order: plane contacts (plane-major: index p * n + particle), then sphere
contacts (s * n + particle), then pairs in the order of `ContactTopology.pairs`.
"""
from __future__ import annotations

import numpy as np

from jaxcon.core.pytree import StaticArray
from jaxcon.core.topology import greedy_colouring, parse_pairs

# collide=True solves every pair in every sweep: O(n^2) work per sweep. Above this many particles, pass
# candidate pairs instead (the neighbour grid that would lift this limit is not built yet).
MAX_ALL_PAIRS_PARTICLES = 2048


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

    def __init__(self, n: int, n_planes: int, n_spheres: int, pairs: np.ndarray, pos=None):
        self.n = int(n)
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
                     np.asarray(pos).tobytes())
        self._hash = hash(self._key)

    @property
    def n_obstacles(self) -> int:
        return self.n_planes + self.n_spheres

    @property
    def k(self) -> int:
        """Number of contact slots (the length of a state's contact impulses)."""
        return self.n_obstacles * self.n + self.n_pairs

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return self is other or (isinstance(other, ContactTopology) and self._hash == other._hash
                                 and self._key == other._key)

    def __repr__(self):
        return (f"ContactTopology({self.n_planes} planes, {self.n_spheres} spheres, {self.n_pairs} pairs in "
                f"{self.rounds} rounds)")


def contact_pairs(collide, n: int, exclude: np.ndarray) -> np.ndarray:
    """Candidate pairs from `collide`: False/None (none), True (every pair not joined by a constraint in
    `exclude`, [m, 2]), or a list of (i, j) pairs (checked)."""
    if collide is None or collide is False:
        return np.zeros((0, 2), np.int64)
    if collide is True:
        if n > MAX_ALL_PAIRS_PARTICLES:
            raise ValueError(
                f"build: `collide=True` checks all n (n - 1) / 2 pairs every sweep, which is limited to "
                f"{MAX_ALL_PAIRS_PARTICLES} particles; this model has {n}. Pass `collide` as a list of candidate "
                "(i, j) pairs instead")
        a, b = np.triu_indices(n, 1)
        pairs = np.stack([a, b], -1)
        if len(exclude):
            joined = set(map(tuple, np.sort(exclude, axis=1).tolist()))
            keep = np.array([(int(p), int(q)) not in joined for p, q in pairs], bool)
            pairs = pairs[keep]
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
