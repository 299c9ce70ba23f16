"""The layout of constraint sets (the speed of user-written constraints). A large set is swept
one colour at a time with each colour a block of its own (`topology.SetColour`): read through strided slices
and written through pads where its rows form boxes of the particle grid (`topology.lattice_colouring` makes
such colours for rows that are translates of a few stencils), through a gather otherwise. Each layout is checked
against the built-in rods given the same colouring, which makes the Gauss-Seidel order the same: the
trajectories agree to rounding."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.topology import lattice_colouring


def _distance(x, p):
    d = x[1] - x[0]
    return p["L"] - jnp.sqrt(jnp.sum(d * d))


def _colour_of(model):
    """Each set constraint's colour (the index of its block among the set's blocks), in user order."""
    t = model.topology
    colour = np.empty(t.m - t.m_pairs, np.int64)
    for c, b in enumerate(b for b in t.blocks if b.generic is not None):
        colour[b.src.array - t.m_pairs] = c
    return colour


def _cloth_pairs(n, rng):
    model, state = jc.scenes.cloth(n, n)
    pairs = np.asarray(model.pairs)
    return pairs[rng.permutation(len(pairs))], np.asarray(state.x)        # the user's order: shuffled


@pytest.mark.parametrize("solver", [jc.PGS(8), jc.Jacobi(8), jc.XPBD(substeps=2), jc.SoftStep(substeps=2)],
                         ids=lambda s: type(s).__name__)
def test_a_cloth_of_user_distances_on_boxes_equals_the_rods(solver):
    """A 7x7 cloth's edges written as a user distance set, in shuffled order, on its grid (`grid_shape`), swept
    unrolled: every colour is a strided box (the lattice colouring: 8 colours, where the greedy one needs 8 and
    gives gathers), and the trajectory and impulses equal the built-in rods' with that colouring (float64, 30
    steps of a 0.5 kg cloth held by two corners, rest lengths 2% short so it is under tension). RATTLE is not
    compared: the two fixed corners keep their distance, so the shortened rods cannot all be met, and RATTLE's
    projection does not settle on such a cloth (its rods and its set rows differ by 1e-3 after 30 steps in
    either layout, and with 50 iterations both diverge)."""
    n = 7
    pairs, x = _cloth_pairs(n, np.random.default_rng(0))
    rest = 0.98 * np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=-1)
    con = jc.Constraint(_distance, pairs, {"L": rest})
    m_set, s_set = jc.build(x, 0.5 / n ** 2, constraints=[con], fixed=[0, n - 1], grid_shape=(n, n),
                            layout="unrolled")
    blocks = [b for b in m_set.topology.blocks if b.generic is not None]
    assert len(blocks) == 8 and all(b.unrolled is not None and b.unrolled.boxes is not None for b in blocks)
    m_rod, s_rod = jc.build(x, 0.5 / n ** 2, rods=pairs, fixed=[0, n - 1], grid_shape=(n, n), layout="unrolled",
                            colouring=_colour_of(m_set))
    m_rod = m_rod.replace(rest_length=jnp.asarray(rest))
    _, ta = jc.rollout(m_rod, s_rod, solver, 1 / 120, 30)
    _, tb = jc.rollout(m_set, s_set, solver, 1 / 120, 30)
    tol = 1e-11
    np.testing.assert_allclose(np.asarray(tb.x), np.asarray(ta.x), atol=tol)
    np.testing.assert_allclose(np.asarray(tb.lam), np.asarray(ta.lam), atol=10 * tol * float(jnp.abs(ta.lam).max()))
    assert float(jnp.abs(ta.x[-1] - x).max()) > 0.05                      # it moved


def test_user_distances_on_an_even_grid_take_the_parity_split():
    """An 8x8 cloth's edges as a user distance set on its grid: its column-parity colours step by 2 along the last
    axis, so the set's model stores each grid row evens first (`Topology._split_for_sets`, as rods get it), every
    colour stays a box, and the trajectory and impulses equal the built-in rods' with that colouring."""
    n = 8
    pairs, x = _cloth_pairs(n, np.random.default_rng(1))
    rest = 0.98 * np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=-1)
    m_set, s_set = jc.build(x, 0.5 / n ** 2, constraints=[jc.Constraint(_distance, pairs, {"L": rest})],
                            fixed=[0, n - 1], grid_shape=(n, n), layout="unrolled")
    t = m_set.topology
    assert t.order is not None and all(b.unrolled.boxes is not None for b in t.blocks)
    assert all(box[1][-1] == 1 for b in t.blocks for box in b.unrolled.boxes)       # unit steps along rows
    m_rod, s_rod = jc.build(x, 0.5 / n ** 2, rods=pairs, fixed=[0, n - 1], grid_shape=(n, n), layout="unrolled",
                            colouring=_colour_of(m_set))
    m_rod = m_rod.replace(rest_length=jnp.asarray(rest))
    _, ta = jc.rollout(m_rod, s_rod, jc.PGS(8), 1 / 120, 30)
    _, tb = jc.rollout(m_set, s_set, jc.PGS(8), 1 / 120, 30)
    np.testing.assert_allclose(np.asarray(tb.x), np.asarray(ta.x), atol=1e-11)
    np.testing.assert_allclose(np.asarray(tb.lam), np.asarray(ta.lam), atol=1e-10 * float(jnp.abs(ta.lam).max()))


def _graph(n=20, draws=36, seed=1):
    """A random graph of distances on n particles in 2-D (no grid), rest lengths 10% short, varied masses."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, 2))
    pairs = np.array(sorted({tuple(sorted(p)) for p in rng.integers(0, n, size=(draws, 2)) if p[0] != p[1]}))
    rest = 0.9 * np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=-1)
    return x, pairs, rest, rng.uniform(0.2, 2.0, n)


def test_an_irregular_graph_of_user_distances_is_gathered_and_equals_the_rods():
    """Distances on a random graph of 20 particles in 2-D (no grid: the colours are gathers, each written back by
    a gather), unrolled, float64: equal to the rods with the same colouring."""
    x, pairs, rest, masses = _graph()
    m_set, s_set = jc.build(x, masses, constraints=[jc.Constraint(_distance, pairs, {"L": rest})], fixed=[0],
                            layout="unrolled")
    blocks = [b for b in m_set.topology.blocks if b.generic is not None]
    assert all(b.unrolled is not None for b in blocks)
    assert all(b.unrolled.boxes is None for b in blocks if b.size >= 4)     # two rows may happen to be a box
    assert any(b.unrolled.boxes is None for b in blocks)
    m_rod, s_rod = jc.build(x, masses, rods=pairs, fixed=[0], layout="unrolled", colouring=_colour_of(m_set))
    m_rod = m_rod.replace(rest_length=jnp.asarray(rest))
    _, ta = jc.rollout(m_rod, s_rod, jc.PGS(10), 1 / 120, 40)
    _, tb = jc.rollout(m_set, s_set, jc.PGS(10), 1 / 120, 40)
    np.testing.assert_allclose(np.asarray(tb.x), np.asarray(ta.x), atol=1e-11)
    assert float(jnp.abs(ta.x[-1] - x).max()) > 0.05


def test_the_gradient_through_gathered_colours_equals_the_scanned_tables():
    """The same graph's gradient with respect to the rest lengths through its unrolled gather colours equals the
    compact (scanned) layout's, where the same greedy colouring makes the same order."""
    x, pairs, rest, masses = _graph()

    def loss(r, layout):
        m, s = jc.build(x, masses, constraints=[jc.Constraint(_distance, pairs, {"L": r})], fixed=[0],
                        layout=layout)
        final, _ = jc.rollout(m, s, jc.PGS(10), 1 / 120, 8)
        return jnp.sum(final.x ** 2)

    g_unrolled = jax.grad(loss)(jnp.asarray(rest), "unrolled")
    g_compact = jax.grad(loss)(jnp.asarray(rest), "compact")
    assert float(jnp.abs(g_compact).max()) > 0
    np.testing.assert_allclose(np.asarray(g_unrolled), np.asarray(g_compact), rtol=1e-9,
                               atol=1e-12 * float(jnp.abs(g_compact).max()))


def test_lattice_colouring_of_stencils():
    """Rows that are translates of a stencil get the fewest classes modulo a vector that keep rows of one class
    apart: 2 for a chain's links and for a grid's edges of one direction, 4 for a cloth's hinges (edge and wings
    span a 2x2 cell); no two rows of a colour share a particle; a row that repeats a particle gives None."""
    n = 9
    view = (n, n)
    hinges = jc.scenes.cloth_hinges(n, n)
    chain = np.stack([np.arange(20), np.arange(1, 21)], -1)
    model, _ = jc.scenes.cloth(n, n)
    for rows, shape, most in ((chain, (21,), 2), (np.asarray(model.pairs), view, 8), (hinges, view, 12)):
        colour = lattice_colouring(rows, shape)
        assert colour.max() + 1 == most
        for c in range(most):
            used = rows[colour == c].reshape(-1)
            assert len(np.unique(used)) == len(used), c
    assert lattice_colouring(np.array([[0, 1, 0], [1, 2, 1]]), (3,)) is None
    assert lattice_colouring(np.array([[0, 1], [1, 2], [0, 1]]), (3,)) is None          # a row given twice


def test_a_set_that_names_one_edge_twice_is_coloured_apart_on_the_grid():
    """Two springs on one edge (a row given twice) on the grid, unrolled: the lattice colouring cannot keep them
    apart, so the set takes the greedy colouring, and every colour still holds each free particle once; the cloth
    swings as without the copy (its largest relative distance error within 1.5x of the single set's)."""
    n = 5
    model, state = jc.scenes.cloth(n, n)
    pairs = np.asarray(model.pairs)
    pairs = np.concatenate([pairs, pairs[:1]])
    x = np.asarray(state.x)
    rest = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=-1)
    m, s = jc.build(x, 1.0 / n ** 2, constraints=[jc.Constraint(_distance, pairs, {"L": rest})], fixed=[0, n - 1],
                    grid_shape=(n, n), layout="unrolled")
    blocks = [b for b in m.topology.blocks if b.generic is not None]
    assert sum(b.size for b in blocks) == len(pairs)
    for b in blocks:
        used = b.i_idx.array.reshape(-1)
        assert len(np.unique(used)) == len(used) or np.isin(used, [0, n - 1]).any()
    _, tr = jc.rollout(m, s, jc.PGS(10), 1 / 60, 30)
    assert np.isfinite(np.asarray(tr.lam)).all()
    err = (np.asarray(jc.violation(m, tr.x)) / rest).max()
    single, s1 = jc.build(x, 1.0 / n ** 2, constraints=[jc.Constraint(_distance, pairs[:-1], {"L": rest[:-1]})],
                          fixed=[0, n - 1], grid_shape=(n, n), layout="unrolled")
    _, t1 = jc.rollout(single, s1, jc.PGS(10), 1 / 60, 30)
    err1 = (np.asarray(jc.violation(single, t1.x)) / rest[:-1]).max()
    assert err < 1.5 * err1, (err, err1)


def test_bendings_hand_written_gradient_equals_autodiff():
    """`jc.constraints.bending` supplies its gradient (`dihedral_grad`, Constraint(grad=...)): it equals
    `jax.grad(dihedral)` on random hinges (float64, 1e-10 relative)."""
    x = jnp.asarray(np.random.default_rng(3).normal(size=(200, 4, 3)))
    auto = jax.vmap(jax.grad(jc.constraints.dihedral))(x, {"rest": jnp.zeros(200)})
    hand = jax.vmap(jc.constraints.dihedral_grad)(x, {"rest": jnp.zeros(200)})
    np.testing.assert_allclose(np.asarray(hand), np.asarray(auto), rtol=1e-10, atol=1e-10 * float(jnp.abs(auto).max()))


def test_a_rollouts_gradient_through_bendings_hand_written_gradient_equals_central_differences():
    """A rollout's gradient with respect to the rest angles through `dihedral_grad` (XPBD, a compliant 4x4
    cloth, float64) equals central differences along a random direction: reverse mode differentiates the
    hand-written gradient in turn."""
    n = 4
    hinges = jc.scenes.cloth_hinges(n, n)
    base, state = jc.scenes.cloth(n, n)
    bend = jc.constraints.bending(hinges, rest=np.full(len(hinges), 0.05), compliance=1e-3)
    assert bend.grad is jc.constraints.dihedral_grad
    model, s0 = jc.build(np.asarray(state.x), 1.0 / n ** 2, rods=np.asarray(base.pairs), fixed=[0, n - 1],
                         constraints=[bend])

    def loss(rest):
        c = model.constraints[0].replace(params={"rest": rest})
        final, _ = jc.rollout(model.replace(constraints=(c,)), s0, jc.XPBD(substeps=2), 1 / 60, 8)
        return jnp.sum(final.x[:, 2] ** 2)

    rest0 = jnp.full(len(hinges), 0.05)
    g = jax.grad(loss)(rest0)
    u = np.random.default_rng(4).normal(size=rest0.shape)
    eps = 1e-6
    fd = (loss(rest0 + eps * u) - loss(rest0 - eps * u)) / (2 * eps)
    assert abs(float(fd)) > 1e-6
    np.testing.assert_allclose(float(jnp.dot(g, u)), float(fd), rtol=1e-6)


def test_a_hand_written_gradient_of_the_wrong_shape_or_kind_is_refused():
    x = np.array([[0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(TypeError, match="`grad`"):
        jc.Constraint(_distance, [(0, 1)], {"L": [1.0]}, grad="not a function")
    con = jc.Constraint(_distance, [(0, 1)], {"L": [1.0]}, grad=lambda x, p: x[0])
    with pytest.raises(ValueError, match=r"`grad` must return the gradient of `fn`, \[2, 2\], got \(2,\)"):
        jc.build(x, np.ones(2), constraints=[con])
    con = jc.Constraint(_distance, [(0, 1)], {"L": [1.0]}, grad=lambda x, p: x @ p["missing"])
    with pytest.raises(ValueError, match="`grad` failed on x"):
        jc.build(x, np.ones(2), constraints=[con])
