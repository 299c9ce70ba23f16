"""Diagnostics: constraint violation, energies and drift, and `diagnose`, a report on a recorded trajectory
(violation, energy, impulses) that names what went wrong.

Each public function checks its arguments where it is called (shapes are known then), and computes in one
jitted program: called eagerly, as in a notebook, a diagnostic compiles once per model and shape instead of
dispatching, and compiling, each of its small operations one by one."""
from __future__ import annotations

import functools
import warnings
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core.layout import safe_norm
from jaxcon.core.model import Model, State, Trajectory, check_partners
from jaxcon.core.pytree import concrete

Array = Any


def nan_max(a, axis=None):
    """jnp.max that returns NaN wherever the reduced values contain a NaN.

    XLA semantics propagate NaN through max, but on CPU jaxlib 0.10.2 reduces large arrays (4096 values and
    more) with a kernel that skips NaN: jnp.max of 4095 ones and a NaN returns 1.0, and a slice of NaN rows
    returned -inf. Diagnostics must not turn a diverged run into a finite number, so they reduce with this."""
    a = jnp.asarray(a)
    return jnp.where(jnp.any(jnp.isnan(a), axis=axis), jnp.nan, jnp.max(a, axis=axis))


def _masses(model: Model):
    w = jnp.asarray(model.inv_mass)
    free = w > 0
    return jnp.where(free, 1 / jnp.where(free, w, 1), 0)


def kinetic_energy(model: Model, v):
    """Kinetic energy (J) of the free particles. v: [..., n, dim]."""
    check_particles("kinetic_energy", model, "v", v)
    return _kinetic_energy(model, v)


@jax.jit
def _kinetic_energy(model: Model, v):
    return 0.5 * jnp.sum(_masses(model) * jnp.sum(v * v, -1), -1)


def energy(model: Model, x, v):
    """Total mechanical energy (J): the free particles' kinetic and gravitational energy, plus the potential
    energy C^2 / (2 alpha) of every compliant constraint of a `jc.Constraint` set (alpha > 0; for a unilateral
    one only while C < 0). x, v: [..., n, dim]."""
    check_particles("energy", model, "x", x)
    check_particles("energy", model, "v", v)
    return _energy(model, x, v)


@jax.jit
def _energy(model: Model, x, v):
    pe = -jnp.sum(_masses(model) * jnp.sum(x * model.gravity, -1), -1)
    return _kinetic_energy(model, v) + pe + _elastic_energy(model, x)


def _elastic_energy(model: Model, x):
    """The potential energy C^2 / (2 alpha) of the compliant rows of the constraint sets at x [..., n, dim]."""
    pe = jnp.zeros(x.shape[:-2], x.dtype)
    for c, C in zip(model.constraints, _set_values(model, x)):
        alpha = jnp.broadcast_to(jnp.asarray(c.compliance, C.dtype), (c.m,))
        soft = alpha > 0
        stretch = jnp.minimum(C, 0) if c.unilateral else C
        pe = pe + jnp.sum(jnp.where(soft, stretch * stretch / (2 * jnp.where(soft, alpha, 1)), 0), -1)
    return pe


def _set_values(model: Model, x, degenerate=0.0) -> list:
    """C of every row of each `jc.Constraint` set at positions x [..., n, dim]: a list of [..., m_set],
    `degenerate` where C is not finite at finite positions (a degenerate configuration, where the solvers leave
    the row inactive: NaN for `violation`, so an inactive row is not reported as satisfied; 0 for the energy);
    NaN where the row's positions are not finite (a diverged run stays visible)."""
    out = []
    for c in model.constraints:
        xs = x[..., c.particles.array, :]                      # [..., m, k, dim]
        f = jax.vmap(c.fn)
        for _ in range(xs.ndim - 3):
            f = jax.vmap(f, in_axes=(0, None))
        C = f(xs, c.params)
        sane = jnp.all(jnp.isfinite(xs), axis=(-1, -2))
        out.append(jnp.where(jnp.isfinite(C), C, jnp.where(sane, degenerate, jnp.nan)))
    return out


def energy_drift(model: Model, state, traj):
    """(E_end - E_0) / max kinetic energy along the trajectory: the energy a rollout gained (> 0) or lost
    (< 0), relative to the energy it exchanged. Fixed particles are excluded."""
    e0 = energy(model, state.x, state.v)
    e1 = energy(model, traj.x[-1], traj.v[-1])
    ke = nan_max(kinetic_energy(model, traj.v), axis=0)
    return (e1 - e0) / jnp.maximum(ke, jnp.finfo(ke.dtype).tiny)


def check_particles(owner: str, model: Model, name: str, a) -> None:
    """Raise unless `a` is [..., n, dim] for this model (before any computation: a wrong shape would otherwise
    index or broadcast into a wrong answer)."""
    t = model.topology
    shape = tuple(jnp.shape(a))
    if len(shape) < 2 or shape[-2:] != (t.n, t.dim):
        raise ValueError(f"{owner}: `{name}` must have shape [..., {t.n}, {t.dim}] (particles, dim) for this model, "
                         f"got {shape}")


def violation(model: Model, x):
    """Constraint violation [..., m], in lam's order: |d - L| / L for rods, max(d - L, 0) / L for ropes (a slack
    rope is not violated; where L = 0 the absolute violation), then for each `jc.Constraint` set |C| (C = 0) or
    max(-C, 0) (C >= 0) in C's own units (radians for `bending` and `angle`, m^2 for `area`, ...). A compliant
    set's C is its elastic deformation, reported as well. x: [..., n, dim]."""
    check_particles("violation", model, "x", x)
    return _violation(model, x)


@jax.jit
def _violation(model: Model, x):
    t = model.topology
    d, _ = safe_norm(x[..., t.j, :] - x[..., t.i, :], axis=-1)
    err = d - model.rest_length
    err = jnp.where(t.is_rope, jnp.maximum(err, 0), jnp.abs(err))
    L = jnp.asarray(model.rest_length)
    parts = [err / jnp.where(L > 0, L, 1)]
    for c, C in zip(model.constraints, _set_values(model, x, jnp.nan)):
        parts.append(jnp.maximum(-C, 0) if c.unilateral else jnp.abs(C))
    return jnp.concatenate(parts, -1)


def _hard(model: Model, dtype):
    """[m] True for the constraints `diagnose` holds to VIOLATION_LIMIT: rods, ropes and the rows of sets with
    compliance 0 (a compliant row's C is its elastic deformation)."""
    t = model.topology
    parts = [jnp.ones(t.m_pairs, bool)]
    for c in model.constraints:
        parts.append(jnp.broadcast_to(jnp.asarray(c.compliance, dtype), (c.m,)) == 0)
    return jnp.concatenate(parts)


def _grid_partners(owner, model, partners, lead):
    """A grid model's partners [..., n, K] (checked), or raise: its pair contacts change from step to step."""
    c = model.contact
    if partners is None:
        raise ValueError(f"{owner}: this model finds its pairs with a neighbour grid, so its pair contacts depend on "
                         "the step: pass `partners` (State.contact_partners or Trajectory.contact_partners)")
    shape = tuple(jnp.shape(partners))
    if shape[-2:] != (model.topology.n, c.grid_k) or (lead is not None and shape[:-2] != tuple(lead)):
        raise ValueError(f"{owner}: `partners` must have shape [..., {model.topology.n}, {c.grid_k}] matching x, "
                         f"got {shape}")
    return jnp.asarray(partners)


def contact_sizes(model: Model, partners=None):
    """[k] (or [..., k]) the size each contact's overlap is measured against: the particle's radius for
    obstacles, the sum of radii for pairs ([0] without contacts). A grid model needs its `partners`
    [..., n, K] (empty slots: size 0)."""
    c = model.contact
    if c is None:
        return jnp.zeros((0,))
    if c.has_grid:
        partners = _grid_partners("contact_sizes", model, partners, None)
    return _contact_sizes(model, partners)


@jax.jit
def _contact_sizes(model: Model, partners):
    c = model.contact
    r = jnp.asarray(model.radius)
    parts = [jnp.tile(r, c.n_obstacles)]
    if c.n_pairs:
        parts.append(r[c.pairs.array[:, 0]] + r[c.pairs.array[:, 1]])
    if c.has_grid:
        p = partners
        lead = p.shape[:-2]
        size = jnp.where(p >= 0, r[:, None] + r[jnp.maximum(p, 0)], 0).reshape(lead + (-1,))
        parts = [jnp.broadcast_to(a, lead + a.shape) for a in parts] + [size]
    return jnp.concatenate(parts, -1)


def penetration(model: Model, x, partners=None):
    """Overlap depth (m, >= 0) of every contact [..., k], in the order of `State.contact_n`: planes
    (max(offset + r - n . x, 0)), spheres (max(R + r - |x - c|, 0)), then pairs (max(r_i + r_j - |x_j - x_i|, 0)).
    [..., 0] for a model without contacts. x: [..., n, dim]. A model with a neighbour grid needs `partners`
    [..., n, K] (State.contact_partners, or Trajectory.contact_partners for a trajectory's x): its pair
    contacts are the slots listed there (empty slots: 0)."""
    check_particles("penetration", model, "x", x)
    c = model.contact
    if c is None:
        return jnp.zeros(jnp.shape(x)[:-2] + (0,), jnp.result_type(x))
    if c.has_grid:
        partners = _grid_partners("penetration", model, partners, jnp.shape(x)[:-2])
    return _penetration(model, jnp.asarray(x), partners)


@jax.jit
def _penetration(model: Model, x, partners):
    c = model.contact
    r = jnp.asarray(model.radius, x.dtype)
    parts = []
    normal = safe_norm(jnp.asarray(model.plane_normal), axis=-1)[1]       # unit, as the solvers use it
    for p in range(c.n_planes):
        parts.append(model.plane_offset[p] + r - jnp.sum(x * normal[p], -1))
    for q in range(c.n_spheres):
        dist, _ = safe_norm(x - model.sphere_centre[q], axis=-1)
        parts.append(model.sphere_radius[q] + r - dist)
    if c.n_pairs:
        i, j = c.pairs.array[:, 0], c.pairs.array[:, 1]
        dist, _ = safe_norm(x[..., j, :] - x[..., i, :], axis=-1)
        parts.append(r[i] + r[j] - dist)
    if c.has_grid:
        p = partners
        pc = jnp.maximum(p, 0)
        flat = pc.reshape(p.shape[:-2] + (-1,))                                     # [..., n K]
        xj = jnp.take_along_axis(x, flat[..., None], axis=-2).reshape(p.shape + (x.shape[-1],))
        dist, _ = safe_norm(xj - x[..., :, None, :], axis=-1)
        over = jnp.where(p >= 0, r[:, None] + r[pc] - dist, 0)
        parts.append(over.reshape(p.shape[:-2] + (-1,)))
    return jnp.maximum(jnp.concatenate(parts, -1), 0)


#: A trajectory is diverged when some constraint is off its rest length by more than this fraction of it
#: (``jc.violation`` > 1.0: a rod stretched to twice its length or collapsed to a point).
VIOLATION_LIMIT = 1.0


#: ... or when a contact overlaps by more than this fraction of its size (`contact_sizes`): a particle half
#: behind a plane or inside a sphere, or two balls whose centres are closer than the mean of their radii. A
#: pair that has passed through itself never overlaps by more than its size, so the limit is below it.
PENETRATION_LIMIT = 0.5


#: ... or when its total energy rose above the initial energy by more than this many energy scales, the scale
#: being ``KE_0 + PE_0 + M |g| sum(L)`` (the initial kinetic energy, the elastic energy of the compliant rows,
#: plus the potential energy all free mass would release by falling the total rest length of the model); where
#: that is 0 (no gravity, motion or stored energy at the start), the largest kinetic plus elastic energy of the
#: run; floored at the machine tiny. A change within rounding of the energies is no gain.
ENERGY_LIMIT = 10.0


class Diagnosis(NamedTuple):
    """Result of `diagnose` for one trajectory (for a batch of rollouts, ``jax.vmap`` it).

      violation:   [steps] largest constraint violation (``jc.violation``) of each step over the rods, ropes
                   and hard (compliance 0) rows of constraint sets.
      energy:      [steps] total mechanical energy (J) after each step (``jc.energy``: with the potential
                   energy of compliant constraint sets).
      energy_gain: [steps] (E - E_0) / energy scale (see ENERGY_LIMIT).
      bad:         [steps] bool, the step is non-finite, over VIOLATION_LIMIT, ENERGY_LIMIT or
                   PENETRATION_LIMIT.
      diverged:    bool, some step is bad.
      first_bad:   int, index of the first bad step, or -1.
      penetration: [steps] deepest contact overlap (m) of each step (``jc.penetration``); 0 without contacts.
      overflow:    [steps] int, candidate pairs the neighbour grid had no room for (Trajectory.contact_overflow;
                   0 for models without a grid). > 0 means contacts may have been missed in that step: build
                   the model with a larger `max_neighbours`. Not counted as bad (it is not a divergence).
      overflowed:  bool, some step has overflow > 0.
    """

    violation: Array
    energy: Array
    energy_gain: Array
    bad: Array
    diverged: Array
    first_bad: Array
    penetration: Array = None
    overflow: Array = None
    overflowed: Array = None


def diagnose(model: Model, traj: Trajectory, state0: Optional[State] = None) -> Diagnosis:
    """Diagnose a rollout: `traj` as returned by ``jc.rollout`` (x, v [steps, n, dim], lam [steps, m]).

    `state0` (the rollout's initial state) sets the reference energy E_0 and its kinetic energy; without it
    the first recorded step is the reference. A step is *bad* when any of its x, v, lam is non-finite, when
    its largest relative violation exceeds VIOLATION_LIMIT (1.0), when its energy exceeds E_0 by more than
    ENERGY_LIMIT (10) energy scales, or when a contact of nonzero size overlaps by more than PENETRATION_LIMIT
    (0.5) of its size. NaNs compare as bad. Callable under jax.jit.

    For a model with a neighbour grid, `overflow` reports each step's `traj.contact_overflow`; when it is known
    now (outside jit) and some step overflowed, a warning says to raise `max_neighbours`.
    """
    if not isinstance(model, Model):
        raise TypeError(f"diagnose: `model` must be a jaxcon Model, got {type(model).__name__}")
    if not isinstance(traj, Trajectory):
        raise TypeError(f"diagnose: `traj` must be a jaxcon Trajectory, got {type(traj).__name__}")
    if state0 is not None and not isinstance(state0, State):
        raise TypeError(f"diagnose: `state0` must be a jaxcon State or None, got {type(state0).__name__}")
    t = model.topology
    if jnp.ndim(traj.x) != 3:
        raise ValueError("diagnose: `traj.x` must be [steps, n, dim] (vmap diagnose over batches), got shape "
                         f"{jnp.shape(traj.x)}")
    steps = jnp.shape(traj.x)[0]
    for name, want in (("x", (steps, t.n, t.dim)), ("v", (steps, t.n, t.dim)), ("lam", (steps, t.m))):
        got = tuple(jnp.shape(getattr(traj, name)))
        if got != want:
            raise ValueError(f"diagnose: `traj.{name}` has shape {got}, but this model ({t.n} particles, dim {t.dim}, "
                             f"{t.m} constraints) and {steps} recorded steps need {want}: is it the model that "
                             "made the trajectory?")
    if state0 is not None:
        for name, want in (("x", (t.n, t.dim)), ("v", (t.n, t.dim))):
            got = tuple(jnp.shape(getattr(state0, name)))
            if got != want:
                raise ValueError(f"diagnose: `state0.{name}` has shape {got}, this model needs {want}")
    _check_contact_record(model, traj, steps)
    grid = model.contact is not None and model.contact.has_grid
    d = _diagnosis(model, traj, state0)
    known = concrete(d.overflow)
    if grid and known is not None and np.any(np.asarray(known) > 0):
        k = int(np.argmax(np.asarray(known) > 0))
        warnings.warn(f"diagnose: the neighbour grid ran out of room in {int(np.sum(np.asarray(known) > 0))} "
                      f"step(s), first at step {k} ({int(np.asarray(known)[k])} candidate pairs without a slot): "
                      f"contacts may have been missed. Build the model with a larger `max_neighbours` (now "
                      f"{model.contact.grid_k})", stacklevel=2)
    return d


def _check_contact_record(model: Model, traj: Trajectory, steps: int) -> None:
    """`traj`'s contact arrays must be the ones this model records: none without contacts; contact_n [T, k] and
    contact_t [T, k, dim] (each may be None) with them; a grid's contact_partners [T, n, K] and contact_overflow
    [T] (both needed). A trajectory of another contact model is refused instead of measured against this one."""
    t, c = model.topology, model.contact
    names = ("contact_n", "contact_t", "contact_partners", "contact_overflow")
    grid = c is not None and c.has_grid
    want = {"contact_n": None if c is None else (steps, c.k), "contact_t": None if c is None else (steps, c.k, t.dim),
            "contact_partners": (steps, t.n, c.grid_k) if grid else None,
            "contact_overflow": (steps,) if grid else None}
    what = "no contacts" if c is None else f"{c.k} contact slots ({c!r})"
    for name in names:
        a = getattr(traj, name)
        if a is None:
            if grid and name in ("contact_partners", "contact_overflow"):
                raise ValueError("diagnose: this model has a neighbour grid, so `traj` needs its contact_partners "
                                 "and contact_overflow (as jc.rollout records them)")
            continue
        if want[name] is None:
            raise ValueError(f"diagnose: `traj.{name}` is set, but this model has {what}"
                             f"{'' if c is None else ' and no neighbour grid'}: is it the model that made the "
                             "trajectory?")
        got = tuple(jnp.shape(a))
        if got != want[name]:
            raise ValueError(f"diagnose: `traj.{name}` has shape {got}, but this model ({what}) and {steps} recorded "
                             f"steps need {want[name]}: is it the model that made the trajectory?")
    if grid:
        check_partners("diagnose", "traj.contact_partners", traj.contact_partners)


@functools.partial(jax.jit, static_argnames=("energy",))
def _diagnosis(model: Model, traj: Trajectory, state0: Optional[State], energy: bool = True) -> Diagnosis:
    """`diagnose` after its checks (the shapes, and a grid model's partners): one program. `energy=False` leaves
    the energy gain out of `bad` (`jc.fit` of a driven experiment: the drive's work is no divergence)."""
    t = model.topology
    x, v = traj.x, traj.v
    if t.m:
        rows = _violation(model, x)         # NaN for a row whose C is not finite, compliant or not: flagged
        viol = nan_max(jnp.where(_hard(model, x.dtype) | jnp.isnan(rows), rows, 0), axis=-1)
    else:
        viol = jnp.zeros(x.shape[:1], x.dtype)
    e = _energy(model, x, v)
    x0, v0 = (x[0], v[0]) if state0 is None else (state0.x, state0.v)
    e0 = _energy(model, x0, v0)
    mass = jnp.sum(_masses(model))
    ke0 = _kinetic_energy(model, v0)
    # With contacts, particles may fall without any constraint, and a model of constraint sets alone has no
    # rest lengths: the height scale is then also the initial extent (without it, a spring of a set hanging
    # from a pivot had a scale of ~1e-308 J and an energy gain of -3.8e303).
    extent = 0 if model.contact is None and t.m_pairs else jnp.linalg.norm(jnp.max(x0, 0) - jnp.min(x0, 0)) + (
        jnp.max(jnp.abs(x0)))
    scale = ke0 + _elastic_energy(model, x0) + mass * jnp.linalg.norm(model.gravity) * (
        jnp.sum(model.rest_length) + extent)
    # Without gravity, motion or stored energy at the start, the scale is 0: the energy the run exchanges
    # (its largest kinetic plus elastic energy) is the scale then, and a change within rounding is no gain
    # (it was (1e-18 J) / tiny = inf).
    fi = jnp.finfo(jnp.result_type(scale))
    exchanged = nan_max(_kinetic_energy(model, v) + _elastic_energy(model, x))
    scale = jnp.maximum(jnp.where(scale > fi.tiny, scale, exchanged), fi.tiny)
    change = e - e0
    change = jnp.where(jnp.abs(change) <= 64 * fi.eps * jnp.maximum(jnp.abs(e), jnp.abs(e0)), 0, change)
    gain = change / scale
    finite = (jnp.all(jnp.isfinite(x), axis=(-1, -2)) & jnp.all(jnp.isfinite(v), axis=(-1, -2))
              & jnp.all(jnp.isfinite(traj.lam), axis=-1))
    ok = finite & (viol <= VIOLATION_LIMIT) & ((gain <= ENERGY_LIMIT) if energy else True)
    grid = model.contact is not None and model.contact.has_grid
    partners = traj.contact_partners if grid else None
    if model.contact is None:
        pen = jnp.zeros(x.shape[:1] + (0,), x.dtype)
    else:
        pen = _penetration(model, x, partners)
    if pen.shape[-1]:
        size = _contact_sizes(model, partners)
        ok = ok & jnp.all((pen <= PENETRATION_LIMIT * size) | (size <= 0), axis=-1)
        pen = jnp.max(pen, -1)
    else:
        pen = jnp.zeros(x.shape[:1], x.dtype)
    bad = ~ok
    first = jnp.where(jnp.any(bad), jnp.argmax(bad), -1)
    overflow = jnp.asarray(traj.contact_overflow) if grid else jnp.zeros(x.shape[:1], jnp.int32)
    return Diagnosis(viol, e, gain, bad, jnp.any(bad), first, pen, overflow, jnp.any(overflow > 0))
