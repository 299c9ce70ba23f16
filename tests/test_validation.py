"""Bad input gets a clear error naming the argument, raised before tracing; tracers pass validation."""
import argparse
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc

X = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])


@pytest.mark.parametrize("kwargs, match", [
    (dict(positions=np.zeros((3,))), "positions"),
    (dict(positions=np.zeros((3, 4))), "positions"),
    (dict(positions=np.where(np.arange(6).reshape(3, 2) == 2, np.nan, X)), "positions"),
    (dict(masses=[1.0, 1.0]), "masses"),
    (dict(masses=[1.0, -1.0, 1.0]), "masses"),
    (dict(masses=[1.0, np.inf, 1.0]), "masses"),
    (dict(masses=[1.0, 0.0, 1.0]), "masses"),
    (dict(rods=[(0, 3)]), r"rods\[0\].*out of range"),
    (dict(rods=[(0, 1), (-1, 2)]), r"rods\[1\].*out of range"),
    (dict(rods=[(0, 1), (2, 2)]), r"rods\[1\].*itself"),
    (dict(rods=[(0, 1, 2)]), "rods"),
    (dict(rods=[(0.5, 1)]), "rods"),
    (dict(ropes=[(1, 1)]), r"ropes\[0\].*itself"),
    (dict(rods=None, ropes=None), "at least one constraint"),
    (dict(fixed=[5]), "fixed"),
    (dict(rest_lengths=[1.0]), "rest_lengths"),
    (dict(rest_lengths=[1.0, -0.5]), "rest_lengths"),
    (dict(rest_lengths=[1.0, np.nan]), "rest_lengths"),
    (dict(velocities=np.zeros((2, 2))), "velocities"),
    (dict(gravity=[0.0, -9.81, 0.0]), "gravity"),
    (dict(colouring=[0, 0]), "share particle 1"),
    (dict(grid_shape=(2, 2)), "grid_shape"),
    (dict(gravity=-9.81), "gravity.*>= 0"),                   # a scalar is a magnitude: -9.81 would point up
    (dict(gravity=1j), "gravity.*real"),
    (dict(fixed=[0.7]), "fixed"),                             # was truncated to particle 0
    (dict(fixed=[True, False]), r"fixed.*shape \(3,\)"),       # a mask of the wrong length
    (dict(masses=[1.0, 1e39, 1.0], positions=X.astype(np.float32)), "masses.*particle 1.*inverse"),
    (dict(masses=[1.0, 1e-39, 1.0], positions=X.astype(np.float32)), "masses.*particle 1.*inverse"),
    (dict(masses=[1.0, "2", 1.0]), "masses.*real"),
    (dict(positions=X + 1j), "positions.*complex"),           # was cast to real with a warning
    (dict(positions=X > 0), "positions.*bool"),
    (dict(rods=[(0, 1), (1, 2, 0)]), "rods.*pairs"),           # ragged
    (dict(dtype=np.int32), "dtype"),
    (dict(velocities=np.zeros((3, 2)) + 1j), "velocities.*complex"),
])
def test_build_rejects_bad_input(kwargs, match):
    args = dict(positions=X, masses=[1.0, 1.0, 1.0], rods=[(0, 1), (1, 2)], fixed=[0])
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        jc.build(**args)


def test_fixed_accepts_a_boolean_mask():
    """A mask fixes the particles where it is True (`fixed=[True, False, False]` used to fix particles 0 and 1,
    read as indices 1 and 0)."""
    model, _ = jc.build(X, [1.0, 2.0, 4.0], rods=[(0, 1), (1, 2)], fixed=[True, False, False])
    np.testing.assert_array_equal(np.asarray(model.inv_mass), [0.0, 0.5, 0.25])
    model, _ = jc.build(X, [1.0, 2.0, 4.0], rods=[(0, 1), (1, 2)], fixed=np.array([False, False, True]))
    np.testing.assert_array_equal(np.asarray(model.inv_mass), [1.0, 0.5, 0.0])
    model, _ = jc.build(X, [1.0, 2.0, 4.0], rods=[(0, 1), (1, 2)], fixed=[2.0])     # integral floats are indices
    np.testing.assert_array_equal(np.asarray(model.inv_mass), [1.0, 0.5, 0.0])


def test_scalar_gravity_is_a_downward_magnitude():
    model, _ = jc.build(X, [1.0, 1.0, 1.0], rods=[(0, 1)], gravity=3.7)
    np.testing.assert_array_equal(np.asarray(model.gravity), [0.0, -3.7])
    model, _ = jc.build(X, [1.0, 1.0, 1.0], rods=[(0, 1)], gravity=[0.0, 3.7])   # a vector is taken as given
    np.testing.assert_array_equal(np.asarray(model.gravity), [0.0, 3.7])


def test_heavy_particle_in_float64_is_not_fixed():
    """1e300 kg has a normal inverse in float64: the particle is free and falls (its link cannot hold it)."""
    model, state = jc.build(X, [1.0, 1e300, 1.0], rods=[(0, 1), (1, 2)], fixed=[0])
    assert float(model.inv_mass[1]) > 0
    final, _ = jc.rollout(model, state, jc.PGS(), 1 / 240, 24)
    assert np.isfinite(np.asarray(final.x)).all() and float(final.x[1, 1]) < -0.01


def test_fixed_particle_mass_is_ignored():
    model, _ = jc.build(X, [0.0, 1.0, 2.0], rods=[(0, 1), (1, 2)], fixed=[0])
    np.testing.assert_allclose(np.asarray(model.inv_mass), [0.0, 1.0, 0.5])


@pytest.mark.parametrize("make, match", [
    (lambda: jc.PGS(iterations=0), "iterations"),
    (lambda: jc.PGS(iterations=2.5), "iterations"),
    (lambda: jc.PGS(substeps=0), "substeps"),
    (lambda: jc.PGS(beta=-0.1), "beta"),
    (lambda: jc.PGS(beta=1.5), "beta"),
    (lambda: jc.PGS(beta=float("nan")), "beta"),
    (lambda: jc.PGS(beta=jnp.ones(2)), "beta"),
    (lambda: jc.PGS(warm_start="yes"), "warm_start"),
    (lambda: jc.PGS(beta="0.5"), "beta.*real"),               # was accepted as a string
    (lambda: jc.PGS(beta=1j), "beta.*complex"),
    (lambda: jc.XPBD(compliance="0"), "compliance.*real"),
    (lambda: jc.Direct(beta=0.3 + 0j), "beta.*complex"),
])
def test_solver_rejects_bad_arguments(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_rollout_and_step_reject_bad_calls():
    model, state = jc.scenes.pendulum()
    s = jc.PGS()
    for dt in (0.0, -1 / 240, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="dt"):
            jc.rollout(model, state, s, dt, 10)
        with pytest.raises(ValueError, match="dt"):
            jc.step(model, state, s, dt)
    with pytest.raises(ValueError, match="steps"):
        jc.rollout(model, state, s, 1 / 240, 0)
    with pytest.raises(TypeError, match="steps"):
        jc.rollout(model, state, s, 1 / 240, 10.0)
    with pytest.raises(ValueError, match="save_every"):
        jc.rollout(model, state, s, 1 / 240, 10, save_every=3)
    with pytest.raises(ValueError, match="state.x"):
        jc.rollout(model, state.replace(x=jnp.zeros((3, 2))), s, 1 / 240, 10)
    with pytest.raises(ValueError, match="state.v"):
        jc.rollout(model, state.replace(v=state.v.at[1, 0].set(jnp.nan)), s, 1 / 240, 10)
    with pytest.raises(TypeError, match="solver"):
        jc.rollout(model, state, "PGS", 1 / 240, 10)
    with pytest.raises(ValueError, match="rest_length"):
        model.replace(rest_length=jnp.ones(3))
    with pytest.raises(ValueError, match="inv_mass"):
        model.replace(inv_mass=jnp.array([0.0, -1.0]))


@pytest.mark.parametrize("dt, match", [
    (0.01 + 1j, "dt.*complex"),                  # was cast to real with a warning
    ("0.01", "dt.*str"),
    (np.array([0.01]), "dt.*scalar"),
    (1e-45, "dt.*outside the range float32"),    # 0 in float32: NaN
    (1e30, "dt.*outside the range float32"),     # h^2 g overflows float32: NaN
])
def test_dt_must_be_a_usable_real_scalar(dt, match):
    model, state = jc.scenes.pendulum(dtype=np.float32)
    with pytest.raises((ValueError, TypeError), match=match):
        jc.rollout(model, state, jc.PGS(), dt, 3)


def test_dt_range_follows_dtype_and_substeps():
    model64, state64 = jc.scenes.pendulum()
    final, _ = jc.rollout(model64, state64, jc.PGS(), 1e-45, 2)     # representable in float64: it runs
    assert np.isfinite(np.asarray(final.x)).all()
    model, state = jc.scenes.pendulum(dtype=np.float32)
    with pytest.raises(ValueError, match="20000 substeps"):
        jc.rollout(model, state, jc.XPBD(substeps=20000), 2e-13, 1)


@pytest.mark.parametrize("field, value, match", [
    ("x", jnp.zeros((2, 2), jnp.int32), "state.x.*floating"),
    ("v", jnp.zeros((2, 2), bool), "state.v.*floating"),
    ("x", [[0.0, 0.0], [0.0, -1.0]], "state.x.*array"),
    ("lam", (0.0,), "state.lam.*array"),
])
def test_states_must_be_float_arrays(field, value, match):
    model, state = jc.scenes.pendulum()
    with pytest.raises(TypeError, match=match):
        jc.rollout(model, state.replace(**{field: value}), jc.PGS(), 1 / 240, 3)


def test_recording_that_cannot_fit_in_memory_is_refused_before_compiling():
    model, state = jc.scenes.pendulum()
    with pytest.raises(ValueError, match="save_every"):
        jc.rollout(model, state, jc.PGS(), 1 / 240, 10 ** 12)
    batch = jax.tree.map(lambda a: jnp.broadcast_to(a, (4,) + a.shape), state)
    with pytest.raises(ValueError, match="save_every"):
        jc.batched_rollout(model, batch, jc.PGS(), 1 / 240, 10 ** 12)
    # keeping only the final state needs no record: accepted (not run here)
    jc.core.sim.check_record_memory("rollout", model, state, 10 ** 12, 10 ** 12)


def test_batched_rollout_rejects_an_empty_batch():
    model, state = jc.scenes.pendulum()
    empty = jax.tree.map(lambda a: jnp.zeros((0,) + a.shape, a.dtype), state)
    with pytest.raises(ValueError, match="empty batch"):
        jc.batched_rollout(model, empty, jc.PGS(), 1 / 240, 3)


def test_penalty_above_its_stability_limit_warns_before_running():
    """The default Penalty at dt 1/240 is above its stability limit on a unit double pendulum (it stretched it
    453x, silently): the call now says so, naming substeps; below the limit it is silent."""
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5))
    solver = jc.Penalty()
    assert 1 / 240 > solver.stability_limit(model)
    with pytest.warns(RuntimeWarning, match="substeps >= 2"):
        jc.rollout(model, state, solver, 1 / 240, 2)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jc.rollout(model, state, jc.Penalty(substeps=2), 1 / 240, 2)


def test_diagnostics_check_shapes_against_the_model():
    model, state = jc.scenes.chain(3)
    other, _ = jc.scenes.cloth(3, 3)
    _, tr = jc.rollout(model, state, jc.PGS(), 1 / 240, 4)
    with pytest.raises(ValueError, match=r"violation: `x`"):
        jc.violation(model, tr.x[:, :3])
    with pytest.raises(ValueError, match=r"energy: `x`"):
        jc.energy(model, tr.x[..., :1], tr.v)
    with pytest.raises(ValueError, match=r"traj.lam"):
        jc.diagnose(model, tr.replace(lam=tr.lam[:, :2]))
    with pytest.raises(ValueError, match="model that made the trajectory"):
        jc.diagnose(other, tr)
    with pytest.raises(ValueError, match=r"state0.x"):
        jc.diagnose(model, tr, state.replace(x=state.x[:2]))


@pytest.mark.parametrize("make, match", [
    (lambda: jc.scenes.pendulum(length=-1.0), "length"),
    (lambda: jc.scenes.double_pendulum(masses=(1.0,)), "masses"),
    (lambda: jc.scenes.chain(n_links=0), "n_links"),
    (lambda: jc.scenes.chain(kind="spring"), "kind"),
    (lambda: jc.scenes.cloth(nx=1), "nx"),
    (lambda: jc.scenes.cloth(mass=0.0), "mass"),
    (lambda: jc.scenes.pendulum(dtype=np.int32), "dtype"),          # truncated the positions to the pivot
    (lambda: jc.scenes.pendulum(length=[1.0, 2.0]), "length.*scalar"),
    (lambda: jc.scenes.pendulum(angle=0.3j), "angle.*complex"),
    (lambda: jc.scenes.double_pendulum(angles=(0.1, np.nan)), "angles.*finite"),
    (lambda: jc.scenes.chain(4, end_mass=-1.0), "end_mass"),
    (lambda: jc.scenes.cloth(3, 3, size="1"), "size.*real"),
    (lambda: jc.scenes.chain(4, gravity=-9.81), "gravity"),
    (lambda: jc.scenes.billiards(rows=23), "rack of 23 rows does not fit.*at most 13 rows"),   # started overlapped
    (lambda: jc.scenes.billiards(gap=-0.01), "gap.*>= 0"),
    (lambda: jc.scenes.billiards(max_neighbours=0), "max_neighbours"),
])
def test_scenes_reject_bad_arguments(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_validation_lets_tracers_through():
    """Value checks are skipped for tracers, so parameters built inside jit / grad / vmap still work."""
    model, state = jc.scenes.pendulum(dtype=np.float64)

    @jax.jit
    def f(rest, beta, dt):
        m = model.replace(rest_length=rest)
        return jc.rollout(m, state, jc.PGS(beta=beta), dt, 5)[0].x

    assert np.isfinite(np.asarray(f(model.rest_length, 0.2, 1 / 240))).all()


@pytest.mark.parametrize("argv, match", [
    (["bench", "--repeats", "0"], "--repeats: must be an integer >= 1"),
    (["bench", "--repeats", "two"], "--repeats: must be an integer >= 1"),
    (["bench", "--out", "/no/such/folder/bench.json"], "does not exist or is not writable"),
    ([], "choose a command: demo or bench"),
    (["frob"], "invalid choice: 'frob'"),
    (["demo", "--bogus"], "unrecognized arguments: --bogus"),
    (["bench", "--speed-vs-error", "--out-dir", __file__], "--out-dir .*: not a writable folder"),
])
def test_cli_refuses_bad_arguments_before_running(argv, match, capsys):
    from jaxcon.bench.cli import main
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert err.count("\n") == 1 and "Traceback" not in err and "usage:" not in err     # one line


def test_cli_speaks_to_users():
    from jaxcon.bench.cli import _parser
    p = _parser()
    assert "demo" in p.description and "bench" in p.description and "python -m jaxcon" not in p.description
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == {"demo", "bench"}
    for name, sp in sub.choices.items():
        assert sp.description, name
        for action in sp._actions:
            assert action.help, f"{name} {action.option_strings} has no help text"
    assert all(c.help for c in sub._choices_actions)


# ---- model and state checks that replace and leaf-rebuilt objects cannot bypass -----------------------------
def _floor_ball():
    return jc.build(np.array([[0.0, 0.5]]), 1.0, radius=0.1, planes=[((0.0, 1.0), 0.0)],
                    spheres=[((2.0, 0.0), 0.3)])


def _rebuilt(obj, **leaves):
    """`obj` with leaves swapped by unflattening, as jax does: no __post_init__ runs."""
    names = type(obj)._data_fields
    values, treedef = jax.tree_util.tree_flatten(obj, is_leaf=lambda a: a is None)
    return jax.tree_util.tree_unflatten(treedef, [leaves.get(k, v) for k, v in zip(names, values)])


@pytest.mark.parametrize("leaf, value, match", [
    ("plane_normal", np.zeros((1, 2)), r"plane_normal\[0\]` is zero"),     # was accepted: the ball fell through
    ("plane_normal", np.array([[np.nan, 1.0]]), "plane_normal.*finite"),
    ("radius", np.array([-0.1]), "radius.*>= 0"),
    ("sphere_radius", np.array([0.0]), "sphere_radius.*> 0"),
    ("sphere_radius", np.array([-0.3]), "sphere_radius.*> 0"),
])
def test_model_replace_and_rollout_refuse_what_build_refuses(leaf, value, match):
    model, state = _floor_ball()
    with pytest.raises(ValueError, match="Model: .*" + match):
        model.replace(**{leaf: value})
    with pytest.raises(ValueError, match=r"rollout: `model\." + match):       # rebuilt from leaves: checked at entry
        jc.rollout(_rebuilt(model, **{leaf: jnp.asarray(value)}), state, jc.PGS(), 1 / 240, 2)


def test_colliding_particles_keep_a_radius_after_replace():
    x = np.array([[0.0, 0.5], [1.0, 0.5], [2.0, 0.5]])
    pairs, _ = jc.build(x, 1.0, radius=0.1, collide=True)
    with pytest.raises(ValueError, match=r"particles \(0, 1\) may collide.*`radius` 0"):
        pairs.replace(radius=jnp.zeros(3))
    grid, _ = jc.build(x, 1.0, radius=0.1, collide="grid")
    with pytest.raises(ValueError, match="at most one particle may have `radius` 0"):
        grid.replace(radius=jnp.array([0.1, 0.0, 0.0]))
    grid.replace(radius=jnp.array([0.1, 0.0, 0.1]))                  # one point among discs is allowed, as in build


def test_grid_partners_must_be_particles_of_the_model():
    """Out-of-range partners gave NaN penetrations; a state of another model gave a bare shape error."""
    x = np.array([[0.0, 0.2], [0.3, 0.2], [0.6, 0.2]])
    model, state = jc.build(x, 1.0, radius=0.1, collide="grid", planes=[((0.0, 1.0), 0.0)])
    K = model.contact.grid_k
    for bad, entry in ((3, "is 3"), (-2, "is -2"), (1, "is 1")):          # past n, below -1, a particle itself
        p = np.full((3, K), -1, np.int32)
        p[1, 0] = bad
        with pytest.raises(ValueError, match=r"State: `contact_partners` must hold -1 .*" + entry):
            state.replace(contact_partners=jnp.asarray(p))
        with pytest.raises(ValueError, match=r"rollout: `state.contact_partners` must hold -1 .*" + entry):
            jc.rollout(model, _rebuilt(state, contact_partners=jnp.asarray(p)), jc.PGS(), 0.01, 2)
    with pytest.raises(TypeError, match="contact_partners.*integer"):
        state.replace(contact_partners=jnp.zeros((3, K)))
    other, other_state = jc.build(x[:2], 1.0, radius=0.1, collide="grid", planes=[((0.0, 1.0), 0.0)])
    with pytest.raises(ValueError, match=r"state.contact_n` must have shape .*another model"):
        jc.rollout(model, other_state.replace(x=state.x, v=state.v), jc.PGS(), 0.01, 2)
    assert K == 3 and other.contact.grid_k == 2                  # the default 8 capped at the number of particles
    with pytest.raises(ValueError, match=r"state.contact_partners` must have shape \(3, 3\), got shape \(2, 2\).*"
                                         "another model"):
        jc.rollout(model, state.replace(contact_partners=other_state.contact_partners), jc.PGS(), 0.01, 2)
    with pytest.raises(ValueError, match=r"state.contact_n` must have shape \(\d+,\), got a scalar"):
        jc.rollout(model, state.replace(contact_n=jnp.zeros(())), jc.PGS(), 0.01, 2)


def test_diagnose_refuses_the_contact_record_of_another_model():
    """A trajectory made by another contact model was measured against this one's contacts."""
    model, state = _floor_ball()
    _, traj = jc.rollout(model, state, jc.PGS(), 1 / 240, 2)
    two, _ = jc.build(np.array([[0.0, 0.5]]), 1.0, radius=0.1, planes=[((0.0, 1.0), 0.0), ((1.0, 0.0), -1.0)],
                      spheres=[((2.0, 0.0), 0.3)])
    with pytest.raises(ValueError, match=r"diagnose: `traj.contact_n` has shape \(2, 2\).*model that made"):
        jc.diagnose(two, traj)
    with pytest.raises(ValueError, match=r"diagnose: `traj.contact_t`"):
        jc.diagnose(model, traj.replace(contact_t=traj.contact_t[:, :1]))
    plain, _ = jc.build(np.array([[0.0, 0.0], [0.0, 0.5]]), 1.0, rods=[(0, 1)], fixed=[0])
    _, ptraj = jc.rollout(plain, jc.build(np.array([[0.0, 0.0], [0.0, 0.5]]), 1.0, rods=[(0, 1)], fixed=[0])[1],
                          jc.PGS(), 1 / 240, 2)
    with pytest.raises(ValueError, match="`traj.contact_n` is set, but this model has no contacts"):
        jc.diagnose(plain, ptraj.replace(contact_n=jnp.zeros((2, 1))))
    assert not bool(jc.diagnose(model, traj, state).diverged)          # its own model: accepted


# ---- x64 switched after a model was built -------------------------------------------------------------------
def test_a_float64_model_used_after_x64_is_switched_off_is_refused():
    """It used to run silently in float32 (or, for some contact models, crash inside the contact code)."""
    model, state = jc.scenes.falling_chain(2)              # float64: the suite runs with x64 on
    assert state.x.dtype == jnp.float64
    try:
        jax.config.update("jax_enable_x64", False)
        for call in (lambda: jc.rollout(model, state, jc.PGS(), 1 / 240, 2),
                     lambda: jc.step(model, state, jc.PGS(), 1 / 240),
                     lambda: jc.batched_rollout(model, jax.tree.map(lambda a: a[None], state), jc.PGS(), 1 / 240, 2)):
            with pytest.raises(ValueError, match=r"holds float64 arrays.*jax_enable_x64 is off.*Rebuild"):
                call()
        model32, state32 = jc.scenes.pendulum()            # built now: float32
    finally:
        jax.config.update("jax_enable_x64", True)
    final, _ = jc.rollout(model32, state32, jc.PGS(), 1 / 240, 2)     # a float32 model runs in float32 under x64
    assert final.x.dtype == jnp.float32


# ---- half precision and unclear messages ---------------------------------------------------------------------
def test_half_precision_values_are_real_numbers_but_not_a_simulation_dtype():
    """bfloat16 values were called 'not real numbers'; float16 positions built a model no dt could step."""
    for half in (jnp.bfloat16, jnp.float16):
        model, _ = jc.build(X, jnp.ones(3, half), rods=[(0, 1)], velocities=jnp.zeros((3, 2), half), fixed=[0])
        assert model.inv_mass.dtype == jnp.float64                      # cast like any other input
        with pytest.raises(TypeError, match=r"positions.*(bfloat16|float16).*float32 or float64"):
            jc.build(jnp.asarray(X, half), np.ones(3), rods=[(0, 1)], fixed=[0])
        with pytest.raises(TypeError, match=r"`dtype` is .*float32 or float64"):
            jc.scenes.pendulum(dtype=half)
    model, state = jc.scenes.pendulum()
    with pytest.raises(TypeError, match=r"state.x.*bfloat16.*float32 or float64"):
        jc.rollout(model, state.replace(x=state.x.astype(jnp.bfloat16)), jc.PGS(), 1 / 240, 2)
    with pytest.raises(ValueError, match=r"state.v` must be finite"):     # checked as numbers, not refused as unreal
        jc.rollout(model, state.replace(v=state.v.at[1, 0].set(jnp.nan).astype(jnp.bfloat16)), jc.PGS(), 1 / 240, 2)


def test_shape_errors_say_a_scalar_was_passed():
    model, state = jc.scenes.chain(3)
    with pytest.raises(ValueError, match=r"`state.lam` must have shape \(3,\), got a scalar"):
        jc.rollout(model, state.replace(lam=jnp.zeros(())), jc.PGS(), 1 / 240, 2)


def test_cli_refuses_a_directory_as_out(tmp_path, capsys):
    from jaxcon.bench.cli import main
    for out, match in ((str(tmp_path), "is a directory"), (f"{__file__}/bench.json", "folder .* does not exist or is "
                                                                                     "not writable")):
        with pytest.raises(SystemExit) as exc:
            main(["bench", "--small", "--out", out])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert re.search(f"--out {re.escape(out)}: {match}", err), err
