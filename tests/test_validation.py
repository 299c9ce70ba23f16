"""Bad input gets a clear error naming the argument, raised before tracing; tracers pass validation."""
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
])
def test_build_rejects_bad_input(kwargs, match):
    args = dict(positions=X, masses=[1.0, 1.0, 1.0], rods=[(0, 1), (1, 2)], fixed=[0])
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        jc.build(**args)


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


@pytest.mark.parametrize("make, match", [
    (lambda: jc.scenes.pendulum(length=-1.0), "length"),
    (lambda: jc.scenes.double_pendulum(masses=(1.0,)), "masses"),
    (lambda: jc.scenes.chain(n_links=0), "n_links"),
    (lambda: jc.scenes.chain(kind="spring"), "kind"),
    (lambda: jc.scenes.cloth(nx=1), "nx"),
    (lambda: jc.scenes.cloth(mass=0.0), "mass"),
])
def test_scenes_reject_bad_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_validation_lets_tracers_through():
    """Value checks are skipped for tracers, so parameters built inside jit / grad / vmap still work."""
    model, state = jc.scenes.pendulum(dtype=np.float64)

    @jax.jit
    def f(rest, beta, dt):
        m = model.replace(rest_length=rest)
        return jc.rollout(m, state, jc.PGS(beta=beta), dt, 5)[0].x

    assert np.isfinite(np.asarray(f(model.rest_length, 0.2, 1 / 240))).all()
