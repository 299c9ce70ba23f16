"""Split impulses (`stabilization="split"`) for PGS, Jacobi and Direct: position error corrected without kinetic
energy gain, the physical impulse reported, accuracy of Baumgarte's or better, gradients exact.

Baumgarte within an adaptive slop, projection beyond: where a rod's |C| is within its slop (at least 0.5% of its
length, and twice the steady error Baumgarte leaves on its rotation) the velocity solve sees Baumgarte's bias;
beyond it the bias is 0 and the positions are projected back to the rest lengths after the step (PGS, Jacobi:
nonlinear Gauss-Seidel / Jacobi sweeps; Direct: an exact linear correction at Baumgarte's rate). Acceptance scenes: a 20-link chain (2 m, 0.2 kg) at 0.3 rad with every link 25%
too long, with and without a 20:1 end mass, dt 1/240, 1 s; and double pendulums started on the constraint
manifold against SciPy. SWING, the most kinetic energy the chain's swing can supply, is that of the chain at its
rest lengths released at 0.3 rad falling to hanging straight down.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from reference import chain_positions, double_pendulum_positions

DT = 1 / 240
G = 9.81


def _stretched_chain(end_mass=None):
    """The chain at 0.3 rad with rest lengths 0.8 of its links (each link 25% too long), and SWING (J)."""
    model, state = jc.scenes.chain(20, 2.0, 0.2, end_mass=end_mass, angle=0.3)
    hanging = jnp.stack([jnp.zeros(21), -jnp.arange(21) * 0.1], -1)
    swing = float(jc.energy(model, state.x, 0 * state.x) - jc.energy(model, hanging, 0 * state.x))
    return model.replace(rest_length=model.rest_length * 0.8), state, swing


@pytest.mark.parametrize("end_mass, solver, final", [
    (None, jc.PGS(20, stabilization="split"), 3e-3),          # 1.5e-3 measured
    (0.2, jc.PGS(20, stabilization="split"), 1.5e-2),         # 20:1: 7.3e-3 measured (it was 0.82)
    (0.2, jc.Jacobi(20, stabilization="split"), 0.05),        # 20:1, Jacobi: 2.6e-2 measured (it was 0.19)
    (0.2, jc.Direct(stabilization="split"), 1e-4),            # 1.5e-5 measured
], ids=["PGS", "PGS-20to1", "Jacobi-20to1", "Direct-20to1"])
def test_stretched_chain_corrects_without_energy_gain(end_mass, solver, final):
    model, state, swing = _stretched_chain(end_mass)
    assert float(jnp.max(jc.violation(model, state.x))) > 0.24
    _, tr = jc.rollout(model, state, solver, DT, 240)
    stretch = np.asarray(jnp.max(jc.violation(model, tr.x), -1))
    ke = np.asarray(jc.kinetic_energy(model, tr.v))
    assert stretch[-1] < final, stretch[-1]
    assert stretch[-24:].max() < max(4 * final, 2 * stretch[-1])     # settled, not passing through
    assert ke.max() <= swing, (ke.max(), swing)
    assert ke.max() > 0.5 * swing                        # it does swing: the bound is not met by standing still
    # the same chain with Baumgarte: the position error becomes kinetic energy, tens of times the swing's
    _, tb = jc.rollout(model, state, solver.replace(stabilization="baumgarte"), DT, 240)
    assert float(jnp.max(jc.kinetic_energy(model, tb.v))) > 10 * swing


def _mid_swing_double_pendulum():
    """Issue 22's double pendulum: m = (1, 0.7) kg, L = (0.9, 0.6) m, started mid-swing (angles and angular
    velocities), on the constraint manifold. Returns (model, state, angles, omegas, lengths, masses)."""
    L, M = np.array([0.9, 0.6]), np.array([1.0, 0.7])
    th, om = np.array([1.2, -0.4]), np.array([1.5, -2.0])
    u = np.stack([np.sin(th), -np.cos(th)], -1) * L[:, None]
    du = np.stack([np.cos(th), np.sin(th)], -1) * (L * om)[:, None]
    x = np.concatenate([np.zeros((1, 2)), np.cumsum(u, 0)])
    v = np.concatenate([np.zeros((1, 2)), np.cumsum(du, 0)])
    model, state = jc.build(x, np.r_[1.0, M], rods=[(0, 1), (1, 2)], fixed=[0], velocities=v)
    return model, state, th, om, L, M


@pytest.mark.parametrize("hz", [240, 960])
def test_split_is_as_accurate_as_baumgarte_without_position_error(hz):
    """On the manifold there is nothing to correct, and split must not lose accuracy. A plain split solve kept
    J v = 0, so every step moved the bobs along the tangent and the next step took the outward velocity away (289
    mm against Baumgarte's 16.7 mm at 240 Hz); within the slop split is Baumgarte, to the digit here."""
    model, state, th, om, L, M = _mid_swing_double_pendulum()
    steps = 3 * hz
    ref = chain_positions(th, L, M, np.arange(1, steps + 1) / hz, omegas=om)
    err = {}
    for cls in (jc.PGS, jc.Jacobi, jc.Direct):
        for stab in ("baumgarte", "split"):
            solver = cls(10, stabilization=stab) if cls is not jc.Direct else cls(stabilization=stab)
            _, tr = jc.rollout(model, state, solver, 1 / hz, steps)
            err[cls.__name__, stab] = np.sqrt(np.mean(np.sum((np.asarray(tr.x[:, 1:]) - ref) ** 2, -1)))
    for name in ("PGS", "Jacobi", "Direct"):
        assert err[name, "split"] <= 1.2 * err[name, "baumgarte"], err
    assert err["PGS", "split"] < (1.6e-2 if hz == 240 else 2.5e-3), err   # measured 14.6 mm and 1.9 mm


@pytest.mark.parametrize("solver", [jc.PGS(5, stabilization="split"), jc.Jacobi(10, stabilization="split"),
                                    jc.Direct(stabilization="split")], ids=lambda s: type(s).__name__)
def test_split_impulse_is_the_physical_force(solver):
    """A mass hanging at rest: lam / dt = m g (no Baumgarte term mixed in), and nothing moves. Direct's
    relative regularisation (1e-6 of the diagonal) shows in its first step only."""
    model, state = jc.scenes.pendulum(length=0.7, mass=2.5, angle=0.0)
    _, tr = jc.rollout(model, state, solver, DT, 30)
    rtol = 1.01e-6 if isinstance(solver, jc.Direct) else 1e-9
    np.testing.assert_allclose(np.asarray(tr.lam) / DT, 2.5 * G, rtol=rtol)
    np.testing.assert_allclose(np.asarray(tr.x[-1]), np.asarray(state.x), atol=1e-12)


def test_split_reports_velocity_impulse_only_and_ropes_never_push():
    """A rope stretched 20% at rest: the position pass pulls it back in the first step, but lam (the velocity
    impulse) only holds the weight, m g dt; a slack rope gets no correction and no impulse. (Rope 2 starts slack,
    and particle 1 is pulled 0.2 m up, away from it: 0.25 m of slack that particle 2 falls through freely until
    the rope catches it.)"""
    x = np.array([[0.0, 0.0], [0.0, -1.2], [0.0, -1.25]])
    model, state = jc.build(x, [1.0, 2.0, 1.0], ropes=[(0, 1), (1, 2)], fixed=[0], rest_lengths=[1.0, 0.5])
    _, tr = jc.rollout(model, state, jc.PGS(30, beta=0.2, stabilization="split"), DT, 60)
    lam = np.asarray(tr.lam)
    d = np.linalg.norm(np.asarray(tr.x[:, 1] - tr.x[:, 0]), axis=-1)
    np.testing.assert_allclose(d, 1.0, atol=1e-9)                          # corrected at once, and kept
    assert lam.min() >= 0
    np.testing.assert_allclose(lam[:10, 0] / DT, 2.0 * G, rtol=1e-6)        # the weight of particle 1 alone
    d2 = np.linalg.norm(np.asarray(tr.x[:, 2] - tr.x[:, 1]), axis=-1)
    k = int(np.argmax(d2 >= 0.5 * (1 - 1e-9)))                               # first step that ends taut
    assert k >= 5 and np.all(lam[:k, 1] == 0)                               # slack: no impulse
    y2 = np.asarray(tr.x[:k, 2, 1])                                         # ... and exact free fall
    np.testing.assert_allclose(y2, -1.25 - G * DT ** 2 * np.arange(1, k + 1) * np.arange(2, k + 2) / 2, rtol=1e-12)
    assert lam[-1, 1] > 0                                                   # then it catches


def test_split_pgs_converges_to_the_reduced_ode():
    """Double pendulum against SciPy's DOP853: split impulses converge at first order in dt."""
    angles, lengths, masses = (0.5, 0.5), (1.0, 1.0), (1.0, 1.0)
    ref = double_pendulum_positions(angles, lengths, masses, [1.0])[0]
    model, state = jc.scenes.double_pendulum(lengths, masses, angles)
    errors = []
    dts = [1 / 240, 1 / 480, 1 / 960]
    for dt in dts:
        final, _ = jc.rollout(model, state, jc.PGS(50, beta=0.2, stabilization="split"), dt, int(round(1 / dt)))
        errors.append(np.abs(np.asarray(final.x[1:]) - ref).max())
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert 0.8 < slope < 1.3 and errors[-1] < 3e-3, (errors, slope)


@pytest.mark.parametrize("solver", [jc.PGS(8, stabilization="split"), jc.Jacobi(8, stabilization="split"),
                                    jc.Direct(stabilization="split", substeps=2)],
                         ids=lambda s: type(s).__name__)
def test_split_gradients_match_finite_differences(solver):
    """Reverse mode through split impulses against float64 central differences: rest lengths, the initial
    positions and beta, from a violated start (10%: beyond the slop, so the position pass is active in the first
    steps, and Baumgarte's bias within the slop after it)."""
    model, state = jc.scenes.chain(3, 1.2, 0.6, angle=0.8)
    state = state.replace(x=state.x * 1.1)
    w = jnp.array([0.7, -1.3])

    def loss(rest, x0, beta):
        final, _ = jc.rollout(model.replace(rest_length=rest), state.replace(x=x0), solver.replace(beta=beta), DT, 12)
        return jnp.sum(final.x[1:] * w)

    rest, x0, beta = model.rest_length, state.x, 0.25
    g_rest, g_x, g_beta = jax.grad(loss, argnums=(0, 1, 2))(rest, x0, beta)
    f = jax.jit(loss)
    e = 1e-6
    fd_rest = [(f(rest.at[k].add(e), x0, beta) - f(rest.at[k].add(-e), x0, beta)) / (2 * e) for k in range(3)]
    fd_x = [(f(rest, x0.at[p, a].add(e), beta) - f(rest, x0.at[p, a].add(-e), beta)) / (2 * e)
            for p, a in ((1, 0), (2, 1), (3, 0))]
    np.testing.assert_allclose(g_rest, fd_rest, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose([g_x[1, 0], g_x[2, 1], g_x[3, 0]], fd_x, rtol=1e-6, atol=1e-8)
    fd_beta = (f(rest, x0, beta + e) - f(rest, x0, beta - e)) / (2 * e)
    np.testing.assert_allclose(g_beta, fd_beta, rtol=1e-6, atol=1e-8)
    assert np.abs(np.asarray(g_rest)).max() > 1e-2


def test_split_works_in_float32_and_under_vmap():
    model, state = jc.scenes.chain(5, 1.0, 0.5, angle=0.5, dtype=np.float32)
    state = state.replace(x=state.x * 1.2)
    solver = jc.PGS(10, stabilization="split")
    final, tr = jc.rollout(model, state, solver, DT, 60)
    assert final.x.dtype == jnp.float32 and tr.lam.dtype == jnp.float32
    assert float(jnp.max(jc.violation(model, final.x))) < 0.01
    scales = jnp.array([0.9, 1.0, 1.1], jnp.float32)
    finals, _ = jax.vmap(lambda a: jc.rollout(model.replace(rest_length=a * model.rest_length), state, solver, DT,
                                              20))(scales)
    one, _ = jc.rollout(model.replace(rest_length=scales[2] * model.rest_length), state, solver, DT, 20)
    np.testing.assert_allclose(np.asarray(finals.x[2]), np.asarray(one.x), rtol=1e-6, atol=1e-6)


def test_split_is_refused_where_it_cannot_apply():
    with pytest.raises(ValueError, match="stabilization"):
        jc.PGS(stabilization="Split")
    with pytest.raises(ValueError, match="stabilization"):
        jc.Direct(stabilization="soft")
    with pytest.raises(ValueError, match="implicit"):
        jc.PGS(implicit=True, stabilization="split")


def test_baumgarte_default_is_unchanged():
    """The default is the textbook method: explicit 'baumgarte' gives bitwise the same rollout."""
    model, state = jc.scenes.chain(6, 1.2, 0.6, angle=0.8)
    for cls in (jc.PGS, jc.Jacobi, jc.Direct):
        a, _ = jc.rollout(model, state, cls(), DT, 20)
        b, _ = jc.rollout(model, state, cls(stabilization="baumgarte"), DT, 20)
        np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
