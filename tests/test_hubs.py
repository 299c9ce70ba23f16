"""Hubs: one particle carrying many constraints (a wheel's spokes, a fan, a tent pole, a cloth pinned by many
rods). Gauss-Seidel one constraint at a time around a hub amplified rounding error into 1e49 m (XPBD, 16 spokes)
and 4e5 (PGS(10), 64 spokes); the default colouring now solves the constraints at a hub together, exactly, as a
*star* (`topology.star_colouring`, `layout.block_solve`). Every solver must hold a hub released at rest length
at rounding-level violation: the exact motion is a rigid fall, with no constraint force at all."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.topology import STAR_MIN_DEGREE, star_colouring

SOLVERS = [jc.PGS(10), jc.Jacobi(20), jc.XPBD(), jc.SoftStep(), jc.RATTLE(10), jc.Direct(),
           jc.Penalty(stiffness=1e5, substeps=20), jc.PGS(10, stabilization="split")]
IDS = ["PGS", "Jacobi", "XPBD", "SoftStep", "RATTLE", "Direct", "Penalty", "PGS-split"]


def _hub(n_spokes, dim=2, wheel=False, dtype=None):
    """A free hub at the origin joined by rods to `n_spokes` rim particles at unit distance (evenly on a circle
    in 2-D, random on the sphere in 3-D); `wheel` adds a rod between consecutive rim particles."""
    if dim == 2:
        a = 2 * np.pi * np.arange(n_spokes) / n_spokes
        rim = np.stack([np.cos(a), np.sin(a)], -1)
    else:
        v = np.random.default_rng(1).normal(size=(n_spokes, 3))
        rim = v / np.linalg.norm(v, axis=1, keepdims=True)
    x = np.concatenate([np.zeros((1, dim)), rim])
    rods = [(0, k + 1) for k in range(n_spokes)]
    if wheel:
        rods += [(k + 1, (k + 1) % n_spokes + 1) for k in range(n_spokes)]
    return jc.build(x, np.ones(n_spokes + 1), rods=rods, dtype=dtype)


@pytest.mark.parametrize("solver", SOLVERS, ids=IDS)
def test_a_hub_released_at_rest_length_falls_rigidly(solver):
    """A 256-spoke star in 2-D and a 64-spoke wheel in 3-D (float64, dt 1/240, 0.25 s): rounding-level
    violation, and the hub falls freely with the rim (y = -g t^2 / 2)."""
    for model, state in (_hub(256), _hub(64, dim=3, wheel=True)):
        assert model.topology.has_stars
        final, traj = jc.rollout(model, state, solver, 1 / 240, 60)
        assert float(jnp.max(jc.violation(model, traj.x))) < 1e-11, solver
        drop = float(state.x[0, -1] - final.x[0, -1])
        # symplectic Euler falls g dt^2 n (n + 1) / 2 in n steps; the solvers with substeps fall by their own h
        assert drop == pytest.approx(9.81 * 0.25 ** 2 / 2, rel=0.02), (solver, drop)
        np.testing.assert_allclose(np.asarray(final.x - final.x[:1]), np.asarray(state.x - state.x[:1]), atol=1e-9)


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD(), jc.SoftStep()], ids=["PGS", "XPBD", "SoftStep"])
def test_a_hub_holds_in_float32(solver):
    """In float32 XPBD was 129% stretched at 16 spokes; a 64-spoke star now keeps float32 rounding."""
    model, state = _hub(64, dtype=np.float32)
    final, traj = jc.rollout(model, state, solver, 1 / 240, 60)
    assert traj.x.dtype == jnp.float32
    assert float(jnp.max(jc.violation(model, traj.x))) < 1e-5, solver


def test_a_hub_swings_like_the_rigid_body_it_is():
    """A 12-spoke wheel pinned at one rim particle, released from rest: a rigid body, so the violation stays
    at the solver's accuracy and no energy is gained, for the Gauss-Seidel solvers the stars feed (PGS, XPBD,
    SoftStep), against Direct's exact solve."""
    model, state = _hub(12, wheel=True)
    model = model.replace(inv_mass=model.inv_mass.at[1].set(0.0))         # pin rim particle 1
    ref, _ = jc.rollout(model, state, jc.Direct(substeps=4), 1 / 240, 120)
    for solver in (jc.PGS(20), jc.XPBD(substeps=10), jc.SoftStep(substeps=8)):
        final, traj = jc.rollout(model, state, solver, 1 / 240, 120)
        d = jc.diagnose(model, traj, state)
        assert float(np.max(d.violation)) < 1e-3 and float(np.max(d.energy_gain)) < 1e-3, solver
        assert float(jnp.max(jnp.abs(final.x - ref.x))) < 0.02, solver       # the same swing


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD(substeps=4), jc.RATTLE(6)], ids=["PGS", "XPBD", "RATTLE"])
def test_gradient_through_a_star_matches_central_differences(solver):
    """Reverse mode through the stars' block solve (float64): rest lengths and the initial positions, from a
    start with the spokes 2% long, against central differences."""
    model, state = _hub(STAR_MIN_DEGREE)
    state = state.replace(x=state.x.at[1:].multiply(1.02), v=state.v.at[0].set(jnp.array([0.3, 0.1])))
    w = jnp.asarray(np.random.default_rng(0).normal(size=state.x.shape))

    def loss(rest, x0):
        final, _ = jc.rollout(model.replace(rest_length=rest), state.replace(x=x0), solver, 1 / 240, 10)
        return jnp.sum(final.x * w)

    g_rest, g_x = jax.grad(loss, argnums=(0, 1))(model.rest_length, state.x)
    f = jax.jit(loss)
    e = 1e-6
    rest, x0 = model.rest_length, state.x
    fd_rest = [(f(rest.at[k].add(e), x0) - f(rest.at[k].add(-e), x0)) / (2 * e) for k in (0, 4)]
    fd_x = [(f(rest, x0.at[p, a].add(e)) - f(rest, x0.at[p, a].add(-e))) / (2 * e) for p, a in ((0, 0), (3, 1))]
    np.testing.assert_allclose([g_rest[0], g_rest[4]], fd_rest, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose([g_x[0, 0], g_x[3, 1]], fd_x, rtol=1e-5, atol=1e-8)


def test_stars_in_both_layouts_vmap_and_batched_rollout():
    """The same hub in the compact and unrolled layouts, under vmap and through batched_rollout (which takes
    `jax.vmap` for a model with stars): the same trajectory (float64)."""
    x = np.concatenate([_hub(10)[1].x, np.array([[3.0, 0.0], [4.0, 0.0], [5.0, 0.0], [6.0, 0.0], [7.0, 0.0]])])
    rods = [(0, k + 1) for k in range(10)] + [(11, 12), (12, 13), (13, 14), (14, 15), (11, 13), (12, 14)]
    runs = {}
    for lay in ("compact", "unrolled"):
        model, state = jc.build(x, np.ones(16), rods=rods, layout=lay)
        assert model.topology.has_stars and model.topology.layout == lay
        runs[lay] = jc.rollout(model, state, jc.PGS(6), 1 / 120, 20)[1]
    np.testing.assert_allclose(np.asarray(runs["compact"].x), np.asarray(runs["unrolled"].x), atol=1e-13)
    states = jax.tree.map(lambda a: jnp.stack([a, a + 0.01 * (a.ndim == 2) * (a.shape[-1] == 2)]), state)
    finals, _ = jc.batched_rollout(model, states, jc.PGS(6), 1 / 120, 20)
    one, _ = jc.rollout(model, jax.tree.map(lambda a: a[1], states), jc.PGS(6), 1 / 120, 20)
    np.testing.assert_allclose(np.asarray(finals.x[1]), np.asarray(one.x), atol=1e-13)
    np.testing.assert_allclose(np.asarray(runs["unrolled"].lam[-1]), np.asarray(
        jc.rollout(model, state, jc.PGS(6), 1 / 120, 20)[1].lam[-1]), atol=1e-13)


def test_star_colouring():
    """Which constraints form stars: particles with >= STAR_MIN_DEGREE constraints, one constraint per other
    particle (a duplicated rod stays outside), none for a cloth (degree <= 8) or a user colouring."""
    n = 12
    i = np.array([0] * 10 + [0, 11])
    j = np.array(list(range(1, 11)) + [1, 10])           # 10 spokes, a duplicate (0, 1), and a rod (11, 10)
    star, colour = star_colouring(i, j, n)
    assert (star[:10] == 0).all() and star[10] == -1 and star[11] == -1
    assert len(set(colour[:10])) == 1                    # one star, one colour
    cloth, _ = jc.scenes.cloth(8, 8)
    assert not cloth.topology.has_stars
    model, _ = _hub(12)
    assert model.topology.has_stars and "hub stars" in repr(model.topology)
    coloured, _ = jc.build(np.asarray(_hub(12)[1].x), np.ones(13), rods=[(0, k + 1) for k in range(12)],
                           colouring=np.arange(12))
    assert not coloured.topology.has_stars


def _tethered_cloth(n=24, tethers=250):
    """Issue 22's scene: an n x n cloth with `tethers` rods from one fixed anchor above it to random cloth
    particles (3-D)."""
    pairs, _ = jc.scenes.cloth_edges(n, n)
    g = np.stack(np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)), -1).reshape(-1, 2)
    x = np.concatenate([np.concatenate([g, np.zeros((n * n, 1))], 1), [[0.5, 0.5, 1.0]]])
    tether = [(n * n, int(k)) for k in np.random.default_rng(0).choice(n * n, tethers, replace=False)]
    return x, np.concatenate([pairs, tether])


def test_constraints_sharing_a_fixed_particle_share_colours_and_auto_stays_compact():
    """A 24x24 cloth with a 250-rod tether got the unrolled layout with 252 colours (one per tether rod: they
    share the anchor): its first rollout ran for minutes and gigabytes. A fixed particle never moves, so the
    colouring lets constraints share it; the cloth particles a tether makes hubs (degree 9) become stars; and
    'auto' takes the compact layout above 12 colours whatever their width. The program is small (its size is a
    fact of the trace, not a timing)."""
    x, rods = _tethered_cloth()
    model, state = jc.build(x, np.ones(len(x)), rods=rods, fixed=[len(x) - 1])
    t = model.topology
    assert t.compact and t.n_colours <= 20, t
    lowered = jax.jit(lambda s: jc.rollout(model, s, jc.PGS(10), 1 / 60, 4)).lower(state)
    assert lowered.as_text().count("\n") < 3000
    final, _ = jc.rollout(model, state, jc.PGS(10), 1 / 60, 4)
    assert np.isfinite(np.asarray(final.x)).all()
    # more than 12 colours of any width: compact (here 24 colours of about 140 rods, given explicitly)
    pairs, colour = jc.scenes.cloth_edges(24, 24)
    split = colour * 3 + np.arange(len(colour)) % 3
    many, _ = jc.build(x[:-1], np.ones(len(x) - 1), rods=pairs, colouring=split)
    wide, _ = jc.build(x[:-1], np.ones(len(x) - 1), rods=pairs)                    # 8 colours of up to 276
    assert many.topology.compact and not wide.topology.compact


def test_a_fixed_particle_stays_fixed():
    """The colouring relies on which particles were fixed when the model was built: freeing one afterwards is
    refused (its constraints may share a colour), naming the argument."""
    x, rods = _tethered_cloth(4, 6)
    model, _ = jc.build(x, np.ones(len(x)), rods=rods, fixed=[len(x) - 1])
    with pytest.raises(ValueError, match=r"inv_mass\[16\].*fixed when the model was built"):
        model.replace(inv_mass=jnp.ones(len(x)))
    model.replace(inv_mass=model.inv_mass * 2)                # changing the free masses is fine


def test_jacobi_relaxation_counts_free_particles_only():
    """Jacobi's default relaxation is 1 / (largest number of blocks at a free particle): a fixed anchor with 250
    tethers does not slow every other row down 250 times. A tethered cloth particle (8 rods and its tether) is a
    hub whose star counts once, so the largest count is an untethered particle's 8 rods."""
    from jaxcon.solvers.jacobi import max_degree
    x, rods = _tethered_cloth()
    model, _ = jc.build(x, np.ones(len(x)), rods=rods, fixed=[len(x) - 1])
    assert max_degree(model.topology) == 8


def _user_length(x, p):
    return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))


def _set_hub(n_spokes, kind, dim=2, dtype=None):
    """`_hub` with its spokes as a constraint set: the user's own distance function, or `constraints.distance`."""
    _, state = _hub(n_spokes, dim=dim)
    x = np.asarray(state.x)
    spokes = [(0, k + 1) for k in range(n_spokes)]
    con = (jc.Constraint(_user_length, spokes, {"L": np.ones(n_spokes)}) if kind == "fn"
           else jc.constraints.distance(spokes, positions=x))
    return jc.build(x, np.ones(n_spokes + 1), constraints=con, dtype=dtype)


def test_set_stars():
    """A constraint set's hubs become stars as rods' do: rows at a free particle of degree >= STAR_MIN_DEGREE
    that share only it (a duplicated row stays outside, as a duplicated rod), at least STAR_MIN_DEGREE of them;
    none below that degree, at a fixed particle, or among a cloth's bending hinges (which share other particles)."""
    from jaxcon.core.topology import set_stars
    rows = np.array([[0, k] for k in range(1, 11)] + [[1, 0], [11, 10]])
    (hub, ks), = set_stars(rows, 12)
    assert hub == 0 and list(ks) == list(range(10))
    assert set_stars(rows[:8], 12) == [] and set_stars(rows, 12, fixed=np.arange(12) == 0) == []
    tri = np.array([[0, 2 * k + 1, 2 * k + 2] for k in range(9)] + [[0, 1, 3]])     # 3-particle rows at 0
    (hub, ks), = set_stars(tri, 19)
    assert hub == 0 and list(ks) == list(range(9))                # the last row shares particle 1: outside
    model, _ = _set_hub(12, "fn")
    assert model.topology.set_hubs and "set hub stars" in repr(model.topology)
    cloth, _ = jc.scenes.cloth(12, 12, bending=1e-2)           # hinges: 12 rows at a particle, sharing others
    assert max(np.bincount(cloth.topology.sets[0].particles.ravel())) >= STAR_MIN_DEGREE
    assert not cloth.topology.set_hubs


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD(), jc.Jacobi(20), jc.SoftStep(), jc.RATTLE(10)],
                         ids=["PGS", "XPBD", "Jacobi", "SoftStep", "RATTLE"])
def test_a_set_hub_moves_as_the_rods_hub(solver):
    """The same 16-spoke hub hanging from one of its rim particles (fixed), the others thrown at random velocities,
    with its spokes as rods and as a `jc.Constraint` set of the user's distance function (float64): a star of rods
    and a star of set rows are the same rows solved the same way (one block either way, so the same sweep order),
    and the trajectories agree to rounding; before, the set's rows were swept one at a time around the hub (XPBD
    blew up at 16 spokes)."""
    n = 16
    _, state = _hub(n)
    x = np.asarray(state.x)
    spokes = [(0, k + 1) for k in range(n)]
    rods_model, state = jc.build(x, np.ones(n + 1), rods=spokes, fixed=[1])
    set_model, _ = jc.build(x, np.ones(n + 1), fixed=[1],
                            constraints=jc.Constraint(_user_length, spokes, {"L": np.ones(n)}))
    assert rods_model.topology.has_stars and set_model.topology.set_hubs
    v = np.random.default_rng(2).normal(size=x.shape)
    v[1] = 0
    state = state.replace(v=jnp.asarray(v))
    a, _ = jc.rollout(rods_model, state, solver, 1 / 240, 60)
    b, _ = jc.rollout(set_model, state, solver, 1 / 240, 60)
    assert float(jnp.max(jnp.abs(a.x[0] - state.x[0]))) > 1e-2                   # the hub moves
    np.testing.assert_allclose(np.asarray(b.x), np.asarray(a.x), atol=1e-9)


@pytest.mark.parametrize("kind", ["fn", "distance"])
@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD(), jc.SoftStep(), jc.RATTLE(10), jc.Jacobi(40)],
                         ids=["PGS", "XPBD", "SoftStep", "RATTLE", "Jacobi"])
def test_a_set_hub_holds_in_float32(solver, kind):
    """A free 64-spoke hub as a set released at rest length, float32, 60 steps: XPBD reached 1e19 at 16 spokes
    and PGS 7e11 at 64 before a set's hubs were stars; now below 1e-5."""
    model, state = _set_hub(64, kind, dtype=np.float32)
    _, traj = jc.rollout(model, state, solver, 1 / 240, 60)
    assert traj.x.dtype == jnp.float32
    assert float(jnp.max(jc.violation(model, traj.x))) < 1e-5, solver


def test_jacobi_holds_a_100_spoke_hub_in_float32():
    """Jacobi solves a star as one block (block Jacobi) and counts it once at its hub, so a 100-spoke hub takes
    relaxation 1 instead of 1 / 100: 3.9e-3 (Jacobi(10)) before, rounding level now (float32, 1 s)."""
    from jaxcon.solvers.jacobi import max_degree
    model, state = _hub(100, dtype=np.float32)
    assert max_degree(model.topology) == 1
    _, traj = jc.rollout(model, state, jc.Jacobi(10), 1 / 240, 240)
    assert float(jnp.max(jc.violation(model, traj.x))) < 1e-5


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD(substeps=4)], ids=["PGS", "XPBD"])
def test_gradient_through_a_set_star_matches_central_differences(solver):
    """Reverse mode through a set star's block solve (float64): the spokes' rest lengths (a set parameter) and
    the initial positions, from a start with the spokes 2% long, against central differences."""
    model, state = _set_hub(STAR_MIN_DEGREE, "fn")
    assert model.topology.set_hubs
    state = state.replace(x=state.x.at[1:].multiply(1.02), v=state.v.at[0].set(jnp.array([0.3, 0.1])))
    w = jnp.asarray(np.random.default_rng(0).normal(size=state.x.shape))
    con = model.constraints[0]

    def loss(rest, x0):
        m = model.replace(constraints=(con.replace(params={"L": rest}),))
        final, _ = jc.rollout(m, state.replace(x=x0), solver, 1 / 240, 10)
        return jnp.sum(final.x * w)

    rest0 = jnp.asarray(con.params["L"])
    g_rest, g_x = jax.grad(loss, argnums=(0, 1))(rest0, state.x)
    f = jax.jit(loss)
    e = 1e-6
    fd_rest = [(f(rest0.at[k].add(e), state.x) - f(rest0.at[k].add(-e), state.x)) / (2 * e) for k in (0, 4)]
    fd_x = [(f(rest0, state.x.at[p, a].add(e)) - f(rest0, state.x.at[p, a].add(-e))) / (2 * e)
            for p, a in ((0, 0), (3, 1))]
    np.testing.assert_allclose([g_rest[0], g_rest[4]], fd_rest, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose([g_x[0, 0], g_x[3, 1]], fd_x, rtol=1e-5, atol=1e-8)


def test_set_stars_in_both_layouts():
    """A set holding a 10-row hub and a chain of 5 other rows (which take a colour table or blocks of their own):
    its stars come first in either layout, the rest after them, and the compact and unrolled layouts run the same
    trajectory (float64), and the rows hold."""
    n = 10
    _, state = _hub(n)
    x = np.concatenate([np.asarray(state.x), np.array([[3.0, 0.0], [4.0, 0.0], [5.0, 0.0], [6.0, 0.0]])])
    rows = [(0, k + 1) for k in range(n)] + [(3, 11), (11, 12), (12, 13), (13, 14), (11, 13)]
    runs = {}
    for lay in ("compact", "unrolled"):
        model, state = jc.build(x, np.ones(len(x)), constraints=jc.Constraint(_user_length, rows, {
            "L": np.linalg.norm(x[[b for _, b in rows]] - x[[a for a, _ in rows]], axis=1)}), layout=lay)
        t = model.topology
        assert [len(ks) for _, _, ks in t.set_hubs] == [n] and t.blocks[0].hub_slot is not None
        state = state.replace(v=state.v.at[14].set(jnp.array([0.0, 2.0])))
        runs[lay] = jc.rollout(model, state, jc.PGS(6), 1 / 120, 20)[1]
    np.testing.assert_allclose(np.asarray(runs["compact"].x), np.asarray(runs["unrolled"].x), atol=1e-13)
    assert runs["compact"].lam.shape == (20, len(rows))
    assert float(jnp.max(jc.violation(model, runs["compact"].x))) < 1e-2
    assert float(jnp.max(jnp.abs(runs["compact"].x[-1, 14] - x[14]))) > 0.1                # it moves
