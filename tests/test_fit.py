"""Acceptance tests of jc.fit: data made here with known parameters, recovered from noisy positions."""
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxcon as jc
from jaxcon.core.pytree import pytree_dataclass
from jaxcon.identification.experiments import chain_identification

DT = 1 / 240


def _chain_experiment(seed=0, n=20, beta=0.2):
    return chain_identification(n=n, seed=seed, beta=beta, dt=DT)


def test_fit_chain_rest_lengths_and_beta():
    guess, state, true_L, obs = _chain_experiment()
    t0 = time.perf_counter()
    res = jc.fit(guess, state, jc.PGS(iterations=10, beta=0.3), DT, obs, ("rest_length", "beta"),
                 optimizer="lm", steps=40, patience=5, progress=False)
    elapsed = time.perf_counter() - t0
    assert elapsed < 60, elapsed
    assert np.max(np.abs(res.model.rest_length / true_L - 1)) < 0.01
    assert abs(float(res.solver.beta) / 0.2 - 1) < 0.01
    # the loss reached the noise floor (1 mm^2 per coordinate), from well above it
    assert res.history[0] > 50e-6 and res.history.min() < 1.1e-6
    assert res.iterations == len(res.history) <= 40
    # the fitted model is a valid model with the same topology
    assert res.model.topology == guess.topology and isinstance(res.solver, jc.PGS)


def test_fit_with_adam_decreases_loss_and_compiles_once():
    guess, state, true_L, obs = _chain_experiment(n=5)
    traces = []
    orig = jc.PGS._step

    def counting(self, *a):
        traces.append(1)
        return orig(self, *a)

    jc.PGS._step = counting
    try:
        res = jc.fit(guess, state, jc.PGS(iterations=10, beta=0.2), DT, obs[:60], ("rest_length",),
                     optimizer=optax.adam(1e-3), steps=30, patience=100, progress=False)
    finally:
        jc.PGS._step = orig
    # one trace for the update function (value and gradient share the forward trace), not one per iteration
    assert 1 <= len(traces) <= 2, len(traces)
    assert res.iterations == 30 and not res.converged
    assert res.history[-1] < 0.5 * res.history[0]
    err0 = np.abs(guess.rest_length / true_L - 1).max()
    assert np.abs(res.model.rest_length / true_L - 1).max() < err0


def test_fit_observed_subset_batch_and_sample_steps():
    """Two trajectories from two initial states, observing particles 2 and 5 every 4th step; fit inv_mass of
    the end bob and gravity."""
    model, state = jc.scenes.chain(n_links=5, length=1.0, mass=1.0, angle=0.8, dtype=np.float64)
    truth = model.replace(inv_mass=model.inv_mass.at[5].set(1 / 0.6), gravity=jnp.array([0.0, -9.5]))
    states = jax.tree.map(lambda *a: jnp.stack(a), state,
                          state.replace(v=state.v.at[3].set(jnp.array([0.5, 0.0]))))
    solver = jc.PGS(iterations=20, beta=0.2)
    _, tr = jax.vmap(lambda s: jc.rollout(truth, s, solver, DT, 120))(states)
    ss = np.arange(4, 121, 4)
    obs = tr.x[:, ss - 1][:, :, [2, 5]]
    # only mass ratios are observable (scaling every mass leaves the motion unchanged), and the fit says so
    with pytest.warns(jc.IdentifiabilityWarning, match=r"log inv_mass\[1\].*log inv_mass\[5\]"):
        res = jc.fit(model, states, solver, DT, obs, ("inv_mass", "gravity"), observed_particles=[2, 5],
                     sample_steps=ss, optimizer="lm", steps=30, patience=5, progress=False)
    assert np.all(np.isinf(np.asarray(res.std["inv_mass"])[1:])) and np.isfinite(np.asarray(res.std["gravity"])).all()
    w, wt = np.asarray(res.model.inv_mass), np.asarray(truth.inv_mass)
    np.testing.assert_allclose(w[1:] / w[1], wt[1:] / wt[1], rtol=1e-4)
    assert res.model.inv_mass[0] == 0       # the fixed pivot stays fixed (log transform keeps zeros)
    np.testing.assert_allclose(res.model.gravity, truth.gravity, atol=1e-4)


@pytest.mark.optimised             # up to 60 Levenberg-Marquardt iterations over 480 steps
def test_fit_double_pendulum_lengths_with_windows():
    """A chaotic double pendulum observed for 2 s: fitted with windows of 0.25 s (multiple shooting)."""
    model, state, solver, obs, guess, true_lengths = _double_pendulum_experiment()
    res = jc.fit(guess, state, solver, DT, obs, ("rest_length",), window=60, optimizer="lm", steps=60,
                 patience=5, progress=False)
    np.testing.assert_allclose(res.model.rest_length, true_lengths, rtol=0.01)
    assert res.window_states is not None and res.window_states.x.shape == (7, 3, 2)


def _double_pendulum_experiment():
    rng = np.random.default_rng(1)
    true_lengths = (0.9, 0.6)
    model, state = jc.scenes.double_pendulum(lengths=true_lengths, masses=(1.0, 1.0), angles=(1.5, 2.5))
    solver = jc.PGS(iterations=10, beta=0.2)
    _, tr = jc.rollout(model, state, solver, DT, 480)
    obs = tr.x + 1e-3 * rng.standard_normal(tr.x.shape)
    return model, state, solver, obs, model.replace(rest_length=jnp.array([1.0, 0.5])), true_lengths


# ---- acceptance: default arguments from the nominal start -----------------------------------------
@pytest.mark.optimised             # hundreds of iterations of one program
def test_defaults_fit_a_chain_released_from_a_violated_start():
    """8 links of nominal 0.25 m, true lengths perturbed by up to 10%, true beta 0.35, released at 1 rad from
    positions laid out with the nominal lengths (every link starts up to 10% off its rest length), PGS(10)
    data, every 2nd step of 1 s observed with 1 mm noise. From the nominal lengths and beta 0.2, with default
    arguments: lengths within 1%, beta within 5%. The default grows the horizon (10, 20, ..., 160, 240 steps),
    with Levenberg-Marquardt (9 fitted scalars), compiling once."""
    from jaxcon.identification.experiments import violated_chain_identification
    guess, state, true_L, obs, ss = violated_chain_identification()
    traces = []
    orig = jc.PGS._step

    def counting(self, *a):
        traces.append(1)
        return orig(self, *a)

    jc.PGS._step = counting
    try:
        t0 = time.perf_counter()
        res = jc.fit(guess, state, jc.PGS(10, beta=0.2), DT, obs, ("rest_length", "beta"), sample_steps=ss,
                     progress=False)
        elapsed = time.perf_counter() - t0
    finally:
        jc.PGS._step = orig
    assert np.max(np.abs(np.asarray(res.model.rest_length) / true_L - 1)) < 0.01
    assert abs(float(res.solver.beta) / 0.35 - 1) < 0.05
    assert res.converged and res.reason == "tolerance"
    assert list(np.unique(res.horizons)) == [10, 20, 40, 80, 160, 240] and res.horizons[-1] == 240
    assert res.iterations == len(res.history) == len(res.horizons)
    # compiled once for all stages: the update traces the rollout a fixed number of times (LM: the residuals,
    # their forward-mode Jacobian and the trial step), not once per stage or iteration
    assert len(traces) <= 3, len(traces)
    assert elapsed < 60, elapsed          # the budget set on the 2-core CPU (about 5 s measured)


def test_defaults_fit_double_pendulum_lengths_from_two_seconds():
    model, state, solver, obs, guess, true_lengths = _double_pendulum_experiment()
    res = jc.fit(guess, state, solver, DT, obs, ("rest_length",), progress=False)
    np.testing.assert_allclose(res.model.rest_length, true_lengths, rtol=0.01)
    assert res.converged and res.horizons[-1] == 480


@pytest.mark.optimised             # hundreds of iterations of one program
def test_defaults_fit_cloth_rest_lengths_from_nominal():
    """16x16 cloth (930 edges), every edge's rest length perturbed by up to 5% (median 2.5% off), all particles
    observed for 0.5 s with 1 mm noise, data and fit with XPBD(1 iteration, 4 substeps). From the NOMINAL
    lengths with default arguments (Adam: 930 fitted scalars): median error under 2%. The cloth is
    over-constrained (930 edges, 762 degrees of freedom), so individual lengths are only partly identifiable."""
    rng = np.random.default_rng(0)
    model, state = jc.scenes.cloth(nx=16, ny=16, size=1.0, mass=1.0)
    true_L = model.rest_length * (1 + rng.uniform(-0.05, 0.05, model.n_constraints))
    solver = jc.XPBD(iterations=1, compliance=0.0, substeps=4)
    _, tr = jc.rollout(model.replace(rest_length=true_L), state, solver, DT, 120)
    obs = np.asarray(tr.x) + 1e-3 * rng.standard_normal(tr.x.shape)
    res = jc.fit(model, state, solver, DT, obs, ("rest_length",), progress=False)
    err = np.abs(np.asarray(res.model.rest_length) / np.asarray(true_L) - 1)
    err_nominal = np.abs(np.asarray(model.rest_length) / np.asarray(true_L) - 1)
    assert np.median(err) < 0.02, np.median(err)
    assert np.median(err) < 0.75 * np.median(err_nominal), (np.median(err), np.median(err_nominal))
    assert min(res.history) < 0.5 * res.history[0]


def test_fit_validation():
    model, state = jc.scenes.pendulum(dtype=np.float64)
    obs = np.zeros((10, 2, 2))
    with pytest.raises(ValueError, match="unknown parameter 'length'"):
        jc.fit(model, state, jc.PGS(), DT, obs, ("length",), progress=False)
    with pytest.raises(ValueError, match="observed_particles"):
        jc.fit(model, state, jc.PGS(), DT, obs, observed_particles=[1], progress=False)
    with pytest.raises(ValueError, match="window"):
        jc.fit(model, state, jc.PGS(), DT, obs, window=3, progress=False)
    with pytest.raises(ValueError, match="sample_steps"):
        jc.fit(model, state, jc.PGS(), DT, obs, sample_steps=np.arange(-1, 9), progress=False)   # 0 is allowed


@pytest.mark.parametrize("kwargs, match", [
    (dict(observed=np.full((10, 2, 2), np.nan)), "observed.*finite"),          # returned the initial guess
    (dict(observed=np.full((10, 2, 2), np.inf)), "observed.*finite"),
    (dict(observed=np.zeros((10, 2, 2)) + 1j), "observed.*complex"),
    (dict(learning_rate=float("nan")), "learning_rate"),
    (dict(learning_rate=0.0), "learning_rate"),
    (dict(continuity=-1.0), "continuity"),
    (dict(sample_steps=np.arange(1, 11) + 0.5), "sample_steps.*whole"),       # was truncated
    (dict(optimizer=object()), "optimizer.*optax"),
    (dict(optimizer="sgd"), "optimizer"),
    (dict(horizon="longer"), "horizon"),
    (dict(horizon=[20, 10]), "horizon"),
    (dict(steps=0), "steps"),
    (dict(patience=1.5), "patience"),
])
def test_fit_refuses_bad_input_before_compiling(kwargs, match):
    model, state = jc.scenes.pendulum()
    args = dict(observed=np.zeros((10, 2, 2)), progress=False)
    args.update(kwargs)
    observed = args.pop("observed")
    with pytest.raises((ValueError, TypeError), match=match):
        jc.fit(model, state, jc.PGS(), DT, observed, ("rest_length",), **args)


@pytest.mark.parametrize("kwargs, match", [
    (dict(bounds={"bta": (0.0, 0.5)}), r"`bounds` has the key 'bta'.*not a fitted"),       # a typo was ignored
    (dict(transforms={"rest_lenght": "identity"}), r"`transforms` has the key 'rest_lenght'"),
    (dict(bounds={"beta": (0.5, 0.5)}), r"bounds\['beta'\].*lo < hi"),
    (dict(bounds={"beta": (0.5, 0.1)}), r"bounds\['beta'\].*lo < hi"),
    (dict(bounds={"beta": (0.0, np.inf)}), r"bounds\['beta'\].*finite"),
    (dict(bounds={"beta": (np.nan, 1.0)}), r"bounds\['beta'\].*finite"),
    (dict(bounds={"beta": 0.5}), r"bounds\['beta'\].*pair"),
    (dict(bounds={"beta": (0.3, 0.9)}), r"`beta` starts at 0.2, outside its bounds \(0.3, 0.9\)"),  # was clamped
    (dict(bounds={"rest_length": (2.0, 3.0)}), r"`rest_length` starts at 1, outside its bounds"),
    (dict(bounds={"rest_length": (0.5, 2.0)}, transforms={"rest_length": "log"}), r"bounds\['rest_length'\].*ignored"),
    (dict(transforms={"beta": "sigmoid"}), r"transforms\['beta'\].*'log', 'logit' or 'identity'"),
])
def test_fit_refuses_bad_transforms_and_bounds_naming_the_key(kwargs, match):
    """A typo in a key, empty or reversed bounds, bounds that would be ignored, or a start outside its bounds: a
    clear error before anything compiles (the typo was ignored, the start silently clamped into the bounds)."""
    model, state = jc.scenes.pendulum()
    with pytest.raises(ValueError, match=match):
        jc.fit(model, state, jc.PGS(beta=0.2), DT, np.zeros((10, 2, 2)), ("rest_length", "beta"), progress=False,
               **kwargs)


def test_fit_bounds_keep_a_parameter_inside_them():
    """Bounds on a parameter without a transform of its own use the logistic map onto them (they used to be
    ignored for a 'log' parameter)."""
    from jaxcon.identification.fit import _check_transforms_and_bounds, _parameters
    model, state = jc.scenes.pendulum()
    transforms, bounds = _check_transforms_and_bounds(("rest_length",), None, {"rest_length": (0.5, 2.0)})
    spec, u0 = _parameters(("rest_length",), model, jc.PGS(), state, transforms, bounds)
    p = spec["rest_length"]
    assert (p.kind, p.lo, p.hi) == ("logit", 0.5, 2.0)
    np.testing.assert_allclose(float(p.lo + (p.hi - p.lo) * jax.nn.sigmoid(u0["rest_length"][0])), 1.0)


@pytest.mark.parametrize("solver, name", [(jc.XPBD(), "compliance"), (jc.Penalty(substeps=20), "damping")])
def test_fit_refuses_a_log_parameter_that_starts_at_zero(solver, name):
    """log(0) would freeze the parameter at 0 forever; say so and say what to do."""
    model, state = jc.scenes.pendulum()
    with pytest.raises(ValueError, match=rf"`{name}` starts at 0.*transforms"):
        jc.fit(model, state, solver, DT, np.zeros((10, 2, 2)), (name,), progress=False)
    # what the message suggests works: the identity transform moves it
    _, tr = jc.rollout(model, state, solver.replace(**{name: 1e-3}), DT, 10)
    res = jc.fit(model, state, solver, DT, tr.x, (name,), transforms={name: "identity"}, optimizer="adam",
                 steps=3, progress=False)
    assert float(res.params[name]) != 0.0


def test_fit_reports_why_it_stopped_and_the_last_iteration(capsys):
    guess, state, true_L, obs = _chain_experiment(n=4)
    solver = jc.PGS(iterations=10, beta=0.2)
    short = jc.fit(guess, state, solver, DT, obs[:40], ("rest_length",), steps=3, progress=True)
    assert short.reason.split("; ")[0] == "max_steps" and not short.converged and short.iterations == 3
    assert "misfit" in short.reason            # 3 updates leave the model missing the motion, and it says so
    err = capsys.readouterr().err
    last = err.strip().split("\r")[-1]
    assert " 3/3 " in last and "[max_steps]" in last, last                      # the bar ends on the last update
    done = jc.fit(guess, state, solver, DT, obs[:40], ("rest_length",), progress=False)
    assert done.reason == "tolerance" and done.converged and done.iterations < 300


def test_fit_stops_on_a_non_finite_loss_without_claiming_convergence():
    """An optimiser step that makes the parameters NaN: the next loss is non-finite, the fit stops there, says
    why, and returns the best finite iterate (the initial guess), not 'converged'."""
    guess, state, true_L, obs = _chain_experiment(n=3)
    bad = optax.scale(float("nan"))
    res = jc.fit(guess, state, jc.PGS(), DT, obs[:20], ("rest_length",), optimizer=bad, progress=False)
    assert res.reason.split("; ")[0] == "non-finite loss" and not res.converged
    assert res.iterations == 2 and np.isfinite(res.history[0]) and not np.isfinite(res.history[1])
    np.testing.assert_array_equal(np.asarray(res.model.rest_length), np.asarray(guess.rest_length))


def test_fit_is_float64_under_x64_and_strict_promotion():
    guess, state, true_L, obs = _chain_experiment(n=3)
    model, st = jc.scenes.chain(3, 0.6, 0.3, angle=0.5)      # no dtype: float64 under x64
    _, tr = jc.rollout(model, st, jc.PGS(), DT, 20)
    with jax.numpy_dtype_promotion("strict"):
        res = jc.fit(model, st, jc.PGS(beta=0.3), DT, np.asarray(tr.x), ("rest_length", "beta"), steps=5,
                     progress=False)
    assert res.model.rest_length.dtype == jnp.float64 and jnp.result_type(res.solver.beta) == jnp.float64
    assert res.history.dtype == np.float64


@pytree_dataclass
class _NaNGradientPGS(jc.PGS):
    """PGS whose steps are unchanged but whose gradient with respect to beta is NaN: 0 * sqrt'(0) = 0 * inf."""

    def _step(self, sys, x, v, lam, dt):
        x, v, lam = super()._step(sys, x, v, lam, dt)
        return x + 0 * jnp.sqrt(jnp.maximum(self.beta - 2.0, 0.0)), v, lam


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_fit_stops_on_a_non_finite_gradient_without_claiming_convergence(optimizer):
    """A gradient (Adam) or Jacobian (Levenberg-Marquardt) that is NaN while the loss is finite. Before, Adam
    stepped to NaN parameters and LM refused every step until the tolerance said 'converged' (the float32
    falling chain's friction fit: friction unchanged, converged=True); now the fit stops at once and says why."""
    guess, state, true_L, obs = _chain_experiment(n=3)
    solver = _NaNGradientPGS(iterations=10, beta=0.3)
    res = jc.fit(guess, state, solver, DT, obs[:20], ("beta",), optimizer=optimizer, progress=False)
    assert res.reason.split("; ")[0] == "non-finite gradient" and not res.converged
    assert res.iterations == 1 and np.isfinite(res.history[0])
    assert float(res.solver.beta) == pytest.approx(0.3)


def test_fit_that_ends_above_its_starting_loss_has_not_converged():
    """The rule itself, on scripted updates: the short first stage lowers its own loss while the whole record's
    loss rises, and the last stage then stops at its tolerance above the start. That is not convergence."""
    from jaxcon.identification.fit import _run_stages

    def update(u, opt_state, data, horizon):
        first = int(horizon) == 10
        value = 1.0 / (1 + u) if first else 1.0          # the stage loss: falls in stage 1, flat in stage 2
        full = 1.0 + 0.1 * u                              # the whole record's loss: rises as u moves
        return u + 1, opt_state, value, full, True

    best_u, history, horizons, reason, converged = _run_stages(update, lambda u: None, 0, None, (10, 40), 100,
                                                               1e-4, 3, False)
    assert reason == "loss increased" and not converged
    assert history[0] == 1.0 and best_u > 0
    # the same run whose whole-record loss falls with the stage's is converged
    down = lambda u, o, d, h: (u + 1, o, 1.0 / (1 + u) if int(h) == 10 else 0.5, 1.0 / (1 + u), True)  # noqa: E731
    assert _run_stages(down, lambda u: None, 0, None, (10, 40), 100, 1e-4, 3, False)[3:] == ("tolerance", True)
