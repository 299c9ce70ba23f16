"""System identification: fit parameters of the model, the solver and the initial state (or any pytree put in by
a `setup` function) to observed positions, by Levenberg-Marquardt or optax through whole rollouts (optionally
split into windows: multiple shooting), and say how well the data determine them."""
from __future__ import annotations

import math
import sys
import time
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxcon.core.checks import check_real, check_values
from jaxcon.core.model import Model, State
from jaxcon.core.sim import _check_call, _rollout_jit, check_drive
from jaxcon.core.system import Solver
from jaxcon.diagnostics import _diagnosis, diagnose
from jaxcon.identification import uncertainty as unc
from jaxcon.identification.params import (  # noqa: F401  (re-exported: older imports name them here)
    STATE_PARAMS, TRANSFORMS, ParamSet, _check_transforms_and_bounds, _decode, _encode, _get, _owner, _Param,
    _parameters, _set, _tree_replace, default_params, named_params, setup_params, tangent_velocities)
from jaxcon.identification.uncertainty import IdentifiabilityWarning, MisfitWarning  # noqa: F401

Array = Any


class FitResult(NamedTuple):
    """What `fit` returns.

      model, solver: the inputs with the fitted parameters put in (the best iterate of the last stage run).
      params:        {name: fitted value} for named parameters; with `setup=`, the fitted pytree theta.
      history:       [iterations] loss over the whole record (mean squared position error, m^2, plus the
                     continuity penalty with windows) of each iterate, whatever the stage's horizon.
      iterations:    number of optimiser updates made.
      converged:     True only when all of these hold: the last stage (the whole record) stopped at its tolerance
                     (no relative improvement > tol for `patience` updates) at or below the initial guess's loss;
                     the fitted rollout is finite and `jc.diagnose` does not flag it; no fitted value ran to a
                     bound of its transform (a log value at 0 or inf, or moved by over 1e8x; a logit value
                     within 1e-4 of its range from a bound); the errors left are not correlated from frame to
                     frame (`residual_correlation` <= 0.5: what is left looks like noise, not a misfit), or are
                     those of exact data where there are too few frames to check that.
      window_states: the fitted start states of windows 1.. (multiple shooting), else None.
      reason:        why it stopped: "tolerance", "max_steps", "non-finite loss", "non-finite gradient" (a NaN
                     or inf gradient, or Levenberg-Marquardt Jacobian, at the last iterate: the fit stops there
                     instead of following it) or "loss increased" (the returned iterate's whole-record loss is
                     above the initial guess's; the model returned is that iterate all the same). Every check
                     the result fails follows, after "; ": "diverged: ..." (jc.diagnose flags the fitted
                     rollout), "at a bound: ..." (the values, their starts and the transform), "misfit: ..."
                     (see residual_correlation). reason.split("; ")[0] is why the optimiser stopped.
      horizons:      [iterations] the fitted horizon (steps) of each update's stage.
      state:         the fitted initial state (x0, v0, or what `setup` put in; else the input state).
      std:           shaped like params: the 1-sigma uncertainty of every fitted value, from the Gauss-Newton
                     curvature of the whole-record residuals at the optimum scaled by their variance
                     (SSR / (N - p)), through each transform's derivative; 0 for entries not fitted (a fixed
                     particle), inf for entries in a direction the data do not determine. None with windows,
                     above `STD_MAX_PARAMS` fitted scalars with a first-order optimiser, or at a non-finite
                     Jacobian.
      rms:           root mean square position error (m) of the fitted rollout over every observed coordinate.
      unidentified:  the directions of the fitted parameters (unconstrained coordinates) the data do not
                     determine, as text; each was also warned about (IdentifiabilityWarning).
      residual_correlation: the lag-1 correlation of the position errors from frame to frame (pooled over
                     particles, coordinates and trajectories): near 0 when what is left is measurement noise,
                     near 1 when the model misses the motion. Above 0.5 the fit is not converged ("misfit").
                     None with fewer than 7 frame-to-frame pairs over the recordings (8 frames of one), or errors
                     below 1e-5 of the observed motion (exact data). With too few pairs and errors above that,
                     the fit is not converged ("too few frames to check the fit").
    """

    model: Model
    solver: Solver
    params: Any
    history: np.ndarray
    iterations: int
    converged: bool
    window_states: Optional[State]
    reason: str = "tolerance"
    horizons: Optional[np.ndarray] = None
    state: Optional[State] = None
    std: Any = None
    rms: Optional[float] = None
    unidentified: tuple = ()
    residual_correlation: Optional[float] = None


# ---- observations -------------------------------------------------------------------------------------------
def _as_batched_state(state: State, batched: bool) -> State:
    if batched:
        return state
    return jax.tree.map(lambda a: jnp.asarray(a)[None], state)


def _unbatched(state: State) -> State:
    if np.ndim(state.x) == 3:
        return jax.tree.map(lambda a: a[0], state)
    return state


class _Obs(NamedTuple):
    obs: Any            # [B, S, k, dim] in the state's dtype
    batched: bool
    pidx: np.ndarray    # [k] observed particles
    ss: np.ndarray      # [S] sample step counts (increasing, >= 0; 0 is the initial state)
    T: int              # steps simulated

    @property
    def per_frame(self) -> int:
        """Residuals per observed frame: trajectories x particles x dim."""
        B, _, k, dim = self.obs.shape
        return B * k * dim


def _observations(model, state, observed, observed_particles, sample_steps) -> _Obs:
    dtype = jnp.result_type(state.x)
    check_real("fit", "observed", observed)
    obs = jnp.asarray(observed).astype(dtype)
    batched = obs.ndim == 4
    if obs.ndim not in (3, 4):
        raise ValueError(f"fit: `observed` must have shape [S, k, dim] or [B, S, k, dim], got {obs.shape}")
    check_values("fit", "observed", observed)
    if batched and np.ndim(state.x) != 3:
        raise ValueError("fit: batched `observed` [B, S, k, dim] needs a batch of initial states (state.x "
                         f"[B, n, dim]), got state.x {np.shape(state.x)}")
    if not batched and np.ndim(state.x) != 2:
        raise ValueError(f"fit: unbatched `observed` needs state.x [n, dim], got {np.shape(state.x)}")
    obs_b = obs if batched else obs[None]
    B, S, k, dim = obs_b.shape
    if dim != model.dim:
        raise ValueError(f"fit: `observed` has dim {dim}, the model has dim {model.dim}")
    if batched and np.shape(state.x)[0] != B:
        raise ValueError(f"fit: {B} observed trajectories but {np.shape(state.x)[0]} initial states")
    pidx = np.arange(model.n_particles) if observed_particles is None else np.asarray(observed_particles)
    if pidx.ndim != 1 or len(pidx) != k or pidx.dtype.kind not in "iu":
        raise ValueError(f"fit: `observed_particles` must list the {k} particle indices `observed` holds, got "
                         f"{observed_particles!r}")
    if ((pidx < 0) | (pidx >= model.n_particles)).any():
        raise ValueError("fit: `observed_particles` has an index out of range")
    if sample_steps is None:
        ss = np.arange(1, S + 1)
    else:
        raw = np.asarray(sample_steps)
        if raw.dtype.kind == "f" and np.all(np.isfinite(raw)) and np.all(raw == np.round(raw)):
            raw = raw.astype(np.int64)
        if raw.dtype.kind not in "iu":
            raise ValueError(f"fit: `sample_steps` must be whole step counts, got {sample_steps!r}")
        ss = raw.astype(np.int64)
    if ss.shape != (S,):
        raise ValueError(f"fit: `sample_steps` must have shape ({S},), got {ss.shape}")
    if (ss < 0).any() or (np.diff(ss) <= 0).any() or ss[-1] < 1:
        raise ValueError("fit: `sample_steps` must be increasing step counts >= 0 (0: the observed initial state), "
                         f"the last >= 1, got {sample_steps!r}")
    return _Obs(obs_b, batched, pidx, ss, int(ss[-1]))


def _drive(model, state, ob: _Obs, forces, targets):
    """The experiment's known inputs, checked before anything is traced (`check_drive`: shape, real, finite;
    `targets` need fixed particles): `forces` [T, n, dim] (N) and `targets` [T, n_fixed, dim] (m), T =
    max(sample_steps), entry k held during step k + 1 as in `rollout`; with a batch of B recordings each may
    carry a leading axis B (one per recording) or not (shared by all). Returned as (forces, targets), each None
    or [B, T, ...] in the state's dtype."""
    B = ob.obs.shape[0]
    forces, targets = check_drive("fit", model, forces, targets, ob.T, batch=B if ob.batched else None,
                                  steps_name="max(sample_steps)", copy="recording")
    dtype = jnp.result_type(state.x)

    def per_recording(a, ndim):
        if a is None:
            return None
        a = jnp.asarray(a, dtype)
        return jnp.broadcast_to(a, (B,) + a.shape) if a.ndim == ndim else a

    return per_recording(forces, 3), per_recording(targets, 3)


def _progress(i, total, loss, t0, horizon, width=30, stream=None):
    stream = stream or sys.stderr
    frac = (i + 1) / total
    bar = "#" * int(round(width * frac)) + "." * (width - int(round(width * frac)))
    stream.write(f"\rfit [{bar}] {i + 1}/{total} horizon {horizon} steps, loss {loss:.4e} "
                 f"({time.perf_counter() - t0:.1f} s)")
    stream.flush()


def _check_options(optimizer, learning_rate, continuity, tol, patience, steps):
    for name, value in (("learning_rate", learning_rate), ("continuity", continuity), ("tol", tol)):
        check_real("fit", name, value)
        if np.ndim(value) != 0 or not np.isfinite(float(value)):
            raise ValueError(f"fit: `{name}` must be a finite scalar, got {value!r}")
    if float(learning_rate) <= 0:
        raise ValueError(f"fit: `learning_rate` must be > 0, got {learning_rate!r}")
    if float(continuity) < 0 or float(tol) < 0:
        raise ValueError(f"fit: `continuity` and `tol` must be >= 0, got {continuity!r} and {tol!r}")
    for name, value in (("steps", steps), ("patience", patience)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"fit: `{name}` must be an int >= 1, got {value!r}")
    if isinstance(optimizer, str):
        if optimizer not in _LM_NAMES + ("auto", "adam"):
            raise ValueError(f"fit: unknown optimizer {optimizer!r}: use 'auto', 'adam', 'lm' or an optax "
                             "GradientTransformation")
    elif optimizer is not None and not (callable(getattr(optimizer, "init", None))
                                        and callable(getattr(optimizer, "update", None))):
        raise TypeError(f"fit: `optimizer` must be 'auto', 'adam', 'lm' or an optax GradientTransformation (with "
                        f"init and update), got {type(optimizer).__name__}")


_LM_NAMES = ("lm", "levenberg-marquardt", "gauss-newton")
#: With optimizer="auto", Levenberg-Marquardt is used up to this many fitted scalars (its forward-mode Jacobian
#: costs one tangent per scalar), Adam above.
LM_MAX_PARAMS = 64
#: `FitResult.std` is computed up to this many fitted scalars with a first-order optimiser (one forward-mode
#: Jacobian after the fit); Levenberg-Marquardt has its Jacobian already and always gets it.
STD_MAX_PARAMS = 64
#: horizon="grow": the first stage holds the frames of the first GROW_FIRST_STEPS steps, and at least
#: GROW_RESIDUALS_PER_PARAM residuals per fitted scalar; every next stage twice as many frames.
GROW_FIRST_STEPS = 10
GROW_RESIDUALS_PER_PARAM = 8


def _schedule(horizon, ob: _Obs, n_params: int) -> tuple:
    """Stage horizons (steps), increasing, the last = T. 'grow' counts observed frames (module constants above:
    the first stage at least 4 residuals per fitted scalar, then twice the frames each stage); 'full': (T,); a
    list of step counts: those, each holding at least as many residuals as fitted scalars."""
    ss, T, S = ob.ss, ob.T, len(ob.ss)
    if isinstance(horizon, str):
        if horizon == "full":
            return (T,)
        if horizon != "grow":
            raise ValueError(f"fit: `horizon` must be 'grow', 'full' or a list of step counts, got {horizon!r}")
        frames = max(int(np.sum(ss <= GROW_FIRST_STEPS)), math.ceil(GROW_RESIDUALS_PER_PARAM * n_params
                                                                    / ob.per_frame), 1)
        out = []
        while frames < S:
            out.append(int(ss[frames - 1]))
            frames *= 2
        return tuple(out) + (T,)
    try:
        raw = np.asarray(horizon)
        if raw.ndim != 1 or raw.dtype.kind not in "iuf":
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(f"fit: `horizon` must be 'grow', 'full' or a list of step counts, got {horizon!r}") from None
    if raw.dtype.kind == "f" and not np.all(np.isfinite(raw) & (raw == np.round(raw))):
        raise ValueError(f"fit: `horizon` step counts must be whole numbers, got {horizon!r}")
    hs = tuple(int(h) for h in raw)
    if not hs or any(h < 1 for h in hs) or any(b <= a for a, b in zip(hs, hs[1:])) or hs[-1] > T:
        raise ValueError(f"fit: `horizon` step counts must increase from >= 1 to at most the record's {T} steps, "
                         f"got {hs}")
    held = int(np.sum(ss <= hs[0])) * ob.per_frame
    if held < n_params:
        raise ValueError(f"fit: the first `horizon` stage ({hs[0]} steps) holds {held} observed coordinates for "
                         f"{n_params} fitted scalars: it cannot determine them; start with a longer stage")
    return hs if hs[-1] == T else hs + (T,)


def _param_set(params, setup, model, state, solver, transforms, bounds, ob, dt) -> ParamSet:
    """Named parameters (default: `default_params(solver)`), or theta0 with `setup`. A "v0" fitted from zero
    velocities starts from the observed frames instead (`_velocity_guess`)."""
    if setup is not None:
        if params is None or isinstance(params, str) or (isinstance(params, (tuple, list)) and params
                                                         and all(isinstance(p, str) for p in params)):
            raise ValueError("fit: with `setup=`, `params` must be the initial values theta0 (a pytree of floats) "
                             "that setup(theta, model, state, solver) puts in, got "
                             f"{params!r}")
        return setup_params(params, setup, model, state, solver, transforms, bounds)
    pset = named_params(default_params(solver) if params is None else params, model, solver, state, transforms,
                        bounds)
    free = np.asarray(model.inv_mass) > 0
    if "v0" in pset.u0 and not np.any(np.asarray(state.v)[..., free, :]):
        pset.u0["v0"] = jnp.asarray(_velocity_guess(model, state, ob, dt), jnp.result_type(state.x))
    return pset


def _velocity_guess(model, state, ob: _Obs, dt):
    """Initial velocities from the first (up to 3) observed frames: the derivative at t = 0 of the polynomial
    through them, for the observed particles (0 for the others), then made consistent with the rods at x0 (the
    mass-weighted projection onto J v = 0, which removes what every constraint solver would remove)."""
    x = np.array(np.asarray(_as_batched_state(state, ob.batched).x, np.float64))
    v = np.zeros_like(x)
    q = min(3, len(ob.ss))
    if q >= 2:
        t = ob.ss[:q] * float(dt)
        w = [sum(1 / (t[i] - t[m]) * np.prod([-t[j] / (t[i] - t[j]) for j in range(q) if j not in (i, m)])
                 for m in range(q) if m != i) for i in range(q)]
        v[:, ob.pidx] = np.einsum("q,bqkd->bkd", np.asarray(w), np.asarray(ob.obs, np.float64)[:, :q])
    v[:, np.asarray(model.inv_mass) == 0] = 0
    v = tangent_velocities(model, x, v)
    return v if ob.batched else v[0]


def fit(model: Model, state: State, solver: Solver, dt, observed, params=None, *, setup: Optional[Callable] = None,
        observed_particles=None, sample_steps=None, optimizer=None, learning_rate: float = 3e-3, steps: int = 300,
        window: Optional[int] = None, continuity: float = 1.0, tol: float = 1e-4, patience: int = 20,
        progress: bool = True, transforms: Optional[dict] = None, bounds: Optional[dict] = None,
        checkpoint: Optional[int] = None, horizon="grow", forces=None, targets=None) -> FitResult:
    _check_call("fit", model, _unbatched(state), solver, dt)
    _check_options(optimizer, learning_rate, continuity, tol, patience, steps)
    ob = _observations(model, state, observed, observed_particles, sample_steps)
    drive = _drive(model, state, ob, forces, targets)
    pset = _param_set(params, setup, model, state, solver, transforms, bounds, ob, dt)
    n_fitted = sum(int(np.sum(m)) for m in jax.tree.leaves(pset.masks()))
    stages = _schedule(horizon, ob, n_fitted)
    dtype = jnp.result_type(state.x)
    problem = _Problem(model, solver, ob, pset, jnp.asarray(dt).astype(dtype), checkpoint, _windows(window, ob.T),
                       float(continuity), drive)
    state_b = _as_batched_state(state, ob.batched)
    u0, lam_starts = problem.window_guess({"theta": pset.u0}, state_b, dt, drive)
    method = _optimizer(optimizer, learning_rate, problem, u0, dtype)
    data = shard_batch((ob.obs, state_b, lam_starts, drive), ob.obs.shape[0] if ob.batched else None)
    update = lambda u, o, d, h: method.core(u, o, d, h)[:5]  # noqa: E731
    best_u, history, horizons, reason, converged = _run_stages(update, method.init, u0, data, stages, steps, tol,
                                                             patience, progress)
    return _result(problem, method, best_u, u0, data, lam_starts, history, horizons, reason, converged, n_fitted)


fit.__doc__ = """Fit parameters of `model`, `solver` and the initial state to observed positions.

    The loss is the mean squared difference (m^2) between simulated and observed positions, over the observed
    particles and frames (and trajectories, when batched). What is fitted is either named parameters or, with
    `setup`, any pytree of floats:

      fit(..., params=("rest_length", "x0", "v0"))
      fit(..., params={"angles": a0, "log_ratio": 0.0}, setup=f)   # f(theta, model, state, solver)
                                                                    #   -> (model, state, solver)

    Named parameters are optimised in an unconstrained form (see `TRANSFORMS`): log for lengths, masses and
    compliances (a fixed particle's inverse mass, 0, stays 0), a logistic map onto (0, 1) for beta, unchanged for
    gravity and the initial state. A `setup` pytree is fitted as it is (identity), unless `transforms` say
    otherwise; setup is traced inside the fit, so it must use jax.numpy, and it is called once on theta0 first
    to check what it returns. A global scale, a mass ratio, reduced coordinates for the start (angles) and
    shared parameters are all a few lines of setup.

    By default the fitted horizon grows (`horizon="grow"`), counted in observed frames: the first stage holds
    the frames of the first 10 steps and at least 4 observed coordinates per fitted scalar, each next stage
    twice as many frames, each starting from the last stage's result, and the last stage the whole record.
    Short horizons have smooth losses; a long rollout from a poor guess (a violated start, a chaotic system,
    unknown initial velocities) has a rugged one where gradient methods stall. Every stage runs the same
    fixed-length rollout with the observations beyond its horizon masked out, so the fit compiles once. A
    stage ends when its loss has not improved by a relative `tol` for `patience` updates (or, before the last
    stage, after its share of `steps`).

    After the fit, the result is checked (see `FitResult.converged`): the last stage met its tolerance, the
    fitted rollout is finite and not flagged by `jc.diagnose`, no value ran to a bound of its transform. The
    1-sigma uncertainty of every fitted value (`FitResult.std`) comes from the Gauss-Newton curvature at the
    optimum; a direction of the parameters the data cannot determine (the common scale of all masses, with
    positions alone) gets an `IdentifiabilityWarning` naming the parameters, and std inf.

    A driven experiment (applied forces, a moving anchor) passes its known inputs as `forces` and `targets`, as
    for `rollout`; a known force also sets the mass scale that positions alone leave open.

    Args:
      model, state, solver, dt: as for `rollout`; their values of the fitted parameters are the initial guess.
        For batched observations `state` holds a batch of initial states (leading axis B on x, v, lam).
      observed: [S, k, dim] positions of the `k` observed particles after the steps in `sample_steps`, or
        [B, S, k, dim] for B trajectories. Must be finite.
      params: names of the parameters to fit: fields of Model (rest_length, inv_mass, gravity, ...), leaves of
        the solver (beta, compliance, ...), and "x0" / "v0", the initial positions / velocities of the free
        particles. Default `default_params(solver)`: ("rest_length", "beta") for solvers with a Baumgarte beta
        (PGS, Jacobi, Direct), ("rest_length",) for the others (RATTLE, XPBD, SoftStep, Penalty, split
        impulses). "v0" fitted from zero velocities starts from the first observed frames (the derivative at
        t = 0 of the polynomial through up to 3 of them, made consistent with the rods). With `setup`: the
        initial values theta0, a pytree of floats; FitResult.params is then the fitted pytree.
      setup: f(theta, model, state, solver) -> (model, state, solver), putting theta into them with
        `model.replace(...)`, `state.replace(...)`, `solver.replace(...)` and jax.numpy (it is traced). `state`
        is passed as given (batched when `observed` is).
      observed_particles: [k] particle indices that `observed` holds (default: all, in order).
      sample_steps: [S] increasing whole step counts >= 0 at which the positions were observed: observed[s] is
        the position after sample_steps[s] steps, 0 the initial state (default 1..S). The rollout runs
        max(sample_steps) steps.
      optimizer: "auto" or None (default): Levenberg-Marquardt when at most `LM_MAX_PARAMS` (64) scalars are
        fitted, else Adam(learning_rate). "lm": Levenberg-Marquardt on the residuals with a forward-mode
        Jacobian (one tangent per fitted scalar; far better conditioned than first-order methods when few
        parameters explain many observations). "adam", or any optax GradientTransformation (optax.lbfgs()
        works: it receives value, grad and value_fn).
      learning_rate: Adam's step size (finite, > 0). The default 3e-3 moves a log-parameterised value by about
        0.3% per update; 1e-2 oscillated on the 16x16 cloth's 930 rest lengths (median error 2.1% against 1.7%).
      steps: maximum number of optimiser updates over all stages.
      window: None, or a number of steps W dividing max(sample_steps): multiple shooting. The trajectory is cut
        into windows of W steps; the first starts from `state`, every later one from a free start state (its
        positions and velocities are fitted too, initialised from the observations where observed and from a
        rollout of the initial guess elsewhere). A penalty `continuity` (>= 0) times the squared mismatch
        between the end of each window and the start of the next joins them.
      tol, patience: a stage ends when its best loss has not improved by a relative `tol` for `patience`
        updates.
      progress: write a progress bar with the stage's horizon and loss to stderr.
      transforms: {name: 'log' | 'logit' | 'identity'} overriding `TRANSFORMS` (with `setup`: keyed by theta0's
        top-level dict keys). Every key must be a fitted parameter.
      bounds: {name: (lo, hi)}, finite with lo < hi, for 'logit' parameters (default (0, 1)); a parameter
        given bounds and no transform uses 'logit'. Every key must be a fitted parameter, and the initial value
        within its bounds (a value on a bound starts 1e-6 of the range inside it).
      checkpoint: passed to `rollout` (reverse-mode memory for long horizons).
      horizon: "grow" (default), "full" (one stage: the whole record), or increasing step counts of the
        stages (the whole record is appended as the last stage if missing; the first must hold at least as
        many observed coordinates as fitted scalars).
      forces, targets: the experiment's known inputs, as for `rollout`: `forces` [T, n, dim] (N, held during
        each step) and `targets` [T, n_fixed, dim] (m, the fixed particles' positions after each step, in
        increasing index order), T = max(sample_steps): entry j - 1 is step j, so observed[s] comes after the
        entries before sample_steps[s]. With batched observations [B, T, ...], one per recording, or [T, ...]
        shared by all. Every stage simulates the whole record under the whole drive (stages mask observations,
        not steps); with windows, window w runs steps w W + 1 .. (w + 1) W with entries w W .. (w + 1) W - 1,
        and its fixed particles start on targets[w W - 1] (known, not fitted). Checked before tracing (shape,
        real, finite; `targets` need fixed particles), the error naming the argument. Not fitted; under a drive
        the energy it adds does not count as divergence in `converged`.

    Returns:
      FitResult(model, solver, params, history, iterations, converged, window_states, reason, horizons, state,
      std, rms, unidentified).
    """


def shard_batch(data, batch):
    """Batched fits: put every leaf of `data` whose leading axis is the batch (`batch` trajectories) on all local
    devices, that axis sharded, so the jit-compiled loss and gradient run data-parallel (XLA sums the gradient
    across devices). One device, no batch, or a batch that does not divide evenly: `data` as it is."""
    devices = jax.local_devices()
    if batch is None or len(devices) == 1 or batch % len(devices):
        return data
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    return jax.tree.map(lambda a: jax.device_put(a, sharding) if jnp.ndim(a) and a.shape[0] == batch else a, data)


def _windows(window, T):
    if window is None:
        return 1
    if not isinstance(window, (int, np.integer)) or isinstance(window, bool) or window < 1 or T % window:
        raise ValueError(f"fit: `window` must be an int >= 1 dividing the horizon {T} steps, got {window!r}")
    return T // window


def _optimizer(optimizer, learning_rate, problem, u0, dtype) -> "_Method":
    """The chosen method: Levenberg-Marquardt for "lm" (or "auto" with at most `LM_MAX_PARAMS` fitted
    scalars), else an optax transformation (Adam by default)."""
    n_scalars = sum(int(np.size(v)) for v in jax.tree.leaves(u0))
    if optimizer in _LM_NAMES or (optimizer in (None, "auto") and n_scalars <= LM_MAX_PARAMS):
        mu0 = jnp.asarray(1e-3, dtype)       # Levenberg-Marquardt damping
        return _Method(_lm_core(problem), lambda u: mu0, True)
    opt = optax.adam(learning_rate) if optimizer in (None, "auto", "adam") else optimizer
    opt = optax.with_extra_args_support(opt)     # plain transformations ignore value / value_fn
    return _Method(_optax_core(problem, opt), opt.init, False)


class _Method(NamedTuple):
    core: Callable     # jitted (u, opt_state, data, horizon) -> (u, opt_state, value, full, finite, (J, err))
    init: Callable     # u -> opt_state
    lm: bool           # core returns the Jacobian J of the residuals at u (else None), and the position errors


def _window_states(best_u, lam_starts, batched) -> State:
    """The fitted start state of every window (multiple shooting)."""
    x, v = best_u["__x"], best_u["__v"]
    return State(x if batched else x[0], v if batched else v[0], lam_starts if batched else lam_starts[0])


class _Problem:
    """The residuals of one fit: a fixed-length rollout (per window) with observations beyond the current
    stage's horizon masked out. u = {"theta": the ParamSet's unconstrained values, and with windows "__x",
    "__v": the free start states of windows 1..}."""

    def __init__(self, model, solver, ob, pset: ParamSet, dt, checkpoint, n_win, continuity, drive=(None, None)):
        self.model, self.solver, self.ob, self.pset, self.dt = model, solver, ob, pset, dt
        self.checkpoint, self.n_win, self.continuity = checkpoint, n_win, continuity
        self.W = ob.T // n_win
        # driven (forces or targets given): the drive's work is no divergence (_checked_rollout)
        self.driven = any(a is not None for a in drive)
        self.fixed = np.flatnonzero(np.asarray(model.topology.fixed))           # user indices, targets' order
        self.starts = np.arange(1, n_win) * self.W                               # first steps of windows 1..
        # window of every sample, and its index in that window's record (0: the window's start state)
        self.win_of = np.maximum(ob.ss - 1, 0) // self.W
        self.pos_in = ob.ss - self.win_of * self.W

    def start(self, u, state_b):
        """(model, batched start state, solver) with the fitted parameters put in."""
        return self.pset.apply(u["theta"], self.model, state_b, self.solver, self.ob.batched)

    def simulate(self, m, s, st, n, drive):
        """Rollouts of n steps from the start states st [R, ...] under the drive (forces, targets), each None or
        [R, n, ...]: one per start state."""
        return jax.vmap(lambda st1, f1, t1: _rollout_jit(m, st1, s, self.dt, n, 1, self.checkpoint, True, f1, t1))(
            st, *drive)

    def window_drive(self, drive):
        """The drive [B, T, ...] cut into the windows' steps: [B * n_win, W, ...], window w of recording b at
        b * n_win + w (the order of the flattened window start states)."""
        return tuple(None if a is None else a.reshape((a.shape[0] * self.n_win, self.W) + a.shape[2:])
                     for a in drive)

    def fixed_starts(self, st, drive):
        """[B, n_win - 1, n_fixed, dim] where the fixed particles are when windows 1.. start: on their targets of
        the step before (`targets[start - 1]`), else where the start state holds them (they never move). Known,
        so not fitted."""
        targets = drive[1]
        if targets is not None:
            return targets[:, self.starts - 1]
        x = st.x[:, None, self.fixed]
        return jnp.broadcast_to(x, (x.shape[0], self.n_win - 1) + x.shape[2:])

    def window_guess(self, u0, state_b, dt, drive=(None, None)):
        """Initial free window starts: a rollout of the guess, overwritten by observations where observed (free
        particles only: the fixed ones' positions are known)."""
        if self.n_win == 1:
            return u0, None
        ob, W = self.ob, self.W
        m, st, s = self.start(u0, state_b)
        _, guess = self.simulate(m, s, st, ob.T, drive)
        starts = self.starts
        xs, vs = np.array(guess.x[:, starts - 1]), np.array(guess.v[:, starts - 1])
        lookup = {int(s): q for q, s in enumerate(ob.ss)}
        obs_np = np.asarray(ob.obs)
        free = ~np.isin(ob.pidx, self.fixed)
        for w, s0 in enumerate(starts):
            if s0 in lookup:
                xs[:, w, ob.pidx[free]] = obs_np[:, lookup[s0]][:, free]
            if s0 - 1 in lookup and s0 + 1 in lookup:
                vs[:, w, ob.pidx[free]] = (obs_np[:, lookup[s0 + 1]][:, free]
                                           - obs_np[:, lookup[s0 - 1]][:, free]) / (2 * float(dt))
        dtype = jnp.result_type(state_b.x)
        return {**u0, "__x": jnp.asarray(xs, dtype), "__v": jnp.asarray(vs, dtype)}, jnp.asarray(
            np.asarray(guess.lam[:, starts - 1]), dtype)

    def residuals(self, u, data, horizon):
        """(r, full, aux): residuals r with stage loss sum(r^2) (samples after `horizon` steps masked, each part
        a mean), the loss over the whole record, and aux = (the rollout [B, T, ...] and its start state, the
        position errors [B, S, k, dim] of the whole record)."""
        obs_b, state_b, lam_starts, drive = data
        ob = self.ob
        m, st, s = self.start(u, state_b)
        inside = jnp.asarray(ob.ss) <= horizon                                  # [S]
        if self.n_win == 1:
            _, tr = self.simulate(m, s, st, ob.T, drive)
            xs = jnp.concatenate([jnp.asarray(st.x, tr.x.dtype)[:, None], tr.x], 1)
            err = xs[:, ob.ss][:, :, ob.pidx] - obs_b
            r, full = _masked_mean_residuals(err, inside, 1)
            return r, full, (tr, st, err)
        B = obs_b.shape[0]
        xw = u["__x"]
        if len(self.fixed):                        # the fixed particles' positions are known, not fitted
            xw = xw.at[:, :, self.fixed].set(self.fixed_starts(st, drive).astype(xw.dtype))
        x0 = jnp.concatenate([st.x[:, None], xw], 1)                            # [B, n_win, n, dim]
        v0 = jnp.concatenate([st.v[:, None], u["__v"]], 1)
        l0 = jnp.concatenate([st.lam[:, None], lam_starts], 1)
        flat = State(*(a.reshape((-1,) + a.shape[2:]) for a in (x0, v0, l0)))
        final, tr = self.simulate(m, s, flat, self.W, self.window_drive(drive))
        x_all = tr.x.reshape((B, self.n_win, self.W) + tr.x.shape[2:])
        x_all = jnp.concatenate([x0[:, :, None], x_all], 2)                     # [B, n_win, W + 1, n, dim]
        err = x_all[:, self.win_of, self.pos_in][:, :, ob.pidx] - obs_b
        r, full = _masked_mean_residuals(err, inside, 1)
        fx = final.x.reshape((B, self.n_win) + final.x.shape[1:])[:, :-1]
        fv = final.v.reshape((B, self.n_win) + final.v.shape[1:])[:, :-1]
        joined = jnp.asarray(self.starts) < horizon                               # windows 1.. starting inside
        c = jnp.sqrt(jnp.asarray(self.continuity, r.dtype))
        out = [r]
        free = jnp.asarray(np.asarray(self.model.topology.fixed) == 0)[:, None]   # [n, 1]: no gap at fixed ones
        for gap in (fx - xw, (fv - u["__v"]) * (self.W * self.dt)):
            gap = jnp.where(free, gap, jnp.zeros((), gap.dtype))
            rg, fg = _masked_mean_residuals(gap, joined, 1)
            out.append(c * rg)
            full = full + self.continuity * fg
        tr = jax.tree.map(lambda a: a.reshape((B, self.n_win * self.W) + a.shape[2:]), tr)
        return jnp.concatenate(out), full, (tr, State(x0[:, 0], v0[:, 0], l0[:, 0]), err)


def _masked_mean_residuals(err, inside, axis):
    """err [.., S along `axis`, ...]: (residuals whose squares sum to the mean of err^2 over the entries inside
    the horizon, masked entries exactly 0 with no derivative, and the unmasked mean of err^2)."""
    shape = [1] * err.ndim
    shape[axis] = err.shape[axis]
    mask = jnp.broadcast_to(inside.reshape(shape), err.shape)
    count = jnp.maximum(jnp.sum(mask.astype(err.dtype)), 1)
    r = jnp.where(mask, err, 0) / jnp.sqrt(count)
    full = jnp.mean(jnp.where(jnp.isfinite(err), err, jnp.inf) ** 2)
    return r.ravel(), full


def _lm_core(problem):
    @jax.jit
    def core(u, mu, data, horizon):
        z0, unravel = jax.flatten_util.ravel_pytree(u)
        f = lambda z: problem.residuals(unravel(z), data, horizon)  # noqa: E731

        def with_aux(z):
            r, full, aux = f(z)
            return r, (r, full, aux)

        J, (r, full, aux) = jax.jacfwd(with_aux, has_aux=True)(z0)
        value = jnp.sum(r * r)
        finite = jnp.all(jnp.isfinite(J))        # a non-finite Jacobian: every step would be refused forever
        A, g = J.T @ J, J.T @ r
        D = jnp.diag(jnp.diag(A)) + jnp.finfo(r.dtype).eps * jnp.eye(len(z0), dtype=r.dtype)
        dz = -jnp.linalg.solve(A + mu * D, g)
        new = jnp.sum(f(z0 + dz)[0] ** 2)
        ok = jnp.isfinite(new) & (new < value)
        z = jnp.where(ok, z0 + dz, z0)
        mu = jnp.where(ok, jnp.maximum(mu / 3, 1e-12), mu * 4)
        return unravel(z), mu, value, full, finite, (J, aux[2])

    return core


def _optax_core(problem, opt):
    def stage_loss(u, data, horizon):
        r, full, aux = problem.residuals(u, data, horizon)
        return jnp.sum(r * r), (full, aux)

    @jax.jit
    def core(u, opt_state, data, horizon):
        (value, (full, aux)), grad = jax.value_and_grad(stage_loss, has_aux=True)(u, data, horizon)
        upd, opt_state = opt.update(grad, opt_state, u, value=value, grad=grad,
                                    value_fn=lambda v: stage_loss(v, data, horizon)[0])
        finite = jnp.all(jnp.isfinite(jax.flatten_util.ravel_pytree(grad)[0]))
        return optax.apply_updates(u, upd), opt_state, value, full, finite, (None, aux[2])

    return core


def _jacobian(problem):
    @jax.jit
    def jac(u, data, horizon):
        z0, unravel = jax.flatten_util.ravel_pytree(u)
        return jax.jacfwd(lambda z: problem.residuals(unravel(z), data, horizon)[0])(z0)

    return jac


def _run_stages(update, init, u, data, stages, steps, tol, patience, progress):
    """Run the optimiser stage by stage, each from the previous stage's best point with a fresh optimiser state
    (`init(u)`: Adam's moments from a shorter horizon only push it around). Returns (best u of the last stage
    run, history of whole-record losses, stage horizon of each update, reason, converged).

    It stops at a non-finite loss or gradient (reason "non-finite loss" / "non-finite gradient"), and when the
    returned iterate's whole-record loss is above the initial guess's, the reason is "loss increased"; in
    those cases `converged` is False whatever the tolerance said."""
    history, horizons = [], []
    t0 = time.perf_counter()
    reason, converged, best_u, best_full = "max_steps", False, u, np.inf
    for k, h in enumerate(stages):
        last = k == len(stages) - 1
        # earlier stages get an equal share of half the budget; the last stage gets the rest
        budget = steps - len(history) if last else max(1, steps // (2 * (len(stages) - 1)))
        budget = min(budget, steps - len(history))
        best, best_u, best_full, since = np.inf, u, np.inf, 0
        h_arr, opt_state = jnp.asarray(h), init(u)
        for _ in range(budget):
            u_new, opt_state, value, full, finite = update(u, opt_state, data, h_arr)
            value, full = float(value), float(full)        # the losses of `u` (before this update)
            history.append(full)
            horizons.append(h)
            if not np.isfinite(value):
                reason = "non-finite loss"
                break
            since = 0 if (value < best * (1 - tol) or not np.isfinite(best)) else since + 1
            if value < best:
                best, best_u, best_full = value, u, full
            if not bool(finite):                          # the update would follow a NaN / inf gradient
                reason = "non-finite gradient"
                break
            u = u_new
            if progress and (len(history) % max(1, steps // 100) == 0):
                _progress(len(history) - 1, steps, full, t0, h)
            if since >= patience:
                if last:
                    reason, converged = "tolerance", True
                break
        u = best_u
        if reason.startswith("non-finite") or len(history) >= steps:
            break
    if not reason.startswith("non-finite") and best_full > history[0]:
        reason, converged = "loss increased", False
    if progress:
        _progress(len(history) - 1, steps, history[-1], t0, horizons[-1])
        sys.stderr.write(f"  [{reason}]\n")
        sys.stderr.flush()
    return best_u, history, horizons, reason, converged


def _result(problem, method, best_u, u0, data, lam_starts, history, horizons, reason, converged, n_fitted):
    """The FitResult of the best iterate, checked (`_failures`): jc.diagnose on its rollout, the transforms'
    bounds, the residuals' lag-1 correlation; and, without windows, the Gauss-Newton uncertainty and the
    identifiability of the fitted parameters."""
    pset, ob, windows = problem.pset, problem.ob, problem.n_win > 1
    T = jnp.asarray(ob.T)
    J, err = method.core(best_u, method.init(best_u), data, T)[5]
    diag = _checked_rollout(problem)(best_u, data, T)
    if not method.lm and not windows and n_fitted <= STD_MAX_PARAMS:
        J = _jacobian(problem)(best_u, data, T)
    err = np.asarray(err, np.float64)
    m, st_b, s = problem.start(best_u, data[1])
    failures, corr = _failures(pset, ob, best_u, u0, diag, err, problem.driven)
    if failures:
        converged, reason = False, "; ".join([reason] + failures)
    std, unidentified = None, ()
    if J is not None and not windows:
        J = np.asarray(J, np.float64)
        best_u = _canonical_v0(pset, best_u, J, m, st_b, ob)
        m, st_b, s = problem.start(best_u, data[1])
        active = np.concatenate([np.ravel(a) for a in jax.tree.leaves(pset.masks())])
        gauge = unc.state_gauge(pset, m, st_b, ob.batched, ob.ss[0] == 0)
        found = unc.gauss_newton(J, float(np.mean(err ** 2)), active, gauge, pset.entry_labels())
        if found is not None:
            std, unidentified = unc.std_like(pset, best_u["theta"], found.std_u), found.unidentified
            unc.warn_unidentified(unidentified, pset, stacklevel=4)
    unc.warn_misfit(corr, err, stacklevel=4)
    ws = _window_states(best_u, lam_starts, ob.batched) if windows else None
    state = st_b if ob.batched else jax.tree.map(lambda a: a[0], st_b)
    return FitResult(m, s, pset.decode(best_u["theta"]), np.asarray(history), len(history), converged, ws, reason,
                     np.asarray(horizons), state, std, float(np.sqrt(np.mean(err ** 2))), unidentified, corr)


def _checked_rollout(problem):
    """(diverged [B], first bad step [B]) of jc.diagnose on the rollout of u: one forward program, compiled once
    after the fit (inside the update it cost the 16x16 cloth fit 1.2 s of compilation and 8% per update). Under
    a drive (forces or targets) the energy gain is not counted: the drive does work on the system."""
    @jax.jit
    def check(u, data, horizon):
        traj, start, _ = problem.residuals(u, data, horizon)[2]
        m = problem.start(u, data[1])[0]
        if problem.driven:
            d = jax.vmap(lambda tr, s0: _diagnosis(m, tr, s0, energy=False))(traj, start)
        else:
            d = jax.vmap(diagnose, in_axes=(None, 0, 0))(m, traj, start)
        return d.diverged, d.first_bad

    return check


def _failures(pset, ob, best_u, u0, diag, err, driven=False):
    """(what is wrong with the fitted result, as text; the residuals' lag-1 correlation): a rollout that
    jc.diagnose flags, a value at a bound of its transform, residuals that are correlated in time."""
    failures = []
    bad = np.asarray(diag[0])
    if bad.any():
        b = int(np.argmax(bad))
        what = ("non-finite, a constraint off by more than its length, or a contact overlap; under a drive an "
                "energy gain is not counted" if driven else
                "non-finite, a constraint off by more than its length, or an energy gain")
        failures.append(f"diverged: jc.diagnose flags the fitted rollout{f' of trajectory {b}' if ob.batched else ''}"
                        f" from step {int(np.asarray(diag[1])[b]) + 1} ({what})")
    hits = unc.at_bounds(pset, best_u["theta"], u0["theta"])
    if hits:
        failures.append("at a bound: " + "; ".join(hits))
    obs = np.asarray(ob.obs, np.float64)
    corr = unc.residual_correlation(err, obs)
    if unc.too_few_frames(err, obs):
        failures.append(f"too few frames to check the fit: {unc.lag_pairs(err)} frame-to-frame pair(s) in "
                        f"{err.shape[0]} x {err.shape[1]} observed frames (recordings x frames), the misfit check "
                        f"needs {unc.MIN_LAG_PAIRS} (8 frames of one recording), and the errors left (RMS "
                        f"{1e3 * np.sqrt(np.mean(err ** 2)):.3g} mm) are not those of exact data; observe more "
                        "frames (and check that `observed` is [frames, particles, dim])")
    if corr is not None and corr > unc.MISFIT_CORRELATION:
        failures.append(f"misfit: the position errors (RMS {1e3 * np.sqrt(np.mean(err ** 2)):.3g} mm) are "
                        f"correlated from frame to frame ({corr:.2f}), not noise: the model does not explain the "
                        "data (an initial state that is not fitted, a parameter missing, a local minimum, or a "
                        "solver whose forward error at this dt is above the noise; see docs/fitting.md)")
    return failures, corr


def _canonical_v0(pset, best_u, J, m, st_b, ob):
    """A fitted "v0" with its components along the rods taken out (`tangent_velocities`), where that changes
    the fitted positions by nothing (to first order: |J dz| <= 1e-6 |dz| times J's largest column norm): the
    solver removes them at the first step, so they are arbitrary; the returned v0 is the one the motion uses."""
    if "v0" not in pset.labels or not pset.named:
        return best_u
    v = np.asarray(best_u["theta"]["v0"], np.float64)
    vb = v if ob.batched else v[None]
    t = tangent_velocities(m, np.asarray(st_b.x, np.float64), vb)
    new = jax.tree.map(lambda a: a, best_u)
    new["theta"]["v0"] = jnp.asarray(t if ob.batched else t[0], jnp.result_type(best_u["theta"]["v0"]))
    dz = jax.flatten_util.ravel_pytree(new)[0] - jax.flatten_util.ravel_pytree(best_u)[0]
    dz = np.asarray(dz, np.float64)
    change = np.linalg.norm(J @ dz)
    return new if change <= 1e-6 * np.linalg.norm(J, axis=0).max() * np.linalg.norm(dz) else best_u
