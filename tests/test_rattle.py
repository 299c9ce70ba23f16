"""RATTLE: its compliant rows are implicit (a compliant SHAKE, alpha / (h^2 / 2) on the position multiplier, and the
velocity stage's implicit spring), its sweeps run to a tolerance, and its gradients with respect to a compliance
equal float64 central differences. The conformance cells (jaxcon/bench/conformance/cases_rattle.py) check the
stiff set, the cantilever at its minimum, the pendulum's energy and the static column."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.bench.conformance.cases_rattle import _bend
from jaxcon.solvers.rattle import default_tolerance


def _flat_cantilever(n=3, link=0.05, mass=0.01, alpha=0.1):
    """A 2-D cantilever released straight (particles 0 and 1 fixed): it droops and swings on its bending springs."""
    pos = np.stack([link * np.arange(-1, n + 1), np.zeros(n + 2)], 1)
    bend = jc.Constraint(_bend, [(i - 1, i, i + 1) for i in range(1, n + 1)], {}, compliance=alpha, name="bend")
    return jc.build(pos, np.full(n + 2, mass), rods=[(i, i + 1) for i in range(n + 1)], fixed=[0, 1],
                    constraints=[bend])


def test_gradient_with_respect_to_compliance_equals_central_differences():
    """A cantilever of bending springs (alpha 0.1, h omega above 2 at 240 Hz) released straight: its tip's height
    after 30 steps as a function of the springs' compliance, RATTLE at its defaults. jax.grad equals float64
    central differences (the explicit springs' gradient was 1e53 off)."""
    model, state = _flat_cantilever(n=2)
    bend = model.constraints[0]

    def tip(alpha):
        m = model.replace(constraints=(bend.replace(compliance=jnp.full(bend.m, alpha)),))
        final, _ = jc.rollout(m, state, jc.RATTLE(), 1 / 240, 30)
        return final.x[-1, 1]

    a = 0.1
    g = float(jax.jit(jax.grad(tip))(a))
    d = 1e-5 * a
    fd = (float(tip(a + d)) - float(tip(a - d))) / (2 * d)
    assert np.isfinite(g) and abs(fd) > 1e-3          # the tip does depend on the compliance
    assert g == pytest.approx(fd, rel=1e-5)


def test_stiff_compliant_set_is_stable_and_tends_to_the_hard_row():
    """A pendulum on a distance set: alpha 1e-12 (far beyond an explicit spring's limit at 240 Hz) stays bounded
    and stretches at most alpha T (T <= 3 m g); alpha -> 0 gives the hard row's trajectory."""
    x = np.array([[0.0, 0.0], [1.0, 0.0]])

    def length(x, p):
        return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))

    paths = {}
    for alpha in (1e-12, 0.0):
        link = jc.Constraint(length, [[0, 1]], {"L": [1.0]}, compliance=alpha)
        model, state = jc.build(x, 1.0, fixed=[0], constraints=link)
        _, traj = jc.rollout(model, state, jc.RATTLE(), 1 / 240, 240)
        paths[alpha] = np.asarray(traj.x)
    d = np.linalg.norm(paths[1e-12][:, 1], axis=1)
    assert np.max(np.abs(d - 1)) <= 3 * 9.81 * 1e-12 * 1.05
    assert np.max(np.abs(paths[1e-12] - paths[0.0])) < 1e-8


def test_compliant_hanging_mass_is_static_at_alpha_t_with_zero_velocity():
    """A mass on a compliant distance set, started at its analytic rest (stretch alpha m g): RATTLE keeps it
    there (stretch alpha m g within 1e-9 relative) and reports v = 0 and an impulse m g dt per step."""
    alpha, m, dt = 1e-3, 0.5, 1 / 120
    x = np.array([[0.0, 0.0], [0.0, -(1.0 + alpha * m * 9.81)]])

    def length(x, p):
        return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))

    link = jc.Constraint(length, [[0, 1]], {"L": [1.0]}, compliance=alpha)
    model, state = jc.build(x, m, fixed=[0], constraints=link)
    final, traj = jc.rollout(model, state, jc.RATTLE(), dt, 120)
    stretch = np.linalg.norm(np.asarray(traj.x[:, 1]), axis=1) - 1
    np.testing.assert_allclose(stretch, alpha * m * 9.81, rtol=1e-9)
    assert float(np.max(np.abs(np.asarray(traj.v)))) < 1e-9
    np.testing.assert_allclose(np.asarray(traj.lam), m * 9.81 * dt, rtol=1e-9)


def test_default_tolerance_follows_the_dtype():
    assert default_tolerance(np.float64) == 1e-8
    assert default_tolerance(np.float32) == 1e-6
    assert jc.RATTLE().tolerance is None and jc.RATTLE().iterations == 64
    with pytest.raises(ValueError, match="RATTLE: `tolerance` must be >= 0"):
        jc.RATTLE(tolerance=-1.0)


def test_sweeps_stop_at_the_tolerance():
    """The 3-link pendulum: to the default tolerance RATTLE needs fewer sweeps than its default maximum (64), so a
    maximum of 200 gives the same trajectory bitwise (the sweeps after convergence are skipped); 32 is within the
    tolerance of it, and a loose tolerance is not."""
    th = np.array([1.2, 0.6, -0.4])
    pos = np.vstack([[0, 0], np.cumsum(np.stack([0.5 * np.sin(th), -0.5 * np.cos(th)], 1), 0)])
    model, state = jc.build(pos, np.ones(4), rods=[(0, 1), (1, 2), (2, 3)], fixed=[0])
    run = {k: np.asarray(jc.rollout(model, state, s, 1 / 240, 60)[0].x)
           for k, s in (("default", jc.RATTLE()), ("200", jc.RATTLE(200)), ("32", jc.RATTLE(32)),
                        ("loose", jc.RATTLE(tolerance=1e-3)))}
    np.testing.assert_array_equal(run["default"], run["200"])
    assert np.max(np.abs(run["32"] - run["default"])) < 1e-7
    assert np.max(np.abs(run["loose"] - run["default"])) > 1e-6


def test_rod_of_rest_length_zero_holds_its_bob_at_the_pivot():
    """A bob 0.5 m from a fixed pivot on a rod of rest length 0: moved along the start-of-step direction, SHAKE could
    not remove the sideways part gravity adds and the bob was 0.26 m away after 1 s; projected along the current
    direction it is at the pivot after the first step, at rest."""
    model, state = jc.build(np.array([[0.0, 0.0], [0.5, 0.0]]), [1.0, 1.0], rods=[(0, 1)], fixed=[0],
                            rest_lengths=[0.0])
    final, traj = jc.rollout(model, state, jc.RATTLE(), 1 / 240, 240)
    assert float(np.max(np.linalg.norm(np.asarray(traj.x[:, 1]), axis=-1))) < 1e-12
    assert float(np.max(np.abs(np.asarray(final.v)))) < 1e-12
