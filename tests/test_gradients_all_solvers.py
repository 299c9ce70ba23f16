"""Every solver, every differentiable input: reverse-mode gradients of a rollout loss equal float64 central
finite differences entry by entry, and forward mode (jvp) agrees with reverse mode (vjp).

The inputs are the model's rest lengths, inverse masses and gravity, the initial positions and velocities,
and each solver's own leaves (beta, relaxation, compliance, stiffness, damping, hertz, damping ratio). The
scene is a short 3-link chain with a constraint error at t = 0 (so that Baumgarte / soft-constraint terms
act) and, for the solvers that take ropes, a last link that is a rope kept taut by gravity (smooth: the
clamp is never active, so the derivative is the classical one).
"""
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc

DT = 1 / 120
STEPS = 12

# name -> (solver from a dict of leaves, leaves at the point of evaluation, takes ropes)
SOLVERS = {
    "PGS": (lambda p: jc.PGS(iterations=6, beta=p["beta"]), {"beta": 0.2}, True),
    "Jacobi": (lambda p: jc.Jacobi(iterations=8, beta=p["beta"], relaxation=p["relaxation"]),
               {"beta": 0.2, "relaxation": 0.45}, True),
    "XPBD": (lambda p: jc.XPBD(iterations=2, compliance=p["compliance"], substeps=3),
             {"compliance": 1e-4}, True),
    "Penalty": (lambda p: jc.Penalty(stiffness=p["stiffness"], damping=p["damping"], substeps=4),
                {"stiffness": 2e4, "damping": 5.0}, True),
    "Direct": (lambda p: jc.Direct(beta=p["beta"]), {"beta": 0.2}, False),
    "SoftStep": (lambda p: jc.SoftStep(substeps=2, hertz=p["hertz"], damping_ratio=p["damping_ratio"]),
                 {"hertz": 30.0, "damping_ratio": 1.0}, True),
    "RATTLE": (lambda p: jc.RATTLE(iterations=3), {}, True),
}


def _problem(name):
    make, leaves, ropes = SOLVERS[name]
    x = np.array([[0.0, 0.0], [0.8, -0.6], [1.5, -1.3], [2.0, -2.1]])
    model, state = jc.build(x, [1.0, 1.0, 0.7, 1.3], rods=[(0, 1), (1, 2)] if ropes else [(0, 1), (1, 2), (2, 3)],
                            ropes=[(2, 3)] if ropes else None, fixed=[0],
                            rest_lengths=[1.0, 0.95, 0.9], velocities=np.array(
                                [[0.0, 0.0], [0.2, 0.1], [-0.3, 0.2], [0.4, -0.1]]))

    def loss(p):
        m = model.replace(rest_length=p["rest_length"], inv_mass=p["inv_mass"], gravity=p["gravity"])
        _, tr = jc.rollout(m, state.replace(x=p["x0"], v=p["v0"]), make(p["solver"]), DT, STEPS)
        w = jnp.linspace(0.5, 1.5, tr.x.size).reshape(tr.x.shape)
        return jnp.sum(w * tr.x ** 2) / STEPS + jnp.sum(tr.v[-1] ** 2) + jnp.sum(tr.lam) * 10

    p = dict(rest_length=model.rest_length, inv_mass=model.inv_mass, gravity=model.gravity, x0=state.x,
             v0=state.v, solver={k: jnp.asarray(v, jnp.float64) for k, v in leaves.items()})
    return loss, p


@pytest.mark.parametrize("name", list(SOLVERS))
def test_every_input_matches_central_differences_and_jvp_matches_vjp(name):
    loss, p = _problem(name)
    g = jax.jit(jax.grad(loss))(p)
    f = jax.jit(loss)
    flat, unravel = jax.flatten_util.ravel_pytree(p)
    gflat, _ = jax.flatten_util.ravel_pytree(g)
    flat = np.asarray(flat)
    gflat = np.asarray(gflat)
    names = [f"{jax.tree_util.keystr(path)}[{k}]" for path, leaf in jax.tree_util.tree_flatten_with_path(p)[0]
             for k in range(np.size(leaf))]
    assert np.all(np.isfinite(gflat)), name
    fd = np.full_like(flat, np.nan)
    for k in range(flat.size):
        if "inv_mass" in names[k] and flat[k] == 0:    # the fixed pivot: inverse mass 0 is a boundary
            continue
        e = 1e-6 * max(1.0, abs(flat[k])) if "compliance" not in names[k] else 1e-4 * flat[k]
        up, dn = flat.copy(), flat.copy()
        up[k] += e
        dn[k] -= e
        fd[k] = (float(f(unravel(up))) - float(f(unravel(dn)))) / (2 * e)
    ok = np.isfinite(fd)
    # every input group is exercised, and each moves the loss
    groups = {n[:n.rindex("[")] for n in np.asarray(names)[ok]}
    assert {"['rest_length']", "['inv_mass']", "['gravity']", "['x0']", "['v0']"} <= groups, groups
    for k in np.nonzero(ok)[0]:
        scale = max(abs(fd[k]), 1e-3 * np.max(np.abs(fd[ok])))
        assert abs(gflat[k] - fd[k]) <= 1e-5 * scale, (name, names[k], gflat[k], fd[k])
    for key in p["solver"]:
        k = names.index(f"['solver']['{key}'][0]")
        assert abs(fd[k]) > 0, (name, key)     # the solver's own parameter really acts on the loss

    # forward mode against reverse mode along a random direction
    rng = np.random.default_rng(1)
    t = rng.standard_normal(flat.size)
    _, fwd = jax.jit(lambda q, d: jax.jvp(lambda z: loss(unravel(z)), (q,), (d,)))(jnp.asarray(flat), jnp.asarray(t))
    rev = float(np.dot(gflat, t))
    np.testing.assert_allclose(float(fwd), rev, rtol=1e-10, atol=1e-12 * np.abs(gflat).sum())
