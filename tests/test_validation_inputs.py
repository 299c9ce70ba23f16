"""Bad input, round three: each item gets an error naming the argument, before tracing, or the right result."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core import contact_rows
from jaxcon.identification import uncertainty as unc

DT = 1 / 240


def _dist(x, p):
    return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))


def test_angle_of_a_straight_2d_arm_rests_at_pi_and_is_held_from_either_side():
    """atan2(-0.0, -1) = -pi was the rest of a straight arm, on the branch cut: bent up by 0.1 rad C was
    2 pi - 0.1 and four solvers blew up. Now rest is pi and C is wrapped into (-pi, pi]: +-0.1 either side."""
    x = np.array([[0.0, 1.0], [1.0, 1.0], [2.0, 1.0]])
    c = jc.constraints.angle([[0, 1, 2]], positions=x)
    assert float(c.params["rest"][0]) == pytest.approx(np.pi, abs=1e-15)
    for bend in (0.1, -0.1):
        xb = x.copy()
        xb[2] = [1 + np.cos(bend), 1 + np.sin(bend)]
        assert float(c.fn(jnp.asarray(xb), {"rest": c.params["rest"][0]})) == pytest.approx(bend, abs=1e-12)
    m, s = jc.build(x, 1.0, rods=[(0, 1), (1, 2)], fixed=[0, 1], constraints=c)
    f, tr = jc.rollout(m, s, jc.RATTLE(), DT, 24)
    assert abs(float(f.x[2, 1]) - 1.0) < 1e-6 and np.all(np.isfinite(np.asarray(tr.x)))


def test_area_in_3d_is_the_vector_area_with_its_gradient():
    """A right triangle in the xz plane has area 0.5 (it was 0, its xy projection); C's gradient matches
    central differences; in 2-D the area stays signed."""
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    c = jc.constraints.area([[0, 1, 2]], positions=x)
    assert float(c.params["rest"][0]) == pytest.approx(0.5, abs=1e-15)
    y = jnp.asarray(x + 0.1 * np.random.default_rng(0).standard_normal(x.shape))
    p = {"rest": 0.0}
    g = np.asarray(jax.grad(c.fn)(y, p))
    e = 1e-6
    fd = np.zeros_like(g)
    for a in range(3):
        for d in range(3):
            dy = np.zeros(x.shape)
            dy[a, d] = e
            fd[a, d] = (float(c.fn(y + dy, p)) - float(c.fn(y - dy, p))) / (2 * e)
    np.testing.assert_allclose(g, fd, atol=1e-8)
    clockwise = jc.constraints.area([[0, 2, 1]], positions=np.array([[0.0, 0], [1, 0], [0, 1]]))
    assert float(clockwise.params["rest"][0]) == pytest.approx(-0.5)


@pytest.mark.parametrize("make", [
    lambda P: jc.constraints.angle([[0, 1, 5]], positions=P),
    lambda P: jc.constraints.distance([[0, 7]], positions=P),
    lambda P: jc.constraints.area([[0, 1, -1]], positions=P),
])
def test_rest_from_positions_refuses_indices_out_of_range(make):
    with pytest.raises(ValueError, match=r"particles\[0\].*positions"):
        make(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]))


def test_distance_refuses_a_negative_rest():
    with pytest.raises(ValueError, match="rest.*>= 0"):
        jc.constraints.distance([[0, 1]], rest=-1.0)
    with pytest.raises(ValueError, match="rest"):
        jc.constraints.distance([[0, 1], [1, 2]], rest=[1.0, -0.5])


def test_set_names_are_unique_and_a_model_with_two_of_a_name_is_refused():
    x = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]])
    cs = [jc.Constraint(_dist, [[0, 1]], {"L": [0.5]}, name="d"), jc.Constraint(_dist, [[1, 2]], {"L": [0.5]}, name="d"),
          jc.Constraint(_dist, [[0, 2]], {"L": [1.0]}, name="d_1")]
    m, s = jc.build(x, 1.0, fixed=[0], constraints=cs)
    names = [c.name for c in m.constraints]
    assert names == ["d", "d_2", "d_1"]
    with pytest.raises(ValueError, match="set 'd_2' is named 'd'"):
        m.replace(constraints=(m.constraints[0], m.constraints[1].replace(name="d"), m.constraints[2]))
    from jaxcon.identification.params import _constraint_of
    twin = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(m), jax.tree_util.tree_leaves(m))
    object.__setattr__(twin, "constraints", (m.constraints[0], m.constraints[1].replace(name="d"), m.constraints[2]))
    with pytest.raises(ValueError, match="ambiguous"):
        _constraint_of("d.L", twin)


def test_replace_refuses_a_set_with_another_fn():
    def height(x, p):
        return x[1, 1] + p["L"]
    m, _ = jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0, fixed=[0],
                    constraints=jc.Constraint(_dist, [[0, 1]], {"L": [1.0]}))
    with pytest.raises(ValueError, match="another `fn`.*height"):
        m.replace(constraints=(jc.Constraint(height, [[0, 1]], {"L": [0.0]}, name="_dist"),))
    m.replace(constraints=(m.constraints[0].replace(params={"L": np.array([0.9])}),))     # same kind: accepted


@pytest.mark.parametrize("fn", [lambda x, p: jnp.nan * x[1, 0], lambda x, p: jnp.log(x[1, 1] - 5.0),
                                lambda x, p: jnp.inf + x[1, 0]])
def test_a_set_whose_c_is_not_finite_at_its_positions_is_refused(fn):
    with pytest.raises(ValueError, match="constraint set 'oops'.*not finite"):
        jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0, fixed=[0], constraints=jc.Constraint(fn, [[0, 1]], name="oops"))


def test_violation_of_a_row_that_is_not_finite_is_nan_and_diagnose_flags_it():
    """sqrt(y - 1) >= ... is finite where the bob starts (y = 2) and NaN below y = 1: violation says NaN there
    (it said 0: satisfied), and diagnose flags the step."""
    c = jc.Constraint(lambda x, p: jnp.sqrt(x[1, 1] - 1.0) - 1.0, [[0, 1]], name="sq", compliance=1e-3)
    m, s = jc.build(np.array([[0.0, 0.0], [1.0, 2.0]]), 1.0, fixed=[0], constraints=c)
    assert np.isnan(np.asarray(jc.violation(m, np.array([[0.0, 0.0], [1.0, 0.0]])))).all()
    assert float(jc.violation(m, np.array([[0.0, 0.0], [1.0, 2.0]]))[0]) == 0.0
    x = jnp.stack([s.x, s.x.at[1, 1].set(0.0)])
    tr = jc.Trajectory(x, jnp.zeros_like(x), jnp.zeros((2, 1)))
    d = jc.diagnose(m, tr, s)
    assert not bool(d.bad[0]) and bool(d.bad[1]) and int(d.first_bad) == 1


def _negate(tree, name):
    """`tree` with its leaf `name` negated by jax.tree.map (as an optimiser's update can), bypassing checks."""
    return jax.tree_util.tree_map_with_path(lambda k, a: -a if jax.tree_util.keystr(k) == f".{name}" else a, tree)


def test_leaves_rebuilt_by_tree_map_are_checked_again_at_entry():
    c = jc.Constraint(_dist, [[0, 1]], {"L": [1.0]}, compliance=1e-3)
    m, s = jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0, fixed=[0], constraints=c)
    neg = jax.tree.map(lambda a: -a if a.shape == (1,) and jnp.issubdtype(a.dtype, jnp.floating) else a, m)
    for call in (lambda: jc.rollout(neg, s, jc.PGS(10), DT, 2), lambda: jc.step(neg, s, jc.PGS(10), DT)):
        with pytest.raises(ValueError, match=r"constraints\[0\].compliance.*>= 0"):
            call()
    with pytest.raises(ValueError, match=r"params\['L'\]"):
        jc.step(jax.tree_util.tree_map_with_path(lambda k, a: a * np.nan if "'L'" in jax.tree_util.keystr(k) else a,
                                                 m), s, jc.PGS(10), DT)
    for solver, name in ((jc.PGS(), "beta"), (jc.XPBD(compliance=1e-3), "compliance"),
                         (jc.Penalty(1e4), "stiffness"), (jc.SoftStep(), "hertz")):
        with pytest.raises(ValueError, match=f"solver.*{name}.*>= 0"):
            jc.rollout(m, s, _negate(solver, name), DT, 2)
    with pytest.raises(ValueError, match="solver.*beta"):
        jc.batched_rollout(m, jax.tree.map(lambda a: jnp.stack([a, a]), s), _negate(jc.PGS(), "beta"), DT, 2)
    jax.jit(lambda b: jc.rollout(m, s, jc.PGS(beta=b), DT, 2)[0].x)(0.2)      # traced leaves pass


def test_fit_with_too_few_frames_is_not_converged_unless_the_data_are_exact():
    """A pendulum bob observed moving in a straight line for 6 frames was 'converged' with an RMS of 0.5 m;
    the same frames of the true motion (exact data) still converge."""
    m, s = jc.scenes.pendulum(angle=0.6)
    ss = np.arange(1, 7) * 4
    _, tr = jc.rollout(m, s, jc.RATTLE(), DT, int(ss[-1]))
    obs = np.asarray(tr.x)[ss - 1]
    line = obs.copy()
    line[:, 1] = np.asarray(s.x[1]) + np.outer(ss * DT, [5.0, 3.0])
    bad = jc.fit(m, s, jc.RATTLE(), DT, line, params=("rest_length",), sample_steps=ss, progress=False, steps=20)
    assert not bad.converged and "too few frames" in bad.reason and bad.rms > 0.01
    good = jc.fit(m, s, jc.RATTLE(), DT, obs, params=("rest_length",), sample_steps=ss, progress=False, steps=40,
                  patience=5)
    assert good.converged, good.reason


def test_residual_correlation_counts_pairs_over_recordings():
    rng = np.random.default_rng(1)
    obs = rng.standard_normal((2, 4, 1, 2))
    err = 0.1 * np.ones((2, 4, 1, 2))
    assert unc.lag_pairs(err) == 6 and unc.residual_correlation(err, obs) is None and unc.too_few_frames(err, obs)
    err5 = 0.1 * np.ones((2, 5, 1, 2))
    assert unc.residual_correlation(err5, rng.standard_normal((2, 5, 1, 2))) == pytest.approx(0.8)        # (S - 1) / S for constant errors
    assert not unc.too_few_frames(1e-12 * err, obs)                        # exact data: nothing to check


def _box(P, n=6):
    ang = np.linspace(0, 2 * np.pi, P, endpoint=False)
    planes = [((-np.cos(a), -np.sin(a)), -1.0) for a in ang]
    x = np.random.default_rng(0).uniform(-0.5, 0.5, size=(n, 2))
    return jc.build(x, 1.0, radius=0.05, planes=planes, collide=True, gravity=np.zeros(2))


def _equations(jaxpr) -> int:
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for p in e.params.values():
            for sub in (p if isinstance(p, (list, tuple)) else [p]):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    n += _equations(inner)
    return n


@pytest.mark.parametrize("solver", [jc.PGS(4), jc.XPBD(substeps=2), jc.Penalty(1e4, substeps=2), jc.Jacobi(4),
                                    jc.SoftStep(substeps=2), jc.Direct(), jc.RATTLE(4)], ids=lambda s: type(s).__name__)
def test_program_size_does_not_grow_with_the_number_of_planes(solver):
    """The obstacles are visited by one `each_obstacle`: above UNROLL_OBSTACLES a scan, so a box of 100 planes
    traces to as many equations as one of UNROLL_OBSTACLES + 1 (it grew by ~190 per plane: 100 planes took 136 s
    to compile)."""
    sizes = {}
    for P in (contact_rows.UNROLL_OBSTACLES + 1, 100):
        m, s = _box(P)
        sizes[P] = _equations(jax.make_jaxpr(lambda m, s: jc.rollout(m, s, solver, DT, 2)[0].x)(m, s).jaxpr)
    assert sizes[100] == sizes[contact_rows.UNROLL_OBSTACLES + 1], sizes


def test_many_planes_give_the_same_motion_as_written_out(monkeypatch):
    """The scan over obstacles is the same Gauss-Seidel order as the written-out loop: a 10-plane box stepped
    with the loop written out (UNROLL_OBSTACLES raised) and scanned agree to rounding, the discs bouncing off
    the walls for 20 steps."""
    m, s = _box(10, n=6)
    a = np.arange(6) * 1.1
    out = np.stack([np.cos(a), np.sin(a)], -1)
    s = s.replace(x=jnp.asarray(0.9 * out), v=jnp.asarray(3.0 * out + 0.5 * out[:, ::-1]))   # at the walls in 6 steps
    solvers = (jc.PGS(3), jc.XPBD(substeps=2))      # the sweeps, rows and warm start; the position pass

    def size():
        return _equations(jax.make_jaxpr(lambda m, s: jc.rollout(m, s, solvers[0], DT, 2)[0].x)(m, s).jaxpr)
    scanned = [np.asarray(jc.rollout(m, s, solver, DT, 20)[0].x) for solver in solvers]
    normals = np.asarray(m.plane_normal)
    for a in scanned:                               # held inside the walls (free flight goes 0.25 m past them)
        assert (a @ normals.T - np.asarray(m.plane_offset)).min() > 0.05 - 1e-3
    small = size()
    jax.clear_caches()
    monkeypatch.setattr(contact_rows, "UNROLL_OBSTACLES", 100)
    assert size() > small + 500                    # another program: the loop written out
    for solver, a in zip(solvers, scanned):
        written = np.asarray(jc.rollout(m, s, solver, DT, 20)[0].x)
        np.testing.assert_allclose(a, written, atol=1e-9)
    jax.clear_caches()


def test_leftovers():
    x = np.random.default_rng(0).uniform(-1, 1, size=(20, 2))
    m, _ = jc.build(x, 1.0, radius=0.01, collide="grid", max_neighbours=10_000)
    assert m.contact.grid_k == 20                                  # capped at the number of particles
    assert "contacts: ," not in repr(m) and "neighbour grid of 20" in repr(m)
    m2, s2 = jc.scenes.pendulum(angle=0.6)
    with pytest.raises(ValueError, match="horizon.*whole"):
        jc.fit(m2, s2, jc.RATTLE(), DT, np.zeros((10, 2, 2)), horizon=[2.5, 10], progress=False)


def test_energy_gain_is_finite_at_a_zero_energy_scale():
    """No gravity, no motion, a compliant spring stretched at the start: the scale counts its stored energy,
    and the gain stays near 0 (it was inf); with nothing stored or moving, 0."""
    spring = jc.constraints.distance([[0, 1]], rest=[1.0], compliance=1e-3)
    m, s = jc.build(np.array([[0.0, 0.0], [1.1, 0.0]]), 1.0, fixed=[0], constraints=spring, gravity=np.zeros(2))
    _, tr = jc.rollout(m, s, jc.XPBD(substeps=20), DT, 48)
    d = jc.diagnose(m, tr, s)
    assert np.all(np.isfinite(np.asarray(d.energy_gain))) and float(np.abs(d.energy_gain).max()) < 0.05
    assert not bool(d.diverged)
    m0, s0 = jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0, fixed=[0], constraints=spring, gravity=np.zeros(2))
    _, tr0 = jc.rollout(m0, s0, jc.XPBD(), DT, 4)
    assert float(np.abs(jc.diagnose(m0, tr0, s0).energy_gain).max()) == 0.0


def test_bench_contact_grid_honours_out_and_small(tmp_path, monkeypatch):
    """`bench --contact-grid` ignored `--out` and `--small`. The timing is replaced by a stub here (what is
    checked is the wiring: the sizes and steps run, and the JSON written)."""
    import json

    from jaxcon.bench import cli, contact_grid
    calls = []
    monkeypatch.setattr(contact_grid, "per_step", lambda n, collide, steps: calls.append((n, collide, steps)) or
                        (1.5, 2e-3))
    out = tmp_path / "grid.json"
    assert cli.main(["bench", "--contact-grid", "--small", "--out", str(out)]) == 0
    assert sorted({c[0] for c in calls}) == list(contact_grid.SMALL_SIZES)
    assert {c[2] for c in calls} == {contact_grid.SMALL_STEPS}
    rows = json.loads(out.read_text())["contact_grid"]
    assert [r["n"] for r in rows] == list(contact_grid.SMALL_SIZES) and rows[0]["grid_ms_per_step"] == 2.0
