"""Contacts in `Jacobi` and `SoftStep` against the same analytic answers as PGS (tests/test_contacts.py), in float64.

Jacobi uses PGS's rows, warm start, time-of-impact correction and position pass; with one contact per particle its
mass-splitting relaxation takes the full step, so single contacts match PGS to round-off. SoftStep's contacts are
soft springs while they touch (Box2D v3): a resting contact sinks by the static deflection of that spring, load /
(m_eff omega^2), which the tests below check instead of a zero gap.
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.contact_rows import CONTACT_SLOP
from jaxcon.core import contact_rows as rows_module

G = 9.81
JACOBI, SOFT = jc.Jacobi(20), jc.SoftStep()
SOLVERS = [JACOBI, SOFT]
ids = lambda s: type(s).__name__


def _sink(load_per_mass, hertz):
    """Static deflection of a soft contact: (force / effective mass) / omega^2."""
    return load_per_mass / (2 * math.pi * hertz) ** 2


def _contact_hertz(dt, substeps):
    """SoftStep's default contact stiffness between particles, Box2D's min(30, 0.25 / h); obstacles twice it."""
    return min(30.0, 0.25 * substeps / dt)


@pytest.mark.parametrize("solver", SOLVERS, ids=ids)
@pytest.mark.parametrize("mu, slides", [(0.3, True), (0.6, False)])
def test_incline_slides_with_coulomb_acceleration_or_sticks(solver, mu, slides):
    a = np.pi / 6
    n = np.array([-np.sin(a), np.cos(a)])
    down = -np.array([np.cos(a), np.sin(a)])
    r, dt, m = 0.05, 1 / 240, 2.0
    model, state = jc.build((n * r)[None], m, radius=r, planes=[(n, 0.0)], friction=mu)
    _, traj = jc.rollout(model, state, solver, dt, 240)
    x = np.asarray(traj.x[:, 0])
    speed = np.asarray(traj.v[:, 0]) @ down
    t = dt * np.arange(1, 241)
    # Jacobi: rigid, at the surface; SoftStep: sinks by the static deflection of its 60 Hz obstacle contact
    sink = 0.0 if solver is JACOBI else _sink(G * np.cos(a), 2 * _contact_hertz(dt, solver.substeps))
    gap = x @ n - r
    assert gap.max() < 1e-12 and gap.min() > -sink * (1 + 1e-6) - 1e-12
    if slides:
        np.testing.assert_allclose(speed, G * (np.sin(a) - mu * np.cos(a)) * t, rtol=1e-9)
    else:       # SoftStep creeps while its contact settles into the spring (friction ~ a softer lam_n), then sticks
        creep = (x - n * r) @ down
        assert np.abs(creep).max() < (1e-12 if solver is JACOBI else 0.2 * sink)
        assert np.ptp(creep[60:]) < 1e-12
    cn, ct = np.asarray(traj.contact_n[:, 0]), np.linalg.norm(np.asarray(traj.contact_t[:, 0]), axis=-1)
    np.testing.assert_allclose(cn, m * G * np.cos(a) * dt, rtol=1e-9)              # lam_n = m g cos(a) dt
    np.testing.assert_allclose(ct / cn, mu if slides else np.tan(a), rtol=1e-9)     # on the cone, or inside it


def _apex_heights(traj, r):
    y, v = np.asarray(traj.x[:, 0, 1]) - r, np.asarray(traj.v[:, 0, 1])
    after = np.nonzero((v[1:] > 0) & (v[:-1] <= 0))[0] + 1
    return y[after] + v[after] ** 2 / (2 * G)


def test_bounce_heights_follow_e_squared():
    """Each bounce reaches e^2 of the previous height. The error is first order in the (sub)step: Jacobi at dt
    1/1000 matches PGS to round-off (one contact: its relaxation takes the full step), so PGS's 1.5% bound holds;
    SoftStep's 4 substeps of 1/4000 s give PGS's error at dt 1/4000 (0.29% measured, bound 0.4%)."""
    e, h0, r, dt = 0.8, 0.9, 0.1, 1 / 1000
    model, state = jc.build(np.array([[0.0, h0 + r]]), 1.0, radius=r, planes=[((0.0, 1.0), 0.0)], restitution=e,
                            restitution_threshold=0.01)
    pgs = jc.rollout(model, state, jc.PGS(10), dt, 2500)[1]
    for solver, bound in ((JACOBI, 1.5e-2), (SOFT, 4e-3)):
        _, traj = jc.rollout(model, state, solver, dt, 2500)
        apex = _apex_heights(traj, r)[:5]
        assert len(apex) == 5
        ratio = apex / np.concatenate([[h0], apex[:-1]])
        assert np.abs(ratio / e ** 2 - 1).max() < bound
        assert np.asarray(traj.x[:, 0, 1]).min() > r - _sink(G, 2 * _contact_hertz(dt, 4)) - 1e-12
        if solver is JACOBI:
            np.testing.assert_allclose(np.asarray(traj.x), np.asarray(pgs.x), atol=1e-12)


@pytest.mark.parametrize("solver", SOLVERS, ids=ids)
def test_head_on_elastic_collision_exchanges_velocities(solver):
    x0 = np.array([[0.0, 0.0], [1.0, 0.0]])
    v0 = np.array([[2.0, 0.0], [-1.0, 0.0]])
    model, state = jc.build(x0, 1.0, velocities=v0, radius=0.1, collide=True, restitution=1.0,
                            restitution_threshold=0.0, gravity=np.zeros(2))
    final, _ = jc.rollout(model, state, solver, 1 / 60, 30)
    np.testing.assert_allclose(np.asarray(final.v), v0[::-1], atol=1e-12)
    T, tc = 0.5, 0.8 / 3                        # they touch at tc, then move apart with exchanged velocities
    np.testing.assert_allclose(np.asarray(final.x[:, 0]), [2 * tc - (T - tc), 1 - tc + 2 * (T - tc)], atol=1e-12)


# Jacobi: 2 substeps of 20 iterations (PGS needs 20 sweeps at one substep); SoftStep: 16 substeps with Box2D's
# contact stiffness rule 0.25 / h = 240 Hz (without its 30 Hz cap, a soft 30 Hz contact lets the rack compress).
@pytest.mark.parametrize("solver", [jc.Jacobi(20, substeps=2), jc.SoftStep(substeps=16, contact_hertz=240.0)],
                         ids=ids)
def test_billiards_break_conserves_momentum_and_never_gains_energy(solver):
    model, state = jc.scenes.billiards()
    R = jc.scenes.BALL_RADIUS
    _, traj = jc.rollout(model, state, solver, 1 / 60, 120)
    x = np.concatenate([np.asarray(state.x)[None], np.asarray(traj.x)])
    v = np.concatenate([np.asarray(state.v)[None], np.asarray(traj.v)])
    n = model.n_particles
    cn = np.asarray(traj.contact_n)
    first = int(np.argmax(cn[:, : 4 * n].max(1) > 0))
    assert 0 < first < 100
    p = v.sum(1)
    np.testing.assert_allclose(p[: first + 1], np.broadcast_to(p[0], p[: first + 1].shape), atol=1e-12)
    ke = 0.5 * jc.scenes.BALL_MASS * (v ** 2).sum((1, 2))
    # SoftStep's soft contacts hold energy in their springs and release it in the restitution stage: the kinetic
    # energy alone rose by 6e-5 of the start in one step (kinetic plus stored does not rise); Jacobi's rows are rigid
    assert np.diff(ke).max() <= (1e-4 if isinstance(solver, jc.SoftStep) else 1e-12) * ke[0]
    assert ke[-1] < 0.9 * ke[0]
    d = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1) + np.eye(n)
    assert (2 * R - d).max() < 0.01 * 2 * R                              # never overlap by 1% of a diameter
    assert np.all((x >= R - 0.01 * 2 * R) & (x <= np.array(jc.scenes.TABLE) - R + 0.01 * 2 * R))
    assert cn.min() >= 0
    ct = np.linalg.norm(np.asarray(traj.contact_t), axis=-1)
    assert np.all(ct <= 0.05 * cn + 1e-15)


def _column(n, r=0.1):
    x = np.stack([np.zeros(n), r + 2 * r * np.arange(n)], -1)
    return jc.build(x, 1.0, radius=r, collide=True, planes=[((0.0, 1.0), 0.0)], friction=0.5)


def test_jacobi_brings_a_stack_to_rest():
    """Five balls on the floor, dropped with no warm start: Jacobi's mass splitting (each ball's mass shared by the
    two or three contacts that push on it) brings the column to rest at 40 iterations a step, twice PGS's 20 (with
    20 it keeps oscillating at 0.1 m/s, as PGS does with 5)."""
    n, r, dt = 5, 0.1, 1 / 60
    model, state = _column(n, r)
    final, traj = jc.rollout(model, state, jc.Jacobi(40), dt, 300)
    x, v = np.asarray(traj.x[-60:]), np.asarray(traj.v[-60:])
    assert np.abs(v).max() < 5e-3
    gaps = np.diff(x[..., 1], axis=1) - 2 * r
    # Jacobi keeps PGS's contact slop: a resting contact overlaps by up to CONTACT_SLOP r (measured 5.9e-4 m)
    slop = CONTACT_SLOP * r
    assert gaps.min() > -slop - 1e-3 * 2 * r and x[..., 1].min() > r - slop - 1e-3 * 2 * r
    np.testing.assert_allclose(np.asarray(final.contact_n[0]), n * G * dt, rtol=1e-2)     # the floor holds all


def test_softstep_stack_rests_on_soft_contacts():
    """SoftStep's resting contacts are springs: each gap settles at -(load / effective mass) / omega^2, the floor's
    at 60 Hz holding 5 m g (effective mass m), pair k at 30 Hz holding the 4 - k balls above (effective mass m / 2)."""
    n, r, dt = 5, 0.1, 1 / 60
    model, state = _column(n, r)
    final, traj = jc.rollout(model, state, SOFT, dt, 300)
    y = np.asarray(final.x[:, 1])
    gaps = np.concatenate([[y[0] - r], np.diff(y) - 2 * r])
    hz = _contact_hertz(dt, SOFT.substeps)
    expect = [-_sink(n * G, 2 * hz)] + [-_sink(2 * (n - 1 - k) * G, hz) for k in range(n - 1)]
    np.testing.assert_allclose(gaps, expect, rtol=1e-6)
    assert np.abs(np.asarray(traj.v[-60:])).max() < 1e-8


def test_jacobi_relaxations_converge_on_a_tight_rack():
    """The break's impact step (the cue ball's impulse crossing five rows of balls 0.1 mm apart), solved from the
    state just before it: Jacobi reaches PGS's converged velocities with mass splitting and with a fixed 1/3
    relaxation; it needs 8 to 10 times PGS's iterations to do so (measured: PGS(40) 3e-4 m/s off, Jacobi(40) 0.8).
    Both split their iterations between the compression and the restitution phase, so each phase of Jacobi(640)
    has 320 (Jacobi(320): 7.6e-3 m/s off)."""
    model, state = jc.scenes.billiards()
    before = state.replace(x=state.x.at[0].add(7 / 60 * state.v[0]))     # free flight until step 8's impact
    ref = jc.step(model, before, jc.PGS(1000), 1 / 60).v
    err = lambda s: float(jnp.abs(jc.step(model, before, s, 1 / 60).v - ref).max())
    assert err(jc.Jacobi(640)) < 2e-3
    assert err(jc.Jacobi(640, relaxation=1 / 3)) < 2e-3


@pytest.mark.parametrize("solver, analytic_rtol", [(JACOBI, 0.03), (SOFT, 0.01)], ids=["Jacobi", "SoftStep"])
def test_dropped_ball_gradient_matches_analytic_and_differences(solver, analytic_rtol):
    """An elastic ball dropped from rest bounces at t1 = sqrt(2 h / g) with speed u; at T, d y_T / d y_0 =
    2 g tau / u - 1 (tau = T - t1). First order in the (sub)step: 1.5% off at dt 1/1000 (Jacobi, as PGS), 0.3%
    at SoftStep's substep 1/4000."""
    dt, steps, y0, r = 1 / 1000, 500, 0.5, 0.1

    def y_final(y):
        x = jnp.zeros((1, 2)).at[0, 1].set(y)
        model, state = jc.build(x, 1.0, radius=r, planes=[((0.0, 1.0), 0.0)], restitution=1.0,
                                restitution_threshold=0.0)
        final, _ = jc.rollout(model, state, solver, dt, steps, save_every=steps)
        return final.x[0, 1]

    h0 = y0 - r
    u, t1 = np.sqrt(2 * G * h0), np.sqrt(2 * h0 / G)
    tau = steps * dt - t1
    g = float(jax.grad(y_final)(y0))
    fd = (float(y_final(y0 + 1e-6)) - float(y_final(y0 - 1e-6))) / 2e-6
    assert g == pytest.approx(fd, rel=1e-6)
    assert g == pytest.approx(2 * G * tau / u - 1, rel=analytic_rtol)


@pytest.mark.parametrize("solver", SOLVERS, ids=ids)
def test_collision_gradient_matches_central_differences(solver):
    """Three discs, an off-centre hit with restitution 0.9 and friction 0.2 (the struck ball then hits the third):
    the gradient of the final positions with respect to the cue velocity and the restitution matches float64
    central differences (forward mode here, three inputs; the dropped-ball test above runs reverse mode)."""
    x0 = np.array([[0.0, 0.0], [0.5, 0.05], [0.9, -0.15]])
    wts = jnp.asarray(np.random.default_rng(1).normal(size=x0.shape))

    def loss(p):
        v = jnp.zeros((3, 2)).at[0].set(p[:2])
        model, state = jc.build(x0, 1.0, velocities=v, radius=0.1, collide=True, restitution=p[2], friction=0.2,
                                restitution_threshold=0.0, gravity=np.zeros(2))
        final, _ = jc.rollout(model, state, solver, 1 / 60, 60, save_every=60)
        return jnp.sum(wts * final.x)

    p0 = jnp.array([2.0, 0.1, 0.9])
    g = np.asarray(jax.jacfwd(loss)(p0))
    fd = [(float(loss(p0 + e)) - float(loss(p0 - e))) / 2e-6 for e in 1e-6 * jnp.eye(3)]
    assert np.all(np.isfinite(g)) and np.abs(g).min() > 1e-3
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("solver", SOLVERS, ids=ids)
def test_models_without_contacts_trace_no_contact_code(solver, monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("contact code traced")

    monkeypatch.setattr(rows_module, "rows", boom)
    model, state = jc.scenes.chain(n_links=4)
    jax.make_jaxpr(lambda s: jc.rollout(model, s, solver, 1 / 240, 2))(state)
    model, state = _column(2)
    with pytest.raises(AssertionError, match="contact code traced"):
        jax.make_jaxpr(lambda s: jc.rollout(model, s, solver, 1 / 240, 2))(state)
