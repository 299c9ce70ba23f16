"""Penalty, Jacobi and XPBD solvers and `diagnose`, checked against independent references: a SciPy DOP853
reduced-coordinate double pendulum, analytic statics, PGS's fixed point and float64 central differences."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from reference import double_pendulum_positions

G = 9.81


# ---- reference ---------------------------------------------------------------------------------------------
def double_pendulum_reference(angles, t_end, lengths=(1.0, 1.0), masses=(1.0, 1.0), g=G):
    """Bob positions [2, 2] at t_end (the shared SciPy DOP853 reference, rtol = atol = 1e-12)."""
    return double_pendulum_positions(angles, lengths, masses, [t_end], g)[0]


# Position error at t = 1 s on the mild double pendulum must stay below SLOPE * dt (all three are first order
# in dt). Constants: measured error / dt times about 1.5 (measured: Jacobi 0.76, XPBD(10 substeps) 0.29,
# Penalty(1e7 N/m, 100 substeps) 0.008 at dt = 1/120 .. 1/960; Penalty's spring error floor, about 4e-6 m
# at 1e7 N/m, is reached only below dt = 1/1000).
DP_SOLVERS = {
    "jacobi": (jc.Jacobi(iterations=20, beta=0.2), 1.2),
    "xpbd": (jc.XPBD(iterations=1, compliance=0.0, substeps=10), 0.45),
    "penalty": (jc.Penalty(stiffness=1e7, damping=0.0, substeps=100), 0.012),
}


@pytest.mark.parametrize("name", list(DP_SOLVERS))
def test_double_pendulum_against_dop853(name):
    solver, slope = DP_SOLVERS[name]
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    ref = double_pendulum_reference((0.5, 0.5), 1.0)
    errs = []
    for n in (120, 240):
        final, traj = jc.rollout(model, state, solver, 1.0 / n, n)
        err = float(np.max(np.abs(np.asarray(final.x[1:]) - ref)))
        assert err < slope / n, (name, n, err)
        assert not bool(jc.diagnose(model, traj, state).diverged)
        errs.append(err)
    # first order: halving dt roughly halves the error
    ratios = np.array(errs[1:]) / np.array(errs[:-1])
    assert np.all((ratios > 0.35) & (ratios < 0.65)), (name, errs)


# ---- statics -----------------------------------------------------------------------------------------------
HANG = {
    "jacobi": jc.Jacobi(iterations=20),
    "xpbd": jc.XPBD(iterations=2, substeps=5),
    "penalty": jc.Penalty(stiffness=1e6, damping=200.0, substeps=20),
}


@pytest.mark.parametrize("name", list(HANG))
def test_hanging_mass_tension_is_mg(name):
    """Two masses hanging at rest, one on a rod and one on a rope: after a second, force = lam / dt = m g."""
    masses, dt = np.array([1.0, 2.0, 1.0, 0.5]), 1 / 240
    x = np.array([[0.0, 0.0], [0.0, -1.0], [1.0, 0.0], [1.0, -0.7]])
    model, state = jc.build(x, masses, rods=[(0, 1)], ropes=[(2, 3)], fixed=[0, 2])
    _, traj = jc.rollout(model, state, HANG[name], dt, 240)
    force = np.asarray(traj.lam[-1]) / dt
    np.testing.assert_allclose(force, masses[[1, 3]] * G, rtol=1e-6)


def test_xpbd_compliance_gives_the_spring_stretch():
    """A mass m on a rod of compliance a hangs at the stretch a m g (Hooke); started there, it stays there."""
    mass, a, L = 2.0, 1e-4, 1.0
    stretch = a * mass * G
    model, state = jc.build(np.array([[0.0, 0.0], [0.0, -(L + stretch)]]), np.array([1.0, mass]),
                            rods=[(0, 1)], fixed=[0], rest_lengths=np.array([L]))
    _, traj = jc.rollout(model, state, jc.XPBD(iterations=4, compliance=a, substeps=4), 1 / 60, 60)
    d = np.linalg.norm(np.asarray(traj.x[:, 1] - traj.x[:, 0]), axis=-1)
    np.testing.assert_allclose(d - L, stretch, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(traj.lam[:, 0]) * 60, mass * G, rtol=1e-6)


# ---- ropes -------------------------------------------------------------------------------------------------
ROPE_SOLVERS = {
    "jacobi": jc.Jacobi(iterations=20),
    "xpbd": jc.XPBD(iterations=1, substeps=8),
    "penalty": jc.Penalty(stiffness=1e5, damping=10.0, substeps=20),
}


@pytest.mark.parametrize("name", list(ROPE_SOLVERS))
def test_ropes_never_push(name):
    """Bobs thrown upward: the ropes go slack (zero impulse, shorter than rest), then snap taut; the impulse is
    never negative."""
    x = np.array([[0.0, 0.0], [0.3, -0.4], [0.6, -0.8]])
    v = np.array([[0.0, 0.0], [0.0, 4.0], [1.0, 5.0]])
    model, state = jc.build(x, np.array([1.0, 1.0, 0.5]), ropes=[(0, 1), (1, 2)], fixed=[0], velocities=v)
    _, traj = jc.rollout(model, state, ROPE_SOLVERS[name], 1 / 240, 240)
    lam = np.asarray(traj.lam)
    assert lam.min() >= 0.0
    d = np.linalg.norm(np.asarray(traj.x[:, model.pairs[:, 1]] - traj.x[:, model.pairs[:, 0]]), axis=-1)
    slack = d < 0.9 * 0.5
    assert slack.any() and np.all(lam[slack] == 0)  # a slack rope transmits nothing
    assert lam.max() > 0  # and it does pull once taut
    assert not bool(jc.diagnose(model, traj, state).diverged)


# ---- Jacobi vs PGS -----------------------------------------------------------------------------------------
def test_jacobi_converges_to_pgs_fixed_point():
    model, state = jc.scenes.chain(5, 1.0, 1.0, angle=0.7, dtype=np.float64)
    rng = np.random.default_rng(0)
    state = state.replace(v=jnp.asarray(rng.normal(size=state.v.shape)).at[0].set(0.0))
    pgs = jc.step(model, state, jc.PGS(iterations=3000, warm_start=False), 1 / 60)
    jac = jc.step(model, state, jc.Jacobi(iterations=3000, warm_start=False), 1 / 60)
    few = jc.step(model, state, jc.Jacobi(iterations=5, warm_start=False), 1 / 60)
    np.testing.assert_allclose(jac.v, pgs.v, atol=1e-10)
    np.testing.assert_allclose(jac.lam, pgs.lam, atol=1e-10)
    assert np.abs(few.v - pgs.v).max() > 1e-3  # not trivially equal: 5 Jacobi iterations are far off


# ---- gradients ----------------------------------------------------------------------------------------------
# Against central differences for every input of every solver (Jacobi's beta and relaxation, XPBD's compliance,
# Penalty's stiffness and damping included): tests/test_gradients_all_solvers.py.


# ---- Penalty stability limit -------------------------------------------------------------------------------
def test_penalty_above_stability_limit_is_flagged_not_nan():
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float32)
    solver = jc.Penalty(stiffness=1e6, damping=0.0)
    h_max = solver.stability_limit(model)
    # Gershgorin bound: max(w_i deg_i + w_j deg_j) = 1 * 2 + 1 * 1 for the second rod; the exact limit of
    # this two-spring chain is 2 / sqrt(2.618 k), between 1.0 and 1.07 of it
    np.testing.assert_allclose(h_max, 2 / np.sqrt(1e6 * 3.0), rtol=1e-12)
    stable = jax.jit(lambda dt: jc.rollout(model, state, solver, dt, 400))
    _, ok = stable(0.7 * h_max)
    assert not bool(jc.diagnose(model, ok, state).diverged)
    _, bad = stable(1.5 * h_max)
    d = jc.diagnose(model, bad, state)
    assert bool(d.diverged) and 0 <= int(d.first_bad) < 50
    assert np.isfinite(np.asarray(bad.x)).all()  # clipped: a finite blow-up, reported

    def loss(rest):
        final, _ = jc.rollout(model.replace(rest_length=rest), state, solver, 1.5 * h_max, 400)
        return jnp.sum(final.x ** 2)

    with pytest.warns(RuntimeWarning, match="stability limit"):      # said before tracing, not silently
        g = jax.grad(loss)(model.rest_length)
    assert np.isfinite(np.asarray(g)).all()


# ---- diagnose ----------------------------------------------------------------------------------------------
def test_diagnose_values_and_jit():
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    _, traj = jc.rollout(model, state, jc.XPBD(substeps=10), 1 / 240, 100)
    d = jc.diagnose(model, traj, state)
    dj = jax.jit(jc.diagnose)(model, traj, state)
    np.testing.assert_allclose(d.violation, dj.violation)
    np.testing.assert_allclose(d.violation, np.max(np.asarray(jc.violation(model, traj.x)), -1))
    np.testing.assert_allclose(d.energy, jc.energy(model, traj.x, traj.v))
    assert not bool(d.diverged) and int(d.first_bad) == -1
    # a NaN at step 37 is reported there
    nan_traj = traj.replace(v=traj.v.at[37:, 1, 0].set(jnp.nan))
    dn = jax.jit(jc.diagnose)(model, nan_traj, state)
    assert bool(dn.diverged) and int(dn.first_bad) == 37
    # a 150% stretch, and an energy gain, each on its own
    far = traj.replace(x=traj.x.at[60:, 2].multiply(3.0))
    assert int(jc.diagnose(model, far, state).first_bad) == 60
    fast = traj.replace(v=traj.v.at[80:, 2, 0].set(100.0), x=traj.x)
    df = jc.diagnose(model, fast, state)
    assert int(df.first_bad) == 80 and float(df.violation.max()) < 1e-3
    with pytest.raises(TypeError, match="traj"):
        jc.diagnose(model, state)


# ---- argument checking -------------------------------------------------------------------------------------
@pytest.mark.parametrize("make, exc, match", [
    (lambda: jc.Jacobi(iterations=0), ValueError, "iterations"),
    (lambda: jc.Jacobi(iterations=2.0), TypeError, "iterations"),
    (lambda: jc.Jacobi(beta=1.5), ValueError, "beta"),
    (lambda: jc.Jacobi(relaxation=0.0), ValueError, "relaxation"),
    (lambda: jc.Jacobi(relaxation=3.0), ValueError, "relaxation"),
    (lambda: jc.Jacobi(warm_start=1), TypeError, "warm_start"),
    (lambda: jc.XPBD(substeps=0), ValueError, "substeps"),
    (lambda: jc.XPBD(iterations=None), TypeError, "iterations"),
    (lambda: jc.XPBD(compliance=-1e-3), ValueError, "compliance"),
    (lambda: jc.XPBD(compliance=np.ones(3)), ValueError, "compliance"),
    (lambda: jc.Penalty(stiffness=0.0), ValueError, "stiffness"),
    (lambda: jc.Penalty(stiffness=np.nan), ValueError, "stiffness"),
    (lambda: jc.Penalty(damping=-1.0), ValueError, "damping"),
    (lambda: jc.Penalty(substeps=1.5), TypeError, "substeps"),
])
def test_bad_arguments_raise(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def test_jacobi_warns_of_a_relaxation_that_can_diverge():
    """A fixed relaxation at or above 2 / (largest number of constraints at a particle) is warned of before
    tracing: on a cloth (8 rods at an interior particle) 0.5 overshoots, and a draped 6x6 cloth ran to NaN with
    it. Below the bound, on the cloth or on a chain (2 at a particle), there is no warning."""
    import warnings
    cloth, cloth_state = jc.scenes.cloth(4, 4)
    chain, chain_state = jc.scenes.chain(n_links=3)
    with pytest.warns(RuntimeWarning, match=r"relaxation=0.5 is at or above 2 / 8 = 0.25"):
        jc.rollout(cloth, cloth_state, jc.Jacobi(4, relaxation=0.5), 1 / 240, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jc.rollout(cloth, cloth_state, jc.Jacobi(4, relaxation=0.2), 1 / 240, 2)
        jc.rollout(chain, chain_state, jc.Jacobi(4, relaxation=0.9), 1 / 240, 2)
        jc.rollout(cloth, cloth_state, jc.Jacobi(4), 1 / 240, 2)


def test_solvers_take_traced_parameters_under_vmap():
    model, state = jc.scenes.pendulum(angle=0.5, dtype=np.float64)
    comps = jnp.array([0.0, 1e-3])
    finals = jax.vmap(lambda a: jc.rollout(model, state, jc.XPBD(compliance=a, substeps=4), 1 / 60, 30)[0])(comps)
    one = jc.rollout(model, state, jc.XPBD(compliance=1e-3, substeps=4), 1 / 60, 30)[0]
    np.testing.assert_allclose(finals.x[1], one.x, rtol=1e-12)
    assert np.abs(finals.x[0] - finals.x[1]).max() > 1e-4


def test_plain_scatter_add_reference_is_the_same_pgs():
    """The bench's gradient-compile reference (jaxcon.bench.references.plain_pgs) computes what jc.PGS computes: same final state
    and gradient on a small cloth, so the compile-time comparison is like for like."""
    from jaxcon.bench.references.plain_pgs import plain_pgs_rollout
    model, state = jc.scenes.cloth(5, 4, dtype=np.float64)
    t = model.topology

    def ours(rest):
        final, _ = jc.rollout(model.replace(rest_length=rest), state, jc.PGS(6, beta=0.2), 1 / 240, 15)
        return final.x

    def plain(rest):
        return plain_pgs_rollout(state.x, state.v, state.lam, model.inv_mass, rest, t.i, t.j, t.colour,
                                 model.gravity, 0.2, 1 / 240, 15, 6)[0]

    rest = model.rest_length * 0.97
    np.testing.assert_allclose(np.asarray(ours(rest)), np.asarray(plain(rest)), rtol=0, atol=1e-12)
    g1 = jax.grad(lambda r: jnp.sum(ours(r)[..., 2]))(rest)
    g2 = jax.grad(lambda r: jnp.sum(plain(r)[..., 2]))(rest)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g2), rtol=1e-9, atol=1e-12)
