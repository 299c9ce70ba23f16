"""Precision follows JAX, and scene values may be traced.

With x64 on (conftest) and no `dtype=` passed anywhere, every array jaxcon builds or returns is float64; under
`jax_numpy_dtype_promotion="strict"` no call mixes dtypes implicitly. With x64 off (a subprocess, since the
flag is process-wide) the same calls give float32. Scenes and `jc.build` accept traced values: gradients with
respect to an initial angle, a length or the positions equal central finite differences.
"""
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc

SOLVERS = [jc.PGS(iterations=4), jc.Jacobi(iterations=4), jc.XPBD(substeps=2), jc.Penalty(stiffness=1e3, substeps=4),
           jc.Direct(), jc.SoftStep(substeps=2), jc.RATTLE(iterations=4)]


def _scenes():
    """Every scene and `build` from Python lists (ints and floats), no dtype anywhere."""
    return {
        "pendulum": jc.scenes.pendulum(),
        "double_pendulum": jc.scenes.double_pendulum(),
        "chain": jc.scenes.chain(4, end_mass=2.0),
        "rope_chain": jc.scenes.chain(3, kind="rope"),
        "cloth": jc.scenes.cloth(4, 3),
        "build_lists": jc.build([[0, 0], [1, 0], [2, 0.5]], [1, 2, 3], rods=[(0, 1)], ropes=[(1, 2)], fixed=[0]),
    }


def _float_leaves(tree):
    return [a for a in jax.tree.leaves(tree) if jnp.issubdtype(jnp.result_type(a), jnp.inexact)]


def test_scenes_and_build_default_to_float64_under_x64():
    with jax.numpy_dtype_promotion("strict"):
        for name, built in _scenes().items():
            leaves = _float_leaves(built)
            assert leaves and all(a.dtype == jnp.float64 for a in leaves), (name, {str(a.dtype) for a in leaves})


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_x64_without_dtype_is_float64_under_strict_promotion(solver):
    """Rollout, step, diagnostics and a gradient, on a model from Python lists (rods and ropes: for Direct, its
    complementarity solve; Direct also on a chain, its tridiagonal path) and on a cloth (strided colour blocks)."""
    scenes = _scenes()
    firsts = ("build_lists", "chain") if isinstance(solver, jc.Direct) else ("build_lists",)
    with jax.numpy_dtype_promotion("strict"):
        for name in firsts + ("cloth",):
            model, state = scenes[name]
            final, tr = jc.rollout(model, state, solver, 1 / 240, 4)
            out = [final, tr, jc.diagnose(model, tr, state), jc.energy_drift(model, state, tr),
                   jc.violation(model, tr.x)]
            if name in firsts:
                out.append(jc.step(model, state, solver, 1 / 240))
                grad = jax.grad(lambda L: jnp.sum(jc.rollout(model.replace(rest_length=L), state, solver, 1 / 240,
                                                             3)[0].x))(model.rest_length)
                assert np.isfinite(np.asarray(grad)).all()
                out.append(grad)
            leaves = _float_leaves(out)
            assert leaves and all(a.dtype == jnp.float64 for a in leaves), (name, {str(a.dtype) for a in leaves})


def test_explicit_float32_stays_float32_under_x64():
    with jax.numpy_dtype_promotion("strict"):
        model, state = jc.scenes.chain(4, dtype=np.float32)
        final, tr = jc.rollout(model, state, jc.PGS(), 1 / 240, 3)
        assert {a.dtype for a in _float_leaves((model, state, final, tr, jc.diagnose(model, tr)))} == {jnp.dtype("float32")}
        # a float32 array as a scene value sets the dtype too (dtypes follow the inputs)
        m2, s2 = jc.scenes.pendulum(angle=jnp.float32(0.4))
        assert m2.rest_length.dtype == jnp.float32 and s2.x.dtype == jnp.float32


def test_x64_off_gives_float32_by_default():
    """In a fresh process without x64, the same calls default to float32 (JAX's default float dtype)."""
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp
        import jaxcon as jc
        assert not jax.config.jax_enable_x64
        for model, state in (jc.scenes.pendulum(), jc.scenes.cloth(3, 3),
                             jc.build([[0, 0], [1, 0]], [1, 1], rods=[(0, 1)], fixed=[0])):
            final, tr = jc.rollout(model, state, jc.PGS(), 1 / 240, 2)
            leaves = [a for a in jax.tree.leaves((model, state, final, tr)) if jnp.issubdtype(a.dtype, jnp.inexact)]
            assert {str(a.dtype) for a in leaves} == {"float32"}, {str(a.dtype) for a in leaves}
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "JAX_ENABLE_X64": "0", "JAX_PLATFORMS": "cpu"})
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


def test_rattle_is_second_order_with_default_dtype():
    """The issue that motivated float64 by default: with float32 scenes RATTLE's second order was lost. With
    the default dtype under x64 its error against the reduced-coordinate ODE falls as dt^2."""
    from reference import double_pendulum_positions
    ref = double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [0.5])[0]
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5))
    errs = []
    dts = (1 / 100, 1 / 200, 1 / 400)
    for dt in dts:
        final, _ = jc.rollout(model, state, jc.RATTLE(iterations=30, tolerance=0.0), dt, int(round(0.5 / dt)))
        errs.append(np.abs(np.asarray(final.x[1:]) - ref).max())
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert 1.8 < slope < 2.3, (errs, slope)


# ---- traced scene values ------------------------------------------------------------------------------------
def _central(f, x, eps=1e-5):
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = eps
        g[idx] = (float(f(x + e)) - float(f(x - e))) / (2 * eps)
    return g


def test_grad_with_respect_to_initial_angle_and_lengths():
    def loss(a, lengths):
        model, state = jc.scenes.double_pendulum(lengths=lengths, angles=jnp.stack([a, 0.2]))
        final, _ = jc.rollout(model, state, jc.PGS(iterations=10), 1 / 240, 120)
        return jnp.sum(final.x[2] * jnp.array([1.0, 0.3]))

    a, lengths = 0.6, jnp.array([1.0, 0.7])
    g_a, g_l = jax.grad(loss, argnums=(0, 1))(a, lengths)
    f = jax.jit(loss)
    np.testing.assert_allclose(g_a, _central(lambda x: f(x, lengths), a), rtol=1e-6)
    np.testing.assert_allclose(g_l, _central(lambda x: f(a, jnp.asarray(x)), lengths), rtol=1e-6)
    assert abs(float(g_a)) > 1e-3 and np.all(np.abs(g_l) > 1e-3)     # not a trivially zero derivative


@pytest.mark.parametrize("scene", ["pendulum", "chain", "cloth"])
def test_scene_values_trace_under_jit_grad_and_vmap(scene):
    make = {
        "pendulum": lambda p: jc.scenes.pendulum(length=p, mass=2 * p, angle=p / 3),
        "chain": lambda p: jc.scenes.chain(3, length=p, mass=p, end_mass=p / 2, angle=p),
        "cloth": lambda p: jc.scenes.cloth(3, 3, size=p, mass=p),
    }[scene]

    def loss(p):
        model, state = make(p)
        final, _ = jc.rollout(model, state, jc.PGS(iterations=5), 1 / 240, 10)
        return jnp.sum(final.x ** 2)

    p, f = 1.3, jax.jit(loss)
    np.testing.assert_allclose(jax.grad(loss)(p), _central(f, p), rtol=1e-6)
    np.testing.assert_allclose(jax.vmap(loss)(jnp.array([p, p])), [f(p)] * 2, rtol=1e-12)
    concrete_model, concrete_state = make(p)
    traced_model, traced_state = jax.jit(make)(p)
    for a, b in zip(jax.tree.leaves((concrete_model, concrete_state)), jax.tree.leaves((traced_model, traced_state))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14, atol=1e-15)


def test_grad_through_build_positions_masses_and_velocities():
    x0 = jnp.array([[0.0, 0.0], [1.0, 0.1], [1.8, -0.4]])
    m0 = jnp.array([1.0, 2.0, 0.5])
    v0 = jnp.array([[0.0, 0.0], [0.3, 0.0], [0.0, -0.2]])

    def loss(x, m, v):
        model, state = jc.build(x, m, rods=[(0, 1)], ropes=[(1, 2)], fixed=[0], velocities=v)
        final, _ = jc.rollout(model, state, jc.PGS(iterations=10), 1 / 240, 60)
        return jnp.sum(final.x[1:] ** 2) + jnp.sum(final.v * jnp.array([0.5, -0.2]))

    gx, gm, gv = jax.grad(loss, argnums=(0, 1, 2))(x0, m0, v0)
    f = jax.jit(loss)
    np.testing.assert_allclose(gx, _central(lambda x: f(jnp.asarray(x), m0, v0), x0), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(gm, _central(lambda m: f(x0, jnp.asarray(m), v0), m0), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(gv, _central(lambda v: f(x0, m0, jnp.asarray(v)), v0), rtol=1e-6, atol=1e-9)
    assert gm[0] == 0.0 and abs(gm[1]) > 1e-4       # a fixed particle's mass does not matter; the others do
