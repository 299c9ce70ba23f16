"""Contacts in XPBD (position-level contacts, Mueller et al. 2020) and Penalty (spring-dashpot contacts), in
float64, against the same analytic answers as PGS's tests (tests/test_contacts.py): a ball at rest on a floor,
incline acceleration g (sin a - mu cos a) or sticking, bounce heights e^2k, velocity exchange in a head-on
elastic collision, a billiards break's momentum, energy and overlap, and gradients against central
differences and the analytic stopping distance."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core import contact_rows as rows_module
from jaxcon.solvers import contact as contact_module
from jaxcon.solvers import penalty as penalty_module

G = 9.81
PENALTY = jc.Penalty(stiffness=1e5, substeps=8)          # dt 1/240: h = 0.52 ms, its stability limit 2.6 ms
SOLVERS = [jc.XPBD(), jc.RATTLE(), PENALTY]
#: RATTLE's contacts are XPBD's rows at position level in its SHAKE stage and their velocity pass after its
#: velocity stage, in one step of h: the tests of both run them against the same references.
POSITION_LEVEL = [jc.XPBD(), jc.RATTLE()]


def _ball(y0, *, v0=0.0, e=0.0, mu=0.0, r=0.1, threshold=0.0, gravity=None):
    x = jnp.zeros((1, 2)).at[0, 1].set(y0)
    v = jnp.zeros((1, 2)).at[0, 1].set(v0)
    return jc.build(x, 1.0, velocities=v, radius=r, planes=[((0.0, 1.0), 0.0)], restitution=e, friction=mu,
                    restitution_threshold=threshold, gravity=gravity)


def _check_impulses(traj, mu):
    cn, ct = np.asarray(traj.contact_n), np.linalg.norm(np.asarray(traj.contact_t), axis=-1)
    assert cn.min() >= 0
    assert np.all(ct <= mu * cn * (1 + 1e-12) + 1e-15)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_dropped_ball_comes_to_rest_on_the_floor(solver):
    """Dropped from 0.4 m above the floor, 2 s. XPBD and RATTLE (the same contact rows at position level)
    never let it below the floor and it rests exactly on it; Penalty rests at the spring's static sink m g / k
    and its deepest overlap during the impact stays below the undamped u sqrt(m / k) (8.9 mm; 2.5 mm measured,
    critical damping at e = 0)."""
    dt, k = 1 / 240, float(PENALTY.stiffness)
    model, state = _ball(0.5)
    final, traj = jc.rollout(model, state, solver, dt, 480)
    gap = np.asarray(traj.x[:, 0, 1]) - 0.1
    if not isinstance(solver, jc.Penalty):
        assert gap.min() > -1e-12 and abs(gap[-1]) < 1e-12
    else:
        u = np.sqrt(2 * G * 0.4)
        assert gap.min() > -u * np.sqrt(1 / k)
        assert float(final.x[0, 1]) - 0.1 == pytest.approx(-G / k, rel=1e-6)
    assert np.abs(np.asarray(final.v)).max() < 1e-9
    np.testing.assert_allclose(np.asarray(traj.contact_n[-1]), G * dt, rtol=1e-9)       # lam_n = m g dt
    _check_impulses(traj, 0.0)


@pytest.mark.parametrize("solver", POSITION_LEVEL, ids=lambda s: type(s).__name__)
@pytest.mark.parametrize("mu, slides", [(0.3, True), (0.6, False)])
def test_position_level_incline_slides_with_coulomb_acceleration_or_sticks(solver, mu, slides):
    """Static friction at position level, dynamic friction in the velocity pass (XPBD's substeps, RATTLE's
    SHAKE and velocity stages): sliding at g (sin 30 - mu cos 30) (to 1e-9, measured 1e-11) for mu = 0.3, held
    to 1e-6 m over 1 s for mu = 0.6 (measured 0)."""
    a = np.pi / 6
    n = np.array([-np.sin(a), np.cos(a)])
    down = -np.array([np.cos(a), np.sin(a)])
    r, dt = 0.05, 1 / 240
    model, state = jc.build((n * r)[None], 2.0, radius=r, planes=[(n, 0.0)], friction=mu)
    _, traj = jc.rollout(model, state, solver, dt, 240)
    t = dt * np.arange(1, 241)
    if slides:
        speed = np.asarray(traj.v[:, 0]) @ down
        np.testing.assert_allclose(speed, G * (np.sin(a) - mu * np.cos(a)) * t, rtol=1e-9)
    else:
        assert np.abs(np.asarray(traj.x[:, 0]) - n * r).max() < 1e-6
    assert np.abs(np.asarray(traj.x[:, 0]) @ n - r).max() < 1e-12
    cn, ct = np.asarray(traj.contact_n[:, 0]), np.linalg.norm(np.asarray(traj.contact_t[:, 0]), axis=-1)
    np.testing.assert_allclose(cn, 2.0 * G * np.cos(a) * dt, rtol=1e-9)
    np.testing.assert_allclose(ct / cn, mu if slides else np.tan(a), rtol=1e-9)


@pytest.mark.parametrize("mu, slides", [(0.3, True), (0.6, False)])
def test_penalty_incline_slides_or_holds(mu, slides):
    """Regularised Coulomb friction capped so that it never reverses the slip: sliding at the Coulomb
    acceleration once the normal spring has settled (1e-9), and, as mu f_n h / slip_velocity exceeds the
    particle's mass here, held exactly once the normal spring has loaded (no drift over the last 0.9 s, to
    1e-9 m; it slides 65 um in the first 15 ms, while the normal force builds up from zero; with
    slip_velocity = 1 cm/s it would creep at about 1 cm/s)."""
    a = np.pi / 6
    n = np.array([-np.sin(a), np.cos(a)])
    down = -np.array([np.cos(a), np.sin(a)])
    r, dt = 0.05, 1 / 240
    model, state = jc.build((n * r)[None], 2.0, radius=r, planes=[(n, 0.0)], friction=mu)
    _, traj = jc.rollout(model, state, PENALTY, dt, 240)
    t = dt * np.arange(1, 241)
    speed = np.asarray(traj.v[:, 0]) @ down
    if slides:
        slope = np.polyfit(t[60:], speed[60:], 1)[0]
        assert slope == pytest.approx(G * (np.sin(a) - mu * np.cos(a)), rel=1e-9)
    else:
        drift = (np.asarray(traj.x[:, 0]) - n * r) @ down
        assert np.abs(drift).max() < 1e-4 and np.ptp(drift[24:]) < 1e-9
    _check_impulses(traj, mu)


def _apex_ratios(traj, r, h0, count):
    """Ratios of successive flight tops, from each state just after the ball leaves the floor (no contact
    impulse after one): y + v^2 / (2 g) is exact for a ballistic flight."""
    y, v = np.asarray(traj.x[:, 0, 1]) - r, np.asarray(traj.v[:, 0, 1])
    cn = np.asarray(traj.contact_n[:, 0])
    leave = np.nonzero((cn[1:] == 0) & (cn[:-1] > 0) & (v[1:] > 0))[0] + 1
    apex = (y[leave] + v[leave] ** 2 / (2 * G))[:count]
    assert len(apex) == count
    return apex / np.concatenate([[h0], apex[:-1]])


@pytest.mark.parametrize("solver", POSITION_LEVEL, ids=lambda s: type(s).__name__)
def test_position_level_bounce_heights_follow_e_squared(solver):
    """e = 0.8, dt 1/1000: each bounce reaches e^2 of the previous height, never below the floor. XPBD (10
    substeps) to 0.2% (measured 0.08%; 0.6% with one substep: the impact is resolved at the end of its substep),
    RATTLE (one step) to 0.5% (measured 0.4%)."""
    e, h0 = 0.8, 0.9
    model, state = _ball(h0 + 0.1, e=e, threshold=0.01)
    _, traj = jc.rollout(model, state, solver, 1 / 1000, 2500)
    ratio = _apex_ratios(traj, 0.1, h0, 5)
    assert np.abs(ratio / e ** 2 - 1).max() < (5e-3 if isinstance(solver, jc.RATTLE) else 2e-3)
    assert np.asarray(traj.x[:, 0, 1]).min() > 0.1 - 1e-12


@pytest.mark.parametrize("e", [0.5, 0.8])
def test_penalty_first_bounce_has_the_model_restitution(e):
    """Penalty's contact damping is set from `restitution` (a clamped linear spring-dashpot): the first bounce
    rebounds with e to 2% (measured 0.497 and 0.7998; gravity during the contact lowers later, slower bounces
    a little more)."""
    h0 = 0.9
    model, state = _ball(h0 + 0.1, e=e)
    _, traj = jc.rollout(model, state, jc.Penalty(stiffness=1e5, substeps=10), 1 / 1000, 1500)
    ratio = _apex_ratios(traj, 0.1, h0, 1)
    assert np.sqrt(ratio[0]) == pytest.approx(e, rel=0.02)
    _check_impulses(traj, 0.0)


@pytest.mark.parametrize("solver, position_tol", [(jc.XPBD(substeps=7), 3.0 * (1 / 60) / 7), (jc.RATTLE(), 1e-12)],
                         ids=["XPBD", "RATTLE"])
def test_position_level_head_on_elastic_collision_exchanges_velocities(solver, position_tol):
    """Equal discs, e = 1, dt 1/60: the velocities are exchanged (1e-12), 3 N s of impulse, and the positions are
    those of an impact at the right time: XPBD's to within one substep's relative travel (there is no
    time-of-impact correction), RATTLE's to 1e-12 (measured 4e-16: its drift at the mean velocity puts them
    there)."""
    x0 = np.array([[0.0, 0.0], [1.0, 0.0]])
    v0 = np.array([[2.0, 0.0], [-1.0, 0.0]])
    model, state = jc.build(x0, 1.0, velocities=v0, radius=0.1, collide=True, restitution=1.0,
                            restitution_threshold=0.0, gravity=np.zeros(2))
    final, traj = jc.rollout(model, state, solver, 1 / 60, 30)
    np.testing.assert_allclose(np.asarray(final.v), v0[::-1], atol=1e-12)
    T, tc = 0.5, 0.8 / 3
    exact = np.array([2 * tc - (T - tc), 1 - tc + 2 * (T - tc)])
    assert np.abs(np.asarray(final.x[:, 0]) - exact).max() <= position_tol
    assert np.sum(np.asarray(traj.contact_n)) == pytest.approx(3.0, rel=1e-12)        # m |dv| = 3 N s


@pytest.mark.parametrize("solver, kept", [(jc.XPBD(substeps=20), (0.7, 0.85)), (jc.RATTLE(10), None)],
                         ids=["XPBD", "RATTLE"])
def test_position_level_billiards_break_conserves_momentum_and_never_gains_energy(solver, kept):
    """dt 1/60, 2 s: momentum to 1e-11 until the first cushion contact (measured 1e-13 XPBD, 9e-14 RATTLE), no
    step gains kinetic energy (measured at most +9e-15 XPBD, +3e-16 RATTLE of the initial energy: roundoff), no
    two balls ever overlap by 1% of a diameter with XPBD(substeps=20) (measured: never at a recorded step), 4%
    with RATTLE(10) (measured 2.9%: its one step of dt moves a ball up to two
    diameters, and the position pass's speculative normals stop the pair that used to pass through each other in
    the break, 0.6% before, in a cluster its sweeps leave under-converged). XPBD's break keeps 76% of the kinetic
    energy after it (PGS: 89%): its restitution comes from sequential impacts through the rack
    (`contact_rows.chain_bounces`; 45% when each contact bounced on its own approach speed at the start of the
    substep, 0 for racked balls)."""
    model, state = jc.scenes.billiards()
    dt, R = 1 / 60, jc.scenes.BALL_RADIUS
    _, traj = jc.rollout(model, state, solver, dt, 120)
    x = np.concatenate([np.asarray(state.x)[None], np.asarray(traj.x)])
    v = np.concatenate([np.asarray(state.v)[None], np.asarray(traj.v)])
    n = model.n_particles
    cn = np.asarray(traj.contact_n)
    first = int(np.argmax(cn[:, : 4 * n].max(1) > 0))
    assert 0 < first < 100
    p = v.sum(1)
    np.testing.assert_allclose(p[: first + 1], np.broadcast_to(p[0], p[: first + 1].shape), atol=1e-11)
    ke = 0.5 * jc.scenes.BALL_MASS * (v ** 2).sum((1, 2))
    assert np.diff(ke).max() <= 1e-12 * ke[0]
    if kept is not None:
        assert kept[0] < ke[10] / ke[0] < kept[1]            # after the break (documented above)
    d = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1) + np.eye(n)
    assert (2 * R - d).max() < (0.01 if kept is not None else 0.04) * 2 * R
    assert np.all((x >= R - 1e-9) & (x <= np.array(jc.scenes.TABLE) - R + 1e-9))
    _check_impulses(traj, 0.05)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_sliding_to_rest_distance_and_gradients(solver):
    """A particle sliding on the floor at v0 stops after v0^2 / (2 mu g) (0.2%; measured 0.08% XPBD, 0.09%
    Penalty), and the gradients with respect to v0 and mu match central differences (1e-6) and the analytic
    ones (0.5%). XPBD's differences agree to 2e-5 only (measured 4.5e-6 for mu): its positions carry roundoff
    of about 1e-11 m from v = (p - x) / h, and a larger step straddles the small jumps of its piecewise map
    (the substep in which the particle sticks changes with mu).

    RATTLE takes XPBD's contact rows in one step of h (no substeps): kinetic friction acts in its velocity stage,
    after the drift, so the particle slides v0 h / 2 further, v0^2 / (2 mu g) + v0 h / 2 (to 1e-4, measured
    3e-5), and the derivative of where it stops within its last step differs from the continuous one by up to
    a step's share, mu g h / v0 = 0.8% here (2%; measured 0.3% for v0, 1.3% for mu)."""
    dt, steps = 1 / 240, 480

    def stop(p):
        x = jnp.zeros((1, 2)).at[0, 1].set(0.1)
        model, state = jc.build(x, 1.0, velocities=jnp.stack([jnp.stack([p[0], 0.0])]), radius=0.1,
                                planes=[((0.0, 1.0), 0.0)], friction=p[1])
        final, _ = jc.rollout(model, state, solver, dt, steps, save_every=steps)
        return final.x[0, 0]

    v0, mu = 2.0, 0.4
    p = jnp.array([v0, mu])
    f = jax.jit(stop)
    if isinstance(solver, jc.RATTLE):
        assert float(f(p)) == pytest.approx(v0 ** 2 / (2 * mu * G) + v0 * dt / 2, rel=1e-4)
    else:
        assert float(f(p)) == pytest.approx(v0 ** 2 / (2 * mu * G), rel=2e-3)
    g = np.asarray(jax.grad(stop)(p))
    fd = [(float(f(p + d)) - float(f(p - d))) / 2e-6 for d in 1e-6 * jnp.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=2e-5 if isinstance(solver, jc.XPBD) else 1e-6)
    np.testing.assert_allclose(g, [v0 / (mu * G), -(v0 ** 2) / (2 * mu ** 2 * G)],
                               rtol=2e-2 if isinstance(solver, jc.RATTLE) else 5e-3)


@pytest.mark.parametrize("solver", [jc.XPBD(), jc.RATTLE(), jc.Penalty(stiffness=1e5, substeps=20)],
                         ids=lambda s: type(s).__name__)
def test_glancing_collision_gradient_matches_differences(solver):
    """Two discs of different masses in a glancing collision (the line of motion misses the other centre by a
    quarter of the contact distance) with restitution and friction: d(final positions) / d(initial velocity)
    against central differences (1e-6). The map is smooth here; XPBD's is only piecewise smooth (the impact
    jumps a substep as the timing moves), so a difference step must not straddle such a jump. A start moving
    exactly along the line of centres would sit on a kink (zero tangential velocity, where friction switches
    direction): there the derivative is one-sided and which side the gradient takes follows rounding."""
    def loss(v0):
        x0 = jnp.array([[0.0, 0.0], [1.0, 0.05]])
        model, state = jc.build(x0, jnp.array([1.0, 2.0]), velocities=jnp.zeros((2, 2)).at[0].set(v0),
                                radius=0.1, collide=True, restitution=0.7, restitution_threshold=0.0,
                                friction=0.1, gravity=np.zeros(2))
        final, _ = jc.rollout(model, state, solver, 1 / 60, 36, save_every=36)
        return jnp.sum(final.x * jnp.array([[1.0, 2.0], [-0.5, 3.0]]))

    v0 = jnp.array([2.0, 0.0])
    value_and_grad = jax.jit(jax.value_and_grad(loss))     # also the differences' loss: one compilation
    f = lambda v: value_and_grad(v)[0]                      # noqa: E731
    g = np.asarray(value_and_grad(v0)[1])
    fd = [(float(f(v0 + d)) - float(f(v0 - d))) / 2e-5 for d in 1e-5 * jnp.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_gradients_finite_through_onset_separation_and_sticking(solver):
    def loss(p):
        y0, e, mu, r, off = p
        x = jnp.stack([jnp.stack([0.0, y0])])
        model, state = jc.build(x, 1.0, velocities=np.array([[1.5, 0.0]]), radius=r, planes=[((0.0, 1.0), off)],
                                restitution=e, friction=mu, restitution_threshold=0.2)
        _, traj = jc.rollout(model, state, solver, 1 / 120, 120)
        return jnp.sum(traj.x ** 2) + jnp.sum(traj.v ** 2)

    g = np.asarray(jax.grad(loss)(jnp.array([0.4, 0.5, 0.3, 0.1, 0.0])))
    assert np.all(np.isfinite(g)) and np.all(g != 0)


def test_penalty_stability_limit_counts_contacts():
    """A lone ball on the floor is a spring k to a fixed body, critically damped at e = 0: the limit is
    2 / sqrt(k / m) (sqrt(2) - 1). A model without rods no longer fails there, and a rollout above it warns."""
    model, state = _ball(0.5)
    limit = PENALTY.stability_limit(model)
    assert limit == pytest.approx(2 / np.sqrt(1e5) * (np.sqrt(2) - 1), rel=1e-9)
    with pytest.warns(RuntimeWarning, match="stability limit"):
        jc.rollout(model, state, jc.Penalty(stiffness=1e5), 1 / 240, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jc.rollout(model, state, PENALTY, 1 / 240, 2)


def test_models_without_contacts_trace_no_contact_code(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("contact code traced")

    # every contact stage a solver's one (sub)step can reach: the rows, their warm start and sweeps at velocity
    # and position level, the time of impact and the position pass (`contact.sweep` itself returns at once
    # without contacts, so its rows' update is patched)
    monkeypatch.setattr(rows_module, "rows", boom)
    for name in ("warm_start", "_solve_row", "jacobi_pass", "jacobi_counts", "soft_rows", "position_pass",
                 "position_velocity_pass", "impact_times", "project_overlaps"):
        monkeypatch.setattr(contact_module, name, boom)
    monkeypatch.setattr(penalty_module, "_contact_impulses", boom)
    chain, chain_state = jc.scenes.chain(n_links=4)
    ball, ball_state = _ball(0.5)
    # every solver that takes contacts (PGS plain and split, Jacobi, SoftStep, XPBD, RATTLE, Penalty); 3 steps: a
    # call no other test makes, so it is traced, not cached
    for solver in [jc.PGS(4), jc.PGS(4, stabilization="split"), jc.Jacobi(4), jc.SoftStep()] + SOLVERS:
        jax.make_jaxpr(lambda s, solver=solver: jc.rollout(chain, s, solver, 1 / 240, 3))(chain_state)
        with pytest.raises(AssertionError, match="contact code traced"):
            jax.make_jaxpr(lambda s, solver=solver: jc.rollout(ball, s, solver, 1 / 240, 3))(ball_state)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_contacts_with_rods_a_falling_chain(solver):
    """Rods and contacts in one model: a chain dropped on the floor lands on it (no link below the floor by
    more than 1 mm) with its links at length (2%)."""
    model, state = jc.scenes.falling_chain(n_links=6)
    r = float(model.radius[0])
    if isinstance(solver, jc.Penalty):
        solver = jc.Penalty(stiffness=1e5, substeps=int(np.ceil(1 / 240 / solver.stability_limit(model))) + 1)
    final, traj = jc.rollout(model, state, solver, 1 / 240, 480)
    assert np.asarray(traj.x[..., 1]).min() > r - 1e-3
    d = np.linalg.norm(np.diff(np.asarray(final.x), axis=0), axis=-1)
    np.testing.assert_allclose(d, np.asarray(model.rest_length), rtol=0.02)
    _check_impulses(traj, float(model.friction))


@pytest.mark.parametrize("solver", [jc.PGS(8), jc.Jacobi(12, relaxation=0.4), jc.SoftStep(), jc.XPBD(), jc.RATTLE(),
                                    PENALTY], ids=lambda s: type(s).__name__)
def test_a_contact_that_never_touches_changes_no_constraint_row(solver):
    """Every solver runs one (sub)step whether or not the model has contacts: a floor 100 m below a swinging
    chain of rods and a compliant user-written spring adds the contact kind's stages, which must leave every
    constraint row as it was. Found by this test: Jacobi's iteration with contacts used to treat a set's
    compliant rows as hard (it ignored their spring)."""
    x = np.array([[0.0, 0.0], [0.6, -0.3], [1.1, -0.9], [1.5, -1.6]])
    spring = jc.constraints.distance([[2, 3]], rest=[0.7], compliance=1e-3, name="spring")
    kw = dict(rods=[(0, 1), (1, 2)], fixed=[0], constraints=[spring])
    plain, state = jc.build(x, [1.0, 0.8, 1.3, 0.6], **kw)
    floored, floored_state = jc.build(x, [1.0, 0.8, 1.3, 0.6], planes=[((0.0, 1.0), -100.0)], radius=0.05, **kw)
    final, traj = jc.rollout(plain, state, solver, 1 / 240, 40)
    final_f, traj_f = jc.rollout(floored, floored_state, solver, 1 / 240, 40)
    np.testing.assert_allclose(traj_f.x, traj.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj_f.lam, traj.lam, rtol=0, atol=1e-12)
    assert np.abs(np.asarray(traj_f.contact_n)).max() == 0
    stretch = np.linalg.norm(np.asarray(traj.x[-1, 3] - traj.x[-1, 2])) - 0.7
    assert abs(stretch) > 1e-4          # the spring is soft enough to stretch: a hard row would not
