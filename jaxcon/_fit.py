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

from ._model import Model, State
from ._sim import _check_call, _rollout_jit
from ._solver import Solver

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
}
_EPS = 1e-6


class FitResult(NamedTuple):
    """What `fit` returns.

      model, solver: the inputs with the fitted parameters put in (the best iterate, not the last).
      params:        {name: fitted value}.
      history:       [iterations] loss (mean squared position error, m^2) of each iterate.
      iterations:    number of optimiser updates made.
      converged:     True if stopped early (no relative improvement > tol for `patience` iterations).
      window_states: the fitted start states of windows 1.. (multiple shooting), else None.
    """

    model: Model
    solver: Solver
    params: dict
    history: np.ndarray
    iterations: int
    converged: bool
    window_states: Optional[State]


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


def _kind(name, value, transforms):
    if name in transforms:
        return transforms[name]
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


def _progress(i, total, loss, t0, width=30, stream=None):
    stream = stream or sys.stderr
    frac = (i + 1) / total
    bar = "#" * int(round(width * frac)) + "." * (width - int(round(width * frac)))
    stream.write(f"\rfit [{bar}] {i + 1}/{total} loss {loss:.4e} ({time.perf_counter() - t0:.1f} s)")
    stream.flush()


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
    learning_rate: float = 1e-2,
    steps: int = 300,
    window: Optional[int] = None,
    continuity: float = 1.0,
    tol: float = 1e-4,
    patience: int = 20,
    progress: bool = True,
    transforms: Optional[dict] = None,
    bounds: Optional[dict] = None,
    checkpoint: Optional[int] = None,
):
    """Fit parameters of `model` and `solver`, chosen by name, to observed positions.

    The loss is the mean squared difference (m^2) between simulated and observed positions, over the observed
    particles and sample steps (and trajectories, when batched). Parameters are optimised in an unconstrained
    form: log for lengths, masses and compliances (entries equal to 0, such as the inverse mass of a fixed
    particle, stay 0), a logistic map onto (0, 1) for beta, unchanged for gravity (see `TRANSFORMS`).

    Args:
      model, state, solver, dt: as for `rollout`; their values of the fitted parameters are the initial guess.
        For batched observations `state` holds a batch of initial states (leading axis B on x, v, lam).
      observed: [S, k, dim] positions of the `k` observed particles after the steps in `sample_steps`, or
        [B, S, k, dim] for B trajectories.
      params: names of the parameters to fit: fields of Model (rest_length, inv_mass, gravity) or leaves of
        the solver (beta, compliance, ...).
      observed_particles: [k] particle indices that `observed` holds (default: all, in order).
      sample_steps: [S] increasing step counts >= 1 at which the positions were observed: observed[s] is the
        position after sample_steps[s] steps (default 1..S: after every step). The rollout runs
        max(sample_steps) steps.
      optimizer: an optax GradientTransformation (default optax.adam(learning_rate)); optax.lbfgs() works too
        (it receives value, grad and value_fn). Or "lm": Levenberg-Marquardt on the residuals, with the
        Jacobian from forward mode (one pass per fitted scalar): far better conditioned than first-order
        methods when few parameters (tens to a few hundred) explain many observations.
      steps: maximum number of optimiser updates.
      window: None, or a number of steps W dividing max(sample_steps): multiple shooting. The trajectory is cut
        into windows of W steps; the first starts from `state`, every later one from a free start state (its
        positions and velocities are fitted too, initialised from the observations where observed and from a
        rollout of the initial guess elsewhere). A penalty `continuity` times the squared mismatch between the
        end of each window and the start of the next (positions, and velocities times W dt) joins them. Use it
        for chaotic systems, where a long single rollout makes the loss landscape rugged.
      tol, patience: stop when the best loss has not improved by a relative `tol` for `patience` updates.
      progress: write a progress bar with the loss to stderr.
      transforms: {name: 'log' | 'logit' | 'identity'} overriding `TRANSFORMS`.
      bounds: {name: (lo, hi)} for 'logit' parameters (default (0, 1)).
      checkpoint: passed to `rollout` (reverse-mode memory for long horizons).

    Returns:
      FitResult(model, solver, params, history, iterations, converged, window_states).
    """
    _check_call("fit", model, _unbatched(state), solver, dt)
    transforms = dict(transforms or {})
    bounds = dict(bounds or {})
    if isinstance(params, str):
        params = (params,)
    params = tuple(params)
    if not params:
        raise ValueError("fit: `params` is empty: name at least one parameter to fit")
    if len(set(params)) != len(params):
        raise ValueError(f"fit: `params` names a parameter twice: {params}")
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"fit: `steps` must be an int >= 1, got {steps!r}")

    obs = jnp.asarray(observed, jnp.result_type(state.x))
    batched = obs.ndim == 4
    if obs.ndim not in (3, 4):
        raise ValueError(f"fit: `observed` must have shape [S, k, dim] or [B, S, k, dim], got {obs.shape}")
    if batched and np.ndim(state.x) != 3:
        raise ValueError("fit: batched `observed` [B, S, k, dim] needs a batch of initial states (state.x "
                         f"[B, n, dim]), got state.x {np.shape(state.x)}")
    if not batched and np.ndim(state.x) != 2:
        raise ValueError(f"fit: unbatched `observed` needs state.x [n, dim], got {np.shape(state.x)}")
    B = obs.shape[0] if batched else 1
    obs_b = obs if batched else obs[None]
    S, k, dim = obs_b.shape[1:]
    if dim != model.dim:
        raise ValueError(f"fit: `observed` has dim {dim}, the model has dim {model.dim}")
    if batched and np.shape(state.x)[0] != B:
        raise ValueError(f"fit: {B} observed trajectories but {np.shape(state.x)[0]} initial states")

    pidx = np.arange(model.n_particles) if observed_particles is None else np.asarray(observed_particles)
    if pidx.ndim != 1 or len(pidx) != k:
        raise ValueError(f"fit: `observed_particles` must list the {k} particles `observed` holds, got "
                         f"shape {pidx.shape}")
    if ((pidx < 0) | (pidx >= model.n_particles)).any():
        raise ValueError("fit: `observed_particles` has an index out of range")

    ss = np.arange(1, S + 1) if sample_steps is None else np.asarray(sample_steps).astype(np.int64)
    if ss.shape != (S,):
        raise ValueError(f"fit: `sample_steps` must have shape ({S},), got {ss.shape}")
    if (ss < 1).any() or (np.diff(ss) <= 0).any():
        raise ValueError("fit: `sample_steps` must be increasing step counts >= 1")
    T = int(ss[-1])

    # --- parameters ---
    spec, u0 = {}, {}
    for name in params:
        value = _get(name, model, solver)
        kind = _kind(name, value, transforms)
        lo, hi = bounds.get(name, (0.0, 1.0))
        u, mask = _encode(value, kind, lo, hi)
        dtype = jnp.result_type(state.x)
        spec[name] = _Param(kind, jnp.asarray(mask), jnp.asarray(value, dtype), float(lo), float(hi))
        u0[name] = jnp.asarray(u, dtype)

    state_b = _as_batched_state(state, batched)
    dt_arr = jnp.asarray(dt, jnp.result_type(state.x))

    def decode(u):
        return {name: _decode(u[name], spec[name]) for name in params}

    def simulate(m, s, st, n):
        return jax.vmap(lambda st1: _rollout_jit(m, st1, s, dt_arr, n, 1, checkpoint))(st)

    # --- windows (multiple shooting) ---
    if window is not None:
        if not isinstance(window, (int, np.integer)) or window < 1 or T % window:
            raise ValueError(f"fit: `window` must be an int >= 1 dividing the horizon {T} steps, got {window!r}")
        n_win = T // window
    else:
        n_win = 1
    W = T // n_win
    # position of every sample in the windowed layout: window index and step-in-window (0 = window start)
    win_of = (ss - 1) // W
    pos_in = ss - 1 - win_of * W

    if n_win > 1:
        # initial guess of the free window starts: guess rollout, overwritten by observations where observed
        _, guess = simulate(model, solver, state_b, T)
        starts = np.arange(1, n_win) * W  # step counts at which windows 1.. start
        xs = np.array(guess.x[:, starts - 1])
        vs = np.array(guess.v[:, starts - 1])
        lams = np.asarray(guess.lam[:, starts - 1])
        lookup = {int(s): q for q, s in enumerate(ss)}
        obs_np = np.asarray(obs_b)
        for w, s0 in enumerate(starts):
            if s0 in lookup:
                xs[:, w, pidx] = obs_np[:, lookup[s0]]
            if s0 - 1 in lookup and s0 + 1 in lookup:
                d = (obs_np[:, lookup[s0 + 1]] - obs_np[:, lookup[s0 - 1]]) / (2 * float(dt))
                vs[:, w, pidx] = d
        u0["__x"] = jnp.asarray(xs)
        u0["__v"] = jnp.asarray(vs)
        lam_starts = jnp.asarray(lams)
    else:
        lam_starts = None

    def residuals(u, data):
        """Residual vector r with loss = sum(r^2) (mean squared error plus the continuity penalty)."""
        obs_b, state_b, lam_starts = data
        m, s = _set(model, solver, decode(u))
        if n_win == 1:
            _, tr = simulate(m, s, state_b, T)
            pred = tr.x[:, ss - 1][:, :, pidx]
            r = (pred - obs_b).ravel()
            return r / np.sqrt(r.size)
        x0 = jnp.concatenate([state_b.x[:, None], u["__x"]], 1)        # [B, n_win, n, dim]
        v0 = jnp.concatenate([state_b.v[:, None], u["__v"]], 1)
        l0 = jnp.concatenate([state_b.lam[:, None], lam_starts], 1)
        flat = State(x0.reshape((-1,) + x0.shape[2:]), v0.reshape((-1,) + v0.shape[2:]),
                     l0.reshape((-1,) + l0.shape[2:]))
        final, tr = simulate(m, s, flat, W)
        x_all = tr.x.reshape((B, n_win, W) + tr.x.shape[2:])
        pred = x_all[:, win_of, pos_in][:, :, pidx]
        r = (pred - obs_b).ravel()
        fx = final.x.reshape((B, n_win) + final.x.shape[1:])[:, :-1]
        fv = final.v.reshape((B, n_win) + final.v.shape[1:])[:, :-1]
        gx = (fx - u["__x"]).ravel()
        gv = ((fv - u["__v"]) * (W * dt_arr)).ravel()
        c = jnp.sqrt(jnp.asarray(continuity, r.dtype))
        return jnp.concatenate([r / np.sqrt(r.size), c * gx / np.sqrt(gx.size), c * gv / np.sqrt(gv.size)])

    def loss_fn(u, data):
        r = residuals(u, data)
        return jnp.sum(r * r)

    data = (obs_b, state_b, lam_starts)
    if isinstance(optimizer, str):
        if optimizer not in ("lm", "levenberg-marquardt", "gauss-newton"):
            raise ValueError(f"fit: unknown optimizer {optimizer!r}: pass an optax transformation or 'lm'")
        opt_state0 = jnp.asarray(1e-3, jnp.result_type(state.x))  # LM damping
        flat0, unravel = jax.flatten_util.ravel_pytree(u0)

        @jax.jit
        def update(u, mu, data):
            f = lambda z: residuals(unravel(z), data)
            z = jax.flatten_util.ravel_pytree(u)[0]
            r = f(z)
            J = jax.jacfwd(f)(z)              # [n_residuals, n_params]: one forward pass per parameter
            value = jnp.sum(r * r)
            A = J.T @ J
            g = J.T @ r
            D = jnp.diag(jnp.diag(A)) + jnp.finfo(r.dtype).eps * jnp.eye(len(z))
            dz = -jnp.linalg.solve(A + mu * D, g)
            new = jnp.sum(f(z + dz) ** 2)
            ok = jnp.isfinite(new) & (new < value)
            z = jnp.where(ok, z + dz, z)
            mu = jnp.where(ok, jnp.maximum(mu / 3, 1e-12), mu * 4)
            return unravel(z), mu, value
    else:
        opt = optimizer if optimizer is not None else optax.adam(learning_rate)
        opt_state0 = opt.init(u0)
        value_and_grad = optax.value_and_grad_from_state(loss_fn) if _is_linesearch(opt_state0) else None

        @jax.jit
        def update(u, opt_state, data):
            if value_and_grad is not None:
                value, grad = value_and_grad(u, data, state=opt_state)
            else:
                value, grad = jax.value_and_grad(loss_fn)(u, data)
            upd, opt_state = opt.update(grad, opt_state, u, value=value, grad=grad,
                                        value_fn=lambda v: loss_fn(v, data))
            return optax.apply_updates(u, upd), opt_state, value

    u, opt_state = u0, opt_state0
    history, best, best_u, since, converged = [], np.inf, u0, 0, False
    t0 = time.perf_counter()
    it = 0
    for it in range(steps):
        u_new, opt_state, value = update(u, opt_state, data)
        value = float(value)  # the loss of `u` (before this update)
        history.append(value)
        if not np.isfinite(value):
            break
        if value < best * (1 - tol) or not np.isfinite(best):
            since = 0
        else:
            since += 1
        if value < best:
            best, best_u = value, u
        u = u_new
        if progress and (it % max(1, steps // 100) == 0 or it == steps - 1):
            _progress(it, steps, value, t0)
        if since >= patience:
            converged = True
            break
    if progress:
        sys.stderr.write("\n")
        sys.stderr.flush()

    fitted = {name: v for name, v in decode(best_u).items()}
    m, s = _set(model, solver, fitted)
    ws = None
    if n_win > 1:
        x, v = best_u["__x"], best_u["__v"]
        ws = State(x if batched else x[0], v if batched else v[0], lam_starts if batched else lam_starts[0])
    return FitResult(m, s, fitted, np.asarray(history), it + 1, converged, ws)


def _unbatched(state: State) -> State:
    if np.ndim(state.x) == 3:
        return jax.tree.map(lambda a: a[0], state)
    return state


def _is_linesearch(opt_state) -> bool:
    """True if the optimiser (e.g. optax.lbfgs) keeps a line search state that can hand back value and grad."""
    found = []

    def visit(x):
        if type(x).__name__ == "ScaleByZoomLinesearchState" or type(x).__name__ == "ScaleByBacktrackingLinesearchState":
            found.append(x)
        return x

    jax.tree.map(visit, opt_state, is_leaf=lambda x: type(x).__name__.endswith("LinesearchState"))
    return bool(found)
