"""The neighbour grid for particle-particle contacts (collide="grid", or collide=True above MAX_ALL_PAIRS_PARTICLES (256))."""
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.contact import MAX_ALL_PAIRS_PARTICLES

sys.path.insert(0, os.path.dirname(__file__))
from test_contacts_grid_solvers import _pile as _pile_3d  # noqa: E402  12 balls in 3 layers (with dim=3)

jax.config.update("jax_enable_x64", True)

R = 0.05
BOX = [([0.0, 1.0], 0.0), ([1.0, 0.0], 0.0), ([-1.0, 0.0], -0.6)]       # floor and two walls, 0.6 m apart


def _discs(rows, cols, jitter=0.0, seed=0, gap=0.002):
    rng = np.random.default_rng(seed)
    k = np.arange(rows * cols)
    x = np.stack([(k % cols) * (2 * R + gap) + R + 0.01, (k // cols) * (2 * R + gap) + R + 0.01], -1)
    return x + jitter * rng.uniform(-1, 1, x.shape)


def _pile(collide, **kw):
    """18 discs in 4 staggered rows, slightly apart, falling onto the floor of the box."""
    pts = [[R + 0.05 + c * 2.02 * R + (r % 2) * R, R + 0.002 + 0.12 * r]
           for r in range(4) for c in range(5 - r % 2)]
    x = np.asarray(pts) + np.random.default_rng(0).uniform(-0.003, 0.003, (len(pts), 2))
    return jc.build(x, np.ones(len(x)), radius=R, collide=collide, planes=BOX, friction=0.3, **kw)


@pytest.mark.parametrize("collide", [True, "grid"])
def test_pile_settles_without_overlap(collide):
    model, state = _pile(collide)
    final, traj = jc.rollout(model, state, jc.PGS(10), 1 / 120, 300)
    d = jc.diagnose(model, traj, state)
    assert not bool(d.diverged)
    assert float(jnp.max(d.penetration)) < 0.01 * 2 * R
    assert float(jnp.max(jnp.abs(final.v))) < 0.02
    if collide == "grid":
        assert traj.contact_n.shape == (300, 3 * 18 + 18 * 8)
        assert traj.contact_partners.shape == (300, 18, 8)
        assert int(jnp.max(traj.contact_overflow)) == 0 and not bool(d.overflowed)


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.PGS(10, warm_start=False), jc.Jacobi(20)])
def test_energy_never_increases_without_gravity(solver):
    x = _discs(4, 4, gap=0.03)
    rng = np.random.default_rng(1)
    v = rng.normal(0, 1.0, x.shape)
    box = BOX + [([0.0, -1.0], -0.6)]
    model, state = jc.build(x, np.ones(len(x)), velocities=v, gravity=0.0, radius=R, collide="grid", planes=box,
                            restitution=0.8)
    _, traj = jc.rollout(model, state, solver, 1 / 120, 150)
    ke = np.concatenate([[float(jc.kinetic_energy(model, state.v))], np.asarray(jc.kinetic_energy(model, traj.v))])
    # PGS scales restitution back so that no impulse phase gains energy. Without a warm start it gains none
    # (at most 2e-16 of KE_0 in a step over the velocity seeds 0 to 5). With one, what the 10 sweeps leave of
    # the last step's impulses can: 6.9e-7 of KE_0 in a step here, up to 4.7e-5 over seeds 0 to 5 (all pairs,
    # collide=True, up to 9e-7; Baumgarte plays no part: beta = 0 gives the same), and less with more sweeps:
    # the warm start's known energy, not the restitution. Jacobi has no restitution guard and gains up to 1e-5
    # of KE_0 in a step here, as it does with all pairs (3e-6).
    tol = 1e-12 if isinstance(solver, jc.PGS) and not solver.warm_start else 1e-4
    assert np.all(np.diff(ke) <= tol * ke[0])
    assert ke[-1] < ke[0]           # collisions happened and were inelastic
    assert float(jnp.max(jc.diagnose(model, traj, state).penetration)) < 0.01 * 2 * R


def test_head_on_elastic_collision_exchanges_velocities():
    model, state = jc.build([[0.0, 0.0], [1.0, 0.03]], [1.0, 1.0], velocities=[[2.0, 0.0], [-1.0, 0.0]], gravity=0.0,
                            radius=0.1, collide="grid", restitution=1.0, restitution_threshold=0.0)
    state = state.replace(x=jnp.array([[0.0, 0.0], [1.0, 0.0]]))
    final, traj = jc.rollout(model, state, jc.PGS(10), 0.01, 60)
    np.testing.assert_allclose(final.v, [[-1.0, 0.0], [2.0, 0.0]], atol=1e-9)
    # the contact's impulse (momentum exchanged, 3 N s) is reported in particle 0's slot naming particle 1
    hit = int(np.argmax(np.asarray(traj.contact_n).max(-1)))
    slot = int(np.argmax(np.asarray(traj.contact_partners[hit, 0]) == 1))
    assert int(traj.contact_partners[hit, 0, slot]) == 1
    np.testing.assert_allclose(float(traj.contact_n[hit, slot]), 3.0, rtol=1e-9)


def test_overflow_is_reported():
    """One slot per particle in a packed lattice overflows. (A grid with room reports none: every grid pile,
    friction and gradient test asserts a zero overflow.)"""
    x = _discs(4, 4, gap=0.0)
    model, state = jc.build(x, np.ones(len(x)), radius=R, collide="grid", gravity=0.0, max_neighbours=1)
    _, traj = jc.rollout(model, state, jc.PGS(2), 1 / 60, 2)
    with pytest.warns(UserWarning, match="max_neighbours"):
        d = jc.diagnose(model, traj, state)
    assert bool(d.overflowed) and int(jnp.max(d.overflow)) > 0
    # with save_every, a record holds the overflow of every step since the previous one
    _, every2 = jc.rollout(model, state, jc.PGS(2), 1 / 60, 2, save_every=2)
    assert int(every2.contact_overflow[0]) == int(jnp.sum(traj.contact_overflow))
    # with substeps, the step's one search is counted once (not once per substep)
    _, sub = jc.rollout(model, state, jc.PGS(2, substeps=3), 1 / 60, 1)
    assert int(sub.contact_overflow[0]) == int(traj.contact_overflow[0])


def test_collide_true_above_the_all_pairs_limit_uses_the_grid():
    n = MAX_ALL_PAIRS_PARTICLES + 52
    cols = 50
    k = np.arange(n)
    x = np.stack([(k % cols) * 0.021, (k // cols) * 0.021 + 0.011], -1)        # discs 1 mm apart
    v = np.random.default_rng(2).normal(0, 0.1, x.shape)
    model, state = jc.build(x, np.ones(n), velocities=v, gravity=0.0, radius=0.01, collide=True,
                            planes=[([0.0, 1.0], 0.0)])
    assert model.contact.has_grid and model.contact.n_pairs == 0
    final, traj = jax.jit(lambda s: jc.rollout(model, s, jc.PGS(4), 1 / 60, 5))(state)
    assert np.all(np.isfinite(np.asarray(final.x)))
    assert int(jnp.max(traj.contact_overflow)) == 0
    assert int(jnp.sum(final.contact_partners >= 0)) > n         # the lattice's neighbours were found
    assert float(jnp.max(jc.penetration(model, final.x, final.contact_partners))) < 0.02 * 0.02


def test_candidates_skip_joined_pairs_and_list_each_pair_once():
    from jaxcon.core import layout
    from jaxcon.core.system import System
    from jaxcon.core.contact import partners_out
    from jaxcon.core.grid import neighbours

    # in a row, each touching the next: 2, 0, 1, 4, with 0-1 joined by a rod; 3 far away
    x = np.array([[0.1, 0.0], [0.2, 0.0], [0.0, 0.0], [5.0, 0.0], [0.3, 0.0]])
    model, _ = jc.build(x, np.ones(5), rods=[(0, 1)], radius=0.05, collide="grid", max_neighbours=2)
    sys = System.from_model(model, jnp.float64)
    t = model.topology
    xi = layout.particles_in(t, jnp.asarray(x))
    partners, overflow = neighbours(sys.contact, xi, jnp.zeros_like(xi), 0.01)
    partners = np.asarray(partners_out(model.contact, partners))
    got = {(i, int(j)) for i in range(5) for j in partners[i] if j >= 0}
    assert got == {(0, 2), (1, 4)} and int(overflow) == 0


def test_bad_max_neighbours_and_solvers_without_contacts():
    x = _discs(2, 2)
    for bad in (0, -3, 2.5, True, "8"):
        with pytest.raises(ValueError, match="max_neighbours"):
            jc.build(x, np.ones(4), radius=R, collide="grid", max_neighbours=bad)
    with pytest.raises(ValueError, match="max_neighbours"):
        jc.build(x, np.ones(4), radius=R, collide=[(0, 1)], max_neighbours=4)
    with pytest.raises(ValueError, match="collide"):
        jc.build(x, np.ones(4), radius=R, collide="grids")
    model, state = jc.build(x, np.ones(4), radius=R, collide="grid", planes=BOX)

    class NoContacts(jc.Direct):
        supports_contacts = False

    with pytest.raises(ValueError, match="NoContacts does not support contacts"):     # grid or not
        jc.rollout(model, state, NoContacts(), 0.01, 2)


@pytest.mark.parametrize("solver", [jc.PGS(4, substeps=2), jc.XPBD(2, substeps=4), jc.RATTLE(4)],
                         ids=["PGS", "XPBD", "RATTLE"])
def test_grid_gradients_equal_central_differences(solver):
    """d(final positions)/d(start velocity, radius) through a grid rollout with substeps (disc 0 hits the three
    others, which hit each other within the 12 steps; friction and restitution), against float64 central
    differences."""
    x = _discs(2, 2, gap=0.01)

    def loss(v0, radius):
        model, state = jc.build(x, np.ones(4), velocities=jnp.zeros((4, 2)).at[0].set(v0), gravity=0.0,
                                radius=radius, collide="grid", restitution=0.5, friction=0.2)
        final, traj = jc.rollout(model, state, solver, 0.01, 12)
        return jnp.sum(final.x[:, 0] * jnp.arange(4.0) + final.x[:, 1]), jnp.max(traj.contact_overflow)

    p = (jnp.array([1.5, 0.8]), jnp.asarray(R))
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))
    (_, overflow), g = value_and_grad(*p)
    assert int(overflow) == 0
    f = lambda v0, r: value_and_grad(v0, r)[0][0]        # noqa: E731  (the same program: one compilation)
    eps = 1e-6
    fd_v = [(f(p[0].at[a].add(eps), p[1]) - f(p[0].at[a].add(-eps), p[1])) / (2 * eps) for a in range(2)]
    fd_r = (f(p[0], p[1] + eps) - f(p[0], p[1] - eps)) / (2 * eps)
    np.testing.assert_allclose(np.asarray(g[0]), np.asarray(fd_v), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(float(g[1]), float(fd_r), rtol=1e-5, atol=1e-7)
    assert float(jnp.abs(g[0]).max()) > 0.1


def test_record_memory_counts_every_recorded_array(monkeypatch):
    """The estimate counted x, v and lam only: a grid model's record is mostly contact impulses and partners
    (here 18 discs, no rods: 2 * 18 * 2 position and velocity values against 198 contact slots of 3 values and
    144 partners per step): the old estimate was a tenth of the record, so a record 10x too large for memory passed
    the check."""
    from jaxcon.core import sim
    model, state = _pile("grid")
    final, traj = jc.rollout(model, state, jc.PGS(10), 1 / 120, 300)
    recorded = sum(a.nbytes for a in jax.tree.leaves(traj))
    assert sim.record_bytes(model, state, 300) == recorded
    assert recorded > 10 * 300 * (2 * 18 * 2) * 8                  # the contacts dominate the record
    monkeypatch.setattr(sim, "available_memory", lambda: (recorded, "test memory"))
    with pytest.raises(ValueError, match="save_every"):             # twice the record must fit
        jc.rollout(model, state, jc.PGS(10), 1 / 120, 300)
    jc.core.sim.check_record_memory("rollout", model, state, 300, 3)


def test_contact_grid_bench_times_all_pairs_at_every_size():
    """Its "all pairs" column built collide=True, which is the grid above 256 particles; it lists every pair."""
    from jaxcon.bench.contact_grid import scene
    n = MAX_ALL_PAIRS_PARTICLES + 4
    model, _ = scene(n, "all")
    assert not model.contact.has_grid and model.contact.n_pairs == n * (n - 1) // 2
    assert scene(n, "grid")[0].contact.has_grid


def _row(xs, vs, dim):
    """Discs (dim 2) or balls (dim 3) of radius 5 cm on the x axis, no gravity, elastic at every speed."""
    x, v = np.zeros((len(xs), dim)), np.zeros((len(xs), dim))
    x[:, 0], v[:, 0] = xs, vs
    return x, v


@pytest.mark.parametrize("dim", [2, 3])
def test_an_impact_cannot_send_a_disc_through_one_that_was_no_candidate(dim):
    """B hits A at 30 m/s; A is 5 cm from C, too far for the search made with the velocities before the solve
    (A is at rest). The grid used to move A straight through C in one step (x_A 0.60, 1.10, 1.60 with C left
    at 0.26, no overflow); `grid_step` now finds the pair on A's path, solves the step again with it, and
    passes the momentum on as all pairs do."""
    x, v = _row([0.11, -0.3, 0.26], [0.0, 30.0, 0.0], dim)
    runs = {}
    for collide in (True, "grid"):
        model, state = jc.build(x, np.ones(3), velocities=v, gravity=np.zeros(dim), radius=0.05, collide=collide,
                                restitution=1.0, restitution_threshold=0.0)
        _, runs[collide] = jc.rollout(model, state, jc.PGS(10), 1 / 60, 4)
    grid, pairs = runs["grid"], runs[True]
    xs = np.asarray(grid.x[:, :, 0])
    assert np.all((xs[:, 1] < xs[:, 0]) & (xs[:, 0] < xs[:, 2]))              # B, A, C keep their order
    gaps = np.linalg.norm(np.asarray(grid.x)[:, [0, 0, 1]] - np.asarray(grid.x)[:, [1, 2, 2]], axis=-1)
    assert gaps.min() > 0.1 * (1 - 1e-3)
    assert int(np.max(grid.contact_overflow)) == 0
    np.testing.assert_allclose(np.asarray(grid.v[:, :, 0]).sum(1), 30.0, rtol=1e-12)      # momentum
    # the same outcome as all pairs: B -9 m/s, A and C at 18 and 21 m/s (the slot-by-slot solve ends 0.03 off)
    np.testing.assert_allclose(np.asarray(grid.v), np.asarray(pairs.v), atol=0.05)
    np.testing.assert_allclose(np.asarray(grid.x), np.asarray(pairs.x), atol=2e-3)


def test_a_disc_that_passes_one_and_comes_back_within_a_step_is_caught():
    """With substeps the path bends at every substep. B (30 m/s) hits A, A is no candidate of C (5 cm beyond
    it), and with 8 substeps A passed through C, bounced off a wall and came back to where it started within
    one step: C never moved, and A's straight path from start to end missed C. The path check now widens each
    particle's straight path by its largest departure from its free path over the substeps."""
    x, v = _row([0.0, 0.2, 0.35], [30.0, 0.0, 0.0], 2)
    model, state = jc.build(x, np.ones(3), velocities=v, gravity=0.0, radius=R, collide="grid",
                            planes=[([-1.0, 0.0], -0.45)], restitution=1.0, restitution_threshold=0.0)
    _, traj = jc.rollout(model, state, jc.PGS(10, substeps=8), 1 / 60, 2)
    xs, vs = np.asarray(traj.x[:, :, 0]), np.asarray(traj.v[:, :, 0])
    assert abs(vs[0, 2]) > 1.0                        # C was hit in the first step (before: it stayed at rest)
    assert np.all(np.diff(xs, axis=1) >= 2 * R - 1e-3)          # B, A, C keep their order, none inside another
    assert int(jnp.max(traj.contact_overflow)) == 0


def test_a_pair_the_second_solve_still_misses_is_counted():
    """With a fourth disc D 5 cm beyond C, the second solve sends C into D, which neither search listed:
    GRID_ATTEMPTS = 2 solves cannot follow the chain (B at 30 m/s crosses 0.5 m, ten radii, in the step). The
    step does not pass it silently: the overflow counts it, and `jc.diagnose` flags and warns about it, naming
    both remedies. At a twentieth of the step the searches follow the chain and nothing overflows."""
    x, v = _row([0.11, -0.3, 0.26, 0.41], [0.0, 30.0, 0.0, 0.0], 2)
    model, state = jc.build(x, np.ones(4), velocities=v, gravity=np.zeros(2), radius=0.05, collide="grid",
                            restitution=1.0, restitution_threshold=0.0)
    _, traj = jc.rollout(model, state, jc.PGS(10), 1 / 60, 2)
    assert int(traj.contact_overflow[0]) > 0
    with pytest.warns(UserWarning, match=r"(?s)may have been missed.*max_neighbours.*smaller `dt`"):
        d = jc.diagnose(model, traj, state)
    assert bool(d.overflowed) and int(d.overflow[0]) > 0
    _, fine = jc.rollout(model, state, jc.PGS(10), 1 / 1200, 40)
    assert int(jnp.max(fine.contact_overflow)) == 0
    xs = np.asarray(fine.x[:, :, 0])
    assert np.all(np.diff(xs[:, [1, 0, 2, 3]], axis=1) > 0)                  # none passed through another


def test_contact_passes_sets_the_position_pass_count():
    """`PGS(contact_passes=k)` runs k position passes per step: None is the grid's default
    (`contact.GRID_OVERLAP_PASSES`, bitwise the same step), and one pass leaves more of the start overlaps
    (the staggered rows start 14% of a diameter into each other) than the default's passes do. Bad counts are
    refused with the argument named."""
    from jaxcon.solvers import contact
    pts = [[R + 0.05 + c * 2.02 * R + (r % 2) * R, R + 0.002 + 0.07 * r] for r in range(4) for c in range(5 - r % 2)]
    model, state = jc.build(np.asarray(pts), np.ones(len(pts)), radius=R, collide="grid", planes=BOX, friction=0.3)

    def overlap(x):                                   # the deepest, as a fraction of a diameter
        d = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.eye(len(x)) * 10
        return float((2 * R - d).max()) / (2 * R)

    def deepest(solver):
        x = np.asarray(jc.rollout(model, state, solver, 1 / 120, 1)[0].x)
        return overlap(x), x

    assert overlap(np.asarray(state.x)) > 0.13
    (ov_default, x_default), (_, x_all) = (deepest(jc.PGS(10)),
                                                deepest(jc.PGS(10, contact_passes=contact.GRID_OVERLAP_PASSES)))
    ov_one, _ = deepest(jc.PGS(10, contact_passes=1))
    assert np.array_equal(x_default, x_all)
    assert ov_default < 0.03 and ov_one > 3 * ov_default, (ov_default, ov_one)      # seen: 2.0% and 17%
    with pytest.raises(ValueError, match="PGS: `contact_passes` must be >= 1, got 0"):
        jc.PGS(contact_passes=0)
    with pytest.raises(TypeError, match="`contact_passes` must be a Python int"):
        jc.PGS(contact_passes=2.0)


_REUSED_SEARCH = jc.core.grid.reused_search


def _count_reuse(monkeypatch, mode="keep"):
    """Wrap the grid's search of a rollout step (`grid.reused_search`): returns a list that collects, per step
    run, whether the step took its candidates from the kept list and whether the list it leaves is complete.
    `mode`: "keep" (as the library does),
    "search" (no step may take the list) or "plain" (no kept list at all: `grid.grid_search` at every step, as
    before kept lists existed)."""
    from jaxcon.core import contact, grid
    taken = []

    def wrapped(cs, x, v, h, prev):
        # the same operations either way (a comparison XLA cannot fold), so that both runs compile to the same
        # program: XLA's CPU backend may contract a program's float arithmetic into fused multiply-adds
        # differently once a branch folds away, and a pile turns such rounding into a different landing
        a = prev.anchor[0, 0]
        prev = prev._replace(ok=prev.ok & ((a != a) if mode == "search" else (a == a)))
        found, reuse, reach = _REUSED_SEARCH(cs, x, v, h, prev)
        jax.debug.callback(lambda t, ok: taken.append((bool(t), bool(ok))),
                           prev.ok & jnp.all(reuse.anchor == prev.anchor), reuse.ok)
        return found, reuse, reach

    monkeypatch.setattr(grid, "reused_search", wrapped)
    monkeypatch.setattr(contact, "no_reuse", (lambda *a: None) if mode == "plain" else _NO_REUSE)
    jax.clear_caches()
    return taken


_NO_REUSE = jc.core.contact.no_reuse


def _mixed_radii():
    """A lattice of small discs and one disc 3.2 times larger: cells sized by the large one hold many small
    ones, and the wider list's cells overflow their buckets' scan (a review's case)."""
    rs, sp = 0.05, 0.101
    pts = [[0.3 + i * sp, rs + 0.0005 + j * sp] for i in range(12) for j in range(8)] + [[3.0, 0.17]]
    r = np.full(97, rs)
    r[-1] = 0.16
    return jc.build(np.array(pts), np.ones(97), radius=r, collide="grid",
                    planes=[((0.0, 1.0), 0.0), ((1.0, 0.0), 0.25), ((-1.0, 0.0), -3.5)])


@pytest.mark.parametrize("case", ["discs", "balls, 2 substeps, XPBD", "mixed radii", "3 slots"])
def test_kept_candidate_lists_change_no_result(case, monkeypatch):
    """A rollout takes a step's candidate pairs from the wider list of an earlier search while no pair left out
    of it can have become a candidate (`grid.reused_search`). Every output is bitwise the same as with the wide
    search at every step, and the same to rounding as with the usual search at every step (`grid.grid_search`,
    as before kept lists);
    the lists are taken in most steps of a pile that lands and rests. Where the wider list overflows (mixed
    radii: its wider cells leave bucket entries unscanned; 3 slots: more candidates than slots) the step uses
    the usual search, and reports the same overflow.

    "keep" and "search" are one program (`_count_reuse`), bitwise equal over every step. "plain" is another, and
    programs may contract multiply-adds differently under the suite's XLA flags: the 64-disc pile's are 1e-15
    apart after 29 steps and 1e-2 after 150. So "plain" is compared to 1e-12 over the first 25 steps, in which a
    complete kept list is taken too. The slots are swept whole (`contact_rows.SPARSE_SLOT` 0);
    `test_sparse_slots_change_no_result` covers the gathered slots."""
    from jaxcon.core import contact_rows
    monkeypatch.setattr(contact_rows, "SPARSE_SLOT", 0)
    jax.clear_caches()
    solver, dt, steps = jc.PGS(10), 1 / 60, 150
    if case == "discs":
        model, state = jc.scenes.disc_box(64, collide="grid")
    elif case == "3 slots":
        model, state = jc.scenes.disc_box(64, collide="grid", max_neighbours=3)
    elif case == "mixed radii":
        model, state = _mixed_radii()
        steps = 120
    else:
        model, state = _pile_3d("grid", dim=3)
        solver, dt, steps = jc.XPBD(2, substeps=2), 1 / 120, 200
    runs = {}
    for mode in ("keep", "search", "plain"):
        taken = _count_reuse(monkeypatch, mode)
        final, traj = jc.rollout(model, state, solver, dt, steps)
        jax.block_until_ready(traj.x)
        runs[mode] = (taken, final, traj)
    record, final, traj = runs["keep"]
    taken, complete = [t for t, _ in record], [c for _, c in record]
    assert len(taken) == steps and not taken[0]
    if case in ("discs", "balls, 2 substeps, XPBD"):
        assert sum(taken) > steps // 2 and all(complete)
        assert int(jnp.max(traj.contact_overflow)) == 0
    else:
        assert not all(complete)
        assert (int(jnp.max(traj.contact_overflow)) > 0) == (case == "3 slots")
    assert not any(t for t, _ in runs["search"][0]) and not runs["plain"][0]
    for a, b in zip(jax.tree.leaves((final, traj)), jax.tree.leaves(runs["search"][1:])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # "plain" carries no list, so it is another program, which XLA may contract differently: bitwise until the
    # first rounding difference (step 29 of the 64-disc pile in float64), which the pile then amplifies
    for a, b in zip(jax.tree.leaves(traj), jax.tree.leaves(runs["plain"][2])):
        np.testing.assert_allclose(np.asarray(a)[:25], np.asarray(b)[:25], rtol=1e-12, atol=1e-12)
    assert sum(taken[:25]) > 0 or not all(complete)


def _sliding_discs(n, rods=None):
    """n discs (n a multiple of 4) in 4 rows on the box's floor, sliding apart at up to 0.5 m/s, masses 1 to 2,
    friction 0.4, 8 slots: the scene of the layout tests below."""
    x = _discs(n // 4, 4, jitter=0.004, seed=1, gap=0.0)
    v = np.stack([np.linspace(-0.5, 0.5, n), np.zeros(n)], -1)
    return jc.build(x, np.linspace(1.0, 2.0, n), velocities=v, radius=R, collide="grid", planes=BOX,
                    friction=0.4, max_neighbours=8, rods=rods)


def _assert_same_rollouts(runs, n):
    """Two rollouts `runs` = [(final, traj), (final, traj)] of `_sliding_discs(n)`: float64, the pairs pushing,
    and every output equal to 1e-12."""
    (final, traj), other = runs
    assert traj.x.dtype == jnp.float64
    assert float(jnp.max(traj.contact_n[:, 3 * n:])) > 1e-3           # the pairs push from the first steps
    for a, b in zip(jax.tree.leaves((final, traj)), jax.tree.leaves(other)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)


@pytest.mark.parametrize("solver, n", [(jc.PGS(10), 8), (jc.PGS(6, substeps=2), 8), (jc.Direct(), 8), (jc.PGS(10), 36)],
                         ids=["PGS-8", "PGS substeps-8", "Direct-8", "PGS-36"])
def test_slot_major_impulses_change_no_result(solver, n, monkeypatch):
    """PGS and Direct move a grid's pair impulses slot-major ([K, n]) once per velocity solve
    (`solve_phases(slot_major=True)`, `contact_rows.in_solve`) instead of in every sweep. The rollout equals
    the one that moves them in every sweep, impulses and partners included, in float64. With 8 discs and 8
    slots both layouts have the same shape, so an impulse read in the wrong layout would not raise: it would
    change the result. Dumbbells (rods) with Direct, so that its exact solve runs between the sweeps.

    Six steps: both programs do the same arithmetic, but XLA's CPU backend may contract it into fused
    multiply-adds differently in the two programs (under the suite's XLA flags the 36-disc pile's positions
    differ by 1e-15 after six steps, and by 4e-7 after nine, where a contact switches; under the default flags
    they are bitwise equal for 60 steps). A wrong layout changes the first step's impulses by O(1)."""
    from jaxcon.solvers import direct, pgs
    model, state = _sliding_discs(n, np.arange(n).reshape(-1, 2) if isinstance(solver, jc.Direct) else None)
    runs = []
    for major in (True, False):
        for module in (pgs, direct):
            if not major:
                original = module.solve_phases
                monkeypatch.setattr(module, "solve_phases",
                                    lambda *a, slot_major=False, original=original, **k: original(*a, **k))
        jax.clear_caches()
        runs.append(jc.rollout(model, state, solver, 1 / 60, 6))
        monkeypatch.undo()
    jax.clear_caches()
    _assert_same_rollouts(runs, n)
    assert int(jnp.max(runs[0][1].contact_partners)) >= 0


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.PGS(6, substeps=2), jc.Direct(), jc.SoftStep()],
                         ids=["PGS", "PGS substeps", "Direct", "SoftStep"])
def test_sparse_slots_change_no_result(solver, monkeypatch):
    """A grid slot holding at most n / SPARSE_SLOT rows is swept (and projected by the position pass) on its rows
    gathered (`contact_rows.SparseSlots`, `GatheredSlotColour`) instead of on all n particles. The same updates
    on the same rows in the same order: the rollout equals the one that sweeps every slot whole, in float64
    (six steps, for the reason of `test_slot_major_impulses_change_no_result`). SPARSE_SLOT = 1.25 here, so that
    in 36 discs a slot of at most 29 rows is gathered and a fuller one is not: both kinds are checked for."""
    from jaxcon.core import contact_rows
    n = 36
    model, state = _sliding_discs(n)
    runs = []
    for every in (1.25, 0):
        monkeypatch.setattr(contact_rows, "SPARSE_SLOT", every)
        jax.clear_caches()
        runs.append(jc.rollout(model, state, solver, 1 / 60, 6))
    monkeypatch.undo()
    jax.clear_caches()
    _assert_same_rollouts(runs, n)
    rows = np.sum(np.asarray(runs[0][1].contact_partners) >= 0, axis=1)       # [steps, K] rows per slot
    assert np.any((rows > 0) & (rows <= 29)) and np.any(rows > 29)


@pytest.mark.parametrize("mode", ["forward", "reverse"])
def test_sparse_slots_under_vmap(monkeypatch, mode):
    """Under `jax.vmap` a slot's branch is one for every copy (`contact_rows._slot_branch`: skipped where the
    slot is empty in every copy, else swept whole), not a select of every branch. A batch of two copies of the
    36-disc scene, with their velocities apart, equals each copy's own rollout with every slot swept whole
    (`SPARSE_SLOT` 0), in float64 to 1e-12 over two steps, and so do its derivatives with respect to the start
    velocities' scale: batched in forward mode, or in reverse mode (the extended set: its compile is three
    quarters of this test's time), against each copy's own in forward mode. Each side is one compiled program
    (the positions and partners ride along the derivative as its auxiliary output). Two steps, not six: programs that
    round differently (a batch and a single copy; gathered and whole slots) are 1e-16 apart until a contact
    switches, and up to 3e-5 after it, under the suite's XLA flags with or without sparse slots; in this scene
    one switches in step 3 (step 4 or 5 before speculative rows stopped pushing, `contact_rows._targets`)."""
    from jaxcon.core import contact_rows
    n = 36
    model, state = _sliding_discs(n)
    scale = jnp.array([1.0, 0.5])

    def height(s):                                      # and the final positions and partners alongside
        final, traj = jc.rollout(model, state.replace(v=state.v * s), jc.PGS(10), 1 / 60, 2)
        return jnp.sum(final.x[:, 1]), (final.x, traj.contact_partners)

    def slope(s):                   # forward mode: (the final positions and partners, the derivative): one program
        _, tangent, aux = jax.jvp(height, (s,), (jnp.ones_like(s),), has_aux=True)
        return aux, tangent

    def reverse(s):
        (_, aux), g = jax.value_and_grad(height, has_aux=True)(s)
        return aux, g

    monkeypatch.setattr(contact_rows, "SPARSE_SLOT", 1.25)
    jax.clear_caches()
    (batched, partners), grads = jax.jit(jax.vmap(slope if mode == "forward" else reverse))(scale)
    rows = np.sum(np.asarray(partners[0]) >= 0, axis=1)
    assert np.any((rows > 0) & (rows <= 29))               # a slot each copy alone would gather
    monkeypatch.setattr(contact_rows, "SPARSE_SLOT", 0)
    jax.clear_caches()
    one = jax.jit(slope)                                    # each copy's positions and slope: one program
    for k in range(2):
        (x, _), d = one(scale[k])
        np.testing.assert_allclose(np.asarray(batched[k]), np.asarray(x), rtol=0, atol=1e-12)
        np.testing.assert_allclose(float(grads[k]), float(d), rtol=1e-10)
    assert batched.dtype == jnp.float64 and not np.allclose(batched[0], batched[1])
    monkeypatch.undo()
    jax.clear_caches()


def test_computed_once_is_the_function_it_wraps():
    """`layout.computed_once` runs a row update inside a conditional that is always taken, so that XLA's CPU backend
    computes its results once instead of in every fusion that reads them (docs/contacts.md). It must be the wrapped
    function: the same values and derivatives (reverse and forward mode), under `vmap` with a batched witness (a
    select) too, also where the witness's first entry is -1 (an empty grid slot); and on the CPU the conditional
    must be in the compiled program, or the change measured nothing."""
    from jaxcon.core import layout as L

    def fn(a, b):
        r = jnp.sqrt(a * a + b * b)
        return a * jnp.sin(b) / (1 + r), jnp.maximum(r - 1, 0), (a > b).astype(jnp.int32)

    a = jnp.linspace(-1.0, 2.0, 7, dtype=jnp.float64)
    b = jnp.linspace(0.5, -1.5, 7, dtype=jnp.float64)
    for first in (-1, 0, 5):
        witness = jnp.array([first, 3, -1], jnp.int32)
        got, want = L.computed_once(fn, (a, b), witness), fn(a, b)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))

        def loss(a, b, once):
            out = L.computed_once(fn, (a, b), witness) if once else fn(a, b)
            return jnp.sum(out[0] ** 2) + jnp.sum(out[1])

        for argnums in (0, 1):
            np.testing.assert_allclose(jax.grad(loss, argnums)(a, b, True), jax.grad(loss, argnums)(a, b, False),
                                       rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(jax.jacfwd(loss)(a, b, True), jax.jacfwd(loss)(a, b, False), rtol=1e-14, atol=1e-15)
    batched = jax.vmap(lambda a, w: L.computed_once(fn, (a, b), w))(jnp.stack([a, 2 * a]),
                                                                   jnp.array([[-1, 0], [4, 2]], jnp.int32))
    np.testing.assert_allclose(batched[0][1], fn(2 * a, b)[0], rtol=1e-15)
    np.testing.assert_allclose(batched[1][0], fn(a, b)[1], rtol=1e-15)
    program = jax.jit(lambda a, w: L.computed_once(fn, (a, b), w)[0]).lower(a, jnp.zeros(3, jnp.int32))
    # the conditional only where it pays: XLA's CPU backend (on a GPU the function is called as written)
    assert ("conditional" in program.compile().as_text()) == (jax.default_backend() == "cpu")
    assert "conditional" not in jax.jit(lambda a: L.computed_once(fn, (a, b))[0]).lower(a).compile().as_text()


def test_sort_rows_is_jnp_sort():
    """`layout.sort_rows` (the grid's per-step candidate order, elementwise for short rows) equals `jnp.sort` along
    the rows, with repeated entries (an empty slot's key) and negative ones, and for long rows (the fallback)."""
    from jaxcon.core import layout as L
    rng = np.random.default_rng(3)
    for M in (1, 2, 8, 27, 40):
        key = rng.integers(-5, 12, (64, M)).astype(np.int32)
        key[rng.random(key.shape) < 0.3] = 99
        np.testing.assert_array_equal(np.asarray(jax.jit(L.sort_rows)(key)), np.sort(key, axis=1))
