"""System identification: fit model and solver parameters to observed positions by gradient descent through
whole rollouts (optionally split into windows: multiple shooting)."""
from __future__ import annotations

import dataclasses
import sys
import time
from typing import Any, NamedTuple, Optional, Sequence

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxcon.core.checks import check_real, check_values
from jaxcon.core.model import Model, State
from jaxcon.core.sim import _check_call, _rollout_jit
from jaxcon.core.system import Solver

Array = Any

# How each named parameter is kept in its domain while the optimiser works on an unconstrained value u.
#   log:      value = exp(u)                 (lengths, masses, compliances: > 0)
#   logit:    value = lo + (hi-lo) sigmoid(u) (beta in (0, 1))
#   identity: value = u                      (gravity)
# Names not listed use "log" when all their initial values are > 0, "identity" otherwise.
TRANSFORMS = {
    "rest_length": "log",
    "inv_mass": "log",
    "compliance": "log",
    "stiffness": "log",
    "damping": "log",
    "beta": "logit",
    "gravity": "identity",
    "radius": "log",
    "friction": "log",
    "restitution": "logit",
    "restitution_threshold": "log",
    "plane_offset": "identity",
    "plane_normal": "identity",
    "sphere_centre": "identity",
    "sphere_radius": "log",
}
_EPS = 1e-6


class FitResult(NamedTuple):
    """What `fit` returns.

      model, solver: the inputs with the fitted parameters put in (the best iterate of the last stage run).
      params:        {name: fitted value}.
      history:       [iterations] loss over the whole record (mean squared position error, m^2, plus the
                     continuity penalty with windows) of each iterate, whatever the stage's horizon.
      iterations:    number of optimiser updates made.
      converged:     True only if the last stage (the whole record) stopped at its tolerance: no relative
                     improvement > tol for `patience` updates, and the result's loss is not above the initial
                     guess's. False when it ran out of `steps`, hit a non-finite loss or gradient, ended above
                     its starting loss, or never reached the whole record.
      window_states: the fitted start states of windows 1.. (multiple shooting), else None.
      reason:        why it stopped: "tolerance", "max_steps", "non-finite loss", "non-finite gradient" (a NaN
                     or inf gradient, or Levenberg-Marquardt Jacobian, at the last iterate: the fit stops there
                     instead of following it) or "loss increased" (the returned iterate's whole-record loss is
                     above the initial guess's; the model returned is that iterate all the same).
      horizons:      [iterations] the fitted horizon (steps) of each update's stage.
    """

    model: Model
    solver: Solver
    params: dict
    history: np.ndarray
    iterations: int
    converged: bool
    window_states: Optional[State]
    reason: str = "tolerance"
    horizons: Optional[np.ndarray] = None


# ---- parameter lookup and transforms ------------------------------------------------------------------------
def _owner(name, model, solver):
    if name in Model._data_fields:
        return "model"
    fields = getattr(type(solver), "_data_fields", ())
    if name in fields:
        return "solver"
    raise ValueError(
        f"fit: unknown parameter {name!r}; model parameters are {list(Model._data_fields)}, "
        f"{type(solver).__name__} parameters are {list(fields)}"
    )


def _get(name, model, solver):
    return getattr(model if _owner(name, model, solver) == "model" else solver, name)


def _set(model, solver, values: dict):
    m = {k: v for k, v in values.items() if _owner(k, model, solver) == "model"}
    s = {k: v for k, v in values.items() if _owner(k, model, solver) == "solver"}
    # `replace` validates concrete values; inside jit the values are tracers and validation is skipped.
    model = _tree_replace(model, m)
    solver = _tree_replace(solver, s)
    return model, solver


def _tree_replace(obj, changes):
    """Replace leaves without running __post_init__ (works for tracers and for batched values)."""
    if not changes:
        return obj
    leaves, treedef = jax.tree_util.tree_flatten(obj, is_leaf=lambda x: x is None)
    names = type(obj)._data_fields
    new = [changes.get(n, l) for n, l in zip(names, leaves)] if len(leaves) == len(names) else None
    if new is None:  # nested leaves: fall back to dataclasses.replace
        return dataclasses.replace(obj, **changes)
    return jax.tree_util.tree_unflatten(treedef, new)


def _kind(name, value, transforms, bounds=()):
    if name in transforms:
        return transforms[name]
    if name in bounds:          # bounds keep the value inside them: the logistic map onto (lo, hi)
        return "logit"
    if name in TRANSFORMS:
        return TRANSFORMS[name]
    a = np.asarray(value)
    return "log" if np.all(a > 0) else "identity"


class _Param(NamedTuple):
    kind: str
    mask: Any      # log: entries that are fitted (> 0); zeros (e.g. fixed particles) stay 0
    fixed: Any     # the initial value, used where mask is False
    lo: float
    hi: float


def _encode(value, kind, lo=0.0, hi=1.0):
    v = np.asarray(value, np.float64)
    if kind == "log":
        mask = v > 0
        return np.log(np.where(mask, v, 1.0)), mask
    if kind == "logit":
        p = np.clip((v - lo) / (hi - lo), _EPS, 1 - _EPS)
        return np.log(p) - np.log1p(-p), np.ones(v.shape, bool)
    if kind == "identity":
        return v, np.ones(v.shape, bool)
    raise ValueError(f"fit: unknown transform {kind!r} (use 'log', 'logit' or 'identity')")


def _decode(u, p: _Param):
    if p.kind == "log":
        return jnp.where(p.mask, jnp.exp(u), p.fixed)
    if p.kind == "logit":
        return p.lo + (p.hi - p.lo) * jax.nn.sigmoid(u)
    return u


# ---- observations -------------------------------------------------------------------------------------------
def _as_batched_state(state: State, batched: bool) -> State:
    if batched:
        return state
    return jax.tree.map(lambda a: jnp.asarray(a)[None], state)


def _progress(i, total, loss, t0, horizon, width=30, stream=None):
    stream = stream or sys.stderr
    frac = (i + 1) / total
    bar = "#" * int(round(width * frac)) + "." * (width - int(round(width * frac)))
    stream.write(f"\rfit [{bar}] {i + 1}/{total} horizon {horizon} steps, loss {loss:.4e} "
                 f"({time.perf_counter() - t0:.1f} s)")
    stream.flush()


class _Obs(NamedTuple):
    obs: Any            # [B, S, k, dim] in the state's dtype
    batched: bool
    pidx: np.ndarray    # [k] observed particles
    ss: np.ndarray      # [S] sample step counts (increasing, >= 1)
    T: int              # steps simulated


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
    if (ss < 1).any() or (np.diff(ss) <= 0).any():
        raise ValueError("fit: `sample_steps` must be increasing step counts >= 1")
    return _Obs(obs_b, batched, pidx, ss, int(ss[-1]))


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


def _schedule(horizon, T: int) -> tuple:
    """Stage horizons (steps), increasing, the last = T. 'grow': 10, 20, 40, ... then T; 'full': (T,)."""
    if isinstance(horizon, str):
        if horizon == "full":
            return (T,)
        if horizon != "grow":
            raise ValueError(f"fit: `horizon` must be 'grow', 'full' or a list of step counts, got {horizon!r}")
        out, h = [], min(10, T)
        while h < T:
            out.append(h)
            h *= 2
        return tuple(out) + (T,)
    try:
        hs = tuple(int(h) for h in horizon)
    except (TypeError, ValueError):
        raise ValueError(f"fit: `horizon` must be 'grow', 'full' or a list of step counts, got {horizon!r}") from None
    if not hs or any(h < 1 for h in hs) or any(b <= a for a, b in zip(hs, hs[1:])) or hs[-1] > T:
        raise ValueError(f"fit: `horizon` step counts must increase from >= 1 to at most the record's {T} steps, "
                         f"got {hs}")
    return hs if hs[-1] == T else hs + (T,)


def fit(
    model: Model,
    state: State,
    solver: Solver,
    dt,
    observed,
    params: Sequence[str] = ("rest_length", "beta"),
    *,
    observed_particles=None,
    sample_steps=None,
    optimizer=None,
    learning_rate: float = 3e-3,
    steps: int = 300,
    window: Optional[int] = None,
    continuity: float = 1.0,
    tol: float = 1e-4,
    patience: int = 20,
    progress: bool = True,
    transforms: Optional[dict] = None,
    bounds: Optional[dict] = None,
    checkpoint: Optional[int] = None,
    horizon="grow",
):
    """Fit parameters of `model` and `solver`, chosen by name, to observed positions.

    The loss is the mean squared difference (m^2) between simulated and observed positions, over the observed
    particles and sample steps (and trajectories, when batched). Parameters are optimised in an unconstrained
    form: log for lengths, masses and compliances (a fixed particle's inverse mass, 0, stays 0), a logistic
    map onto (0, 1) for beta, unchanged for gravity (see `TRANSFORMS`).

    By default the fitted horizon grows (`horizon="grow"`): the first stage fits the first 10 steps, each next
    stage twice as many, starting from the last stage's result, and the last stage the whole record. Short
    horizons have smooth losses; a long rollout from a poor guess (a violated start, a chaotic system) has a
    rugged one where gradient methods stall. Every stage runs the same fixed-length rollout with the
    observations beyond its horizon masked out, so the fit compiles once. A stage ends when its loss has not
    improved by a relative `tol` for `patience` updates (or, before the last stage, after its share of
    `steps`); `converged` is True only when the last stage ends that way.

    Args:
      model, state, solver, dt: as for `rollout`; their values of the fitted parameters are the initial guess.
        For batched observations `state` holds a batch of initial states (leading axis B on x, v, lam).
      observed: [S, k, dim] positions of the `k` observed particles after the steps in `sample_steps`, or
        [B, S, k, dim] for B trajectories. Must be finite.
      params: names of the parameters to fit: fields of Model (rest_length, inv_mass, gravity) or leaves of
        the solver (beta, compliance, ...).
      observed_particles: [k] particle indices that `observed` holds (default: all, in order).
      sample_steps: [S] increasing whole step counts >= 1 at which the positions were observed: observed[s] is
        the position after sample_steps[s] steps (default 1..S). The rollout runs max(sample_steps) steps.
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
      transforms: {name: 'log' | 'logit' | 'identity'} overriding `TRANSFORMS`. Every key must be in `params`.
      bounds: {name: (lo, hi)}, finite with lo < hi, for 'logit' parameters (default (0, 1)); a parameter
        given bounds and no transform uses 'logit'. Every key must be in `params`, and the initial value
        within its bounds (a value on a bound starts 1e-6 of the range inside it).
      checkpoint: passed to `rollout` (reverse-mode memory for long horizons).
      horizon: "grow" (default), "full" (one stage: the whole record), or increasing step counts of the
        stages (the whole record is appended as the last stage if missing).

    Returns:
      FitResult(model, solver, params, history, iterations, converged, window_states, reason, horizons).
    """
    _check_call("fit", model, _unbatched(state), solver, dt)
    _check_options(optimizer, learning_rate, continuity, tol, patience, steps)
    params = _param_names(params)
    ob = _observations(model, state, observed, observed_particles, sample_steps)
    stages = _schedule(horizon, ob.T)
    transforms, bounds = _check_transforms_and_bounds(params, transforms, bounds)
    spec, u0 = _parameters(params, model, solver, state, transforms, bounds)
    problem = _Problem(model, solver, ob, spec, jnp.asarray(dt).astype(jnp.result_type(state.x)), checkpoint,
                       _windows(window, ob.T), float(continuity))
    state_b = _as_batched_state(state, ob.batched)
    u0, lam_starts = problem.window_guess(u0, state_b, dt)
    update, init = _optimizer(optimizer, learning_rate, problem, u0, jnp.result_type(state.x))
    data = shard_batch((ob.obs, state_b, lam_starts), ob.obs.shape[0] if ob.batched else None)
    best_u, history, horizons, reason, converged = _run_stages(update, init, u0, data, stages, steps, tol,
                                                             patience, progress)
    fitted = dict(problem.decode(best_u))
    m, s = _set(model, solver, fitted)
    ws = _window_states(best_u, lam_starts, ob.batched) if problem.n_win > 1 else None
    return FitResult(m, s, fitted, np.asarray(history), len(history), converged, ws, reason, np.asarray(horizons))


def shard_batch(data, batch):
    """Batched fits: put every leaf of `data` whose leading axis is the batch (`batch` trajectories) on all local
    devices, that axis sharded, so the jit-compiled loss and gradient run data-parallel (XLA sums the gradient
    across devices). One device, no batch, or a batch that does not divide evenly: `data` as it is."""
    devices = jax.local_devices()
    if batch is None or len(devices) == 1 or batch % len(devices):
        return data
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    return jax.tree.map(lambda a: jax.device_put(a, sharding) if jnp.ndim(a) and a.shape[0] == batch else a, data)


_KINDS = ("log", "logit", "identity")


def _check_transforms_and_bounds(params, transforms, bounds):
    """`transforms` {name: kind} and `bounds` {name: (lo, hi)} as dicts, checked: every key a fitted parameter (a
    typo would otherwise be ignored), kinds known, bounds finite with lo < hi, and only on 'logit' parameters
    (the only transform that keeps a value inside bounds). Returns (transforms, bounds) with float bounds."""
    out = []
    for arg, given in (("transforms", transforms), ("bounds", bounds)):
        if given is None:
            out.append({})
            continue
        if not isinstance(given, dict):
            raise TypeError(f"fit: `{arg}` must be a dict {{parameter name: ...}}, got {type(given).__name__}")
        for key in given:
            if key not in params:
                raise ValueError(f"fit: `{arg}` has the key {key!r}, which is not a fitted parameter (`params` is "
                                 f"{params})")
        out.append(dict(given))
    transforms, bounds = out
    for name, kind in transforms.items():
        if kind not in _KINDS:
            raise ValueError(f"fit: `transforms[{name!r}]` must be 'log', 'logit' or 'identity', got {kind!r}")
    checked = {}
    for name, pair in bounds.items():
        try:
            lo, hi = (float(np.asarray(b)) for b in pair)
        except (TypeError, ValueError):
            raise ValueError(f"fit: `bounds[{name!r}]` must be a pair of numbers (lo, hi), got {pair!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi)) or lo >= hi:
            raise ValueError(f"fit: `bounds[{name!r}]` must be finite with lo < hi, got ({lo}, {hi})")
        if transforms.get(name, "logit") != "logit":
            raise ValueError(f"fit: `bounds[{name!r}]` would be ignored: only the 'logit' transform keeps a value "
                             f"inside bounds, and `transforms[{name!r}]` is {transforms[name]!r}")
        checked[name] = (lo, hi)
    return transforms, checked


def _param_names(params) -> tuple:
    if isinstance(params, str):
        params = (params,)
    params = tuple(params)
    if not params:
        raise ValueError("fit: `params` is empty: name at least one parameter to fit")
    if len(set(params)) != len(params):
        raise ValueError(f"fit: `params` names a parameter twice: {params}")
    return params


def _optimizer(optimizer, learning_rate, problem, u0, dtype):
    """(update, init) of the chosen method: Levenberg-Marquardt for "lm" (or "auto" with at most
    `LM_MAX_PARAMS` fitted scalars), else an optax transformation (Adam by default)."""
    n_scalars = sum(int(np.size(v)) for v in jax.tree.leaves(u0))
    if optimizer in _LM_NAMES or (optimizer in (None, "auto") and n_scalars <= LM_MAX_PARAMS):
        mu0 = jnp.asarray(1e-3, dtype)       # Levenberg-Marquardt damping
        return _lm_update(problem), lambda u: mu0
    opt = optax.adam(learning_rate) if optimizer in (None, "auto", "adam") else optimizer
    opt = optax.with_extra_args_support(opt)     # plain transformations ignore value / value_fn
    return _optax_update(problem, opt), opt.init


def _window_states(best_u, lam_starts, batched) -> State:
    """The fitted start state of every window (multiple shooting)."""
    x, v = best_u["__x"], best_u["__v"]
    return State(x if batched else x[0], v if batched else v[0], lam_starts if batched else lam_starts[0])


def _parameters(params, model, solver, state, transforms, bounds):
    """(spec, u0): each parameter's transform and its unconstrained initial value, in the state's dtype."""
    dtype = jnp.result_type(state.x)
    spec, u0 = {}, {}
    for name in params:
        value = _get(name, model, solver)
        if value is None:
            raise ValueError(f"fit: `{name}` is not set on this model (contact parameters exist only on models "
                             "built with `planes`, `spheres` or `collide`)")
        kind = _kind(name, value, transforms, bounds)
        lo, hi = bounds.get(name, (0.0, 1.0))
        _check_start(name, value, kind, lo, hi)
        u, mask = _encode(value, kind, lo, hi)
        spec[name] = _Param(kind, jnp.asarray(mask), jnp.asarray(value).astype(dtype), float(lo), float(hi))
        u0[name] = jnp.asarray(u).astype(dtype)
    return spec, u0


def _check_start(name, value, kind, lo, hi):
    """The initial value must be one its transform can represent and move: log > 0 (a fixed particle's inverse
    mass, 0, stays 0), logit within [lo, hi] (a value on a bound starts 1e-6 of the range inside it)."""
    v = np.asarray(value, np.float64)
    if kind == "log" and name != "inv_mass" and np.any(v == 0):
        raise ValueError(
            f"fit: `{name}` starts at 0, where its log parameterisation cannot move (it would stay 0); "
            f"start from a small positive value (e.g. {name}=1e-8), or pass transforms={{{name!r}: 'identity'}}")
    if kind == "log" and np.any(v < 0):
        raise ValueError(f"fit: `{name}` has a negative initial value, which its log parameterisation cannot "
                         f"represent; pass transforms={{{name!r}: 'identity'}}")
    if kind == "logit" and np.any((v < lo) | (v > hi)):
        bad = v[(v < lo) | (v > hi)].ravel()[0]
        raise ValueError(f"fit: `{name}` starts at {bad:g}, outside its bounds ({lo:g}, {hi:g}); start inside them "
                         f"or pass bounds={{{name!r}: (lo, hi)}} that contain it")


def _windows(window, T):
    if window is None:
        return 1
    if not isinstance(window, (int, np.integer)) or isinstance(window, bool) or window < 1 or T % window:
        raise ValueError(f"fit: `window` must be an int >= 1 dividing the horizon {T} steps, got {window!r}")
    return T // window


class _Problem:
    """The residuals of one fit: a fixed-length rollout (per window) with observations beyond the current
    stage's horizon masked out."""

    def __init__(self, model, solver, ob, spec, dt, checkpoint, n_win, continuity):
        self.model, self.solver, self.ob, self.spec, self.dt = model, solver, ob, spec, dt
        self.checkpoint, self.n_win, self.continuity = checkpoint, n_win, continuity
        self.W = ob.T // n_win
        self.win_of = (ob.ss - 1) // self.W          # window of every sample, and its step in that window
        self.pos_in = ob.ss - 1 - self.win_of * self.W

    def decode(self, u):
        return {name: _decode(u[name], p) for name, p in self.spec.items()}

    def simulate(self, m, s, st, n):
        return jax.vmap(lambda st1: _rollout_jit(m, st1, s, self.dt, n, 1, self.checkpoint))(st)

    def window_guess(self, u0, state_b, dt):
        """Initial free window starts: a rollout of the guess, overwritten by observations where observed."""
        if self.n_win == 1:
            return u0, None
        ob, W = self.ob, self.W
        _, guess = self.simulate(self.model, self.solver, state_b, ob.T)
        starts = np.arange(1, self.n_win) * W
        xs, vs = np.array(guess.x[:, starts - 1]), np.array(guess.v[:, starts - 1])
        lookup = {int(s): q for q, s in enumerate(ob.ss)}
        obs_np = np.asarray(ob.obs)
        for w, s0 in enumerate(starts):
            if s0 in lookup:
                xs[:, w, ob.pidx] = obs_np[:, lookup[s0]]
            if s0 - 1 in lookup and s0 + 1 in lookup:
                vs[:, w, ob.pidx] = (obs_np[:, lookup[s0 + 1]] - obs_np[:, lookup[s0 - 1]]) / (2 * float(dt))
        dtype = jnp.result_type(state_b.x)
        return {**u0, "__x": jnp.asarray(xs, dtype), "__v": jnp.asarray(vs, dtype)}, jnp.asarray(
            np.asarray(guess.lam[:, starts - 1]), dtype)

    def residuals(self, u, data, horizon):
        """(r, full): residuals r with stage loss sum(r^2) (samples after `horizon` steps masked, each part a
        mean), and the loss over the whole record."""
        obs_b, state_b, lam_starts = data
        ob = self.ob
        m, s = _set(self.model, self.solver, self.decode(u))
        inside = jnp.asarray(ob.ss) <= horizon                                  # [S]
        if self.n_win == 1:
            _, tr = self.simulate(m, s, state_b, ob.T)
            err = tr.x[:, ob.ss - 1][:, :, ob.pidx] - obs_b
            return _masked_mean_residuals(err, inside, 1)
        B = obs_b.shape[0]
        x0 = jnp.concatenate([state_b.x[:, None], u["__x"]], 1)               # [B, n_win, n, dim]
        v0 = jnp.concatenate([state_b.v[:, None], u["__v"]], 1)
        l0 = jnp.concatenate([state_b.lam[:, None], lam_starts], 1)
        flat = State(*(a.reshape((-1,) + a.shape[2:]) for a in (x0, v0, l0)))
        final, tr = self.simulate(m, s, flat, self.W)
        x_all = tr.x.reshape((B, self.n_win, self.W) + tr.x.shape[2:])
        err = x_all[:, self.win_of, self.pos_in][:, :, ob.pidx] - obs_b
        r, full = _masked_mean_residuals(err, inside, 1)
        fx = final.x.reshape((B, self.n_win) + final.x.shape[1:])[:, :-1]
        fv = final.v.reshape((B, self.n_win) + final.v.shape[1:])[:, :-1]
        joined = jnp.asarray(np.arange(1, self.n_win) * self.W) < horizon        # windows 1.. starting inside
        c = jnp.sqrt(jnp.asarray(self.continuity, r.dtype))
        out = [r]
        for gap in (fx - u["__x"], (fv - u["__v"]) * (self.W * self.dt)):
            rg, fg = _masked_mean_residuals(gap, joined, 1)
            out.append(c * rg)
            full = full + self.continuity * fg
        return jnp.concatenate(out), full


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


def _lm_update(problem):
    @jax.jit
    def update(u, mu, data, horizon):
        z0, unravel = jax.flatten_util.ravel_pytree(u)
        f = lambda z: problem.residuals(unravel(z), data, horizon)  # noqa: E731
        def with_aux(z):
            r, full = f(z)
            return r, (r, full)

        J, (r, full) = jax.jacfwd(with_aux, has_aux=True)(z0)
        value = jnp.sum(r * r)
        finite = jnp.all(jnp.isfinite(J))        # a non-finite Jacobian: every step would be refused forever
        A, g = J.T @ J, J.T @ r
        D = jnp.diag(jnp.diag(A)) + jnp.finfo(r.dtype).eps * jnp.eye(len(z0), dtype=r.dtype)
        dz = -jnp.linalg.solve(A + mu * D, g)
        new = jnp.sum(f(z0 + dz)[0] ** 2)
        ok = jnp.isfinite(new) & (new < value)
        z = jnp.where(ok, z0 + dz, z0)
        mu = jnp.where(ok, jnp.maximum(mu / 3, 1e-12), mu * 4)
        return unravel(z), mu, value, full, finite

    return update


def _optax_update(problem, opt):
    def stage_loss(u, data, horizon):
        r, full = problem.residuals(u, data, horizon)
        return jnp.sum(r * r), full

    @jax.jit
    def update(u, opt_state, data, horizon):
        (value, full), grad = jax.value_and_grad(stage_loss, has_aux=True)(u, data, horizon)
        upd, opt_state = opt.update(grad, opt_state, u, value=value, grad=grad,
                                    value_fn=lambda v: stage_loss(v, data, horizon)[0])
        finite = jnp.all(jnp.isfinite(jax.flatten_util.ravel_pytree(grad)[0]))
        return optax.apply_updates(u, upd), opt_state, value, full, finite

    return update

    return update


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


def _unbatched(state: State) -> State:
    if np.ndim(state.x) == 3:
        return jax.tree.map(lambda a: a[0], state)
    return state
