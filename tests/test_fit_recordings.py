"""jc.fit on recordings jaxcon did not make.

The recording (`reference.RECORDING`): a planar double pendulum simulated with SciPy in angle coordinates,
m = 1.0 / 0.7 kg, L = 0.9 / 0.6 m, started mid-swing at angles (1.0, -0.5) rad with angular velocities (1.5, -2.0)
rad/s that the fits do not know, recorded at 30 Hz for 3 s (91 frames, t = 0 included) with 2 mm of Gaussian
noise (seed 23). Fitted with RATTLE at 240 Hz, the solver whose forward error there (0.15 mm RMS with the true
parameters) is below the noise (benchmarks/fit_forward_error.py)."""
import time
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from reference import RECORDING, chain_positions, double_pendulum_recording, pendulum_setup

import jaxcon as jc
from jaxcon.identification import uncertainty as unc
from jaxcon.identification.fit import _Obs, _schedule, _velocity_guess
from jaxcon.identification.params import ParamSet, _Param, default_params, tangent_velocities

DT, EVERY = 1 / 240, 8            # 240 Hz, a frame every 8 steps
L_TRUE, RATIO_TRUE = np.array(RECORDING["lengths"]), RECORDING["masses"][1] / RECORDING["masses"][0]


def _recording():
    t, obs, exact, spec = double_pendulum_recording()
    return obs, np.arange(len(t)) * EVERY


def _first_frame_angles(obs):
    """What a researcher reads off the first frame: the two rods' absolute angles from the downward vertical."""
    x1, x2 = obs[0]
    return np.array([np.arctan2(x1[0], -x1[1]), np.arctan2(x2[0] - x1[0], -(x2[1] - x1[1]))])


def _true_velocities():
    a, w = np.array(RECORDING["angles"]), np.array(RECORDING["omegas"])
    steps = np.stack([np.cos(a), np.sin(a)], -1) * (L_TRUE * w)[:, None]
    return np.cumsum(steps, 0)


@pytest.mark.optimised             # ~90 Levenberg-Marquardt updates over 720 steps
def test_recording_fit_through_setup_reaches_the_noise_floor():
    """Acceptance: lengths within 0.05%, the mass ratio within 0.3%, with converged=True, in
    under 60 s on the 2-core CPU, from lengths (1.0, 0.5), ratio 1 and zero angular velocities; the truth within
    3 std; the errors left are the noise (2 mm, uncorrelated)."""
    obs, ss = _recording()
    a0 = _first_frame_angles(obs)
    theta0 = {"angles": a0, "omegas": np.zeros(2), "lengths": np.array([1.0, 0.5]), "ratio": np.array(1.0)}
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 0.5), masses=(1.0, 1.0), angles=tuple(a0))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error", unc.IdentifiabilityWarning)
        res = jc.fit(model, state, jc.RATTLE(10), DT, obs, theta0, setup=pendulum_setup, observed_particles=[1, 2],
                     sample_steps=ss, transforms={"lengths": "log", "ratio": "log"}, progress=False)
    elapsed = time.perf_counter() - t0
    L, ratio = np.asarray(res.params["lengths"]), float(res.params["ratio"])
    assert res.converged and res.reason == "tolerance", res.reason
    assert np.all(np.abs(L / L_TRUE - 1) < 5e-4), L / L_TRUE - 1
    assert abs(ratio / RATIO_TRUE - 1) < 3e-3, ratio / RATIO_TRUE - 1
    assert elapsed < 60, elapsed
    assert np.all(np.abs(L - L_TRUE) < 3 * np.asarray(res.std["lengths"])), (L - L_TRUE, res.std["lengths"])
    assert abs(ratio - RATIO_TRUE) < 3 * float(res.std["ratio"]), (ratio, res.std["ratio"])
    np.testing.assert_allclose(res.params["omegas"], RECORDING["omegas"], atol=0.02)
    assert 1.8e-3 < res.rms < 2.2e-3 and abs(res.residual_correlation) < 0.2, (res.rms, res.residual_correlation)
    # the stages count frames: the first holds 14 frames (56 coordinates for 7 scalars), not 10 steps (2 frames)
    assert list(np.unique(res.horizons)) == [104, 216, 440, 720]


@pytest.mark.optimised
def test_recording_fit_of_lengths_and_initial_state_from_rest():
    """Acceptance: masses known, params=("rest_length", "x0", "v0") from v0 = 0 (the guess
    comes from the first frames) and lengths (1.0, 0.5) laid out along the first frame's angles: the lengths
    within 0.05% and within 3 std of the truth; the fitted start within 4 std of the true one."""
    obs, ss = _recording()
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 0.5), masses=RECORDING["masses"],
                                             angles=tuple(_first_frame_angles(obs)))
    res = jc.fit(model, state, jc.RATTLE(10), DT, obs, ("rest_length", "x0", "v0"), observed_particles=[1, 2],
                 sample_steps=ss, progress=False)
    L, std = np.asarray(res.params["rest_length"]), res.std
    assert res.converged, res.reason
    assert np.all(np.abs(L / L_TRUE - 1) < 5e-4), L / L_TRUE - 1
    assert np.all(np.abs(L - L_TRUE) < 3 * np.asarray(std["rest_length"]))
    exact0 = double_pendulum_recording()[2][0]
    assert np.all(np.abs(np.asarray(res.params["x0"])[1:] - exact0) < 4 * np.asarray(std["x0"])[1:])
    # v0 comes back without the components along the rods, which RATTLE removes at the first step anyway
    assert np.all(np.abs(np.asarray(res.params["v0"])[1:] - _true_velocities()) < 4 * np.asarray(std["v0"])[1:])
    assert np.all(np.asarray(std["x0"])[0] == 0) and np.all(np.asarray(res.params["x0"])[0] == 0)  # the pivot
    np.testing.assert_allclose(res.state.x, res.params["x0"])


@pytest.mark.optimised
def test_recording_fit_of_both_inverse_masses_warns_that_their_scale_is_not_identifiable():
    """Acceptance: positions alone do not set a mass scale. The fit says so, naming both
    inverse masses, gives them std inf, and does not return a collapsed ratio marked converged (it returns the
    right ratio)."""
    obs, ss = _recording()
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 0.5), masses=(1.0, 1.0),
                                             angles=tuple(_first_frame_angles(obs)))
    with pytest.warns(unc.IdentifiabilityWarning, match=r"\[\+1 log inv_mass\[1\] \+1 log inv_mass\[2\]\]"):
        res = jc.fit(model, state, jc.RATTLE(10), DT, obs, ("rest_length", "inv_mass", "x0", "v0"),
                     observed_particles=[1, 2], sample_steps=ss, progress=False)
    w = np.asarray(res.params["inv_mass"])
    assert np.all(np.isinf(np.asarray(res.std["inv_mass"])[1:])) and res.std["inv_mass"][0] == 0
    assert len(res.unidentified) == 1 and "inv_mass[1]" in res.unidentified[0]
    ratio = w[1] / w[2]                                         # m2 / m1
    assert res.converged and abs(ratio / RATIO_TRUE - 1) < 5e-3, (res.reason, ratio)
    assert np.all(np.isfinite(np.asarray(res.std["rest_length"])))     # the lengths are still determined


@pytest.mark.optimised
def test_recording_fit_without_the_initial_velocities_is_not_converged():
    """RATTLE's default params (no beta: it has none), the unknown initial velocities left at 0: the lengths
    cannot explain the motion. Before, such a fit said converged=True with the lengths off by up to 19%; now
    the errors it leaves (about 0.2 m) are correlated from frame to frame and it says 'misfit'."""
    obs, ss = _recording()
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 0.5), angles=tuple(_first_frame_angles(obs)))
    res = jc.fit(model, state, jc.RATTLE(10), DT, obs, observed_particles=[1, 2], sample_steps=ss, progress=False)
    assert set(res.params) == {"rest_length"}
    assert not res.converged and "misfit" in res.reason and res.residual_correlation > 0.9, res.reason
    assert res.rms > 0.05


# ---- the parts, without compiling -----------------------------------------------------------------------------
def test_default_params_follow_the_solver():
    assert default_params(jc.PGS()) == ("rest_length", "beta")
    assert default_params(jc.Jacobi()) == default_params(jc.Direct()) == ("rest_length", "beta")
    assert default_params(jc.PGS(stabilization="split")) == ("rest_length", "beta")   # beta acts within the slop
    for solver in (jc.RATTLE(), jc.XPBD(), jc.SoftStep(), jc.Penalty()):
        assert default_params(solver) == ("rest_length",), solver


def test_the_growing_horizon_counts_observed_frames():
    """At 240 Hz with a frame every 8 steps, 10 steps hold 2 frames (8 coordinates for 7 or 10 scalars): the
    first stage now holds at least 8 coordinates per fitted scalar, then twice the frames each stage."""
    obs = np.zeros((1, 91, 2, 2))
    ob = _Obs(obs, False, np.array([1, 2]), np.arange(91) * 8, 720)
    assert _schedule("grow", ob, 7) == (104, 216, 440, 720)           # 14, 28, 56 frames, then all 91
    assert _schedule("grow", ob, 10) == (152, 312, 632, 720)          # 20, 40, 80
    # every step observed with many particles: the first 10 steps, as before
    dense = _Obs(np.zeros((1, 240, 9, 2)), False, np.arange(9), np.arange(2, 481, 2), 480)
    assert _schedule("grow", dense, 9) == (10, 20, 40, 80, 160, 320, 480)
    with pytest.raises(ValueError, match=r"first `horizon` stage \(8 steps\) holds 8 observed coordinates for 10"):
        _schedule([8, 720], ob, 10)


def test_initial_velocities_are_guessed_from_the_first_frames():
    obs, ss = _recording()
    model, state = jc.scenes.double_pendulum(lengths=(0.9, 0.6), masses=(1.0, 0.7),
                                             angles=tuple(_first_frame_angles(obs)))
    ob = _Obs(jnp.asarray(obs)[None], False, np.array([1, 2]), ss, int(ss[-1]))
    v = _velocity_guess(model, state, ob, DT)
    assert np.all(v[0] == 0)
    np.testing.assert_allclose(v[1:], _true_velocities(), atol=0.1)
    # consistent with the rods: no velocity along either of them
    np.testing.assert_allclose(tangent_velocities(model, np.asarray(state.x)[None], v[None])[0], v, atol=1e-12)
    d1, d2 = np.asarray(state.x[1]), np.asarray(state.x[2] - state.x[1])
    assert abs(v[1] @ d1) < 1e-12 and abs((v[2] - v[1]) @ d2) < 1e-12


def test_gauss_newton_is_the_least_squares_covariance_and_names_what_is_undetermined():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((200, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.standard_normal(200)
    b, *_ = np.linalg.lstsq(X, y, rcond=None)
    e = X @ b - y
    want = np.sqrt(np.diag(e @ e / (200 - 3) * np.linalg.inv(X.T @ X)))
    scale = 1 / np.sqrt(200)                      # fit's residuals carry 1/sqrt(N): the result does not depend on it
    got = unc.gauss_newton(X * scale, float(np.sum((e * scale) ** 2)), np.ones(3, bool), labels=["a", "b", "c"])
    np.testing.assert_allclose(got.std_u, want, rtol=1e-10)
    assert got.unidentified == ()
    # a parameter that duplicates another: their difference is undetermined, both get std inf, the third not
    X2 = np.c_[X, X[:, 0]]
    got = unc.gauss_newton(X2, float(e @ e), np.ones(4, bool), labels=["a", "b", "c", "a2"])
    assert np.isinf(got.std_u[[0, 3]]).all() and np.isfinite(got.std_u[[1, 2]]).all()
    assert got.unidentified in (("+1 a -1 a2",), ("-1 a +1 a2",)), got.unidentified
    # ... unless that direction is a known gauge (changes nothing any step keeps): dropped, not reported
    gauge = np.array([[1.0], [0.0], [0.0], [-1.0]])
    got = unc.gauss_newton(X2, float(e @ e), np.ones(4, bool), gauge, labels=["a", "b", "c", "a2"])
    assert got.unidentified == () and got.gauge == 1 and np.isfinite(got.std_u).all()
    # an entry that is not fitted (inactive) gets std 0
    got = unc.gauss_newton(X2, float(e @ e), np.array([True, True, True, False]))
    assert got.std_u[3] == 0 and np.isfinite(got.std_u[:3]).all()


def test_values_at_a_bound_of_their_transform_are_found():
    def pset(kind, value, lo=0.0, hi=1.0):
        p = _Param(kind, jnp.ones(np.shape(value), bool), jnp.asarray(value), lo, hi)
        return ParamSet({"p": jnp.asarray(value)}, [p], ["p"], None, True)

    start = {"p": np.zeros(4)}                                                        # log of [1, 1, 1, 1]
    moved = {"p": np.array([0.0, -800.0, np.log(2.6e34), np.log(5e7)])}              # 1, 0, 2.6e34, 5e7
    hits = unc.at_bounds(pset("log", np.ones(4)), moved, start)
    assert [h.split(" =")[0] for h in hits] == ["p[1]", "p[2]"], hits
    assert "2.6e+34" in hits[1] and "log transform" in hits[1]
    beta = pset("logit", 0.2)
    assert unc.at_bounds(beta, {"p": np.array(12.0)}, {"p": np.array(0.0)})          # 1 - 6e-6 of the range
    assert not unc.at_bounds(beta, {"p": np.array(5.0)}, {"p": np.array(0.0)})
    assert not unc.at_bounds(pset("identity", 0.0), {"p": np.array(1e30)}, {"p": np.array(0.0)})


def test_residual_correlation_tells_noise_from_a_misfit():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 3, 91)
    obs = np.sin(t)[None, :, None, None] * np.ones((1, 91, 2, 2))
    assert abs(unc.residual_correlation(2e-3 * rng.standard_normal(obs.shape), obs)) < 0.2
    assert unc.residual_correlation(0.05 * np.cos(3 * t)[None, :, None, None] + 0 * obs, obs) > 0.9
    assert unc.residual_correlation(1e-9 * np.cos(t)[None, :, None, None] + 0 * obs, obs) is None   # exact data
    # beyond chance but below a misfit (PGS(10) at 240 Hz leaves 0.23 on the recording): a MisfitWarning
    err = 2e-3 * rng.standard_normal(obs.shape) + 2e-3 * np.cos(3 * t)[None, :, None, None]
    corr = unc.residual_correlation(err, obs)
    assert 0.21 < corr < 0.5, corr
    with pytest.warns(jc.MisfitWarning, match=r"correlated from frame to frame \(0\.\d\d, beyond chance"):
        unc.warn_misfit(corr, err)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        unc.warn_misfit(0.1, err)                  # within chance: 4 / sqrt(360) = 0.21
        unc.warn_misfit(0.9, err)                  # a misfit fails the fit instead (reason "misfit")


def test_setup_and_params_are_checked_before_anything_is_traced():
    obs, ss = _recording()
    model, state = jc.scenes.double_pendulum(lengths=(0.9, 0.6))
    args = (model, state, jc.RATTLE(), DT, obs)
    kw = dict(observed_particles=[1, 2], sample_steps=ss, progress=False)
    with pytest.raises(TypeError, match="`setup` must return a tuple"):
        jc.fit(*args, {"s": 1.0}, setup=lambda th, m, s, sv: m, **kw)
    with pytest.raises(TypeError, match="`setup` must return a State shaped like `state`"):
        jc.fit(*args, {"s": 1.0}, setup=lambda th, m, s, sv: (m, s.replace(x=s.x[:2], v=s.v[:2]), sv), **kw)
    with pytest.raises(TypeError, match="`setup` must return a RATTLE"):
        jc.fit(*args, {"s": 1.0}, setup=lambda th, m, s, sv: (m, s, jc.PGS()), **kw)
    with pytest.raises(ValueError, match="with `setup=`, `params` must be the initial values theta0"):
        jc.fit(*args, ("rest_length",), setup=pendulum_setup, **kw)
    with pytest.raises(TypeError, match="pass setup=f"):
        jc.fit(*args, {"s": 1.0}, **kw)
    with pytest.raises(ValueError, match=r"transforms.*'scale'.*not a fitted parameter"):
        jc.fit(*args, {"s": 1.0}, setup=lambda th, m, s, sv: (m, s, sv), transforms={"scale": "log"}, **kw)
    with pytest.raises(ValueError, match=r"unknown parameter 'x'.*'x0', 'v0'"):
        jc.fit(*args, ("x",), **kw)


def test_setup_works_with_windows_batches_and_first_order_optimisers():
    """A global scale on all rest lengths (one scalar), a single pendulum from SciPy at two release angles:
    batched, windowed and with Adam at once, through setup= (one small compilation)."""
    t = np.arange(0, 41) * DT
    obs = np.stack([chain_positions([a], [0.8], [1.0], t) for a in (0.5, 1.0)])            # [2, 41, 1, 2]
    model, state = jc.scenes.pendulum(length=1.0, angle=0.5)
    states = jc.State(*(jnp.stack([a, b]) for a, b in zip(
        (state.x, state.v, state.lam), (jc.scenes.pendulum(length=1.0, angle=1.0)[1].x, state.v, state.lam))))

    def scale_all(theta, m, s, sv):                 # lengths and the start laid out with them
        return m.replace(rest_length=theta["scale"] * m.rest_length), s.replace(x=theta["scale"] * s.x), sv

    res = jc.fit(model, states, jc.RATTLE(), DT, obs, {"scale": 1.0}, setup=scale_all, observed_particles=[1],
                 sample_steps=np.arange(41), window=20, transforms={"scale": "log"}, optimizer="adam",
                 learning_rate=0.05, steps=60, progress=False)
    assert abs(float(res.params["scale"]) - 0.8) < 0.01, res.params
    assert res.std is None and res.window_states.x.shape[0] == 2       # no std with windows (docs/fitting.md)
    np.testing.assert_allclose(res.state.x[:, 1], float(res.params["scale"]) * np.asarray(states.x[:, 1]))
