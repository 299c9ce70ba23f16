"""Diagnostics of `jc.Constraint` sets: `jc.violation` reports every constraint in lam's order, `diagnose`
holds the hard ones to its limit, and `jc.energy` counts a compliant constraint's potential energy C^2 / (2 alpha)."""
import jax.numpy as jnp
import numpy as np

import jaxcon as jc


def _floor(x, p):
    return x[0, 1]                                  # the height of one particle: C >= 0 keeps it above y = 0


def test_violation_lists_rods_then_every_set_in_lams_order_in_their_own_units():
    """A rod stretched 10%, a hard distance set 0.05 m long, a unilateral floor set 0.02 m under and one 0.3 m
    above: [0.1, 0.05, 0.02, 0] (a rod relative to its length, a set in C's units; a satisfied unilateral row
    is not violated), for one configuration and for a stack of two; NaN for NaN positions, sets included (a C
    that is not finite at finite positions is a degenerate row, reported as 0)."""
    dist = jc.constraints.distance(np.array([[1, 2]]), rest=np.array([0.5]))
    floor = jc.Constraint(_floor, np.array([[2], [3]]), unilateral=True, name="floor")
    x0 = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.5], [3.0, 0.5]])
    model, state = jc.build(x0, 1.0, rods=[(0, 1)], constraints=[dist, floor], fixed=[0])
    x = np.array([[0.0, 1.0], [1.1, 1.0], [1.1, -0.02], [3.0, 0.3]])
    want = [0.1, 1.02 - 0.5, 0.02, 0.0]
    np.testing.assert_allclose(np.asarray(jc.violation(model, x)), want, atol=1e-12)
    both = np.asarray(jc.violation(model, np.stack([x0, x])))
    assert both.shape == (2, 4)
    np.testing.assert_allclose(both[1], want, atol=1e-12)
    np.testing.assert_allclose(both[0], [0, 0, 0, 0], atol=1e-12)
    diverged = np.asarray(jc.violation(model, np.full_like(x, np.nan)))
    assert np.isnan(diverged).all()                 # a diverged run is not reported as satisfied


def test_a_compliant_spring_conserves_the_energy_that_counts_its_stretch():
    """A 1 kg mass on a compliant distance constraint (alpha 1e-3 m/N: k = 1000 N/m) below a pivot, released at
    its rest length, swings down to a stretch of 2 m g / k (analytic: 19.62 mm) and back. `jc.energy` counts
    k s^2 / 2: it equals a hand computation of 1/2 m v^2 + m g y + k s^2 / 2, and stays within 2% of the
    0.19 J the spring exchanges with gravity (XPBD, 100 substeps), where kinetic plus gravitational energy alone
    loses all of it at the bottom. `diagnose` does not count the spring's stretch as a violation (it is
    compliant); its energy gain stays near 0 (the pivot gives the model no rest length for its energy scale;
    the scale was 1e-308 J and the gain -3.8e303)."""
    alpha, m, g = 1e-3, 1.0, 9.81
    spring = jc.constraints.distance(np.array([[0, 1]]), rest=np.ones(1), compliance=alpha)
    model, state = jc.build([[0.0, 0.0], [0.0, -1.0]], [1.0, m], fixed=[0], constraints=[spring])
    final, traj = jc.rollout(model, state, jc.XPBD(substeps=100), 1 / 240, 240)
    x, v = np.asarray(traj.x), np.asarray(traj.v)
    stretch = np.linalg.norm(x[:, 1] - x[:, 0], axis=-1) - 1
    by_hand = 0.5 * m * np.sum(v[:, 1] ** 2, -1) + m * g * x[:, 1, 1] + 0.5 * stretch ** 2 / alpha
    E = np.asarray(jc.energy(model, traj.x, traj.v))
    np.testing.assert_allclose(E, by_hand, rtol=0, atol=1e-12)
    exchanged = 2 * (m * g) ** 2 * alpha
    E0 = float(jc.energy(model, state.x, state.v))
    assert np.abs(E - E0).max() < 0.02 * exchanged
    assert abs(stretch.max() - 2 * m * g * alpha) < 0.01 * 2 * m * g * alpha
    without_spring = 0.5 * m * np.sum(v[:, 1] ** 2, -1) + m * g * x[:, 1, 1]
    assert np.abs(without_spring - E0).max() > 0.9 * exchanged
    d = jc.diagnose(model, traj, state)
    assert float(d.violation.max()) == 0.0 and float(np.asarray(jc.violation(model, traj.x)).max()) > 0.019
    assert not bool(d.diverged) and float(np.abs(d.energy_gain).max()) < 1e-3


def test_diagnose_holds_hard_set_rows_to_the_violation_limit():
    """A hard set (compliance 0) pulled 1.5 rest lengths apart is a violation of 1.5 m that `diagnose` flags
    (over VIOLATION_LIMIT = 1); the same row compliant is not flagged (its stretch is elastic energy, which the
    record starts with)."""
    x0 = np.array([[0.0, 0.0], [1.0, 0.0]])
    far = jnp.asarray(np.array([[[0.0, 0.0], [2.5, 0.0]]]))
    for alpha, flagged in ((0.0, True), (1e-2, False)):
        row = jc.constraints.distance(np.array([[0, 1]]), rest=np.ones(1), compliance=alpha)
        model, state = jc.build(x0, 1.0, constraints=[row], gravity=0.0)
        traj = jc.Trajectory(far, jnp.zeros_like(far), jnp.zeros((1, 1)))
        d = jc.diagnose(model, traj, state.replace(x=far[0]))     # started there: no energy gained
        assert bool(d.diverged) == flagged, alpha
        assert float(d.violation[0]) == (1.5 if flagged else 0.0)
