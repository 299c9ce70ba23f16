"""What `jc.fit` fits: named leaves of the model, the solver and the initial state ("x0", "v0"), or any pytree of
floats that a user's `setup` function puts in. Every fitted leaf is kept in its domain by a transform of an
unconstrained value u, which is what the optimiser moves."""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core.model import Model, State
from jaxcon.core.system import Solver

# How each named parameter is kept in its domain while the optimiser works on an unconstrained value u.
#   log:      value = exp(u)                 (lengths, masses, compliances: > 0)
#   logit:    value = lo + (hi-lo) sigmoid(u) (beta in (0, 1))
#   identity: value = u                      (gravity, the initial state)
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
    "x0": "identity",
    "v0": "identity",
}
#: The initial state's parameters: positions and velocities of the free particles (fixed ones keep theirs).
STATE_PARAMS = ("x0", "v0")
_KINDS = ("log", "logit", "identity")
_EPS = 1e-6


def default_params(solver) -> tuple:
    """The parameters `fit` fits when `params` is not given: the rest lengths, and Baumgarte's beta where the
    solver has one (PGS, Jacobi, Direct; with split impulses too, where beta acts within the slop). RATTLE,
    XPBD, SoftStep and Penalty have no beta."""
    fields = getattr(type(solver), "_data_fields", ())
    if "beta" in fields:
        return ("rest_length", "beta")
    return ("rest_length",)


# ---- parameter lookup -----------------------------------------------------------------------------------------
def _constraint_of(name, model):
    """The constraint set and key a dotted name "<set>.<param>" or "<set>.compliance" refers to, or None."""
    if "." not in name:
        return None
    set_name, key = name.split(".", 1)
    sets = {c.name: c for c in getattr(model, "constraints", ())}
    same = [c for c in getattr(model, "constraints", ()) if c.name == set_name]
    if len(same) > 1:
        raise ValueError(f"fit: parameter {name!r} is ambiguous: the model has {len(same)} constraint sets named "
                         f"{set_name!r}; give the sets unique names")
    if set_name not in sets:
        raise ValueError(f"fit: unknown parameter {name!r}: the model has no constraint set {set_name!r} (its sets "
                         f"are {sorted(sets)})")
    c = sets[set_name]
    if key != "compliance" and key not in c.params:
        raise ValueError(f"fit: unknown parameter {name!r}: set {set_name!r} has the parameters "
                         f"{sorted(c.params) + ['compliance']}")
    return c, key


def _owner(name, model, solver):
    if name in STATE_PARAMS:
        return "state"
    if _constraint_of(name, model) is not None:
        return "constraint"
    if name in Model._data_fields:
        return "model"
    fields = getattr(type(solver), "_data_fields", ())
    if name in fields:
        return "solver"
    raise ValueError(
        f"fit: unknown parameter {name!r}; model parameters are {list(Model._data_fields)}, "
        f"{type(solver).__name__} parameters are {list(fields)}, the initial state's are {list(STATE_PARAMS)}, "
        f"a constraint set's are '<set>.<param>' and '<set>.compliance' "
        f"(the default for {type(solver).__name__} is {default_params(solver)}); anything else (a scale, a ratio, "
        "shared or reduced coordinates) can be fitted as a pytree with `setup=`")


def _get(name, model, solver, state=None):
    owner = _owner(name, model, solver)
    if owner == "state":
        return state.x if name == "x0" else state.v
    if owner == "constraint":
        c, key = _constraint_of(name, model)
        return c.compliance if key == "compliance" else c.params[key]
    return getattr(model if owner == "model" else solver, name)


def _set(model, solver, values: dict):
    m = {k: v for k, v in values.items() if _owner(k, model, solver) == "model"}
    s = {k: v for k, v in values.items() if _owner(k, model, solver) == "solver"}
    # `replace` validates concrete values; inside jit the values are tracers and validation is skipped.
    model = _tree_replace(model, m)
    solver = _tree_replace(solver, s)
    for name, value in values.items():
        if _owner(name, model, solver) == "constraint":
            model = _constraint_replace(model, *_constraint_of(name, model), value)
    return model, solver


def _constraint_replace(model, c, key, value):
    """`model` with constraint set `c`'s parameter `key` (or its compliance) set to `value`, without checks (the
    value may be a tracer or batched)."""
    leaves, treedef = jax.tree_util.tree_flatten(c)
    keys = sorted(c.params) + ["compliance"]
    leaves[keys.index(key)] = value
    new = jax.tree_util.tree_unflatten(treedef, leaves)
    return jax.tree_util.tree_map(lambda x: new if x is c else x, model, is_leaf=lambda x: x is c)


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


# ---- transforms -------------------------------------------------------------------------------------------------
def _kind(name, value, transforms, bounds=()):
    if name in transforms:
        return transforms[name]
    if name in bounds:          # bounds keep the value inside them: the logistic map onto (lo, hi)
        return "logit"
    if name in TRANSFORMS:
        return TRANSFORMS[name]
    if name.endswith(".compliance"):        # a constraint set's compliance: > 0
        return "log"
    a = np.asarray(value)
    return "log" if np.all(a > 0) else "identity"


class _Param(NamedTuple):
    kind: str
    mask: Any      # entries that are fitted; the others (a fixed particle's inverse mass, position) keep `fixed`
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
    return jnp.where(p.mask, u, p.fixed)


def derivative(u, p: _Param):
    """d value / d u of each entry (0 where not fitted): the delta method's factor."""
    u = np.asarray(u, np.float64)
    if p.kind == "log":
        d = np.exp(u)
    elif p.kind == "logit":
        s = 1 / (1 + np.exp(-u))
        d = (p.hi - p.lo) * s * (1 - s)
    else:
        d = np.ones_like(u)
    return np.where(np.asarray(p.mask), d, 0.0)


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
    if isinstance(params, dict):
        raise TypeError(f"fit: `params` is a dict of values: to fit a pytree theta0 pass setup=f, "
                        "f(theta, model, state, solver) -> (model, state, solver); named parameters are a tuple "
                        "of names")
    try:
        params = tuple(params)
    except TypeError:
        raise TypeError(f"fit: `params` must be parameter names (or, with `setup=`, a pytree of floats), got "
                        f"{type(params).__name__}") from None
    if not all(isinstance(p, str) for p in params):
        raise TypeError(f"fit: `params` must be parameter names; to fit a pytree of values {params!r} pass "
                        "setup=f, f(theta, model, state, solver) -> (model, state, solver)")
    if not params:
        raise ValueError("fit: `params` is empty: name at least one parameter to fit")
    if len(set(params)) != len(params):
        raise ValueError(f"fit: `params` names a parameter twice: {params}")
    return params


def _check_start(name, value, kind, lo, hi):
    """The initial value must be one its transform can represent and move: log > 0 (a fixed particle's inverse
    mass, 0, stays 0), logit within [lo, hi] (a value on a bound starts 1e-6 of the range inside it)."""
    v = np.asarray(value, np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"fit: `{name}` has a non-finite initial value")
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


def _parameters(params, model, solver, state, transforms, bounds):
    """(spec, u0): each named parameter's transform and its unconstrained initial value, in the state's dtype.
    x0 and v0 fit the free particles only (inverse mass > 0); fixed particles keep their positions and
    velocities."""
    dtype = jnp.result_type(state.x)
    spec, u0 = {}, {}
    for name in params:
        value = _get(name, model, solver, state)
        if value is None:
            raise ValueError(f"fit: `{name}` is not set on this model (contact parameters exist only on models "
                             "built with `planes`, `spheres` or `collide`)")
        kind = _kind(name, value, transforms, bounds)
        lo, hi = bounds.get(name, (0.0, 1.0))
        _check_start(name, value, kind, lo, hi)
        u, mask = _encode(value, kind, lo, hi)
        if name in STATE_PARAMS:
            mask = mask & np.broadcast_to((np.asarray(model.inv_mass) > 0)[:, None], np.shape(value))
        spec[name] = _Param(kind, jnp.asarray(mask), jnp.asarray(value).astype(dtype), float(lo), float(hi))
        u0[name] = jnp.asarray(u).astype(dtype)
    return spec, u0


# ---- parameter sets ---------------------------------------------------------------------------------------------
class ParamSet:
    """The fitted parameters as one pytree u of unconstrained values, and how they reach a rollout.

      u0:      the initial unconstrained values (a dict {name: array} for named parameters, else theta0's tree).
      specs:   [leaves] each leaf's _Param (transform, fitted mask, bounds).
      labels:  [leaves] each leaf's name for messages ("rest_length", "params['ratio']").
      put:     (values, model, state_b, solver, batched) -> (model, state_b, solver) for the rollout; state_b is
               the batched start state [B, n, dim].
      named:   True for named parameters (then x0 / v0 gauge directions are known, see `uncertainty`).
    """

    def __init__(self, u0, specs, labels, put: Callable, named: bool):
        self.u0, self.specs, self.labels, self.put, self.named = u0, specs, labels, put, named
        self.treedef = jax.tree_util.tree_structure(u0)

    def decode(self, u):
        leaves = self.treedef.flatten_up_to(u)
        return self.treedef.unflatten([_decode(a, p) for a, p in zip(leaves, self.specs)])

    def apply(self, u, model, state_b, solver, batched):
        return self.put(self.decode(u), model, state_b, solver, batched)

    def masks(self):
        """A pytree like u0: True where an entry is fitted."""
        return self.treedef.unflatten([np.broadcast_to(np.asarray(p.mask), np.shape(a))
                                       for p, a in zip(self.specs, jax.tree.leaves(self.u0))])

    def entry_labels(self) -> list:
        """The name of every scalar in ravel order, with its transform ("log inv_mass[2]", "x0[1, 0]",
        "params['ratio']")."""
        out = []
        for lab, a, p in zip(self.labels, jax.tree.leaves(self.u0), self.specs):
            shape, pre = np.shape(a), ("" if p.kind == "identity" else p.kind + " ")
            out += [pre + lab] if not shape else [f"{pre}{lab}[{', '.join(map(str, i))}]" for i in np.ndindex(*shape)]
        return out


def named_params(params, model, solver, state, transforms, bounds) -> ParamSet:
    names = _param_names(params)
    transforms, bounds = _check_transforms_and_bounds(names, transforms, bounds)
    spec, u0 = _parameters(names, model, solver, state, transforms, bounds)
    keys = list(jax.tree_util.tree_structure(u0).flatten_up_to({k: k for k in u0}))
    return ParamSet(u0, [spec[k] for k in keys], keys, _put_named, True)


def _put_named(values, model, state_b, solver, batched):
    values = dict(values)
    state = {k: values.pop(k) for k in STATE_PARAMS if k in values}
    model, solver = _set(model, solver, values)
    changes = {("x" if k == "x0" else "v"): (v if batched else v[None]) for k, v in state.items()}
    return model, _tree_replace(state_b, changes), solver


def setup_params(theta0, setup, model, state, solver, transforms, bounds) -> ParamSet:
    """A pytree theta0 of floats, put into the model, state and solver by setup(theta, model, state, solver).
    Every leaf is fitted, unchanged ('identity') unless `transforms` / `bounds` (keyed by theta0's top-level dict
    keys) say otherwise. setup is called once here, on theta0, and its result checked."""
    if not callable(setup):
        raise TypeError(f"fit: `setup` must be a function f(theta, model, state, solver) -> (model, state, solver), "
                        f"got {type(setup).__name__}")
    dtype = jnp.result_type(state.x)
    flat, treedef = jax.tree_util.tree_flatten_with_path(theta0)
    if not flat:
        raise ValueError("fit: `params` (theta0, with `setup=`) has no leaves: give the initial values to fit")
    keys = tuple(theta0) if isinstance(theta0, dict) else ()
    if (transforms or bounds) and not keys:
        raise ValueError("fit: with `setup=`, `transforms` and `bounds` are keyed by theta0's top-level dict keys; "
                         f"theta0 is a {type(theta0).__name__}")
    transforms, bounds = _check_transforms_and_bounds(keys, transforms, bounds)
    specs, labels, u_leaves = [], [], []
    for path, leaf in flat:
        label = "params" + jax.tree_util.keystr(path)
        a = np.asarray(leaf)
        if a.dtype.kind not in "fiu" or a.dtype == bool:
            raise TypeError(f"fit: `params` ({label}) must hold real floats, got dtype {a.dtype}")
        top = path[0].key if keys and hasattr(path[0], "key") else None
        kind = transforms.get(top, "logit" if top in bounds else "identity")
        lo, hi = bounds.get(top, (0.0, 1.0))
        _check_start(label, a, kind, lo, hi)
        u, mask = _encode(a, kind, lo, hi)
        specs.append(_Param(kind, jnp.asarray(mask), jnp.asarray(a).astype(dtype), float(lo), float(hi)))
        labels.append(label)
        u_leaves.append(jnp.asarray(u).astype(dtype))
    theta = treedef.unflatten([jnp.asarray(a).astype(dtype) for _, a in flat])
    _check_setup(setup, theta, model, state, solver)

    def put(values, model, state_b, solver, batched):
        st = state_b if batched else jax.tree.map(lambda a: a[0], state_b)
        m, st, s = setup(values, model, st, solver)
        return m, (st if batched else jax.tree.map(lambda a: jnp.asarray(a)[None], st)), s

    return ParamSet(treedef.unflatten(u_leaves), specs, labels, put, False)


def _check_setup(setup, theta, model, state, solver):
    """setup(theta0, ...) must return (Model with the same topology, State with the same shapes, a solver of the
    same type): said here, before anything is traced."""
    out = setup(theta, model, state, solver)
    if not (isinstance(out, tuple) and len(out) == 3):
        raise TypeError("fit: `setup` must return a tuple (model, state, solver), got "
                        f"{type(out).__name__}")
    m, st, s = out
    if not isinstance(m, Model) or m.topology != model.topology:
        raise TypeError("fit: `setup` must return the model (with its values replaced: model.replace(...)) as its "
                        f"first item, got {type(m).__name__}" + ("" if not isinstance(m, Model) else
                                                                 " with another topology"))
    if not isinstance(st, State) or np.shape(st.x) != np.shape(state.x) or np.shape(st.v) != np.shape(state.v):
        raise TypeError("fit: `setup` must return a State shaped like `state` as its second item (x "
                        f"{np.shape(state.x)}), got {type(st).__name__}"
                        + (f" with x {np.shape(st.x)}" if isinstance(st, State) else ""))
    if type(s) is not type(solver) or not isinstance(s, Solver):
        raise TypeError(f"fit: `setup` must return a {type(solver).__name__} as its third item, got "
                        f"{type(s).__name__}")


def tangent_velocities(model, x, v):
    """v [B, n, dim] with the components along the model's rods removed at positions x [B, n, dim]: the
    mass-weighted projection onto J(x) v = 0 (v - M^-1 J^T (J M^-1 J^T)^+ J v), what a constraint solver's first
    step removes. Ropes are left alone (they act one way). NumPy, float64."""
    t = model.topology
    rods = np.nonzero(~np.asarray(t.is_rope))[0]
    v = np.array(v, np.float64)
    if not len(rods):
        return v
    inv_m = np.repeat(np.asarray(model.inv_mass, np.float64), x.shape[-1])
    i, j, rows = t.i[rods], t.j[rods], np.arange(len(rods))
    for b in range(len(x)):
        d = x[b, j] - x[b, i]
        n = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
        G = np.zeros((len(rods),) + x.shape[1:])
        G[rows, i] -= n
        G[rows, j] += n
        G = G.reshape(len(rods), -1)
        WGt = inv_m[:, None] * G.T
        lam = np.linalg.lstsq(G @ WGt, G @ v[b].ravel(), rcond=None)[0]
        v[b] -= (WGt @ lam).reshape(v[b].shape)
    return v
