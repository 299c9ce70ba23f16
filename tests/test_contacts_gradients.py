"""Derivatives through contacts in float32 and float64, and bad contact leaves under jit.

- Reverse mode (jax.grad) of every contact leaf (radius, friction, restitution, restitution_threshold,
  plane_normal, plane_offset, sphere_centre, sphere_radius) with PGS equals float64 central differences (along
  a random direction per leaf) on each contact scene (falling chain, billiards, drape), in float32 and float64,
  and forward mode (jax.jvp) in float32 on the falling chain and the drape and in float64 on the drape. Before, the
  falling chain's friction gradient was NaN in float32 (restitution_scale's unused root: 0 * inf), and the
  drape's float64 gradient was 2% off jacfwd (gaps within rounding of 0 were classified by each program's own
  rounding). The other contact solvers' gradients are finite.
- A NaN or out-of-range friction or restitution reaching a rollout under jit makes its outputs NaN.
"""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.solvers.contact import restitution_scale

LEAVES = ("radius", "friction", "restitution", "restitution_threshold", "plane_normal", "plane_offset",
          "sphere_centre", "sphere_radius")


def _scene(name, dtype):
    """(model, state, dt, steps): short runs through the first contacts."""
    if name == "falling_chain":
        model, state = jc.scenes.falling_chain(5, angle=0.1, restitution=0.3, dtype=dtype)
        return model, state, 1 / 120, 60
    if name == "billiards":
        model, state = jc.scenes.billiards(rows=2, dtype=dtype)
        return model, state, 1 / 60, 16
    model, state = jc.scenes.drape(4, height=0.68, dtype=dtype)       # off the sphere's axis: no ties
    model = model.replace(sphere_centre=model.sphere_centre + jnp.asarray([[0.013, -0.021, 0.0]], dtype),
                          restitution=jnp.asarray(0.2, dtype))
    return model, state, 1 / 60, 12


def _problem(name, dtype, solver):
    model, state, dt, steps = _scene(name, dtype)
    p = {k: getattr(model, k) for k in LEAVES if getattr(model, k) is not None and np.size(getattr(model, k))}

    def loss(p):
        _, tr = jc.rollout(model.replace(**p), state, solver, dt, steps)
        w = jnp.linspace(0.5, 1.5, tr.x[-1].size, dtype=dtype).reshape(tr.x[-1].shape)
        return jnp.sum(w * tr.x[-1]) + 0.1 * jnp.sum(w * tr.v[-1])

    return loss, p


def _flat(g, p):
    return np.concatenate([np.ravel(np.asarray(g[k], np.float64)) for k in p])


def test_restitution_scale_reverse_mode_is_finite_when_the_phases_agree():
    """Nothing bounces, and the two phases' velocities differ by rounding (c ~ 1e-27): s = 1 with a zero
    gradient, where d s / d c ~ 1 / c^2 used to overflow float32 and 0 * inf made the cotangents NaN."""
    vc = np.float32([[1e-7, -2e-7, 5e-8], [-2.0, -2.0, -2.0]])
    w = np.float32([[12.0, 12.0, 12.0]])
    for bounce in (False, True):
        grads = jax.jit(jax.grad(lambda vf, vc, vn: restitution_scale(w, vf, vc, vn, jnp.asarray(bounce)),
                                 argnums=(0, 1, 2)))(vc, vc, vc + np.float32(1e-14))
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)


@pytest.mark.optimised          # the NaN came from the compiled program's rounding (not at XLA's lowest effort)
def test_falling_chain_friction_gradient_in_float32():
    """The reported reproducer: grad was NaN; jacfwd gives -5.03e-5, float64 -5.0313e-5."""
    def end_x(mu, dtype):
        model, state = jc.scenes.falling_chain(5, angle=0.1, dtype=dtype)
        final, _ = jc.rollout(model.replace(friction=mu), state, jc.PGS(10), 1 / 120, 60)
        return final.x[0, 0]

    mu32 = jnp.float32(0.5)
    g = float(jax.grad(end_x)(mu32, np.float32))
    assert np.isfinite(g)
    assert g == pytest.approx(float(jax.jacfwd(end_x)(mu32, np.float32)), rel=1e-4)
    f64 = jax.jit(lambda mu: end_x(mu, np.float64))
    cd = (float(f64(0.5 + 1e-6)) - float(f64(0.5 - 1e-6))) / 2e-6
    assert cd == pytest.approx(-5.0313e-5, rel=1e-4)
    assert g == pytest.approx(cd, rel=1e-3)


@pytest.mark.parametrize("name", ["falling_chain", "billiards", "drape"])
def test_contact_leaf_gradients_reverse_equals_forward_and_differences(name):
    """Reverse against forward mode along a random direction of all the leaves together (jvp: one compiled
    program where jacfwd would be one as well, but ~20 times the work) in float32 on the falling chain and the
    drape, and in float64 on the drape (where they were 2% apart); then float64 central differences along a
    random direction per leaf, which both dtypes' reverse-mode gradients must match on every scene (billiards is
    checked by those alone, to save the suite a 10 s compilation)."""
    rng = np.random.default_rng(0)
    grads = {}
    for dtype in (np.float32, np.float64):
        loss, p = _problem(name, dtype, jc.PGS(10))
        value_and_grad = jax.jit(jax.value_and_grad(loss))       # float64: also the differences' loss (below)
        g = value_and_grad(p)[1]
        rev = _flat(g, p)
        assert np.all(np.isfinite(rev)), (dtype, g)
        if (dtype == np.float32 and name != "billiards") or name == "drape":
            t = {k: jnp.asarray(rng.normal(size=np.shape(a)), dtype) for k, a in p.items()}
            fwd = float(jax.jit(lambda p, t: jax.jvp(loss, (p,), (t,))[1])(p, t))
            dot = float(rev @ _flat(t, p))
            assert dot == pytest.approx(fwd, rel=1e-4 if dtype == np.float32 else 1e-10), dtype
        grads[dtype] = g
    f = lambda q: value_and_grad(q)[0]          # noqa: E731  (the float64 program: one compilation fewer)
    scale = np.abs(_flat(grads[np.float64], p)).max()
    for k in p:
        a = np.asarray(p[k], np.float64)
        u = rng.normal(size=a.shape)
        u /= np.linalg.norm(u)
        e = 1e-6
        cd = (float(f({**p, k: jnp.asarray(a + e * u)})) - float(f({**p, k: jnp.asarray(a - e * u)}))) / (2 * e)
        assert float(np.sum(np.asarray(grads[np.float64][k]) * u)) == pytest.approx(
            cd, abs=1e-5 * (abs(cd) + 1e-3 * scale)), k
        # float32: the same derivative, of a trajectory that rounds differently
        assert float(np.sum(np.asarray(grads[np.float32][k], np.float64) * u)) == pytest.approx(
            cd, abs=1e-2 * (abs(cd) + 1e-2 * scale)), k


# One scene each (every scene is covered with PGS above): reverse mode through their own contact code.
@pytest.mark.parametrize("name, solver", [("falling_chain", jc.Jacobi(20)), ("drape", jc.XPBD(substeps=4)),
                                          ("drape", jc.SoftStep(substeps=2)),
                                          ("falling_chain", jc.Penalty(stiffness=2e4, substeps=10)),
                                          ("falling_chain", jc.RATTLE())],
                         ids=["Jacobi-falling_chain", "XPBD-drape", "SoftStep-drape", "Penalty-falling_chain",
                              "RATTLE-falling_chain"])
def test_other_solvers_contact_leaf_gradients_are_finite_in_float32(name, solver):
    loss, p = _problem(name, np.float32, solver)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        g = jax.jit(jax.grad(loss))(p)
    assert np.all(np.isfinite(_flat(g, p))), g
    assert np.any(_flat(g, p) != 0)


BAD = [("friction", np.nan), ("friction", -0.5), ("restitution", np.nan), ("restitution", -0.2),
       ("restitution", 1.5)]


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.Jacobi(20), jc.XPBD(substeps=4), jc.SoftStep(substeps=2),
                                    jc.Penalty(stiffness=2e4, substeps=10), jc.RATTLE()],
                         ids=["PGS", "Jacobi", "XPBD", "SoftStep", "Penalty", "RATTLE"])
def test_bad_friction_or_restitution_under_jit_gives_nan_outputs(solver):
    """`Model` refuses these values when they are concrete; traced (an optimiser step with a NaN gradient), they
    used to give a finite trajectory (a NaN friction made PGS frictionless). Now the outputs are NaN."""
    model, state = jc.scenes.falling_chain(3, angle=0.1, height=0.05, restitution=0.3, dtype=np.float32)

    @jax.jit
    def run(mu, e):
        final, traj = jc.rollout(model.replace(friction=mu, restitution=e), state, solver, 1 / 120, 10)
        return final.x, traj.contact_n

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        good = run(jnp.float32(0.5), jnp.float32(0.3))
        assert all(np.all(np.isfinite(np.asarray(a))) for a in good)
        for leaf, value in BAD:
            kw = {"mu": jnp.float32(0.5), "e": jnp.float32(0.3)}
            kw["mu" if leaf == "friction" else "e"] = jnp.float32(value)
            x, cn = run(**kw)
            assert np.all(np.isnan(np.asarray(x))), (leaf, value)


def test_bad_restitution_under_jit_gives_nan_with_a_grid():
    x = np.array([[0.0, 0.05], [0.2, 0.05], [0.4, 0.05]])
    model, state = jc.build(x, np.ones(3), radius=0.05, collide="grid", planes=[((0.0, 1.0), 0.0)])
    run = jax.jit(lambda e: jc.rollout(model.replace(restitution=e), state, jc.PGS(4), 1 / 60, 3)[0].x)
    assert np.all(np.isfinite(np.asarray(run(0.5))))
    assert np.all(np.isnan(np.asarray(run(np.nan))))


def test_contacts_within_rounding_of_touching_do_not_depend_on_the_rounding():
    """The position pass leaves corrected contacts at C = 0 +- rounding. Whether such a contact was separated
    (an impact at toi = C / |vn|) or touching used to follow the sign of that rounding, which the forward- and
    reverse-mode programs compute differently (the drape's jax.grad was 2% off jax.jacfwd, at XLA's default
    effort). Now the rows and their derivatives are the same on both sides of C = 0: a plane, a sphere and a
    pair, each approached at 1 m/s with its gap at +-1e-16 m."""
    from jaxcon.core import layout
    from jaxcon.core.system import System
    from jaxcon.core import contact_rows

    r, h = 0.1, 1 / 60
    # particle 0 on the floor, 1 on a sphere's top, 3 on 2 (pair 2-3), far apart
    base = np.array([[0.0, r], [5.0, 1.0 + r], [10.0, 1.0], [10.0, 1.0 + 2 * r]])
    v = np.array([[0.0, -1.0], [0.0, -1.0], [0.0, 0.0], [0.0, -1.0]])
    model, _ = jc.build(base, np.ones(4), radius=r, planes=[((0.0, 1.0), 0.0)], spheres=[((5.0, 0.0), 1.0)],
                        collide=[(2, 3)])
    sys_ = System.from_model(model, jnp.float64)
    t = model.topology

    def row_values(x):
        xi, vi = layout.particles_in(t, x), layout.particles_in(t, jnp.asarray(v))
        obs, pairs = contact_rows.rows(sys_.contact, sys_.w, xi, vi, vi, 0.2, h)
        return (obs.target, obs.toi, obs.gap, pairs.target, pairs.toi, pairs.gap)

    tangent = jnp.asarray(np.random.default_rng(1).normal(size=base.shape))
    out = {}
    for sign in (1.0, -1.0):
        x = jnp.asarray(base + sign * 1e-16 * np.array([[0, 1], [0, 1], [0, 0], [0, 1]]))
        out[sign] = jax.jvp(row_values, (x,), (tangent,))
    for a, b in zip(jax.tree.leaves(out[1.0]), jax.tree.leaves(out[-1.0])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    toi = np.asarray(out[1.0][0][1])
    assert toi[0, 0] > 0 and toi[1, 1] > 0          # approaching: impacts at toi ~ 0, for their derivative
