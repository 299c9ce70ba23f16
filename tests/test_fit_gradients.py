"""Gradients of rollout losses through PGS against float64 central finite differences, jvp against vjp, and
finite gradients at the non-smooth places (coincident particles, a rope going slack and taut)."""
import jax
import jax.numpy as jnp
import numpy as np

import jaxcon as jc

DT = 1 / 240
STEPS = 30   # short, smooth horizon: central differences with eps 1e-6 are accurate to ~1e-9 relative


def _setup():
    model, state = jc.scenes.chain(n_links=3, length=1.0, mass=1.0, angle=0.7, dtype=np.float64)
    # a constraint error at t = 0 so that beta acts
    state = state.replace(x=state.x.at[2].add(jnp.array([0.01, -0.02])), v=state.v.at[3].set(jnp.array([0.3, 0.1])))
    return model, state


def _loss(model, state):
    def loss(p):
        m = model.replace(rest_length=p["rest_length"], inv_mass=p["inv_mass"], gravity=p["gravity"])
        _, tr = jc.rollout(m, state.replace(x=p["x0"], v=p["v0"]), jc.PGS(iterations=5, beta=p["beta"]), DT,
                           STEPS)
        w = jnp.linspace(0.5, 1.5, tr.x.size).reshape(tr.x.shape)
        return jnp.sum(w * tr.x ** 2) / STEPS + jnp.sum(tr.lam)
    p = dict(rest_length=model.rest_length, inv_mass=model.inv_mass, gravity=model.gravity, beta=jnp.asarray(0.2),
             x0=state.x, v0=state.v)
    return loss, p


def test_gradients_match_central_differences():
    model, state = _setup()
    loss, p = _loss(model, state)
    g = jax.jit(jax.grad(loss))(p)
    f = jax.jit(loss)
    eps = 1e-6
    for name in p:
        flat = np.asarray(p[name], np.float64).ravel()
        fd = np.zeros_like(flat)
        for k in range(flat.size):
            if name == "inv_mass" and flat[k] == 0:   # the fixed pivot: inverse mass 0 is a boundary
                fd[k] = np.nan
                continue
            up, dn = flat.copy(), flat.copy()
            up[k] += eps
            dn[k] -= eps
            fd[k] = (f({**p, name: up.reshape(np.shape(p[name]))}) - f({**p, name: dn.reshape(np.shape(p[name]))})) / (2 * eps)
        ad = np.asarray(g[name]).ravel()
        ok = np.isfinite(fd)
        scale = np.max(np.abs(fd[ok]))
        assert scale > 0, name
        np.testing.assert_allclose(ad[ok], fd[ok], rtol=1e-5, atol=1e-5 * scale, err_msg=name)


def test_jvp_agrees_with_vjp():
    model, state = _setup()
    loss, p = _loss(model, state)
    rng = np.random.default_rng(0)
    t = jax.tree.map(lambda a: jnp.asarray(rng.standard_normal(np.shape(a))), p)
    _, fwd = jax.jit(lambda p, t: jax.jvp(loss, (p,), (t,)))(p, t)
    g = jax.grad(loss)(p)
    rev = sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(t)))
    np.testing.assert_allclose(fwd, rev, rtol=1e-10)


def test_gradients_finite_with_coincident_particles():
    x = np.array([[0.0, 0.0], [0.0, -1.0], [0.0, -1.0]])     # particles 1 and 2 coincide
    model, state = jc.build(x, [1.0, 1.0, 1.0], rods=[(0, 1), (1, 2)], fixed=[0], rest_lengths=[1.0, 0.0])

    def loss(rest, x0):
        _, tr = jc.rollout(model.replace(rest_length=rest), state.replace(x=x0), jc.PGS(iterations=5), DT, 20)
        return jnp.sum(tr.x ** 2) + jnp.sum(tr.lam ** 2)

    g = jax.grad(loss, argnums=(0, 1))(model.rest_length, state.x)
    assert all(np.all(np.isfinite(a)) for a in g)
    assert np.abs(g[0][0]) > 0    # the well-defined rod still carries gradient


def test_gradients_finite_when_rope_goes_slack_and_taut():
    """A pendulum on a rope thrown inwards: the rope goes slack, the bob flies, the rope snaps taut again.

    Subgradient at the clamp: lam = max(lam_unclamped, 0) is differentiated as jnp.maximum does, i.e. 1 where
    lam_unclamped > 0, 0 where < 0 and 1/2 at an exact tie (measure zero along a trajectory). The slack-rope
    bias C / h switches to beta C / h at C = 0 (the derivative jumps there; jnp.where picks one side).
    """
    model, state = jc.scenes.pendulum(length=1.0, angle=0.5, kind="rope", dtype=np.float64)
    state = state.replace(v=state.v.at[1].set(jnp.array([-1.0, 2.5])))

    def run(rest):
        _, tr = jc.rollout(model.replace(rest_length=rest), state, jc.PGS(iterations=5), DT, 240)
        return tr

    tr = run(model.rest_length)
    d = np.linalg.norm(np.asarray(tr.x[:, 1]), axis=-1)
    assert (d < 0.95).any() and (np.asarray(tr.lam)[:, 0] > 0).any()    # really slack, then taut
    assert np.argmax(d < 0.95) < np.max(np.nonzero(np.asarray(tr.lam)[:, 0] > 0)[0])

    def loss(rest):
        return jnp.sum(run(rest).x[-1] ** 2)

    g = jax.grad(loss)(model.rest_length)
    assert np.all(np.isfinite(g)) and np.abs(g[0]) > 0
    # away from switching times the gradient is the derivative: compare to central differences
    eps = 1e-7
    fd = (loss(model.rest_length + eps) - loss(model.rest_length - eps)) / (2 * eps)
    np.testing.assert_allclose(g[0], fd, rtol=1e-4)
