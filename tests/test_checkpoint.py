"""rollout(..., checkpoint=K): identical values and gradients, less reverse-mode memory."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc


def _setup():
    model, state = jc.scenes.chain(n_links=5, length=1.0, mass=1.0, angle=1.2, dtype=np.float64)
    return model, state


def _loss(model, state, steps, save_every, checkpoint):
    def loss(rest, beta, x0):
        _, tr = jc.rollout(model.replace(rest_length=rest), state.replace(x=x0), jc.PGS(iterations=4, beta=beta),
                           1 / 240, steps, save_every=save_every, checkpoint=checkpoint)
        return jnp.mean(tr.x ** 2) + jnp.mean(tr.lam ** 2) + jnp.mean(tr.v ** 2)
    return loss


@pytest.mark.parametrize("steps,save_every,checkpoint", [(63, 3, 6)])
def test_checkpoint_same_values_and_gradients(steps, save_every, checkpoint):
    model, state = _setup()
    args = (model.rest_length, 0.2, state.x)
    ref_v, ref_g = jax.value_and_grad(_loss(model, state, steps, save_every, None), argnums=(0, 1, 2))(*args)
    v, g = jax.value_and_grad(_loss(model, state, steps, save_every, checkpoint), argnums=(0, 1, 2))(*args)
    np.testing.assert_allclose(v, ref_v, rtol=1e-12, atol=0)
    for a, b in zip(g, ref_g):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    # the recorded trajectory itself is the same array
    f0, t0 = jc.rollout(model, state, jc.PGS(iterations=4), 1 / 240, steps, save_every=save_every)
    f1, t1 = jc.rollout(model, state, jc.PGS(iterations=4), 1 / 240, steps, save_every=save_every,
                        checkpoint=checkpoint)
    assert t1.x.shape == t0.x.shape == (steps // save_every, model.n_particles, 2)
    np.testing.assert_allclose(t1.x, t0.x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(f1.lam, f0.lam, rtol=1e-12, atol=1e-15)


def _grad_temp_bytes(model, state, steps, save_every, checkpoint, remat=None):
    def loss(rest):
        m, solver = model.replace(rest_length=rest), jc.PGS(iterations=5)
        if remat is None:       # what users get
            _, tr = jc.rollout(m, state, solver, 1 / 240, steps, save_every=save_every, checkpoint=checkpoint)
        else:
            from jaxcon.core.sim import _rollout_jit
            _, tr = _rollout_jit(m, state, solver, 1 / 240, steps, save_every, checkpoint, remat)
        return jnp.mean(tr.x ** 2)
    return jax.jit(jax.grad(loss)).lower(model.rest_length).compile().memory_analysis().temp_size_in_bytes


def test_checkpoint_reduces_reverse_mode_memory():
    # 400 steps, every 10th recorded: without checkpointing reverse mode keeps each step's carry (x, v, lam);
    # with checkpoint=50 it keeps 8 chunk boundaries plus one chunk's 50 carries. Measured (x64, CPU):
    # 107 kB against 27 kB.
    model, state = _setup()
    full, ck = (_grad_temp_bytes(model, state, 400, 10, c) for c in (None, 50))
    assert ck < 0.5 * full, (ck, full)


def test_steps_are_rematerialised_in_reverse_mode():
    # each step is recomputed from its carry in the backward pass instead of storing its intermediates (the
    # per-colour frames, biases and every sweep's impulses): measured 107 kB against 476 kB stored
    model, state = _setup()
    remat = _grad_temp_bytes(model, state, 400, 10, None)
    stored = _grad_temp_bytes(model, state, 400, 10, None, remat=False)
    assert remat < 0.5 * stored, (remat, stored)


def test_checkpoint_validation():
    model, state = _setup()
    with pytest.raises(ValueError, match="multiple of `save_every`"):
        jc.rollout(model, state, jc.PGS(), 1 / 240, 20, save_every=2, checkpoint=3)
    with pytest.raises(ValueError, match="checkpoint"):
        jc.rollout(model, state, jc.PGS(), 1 / 240, 20, checkpoint=0)
    with pytest.raises(TypeError, match="checkpoint"):
        jc.rollout(model, state, jc.PGS(), 1 / 240, 20, checkpoint=2.0)
