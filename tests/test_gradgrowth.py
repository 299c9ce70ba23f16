"""Gradient growth with horizon (jaxcon.identification.gradgrowth)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.identification.fit import _tree_replace
from jaxcon.identification.gradgrowth import gradient_norms, growth_rate

DT = 1 / 240


@pytest.fixture(scope="module")
def cloth():
    return jc.scenes.cloth(4, 4, dtype=np.float64)


def test_matches_jax_grad_of_rollout(cloth):
    """The chunked reverse sweep is the exact gradient: compare with jax.grad of the rollout (float64)."""
    model, state = cloth
    solver = jc.PGS(iterations=5)
    norms, grads = gradient_norms(model, state, solver, DT, [10, 30], return_grads=True)

    def losses(r):   # both horizons from one recorded 30-step rollout: one compilation
        m = _tree_replace(model, {"rest_length": r})
        x = jc.rollout(m, state, solver, DT, 30)[1].x
        return jnp.stack([jnp.mean(x[9] ** 2), jnp.mean(x[29] ** 2)])

    refs = np.asarray(jax.jit(jax.jacrev(losses))(model.rest_length))
    for g, nrm, ref in zip(grads, norms, refs):
        np.testing.assert_allclose(g, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
        assert nrm == pytest.approx(np.linalg.norm(ref), rel=1e-9)


def test_growth_with_and_without_warm_start():
    """5x5 cloth, PGS(5), dt 1/240, 50 -> 300 steps (float64). warm_start_factor is a leaf, so both runs share
    one compilation; factor 0 is the forward pass of warm_start=False. Measured: full warm start 3.9 -> 7.5e4,
    no warm start 0.54 -> 5.9 (docs/fitting.md)."""
    model, state = jc.scenes.cloth(5, 5, dtype=np.float64)
    H = [50, 300]
    full = gradient_norms(model, state, jc.PGS(iterations=5), DT, H)
    cold = gradient_norms(model, state, jc.PGS(iterations=5, warm_start_factor=0.0), DT, H)
    assert np.all(np.isfinite(full)) and np.all(np.isfinite(cold)) and np.all(cold > 0)
    assert full[1] > 1e3 * full[0]           # grows geometrically with the horizon
    assert cold[1] < 1e2 * cold[0]           # the damped, cold-started solver much less
    assert full[1] > 1e3 * cold[1]
    assert growth_rate(H, full, DT)["slope_per_step"] > 0.02


def test_warm_start_gradient_false_does_not_bound_growth():
    """Stopping the gradient through the warm-start impulses gives a truncated Jacobian, and on a swinging
    cloth its product grows too (measured 0.54 -> 1.3e4 on 5x5 over 50 -> 300 steps; on 16x16 faster than
    the full gradient, docs/fitting.md). Guards the documented finding."""
    model, state = jc.scenes.cloth(5, 5, dtype=np.float64)
    g = gradient_norms(model, state, jc.PGS(iterations=5, warm_start_gradient=False), DT, [50, 300])
    assert np.all(np.isfinite(g))
    assert g[1] > 1e2 * g[0]


def test_rejects_bad_horizons(cloth):
    model, state = cloth
    with pytest.raises(ValueError, match="horizons"):
        gradient_norms(model, state, jc.PGS(), DT, [200, 50])
    with pytest.raises(ValueError, match="loss"):
        gradient_norms(model, state, jc.PGS(), DT, [10], loss="nope")
