"""Driven systems: `forces` (external forces per step) and `targets` (prescribed paths of the fixed particles) in
`rollout`, `step` and `batched_rollout`.

References: SciPy's DOP853 solution of the pendulum on a moving pivot in its angle coordinate, Kapitza's
stability criterion for the inverted pendulum on a shaken pivot (a^2 w^2 > 2 g L), analytic equilibria and
constant-force motion, and float64 central differences for the gradients.
"""
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxcon as jc

G = 9.81

SOLVERS = {
    "PGS": jc.PGS(iterations=6),
    "Jacobi": jc.Jacobi(iterations=8),
    "XPBD": jc.XPBD(iterations=2, substeps=3),
    "Penalty": jc.Penalty(stiffness=2e4, damping=5.0, substeps=4),
    "Direct": jc.Direct(),
    "SoftStep": jc.SoftStep(substeps=2, hertz=30.0, damping_ratio=1.0),
    "RATTLE": jc.RATTLE(iterations=3),
}


# ---- a pendulum whose pivot moves as x_p = A sin(w t), against SciPy ------------------------------------------
def _moving_pivot_reference(ts, L, A, w, th0, T):
    """Bob positions [len(ts), 2] of a pendulum (length L, angle th from the downward vertical) whose pivot moves
    along x as x_p(t) = A sin(w t). Lagrangian of the bob at (x_p + L sin th, -L cos th):
    m L^2 th'' + m L cos(th) x_p'' + m g L sin(th) = 0, so th'' = -(g sin th + x_p'' cos th) / L with
    x_p'' = -A w^2 sin(w t). Starts at th0 with th' = 0 (the bob moving with the pivot, at A w)."""
    def rhs(t, y):
        return [y[1], -(G * np.sin(y[0]) - A * w * w * np.sin(w * t) * np.cos(y[0])) / L]
    sol = solve_ivp(rhs, (0.0, T), [th0, 0.0], method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True)
    th = sol.sol(ts)[0]
    return np.stack([A * np.sin(w * ts) + L * np.sin(th), -L * np.cos(th)], -1)


def test_pendulum_on_a_moving_pivot_matches_scipy():
    """Measured (float64): PGS(10) 2.0e-3 m at 240 Hz, 1.04e-3 m at 480 Hz (first order, as without a drive);
    RATTLE 3.3e-5 m at 240 Hz (second order: the piecewise-linear pivot path costs it no order). The sign of
    x_p'' matters: with it flipped the reference is 0.78 m away."""
    L, A, w, th0, T = 1.0, 0.1, 5.0, 0.3, 3.0
    model, state = jc.scenes.pendulum(length=L, angle=th0)
    state = state.replace(v=state.v.at[1].set(jnp.array([A * w, 0.0])))
    err = {}
    for name, solver, hz in (("PGS", jc.PGS(iterations=10), 240), ("PGS", jc.PGS(iterations=10), 480),
                             ("RATTLE", jc.RATTLE(), 240)):
        n = int(round(T * hz))
        ts = np.arange(1, n + 1) / hz
        targets = np.stack([A * np.sin(w * ts), 0 * ts], -1)[:, None, :]
        _, tr = jc.rollout(model, state, solver, 1 / hz, n, targets=targets)
        err[name, hz] = np.abs(np.asarray(tr.x[:, 1]) - _moving_pivot_reference(ts, L, A, w, th0, T)).max()
        np.testing.assert_array_equal(np.asarray(tr.x[:, 0]), targets[:, 0])     # the pivot is on its path
    assert err["PGS", 240] < 2.5e-3 and err["RATTLE", 240] < 5e-5, err
    assert 1.8 < err["PGS", 240] / err["PGS", 480] < 2.2, err


# ---- Kapitza's pendulum ------------------------------------------------------------------------------------------
def test_kapitza_inverted_pendulum_stands_when_shaken_fast_enough():
    """An inverted pendulum (L 0.5 m, 0.1 rad off upright) on a pivot shaken vertically, y_p = a cos(w t),
    a = 5 cm: Kapitza's criterion a^2 w^2 > 2 g L asks w > 62.6 rad/s. At w = 120 (a^2 w^2 = 3.7 x 2 g L) it
    swings slowly about the upright (to the other side and back) and never tilts past its start; at w = 40
    (0.41 x 2 g L) it falls. Both hold at 1000, 2000 and 4000 Hz (PGS and RATTLE; measured)."""
    L, a, tilt, hz, T = 0.5, 0.05, 0.1, 2000, 2.0
    x = np.array([[0.0, a], [L * np.sin(tilt), a + L * np.cos(tilt)]])
    model, state = jc.build(x, [1.0, 1.0], rods=[(0, 1)], fixed=[0])
    n = int(T * hz)
    ts = np.arange(1, n + 1) / hz
    run = jax.jit(lambda tg: jc.rollout(model, state, jc.PGS(), 1 / hz, n, targets=tg)[1].x)

    def tilts(w):
        xs = np.asarray(run(np.stack([0 * ts, a * np.cos(w * ts)], -1)[:, None, :]))
        d = xs[:, 1] - xs[:, 0]
        return np.arctan2(d[:, 0], d[:, 1])            # from the upward vertical

    assert (a * 120) ** 2 > 3 * 2 * G * L and (a * 40) ** 2 < 0.5 * 2 * G * L
    up = tilts(120.0)
    assert np.abs(up).max() < 1.05 * tilt and up.min() < -0.5 * tilt, (np.abs(up).max(), up.min())
    assert np.abs(tilts(40.0)).max() > 2.0


# ---- forces, and fixed particles that must not move ---------------------------------------------------------
@pytest.mark.parametrize("name", list(SOLVERS))
def test_forces_hold_and_push_and_an_undriven_fixed_particle_never_moves(name):
    """Particle 0: fixed, with a velocity and a force in its state, and no targets: it never moves. Particle 1
    (2 kg) on a rod from it at 0.5 rad with a horizontal force m g tan(0.5): the equilibrium, it stays there.
    Particle 2 (0.5 kg, free) with a force m (3, g): gravity cancelled, it accelerates at 3 m/s^2 along x,
    x = a T^2 / 2 (symplectic Euler's error a T dt / 2, velocity Verlet's 0)."""
    th, dt, n, acc = 0.5, 1 / 120, 24, 3.0
    x = np.array([[0.0, 0.0], [np.sin(th), -np.cos(th)], [3.0, 1.0]])
    model, state = jc.build(x, [1.0, 2.0, 0.5], rods=[(0, 1)], fixed=[0],
                            velocities=np.array([[1.0, -2.0], [0.0, 0.0], [0.0, 0.0]]))
    forces = np.broadcast_to(np.array([[5.0, 5.0], [2.0 * G * np.tan(th), 0.0], [0.5 * acc, 0.5 * G]]), (n, 3, 2))
    final, tr = jc.rollout(model, state, SOLVERS[name], dt, n, forces=forces)
    assert np.all(np.asarray(tr.x[:, 0]) == 0.0) and np.all(np.asarray(tr.v[:, 0]) == 0.0)
    d = np.asarray(tr.x[:, 1] - tr.x[:, 0])
    np.testing.assert_allclose(np.arctan2(d[:, 0], -d[:, 1]), th, rtol=0, atol=1e-9)
    T = n * dt
    err = np.asarray(final.x[2]) - [3.0 + acc * T * T / 2, 1.0]
    assert abs(err[0]) <= 0.51 * acc * T * dt and abs(err[1]) < 1e-12, err


# ---- gradients with respect to forces and targets ----------------------------------------------------------------
@pytest.mark.parametrize("name", list(SOLVERS))
def test_gradients_wrt_forces_and_targets_match_central_differences(name):
    """A double pendulum whose pivot is driven, started off its rest lengths, 6 steps: the gradient with respect
    to every entry of `forces` [6, 3, 2] and `targets` [6, 1, 2] equals float64 central differences."""
    steps, dt = 6, 1 / 120
    x = np.array([[0.0, 0.0], [0.8, -0.6], [1.5, -1.3]])
    model, state = jc.build(x, [1.0, 1.0, 0.7], rods=[(0, 1), (1, 2)], fixed=[0], rest_lengths=[1.0, 0.95],
                            velocities=np.array([[0.0, 0.0], [0.2, 0.1], [-0.3, 0.2]]))
    rng = np.random.default_rng(0)
    p = {"forces": jnp.asarray(rng.normal(size=(steps, 3, 2))),
         "targets": jnp.asarray(np.cumsum(rng.normal(scale=0.01, size=(steps, 1, 2)), 0))}

    def loss(p):
        _, tr = jc.rollout(model, state, SOLVERS[name], dt, steps, forces=p["forces"], targets=p["targets"])
        w = jnp.linspace(0.5, 1.5, tr.x.size).reshape(tr.x.shape)
        return jnp.sum(w * tr.x ** 2) + jnp.sum(tr.v[-1] ** 2) + jnp.sum(tr.lam) * 10

    g = jax.flatten_util.ravel_pytree(jax.jit(jax.grad(loss))(p))[0]
    flat, unravel = jax.flatten_util.ravel_pytree(p)
    f = jax.jit(lambda q: loss(unravel(q)))
    # XPBD's v = (p - x) / h amplifies rounding: its central differences reach 1e-7 of the gradient at a
    # step of 1e-4 and only 1e-5 at 1e-6 (measured), so it takes the larger step
    eye, e = np.eye(flat.size), 1e-4 if name == "XPBD" else 1e-6
    fd = np.array([(float(f(flat + e * eye[k])) - float(f(flat - e * eye[k]))) / (2 * e) for k in range(flat.size)])
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-7)
    on_pivot = np.asarray(jax.flatten_util.ravel_pytree({"forces": jnp.zeros((steps, 3, 2)).at[:, 0].set(1),
                                                         "targets": jnp.zeros((steps, 1, 2))})[0]) > 0
    assert np.all(np.asarray(g)[on_pivot] == 0)                # a force on a fixed particle does nothing
    assert np.all(np.abs(np.asarray(g)[~on_pivot]) > 1e-6)     # every other input moves the loss


# ---- step, save_every, checkpoint, vmap, batched_rollout -----------------------------------------------------
def _driven_pendulum(dtype=None):
    model, state = jc.build(np.array([[0.0, 0.0], [0.6, -0.8], [1.2, -1.5]]), [1.0, 1.0, 0.5],
                            rods=[(0, 1), (1, 2)], fixed=[0], dtype=dtype)
    rng = np.random.default_rng(1)
    return model, state, rng.normal(size=(3, 8, 3, 2)), np.cumsum(rng.normal(scale=0.02, size=(3, 8, 1, 2)), 1)


@pytest.mark.parametrize("name", ["PGS", "Direct"])       # the batch-minor path, and jax.vmap inside batched_rollout
def test_step_save_every_checkpoint_vmap_and_batched_agree(name):
    model, state, F, X = _driven_pendulum()
    solver, dt = SOLVERS[name], 1 / 120
    finals, trs = zip(*(jc.rollout(model, state, solver, dt, 8, forces=F[b], targets=X[b]) for b in range(3)))
    ref_x = np.stack([np.asarray(t.x) for t in trs])
    s = jc.step(model, state, solver, dt, forces=F[0, 0], targets=X[0, 0])
    np.testing.assert_allclose(np.asarray(s.x), ref_x[0, 0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(s.v[0]), X[0, 0, 0] / dt, rtol=1e-14)   # the pivot's path velocity
    _, tr = jc.rollout(model, state, solver, dt, 8, forces=F[0], targets=X[0], save_every=2, checkpoint=6)
    np.testing.assert_allclose(np.asarray(tr.x), ref_x[0, 1::2], rtol=0, atol=1e-14)
    states = jax.tree.map(lambda a: jnp.stack([a] * 3), state)
    vm = jax.vmap(lambda f, t: jc.rollout(model, state, solver, dt, 8, forces=f, targets=t)[1].x)(F, X)
    np.testing.assert_allclose(np.asarray(vm), ref_x, rtol=0, atol=1e-13)
    _, btr = jc.batched_rollout(model, states, solver, dt, 8, forces=F, targets=X, chunk=2)
    np.testing.assert_allclose(np.asarray(btr.x), ref_x, rtol=0, atol=1e-13)
    _, shared = jc.batched_rollout(model, states, solver, dt, 8, forces=F[1], targets=X[1])   # shared by the batch
    np.testing.assert_allclose(np.asarray(shared.x), np.stack([ref_x[1]] * 3), rtol=0, atol=1e-13)


def test_batched_gradient_and_a_driven_bat_hitting_a_ball():
    """The gradient of a batched rollout with respect to per-copy forces and targets is each copy's own; and a
    fixed particle driven at 2 m/s into a resting ball (no restitution, no gravity) leaves it moving at 2 m/s
    (PGS), the bat's position passes never moving the bat."""
    model, state, F, X = _driven_pendulum()
    states = jax.tree.map(lambda a: jnp.stack([a] * 3), state)

    def batched(F, X):
        return jnp.sum(jc.batched_rollout(model, states, jc.PGS(), 1 / 120, 8, forces=F, targets=X)[0].x ** 2)

    def single(f, x):
        return jnp.sum(jc.rollout(model, state, jc.PGS(), 1 / 120, 8, forces=f, targets=x)[0].x ** 2)

    gb = jax.grad(batched, argnums=(0, 1))(F, X)
    gs = jax.vmap(jax.grad(single, argnums=(0, 1)))(F, X)
    for a, b in zip(gb, gs):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
    u, hz, n = 2.0, 240, 48
    model, state = jc.build(np.array([[0.0, 0.0], [0.5, 0.0]]), [1.0, 1.0], fixed=[0], radius=0.1, collide=True,
                            gravity=0.0)
    ts = np.arange(1, n + 1) / hz
    final, tr = jc.rollout(model, state, jc.PGS(), 1 / hz, n, targets=np.stack([u * ts, 0 * ts], -1)[:, None])
    np.testing.assert_allclose(np.asarray(final.v[1]), [u, 0.0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(final.x[1, 0] - final.x[0, 0]), 0.2, rtol=0, atol=1e-9)


# ---- bad input and dtypes -----------------------------------------------------------------------------------------
def test_bad_forces_and_targets_are_refused_naming_them():
    model, state, F, X = _driven_pendulum()
    solver = jc.PGS()
    cases = [
        (dict(forces=F[0, :7]), "`forces` must have shape \\(steps, n, dim\\) = \\(8, 3, 2\\)"),
        (dict(targets=np.concatenate([X[0], X[0]], 1)), "`targets` must have shape \\(steps, n_fixed, dim\\) = \\(8, 1, 2\\)"),
        (dict(forces=np.where(np.arange(48).reshape(8, 3, 2) == 5, np.nan, F[0])), "`forces` must be finite"),
        (dict(targets=X[0] + np.inf), "`targets` must be finite"),
    ]
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            jc.rollout(model, state, solver, 1 / 120, 8, **kw)
    with pytest.raises(TypeError, match="`forces` must be real"):
        jc.rollout(model, state, solver, 1 / 120, 8, forces=F[0] * 1j)
    with pytest.raises(ValueError, match="`forces` must have shape \\(n, dim\\) = \\(3, 2\\)"):
        jc.step(model, state, solver, 1 / 120, forces=F[0])
    with pytest.raises(ValueError, match="`targets` must have shape \\(batch, steps, n_fixed, dim\\)"):
        jc.batched_rollout(model, jax.tree.map(lambda a: jnp.stack([a] * 3), state), solver, 1 / 120, 8,
                           targets=X[:2])
    free, fstate = jc.build(np.array([[0.0, 0.0], [1.0, 0.0]]), [1.0, 1.0], rods=[(0, 1)])
    with pytest.raises(ValueError, match="`targets` .* no fixed particles"):
        jc.rollout(free, fstate, solver, 1 / 120, 8, targets=X[0])


def test_dtypes_follow_the_state():
    model, state, F, X = _driven_pendulum()
    final, tr = jc.rollout(model, state, jc.PGS(), 1 / 120, 8, forces=F[0], targets=X[0])
    assert final.x.dtype == tr.v.dtype == jnp.float64
    m32, s32, _, _ = _driven_pendulum(np.float32)
    final, tr = jc.rollout(m32, s32, jc.PGS(), 1 / 120, 8, forces=F[0], targets=X[0])
    assert final.x.dtype == final.v.dtype == tr.x.dtype == tr.lam.dtype == jnp.float32
    s = jc.step(m32, s32, jc.PGS(), 1 / 120, forces=F[0, 0], targets=X[0, 0])
    assert s.x.dtype == s.v.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(tr.x[-1, 0]), X[0, -1, 0].astype(np.float32), rtol=0, atol=0)
