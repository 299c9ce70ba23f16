"""Self-collision of models with rods: `collide=True` on a chain or a cloth keeps every pair of
its particles apart except those one constraint joins and those already within contact distance at build.

The acceptance check is geometric and independent of the solver: over every recorded step, no pair that is not
skipped comes closer than one radius (the contact keeps them two radii apart; a pair at less than one radius
has half passed through). Each scene is also run without self-collision, where the same check fails, so the
check can fail."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.contact import joined_at_rest
from jaxcon.scenes import cloth_edges


def _closest(X, skipped, r):
    """The smallest distance (in radii r) over the frames X [T, n, dim] between two particles not in `skipped`
    [m, 2] (the pairs `collide=True` leaves out), and the frame where it happens."""
    n = X.shape[1]
    free = ~np.eye(n, dtype=bool)
    free[skipped[:, 0], skipped[:, 1]] = free[skipped[:, 1], skipped[:, 0]] = False
    best = [np.linalg.norm(f[:, None] - f[None], axis=-1)[free].min() for f in np.asarray(X, np.float64)]
    return min(best) / r, int(np.argmin(best))


def _beads(n, spacing, y=0.0):
    return np.stack([np.arange(n) * spacing, np.full(n, y)], -1)


def test_collide_skips_pairs_of_one_constraint_and_pairs_touching_at_build_within_one_piece():
    """Two parallel chains of 8 beads, 1 m apart along each, 1.5 m between the chains, radius 1.05 m (contact
    distance 2.1 m): within a chain the rods' pairs and the second neighbours (2 m) are skipped, the third ones
    (3 m) collide; across the chains every pair collides, the ones that start within contact distance too (two
    pieces, like a rack of touching balls). A row of a constraint set (an area) joins its four particles whatever
    their distance. The same pairs are skipped by all pairs and by the grid; an explicit list skips nothing."""
    x = np.concatenate([_beads(8, 1.0), _beads(8, 1.0, 1.5)])
    rods = [(k, k + 1) for k in range(7)] + [(8 + k, 9 + k) for k in range(7)]
    a, b = np.triu_indices(16, 1)
    same = (a < 8) == (b < 8)
    hop = np.abs(a - b)
    want = set(zip(a[same & (hop <= 2)].tolist(), b[same & (hop <= 2)].tolist()))
    model, _ = jc.build(x, 1.0, rods=rods, radius=1.05, collide=True, gravity=0.0)
    listed = set(map(tuple, np.sort(model.contact.pairs.array, 1).tolist()))
    assert listed == set(zip(a.tolist(), b.tolist())) - want
    assert (1, 9) in listed and (0, 3) in listed and (0, 2) not in listed

    grid, _ = jc.build(x, 1.0, rods=rods, radius=1.05, collide="grid", gravity=0.0)
    ct = grid.contact
    uid, table = ct.grid_uid.array, ct.grid_exclude.array
    from_grid = {tuple(sorted((int(uid[p]), int(uid[q])))) for p in range(16) for q in table[p] if q >= 0}
    assert from_grid == want

    quad = jc.constraints.area(np.array([[0, 1, 5, 7]]), rest=np.zeros(1), compliance=1.0)
    with_set, _ = jc.build(x[:8], 1.0, rods=rods[:7], radius=0.45, collide=True, constraints=[quad], gravity=0.0)
    kept = set(map(tuple, np.sort(with_set.contact.pairs.array, 1).tolist()))
    assert {(0, 5), (0, 7), (5, 7), (1, 7)}.isdisjoint(kept) and (0, 6) in kept and (0, 2) in kept

    explicit, _ = jc.build(x, 1.0, rods=rods, radius=1.05, collide=[(0, 2), (0, 9)], gravity=0.0)
    assert explicit.contact.n_pairs == 2


def test_a_whole_body_row_and_a_shared_pivot_do_not_make_neighbours():
    """A row that spans a whole body (the 8 particles of an `area` polygon) joins them into one piece but does
    not make its far sides neighbours: only the pairs within contact distance are skipped. Two pendulums on one
    fixed pivot are two pieces (a fixed particle joins nothing), so their touching bobs collide."""
    ring = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], -1)
    edges = [(k, (k + 1) % 8) for k in range(8)]
    poly = jc.constraints.area(np.arange(8)[None], rest=np.zeros(1))
    model, _ = jc.build(ring, 1.0, rods=edges, radius=0.2, collide=True, constraints=[poly])
    listed = set(map(tuple, np.sort(model.contact.pairs.array, 1).tolist()))
    assert (0, 4) in listed and (0, 2) in listed and (0, 1) not in listed and len(listed) == 28 - 8

    bobs, _ = jc.build([[0.0, 0.0], [-0.05, -1.0], [0.05, -1.0]], 1.0, rods=[(0, 1), (0, 2)], fixed=[0],
                       radius=0.06, collide=True)
    assert set(map(tuple, np.sort(bobs.contact.pairs.array, 1).tolist())) == {(1, 2)}


def test_collide_refuses_traced_positions_when_it_must_find_the_pairs_touching_at_build():
    """Which pairs start within contact distance is static topology: under a transformation that traces the
    positions it cannot be decided, and build says so instead of guessing. Without rods nothing is skipped, so
    the traced positions are fine there."""
    x = _beads(6, 1.0)

    def with_rods(x):
        return jc.build(x, 1.0, rods=[(k, k + 1) for k in range(5)], radius=0.3, collide=True)[1].x.sum()

    with pytest.raises(TypeError, match="`positions` and `radius` known now"):
        jax.grad(with_rods)(jnp.asarray(x))
    free = jax.grad(lambda x: jc.build(x, 1.0, radius=0.3, collide=True)[1].x.sum())(jnp.asarray(x))
    assert np.all(np.asarray(free) == 1)


def test_a_chain_that_coils_on_the_floor_never_passes_through_itself_2d_float32():
    """A 2-D chain of 40 links (float32), held upright with its foot on the floor and tipped a little, falls and
    piles up on itself: with `collide="grid"` (the float32 grid with substeps) no two of its beads that no rod
    joins come closer than one radius (PGS, 2 substeps), and the grid had room for every candidate. (That the
    check can fail is shown on the cloth below.)"""
    n, link = 41, 0.05
    up = np.arange(n) * link
    x = np.stack([0.15 * up, 0.026 + up], -1).astype(np.float32)
    rods = np.stack([np.arange(n - 1), np.arange(1, n)], -1)
    model, state = jc.build(x, 0.02, rods=rods, radius=0.02, collide="grid", planes=[((0.0, 1.0), 0.0)],
                            friction=0.5, dtype=np.float32)
    final, traj = jc.rollout(model, state, jc.PGS(10, substeps=2), 1 / 60, 90)
    assert traj.x.dtype == jnp.float32 and np.isfinite(np.asarray(traj.x)).all()
    assert int(np.asarray(traj.contact_overflow).sum()) == 0
    closest, at = _closest(traj.x, joined_at_rest(n, [rods], x, np.full(n, 0.02)), 0.02)
    assert closest >= 1.0, (closest, at)
    # it piled up: a bead on a third layer or higher (centres 0.02 + 2 * 0.04 sin 60 deg = 0.089 m up, packed). The
    # pile is chaotic in float32: its top bead ended at 0.1006 and, compiled with XLA's other CPU emitters,
    # 0.0993 (the closest approach passed in both)
    assert float(final.x[:, 1].max()) > 0.085


@pytest.mark.parametrize("n", [24, 10])
@pytest.mark.parametrize("solver", [jc.PGS(10, substeps=2), jc.XPBD(1, substeps=8)], ids=["PGS", "XPBD"])
def test_a_cloth_dropped_and_folded_on_the_floor_never_passes_through_itself(solver, n):
    """Issue 25's acceptance: the free n-by-n cloth of `jc.scenes.cloth_drop` on the neighbour grid (24x24: 576
    particles, the grid of `collide=True`, 120 steps; 10x10: `collide="grid"`, 100 steps; float64) lands almost
    upright and folds onto itself in three to five layers. No two of its particles that no rod joins ever come closer than
    one radius, and the grid had room for every candidate. The fold is real: some particles end four radii or
    more above the floor."""
    model, state = jc.scenes.cloth_drop(n, tilt=0.1, collide=True if n > 16 else "grid")
    assert model.contact.has_grid
    r = float(model.radius[0])
    final, traj = jax.jit(lambda s: jc.rollout(model, s, solver, 1 / 60, 120 if n > 16 else 100))(state)
    skipped = joined_at_rest(n * n, [cloth_edges(n, n)[0]], np.asarray(state.x), np.full(n * n, r))
    closest, at = _closest(traj.x, skipped, r)
    assert closest >= 1.0, (closest, at)
    assert float(final.x[:, 2].max()) > 4 * r
    assert float(final.x[:, 2].min()) > 0.5 * r
    if n == 10:
        assert int(np.asarray(traj.contact_overflow).sum()) == 0


def test_the_same_cloth_without_self_collision_passes_through_itself():
    """The check above can fail: the same 10x10 cloth in a model that lists no particle pairs (the floor only)
    folds through itself, pairs at less than half a radius."""
    model, state = jc.scenes.cloth_drop(10, tilt=0.1, collide="grid")
    r = float(model.radius[0])
    edges = cloth_edges(10, 10)[0]
    floor_only, floor_state = jc.build(state.x, 0.5 / 100, rods=edges, radius=r, planes=[((0.0, 0.0, 1.0), 0.0)],
                                       friction=0.3)
    final, traj = jax.jit(lambda s: jc.rollout(floor_only, s, jc.PGS(10, substeps=2), 1 / 60, 100))(floor_state)
    closest, _ = _closest(traj.x, joined_at_rest(100, [edges], np.asarray(state.x), np.full(100, r)), r)
    assert closest < 0.5, closest


@pytest.mark.parametrize("solver", [jc.PGS(4, substeps=2), jc.XPBD(2, substeps=2)], ids=["PGS", "XPBD"])
def test_self_collision_gradients_equal_central_differences(solver):
    """d(final positions)/d(start velocity, radius, friction) through 24 steps of a 5x5 `cloth_drop` (0.25 m, on the
    neighbour grid: its search, path check and slots are in the program) in which its particles touch each other (the listed pairs' impulses are positive in 10 or more pair-steps) and
    the floor, against float64 central differences; every gradient finite. The steps are 1e-7: contacts that
    start or end in a fold are dense in the radius (at 32 steps a step of 1e-6 already straddles one)."""
    model, state = jc.scenes.cloth_drop(5, size=0.25, tilt=0.1, collide="grid")
    assert model.contact.has_grid
    w = jnp.asarray(np.random.default_rng(0).normal(size=(25, 3)))

    def loss(v0, radius, mu):
        m = model.replace(radius=jnp.full(25, radius), friction=mu)
        final, traj = jc.rollout(m, state.replace(v=state.v + v0), solver, 1 / 60, 24)
        pairs = traj.contact_n[:, model.contact.n_planes * 25:]
        return jnp.sum(final.x * w), (jnp.sum(pairs > 0), jnp.max(traj.contact_overflow))

    p = (jnp.array([0.0, 0.3, -0.2]), model.radius[0], jnp.asarray(0.3))
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))
    (_, (touching, overflow)), g = value_and_grad(*p)
    assert int(touching) >= 10 and int(overflow) == 0
    f = lambda *q: value_and_grad(*q)[0][0]        # noqa: E731  (the same program: one compilation)
    eps = 1e-7
    fd_v = [(f(p[0].at[a].add(eps), *p[1:]) - f(p[0].at[a].add(-eps), *p[1:])) / (2 * eps) for a in range(3)]
    fd_r = (f(p[0], p[1] + eps, p[2]) - f(p[0], p[1] - eps, p[2])) / (2 * eps)
    fd_mu = (f(p[0], p[1], p[2] + eps) - f(p[0], p[1], p[2] - eps)) / (2 * eps)
    assert all(np.isfinite(np.asarray(a)).all() for a in g)
    np.testing.assert_allclose(np.asarray(g[0]), np.asarray(fd_v), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(float(g[1]), float(fd_r), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(float(g[2]), float(fd_mu), rtol=1e-5, atol=1e-7)
