"""`diagnose`: per-step health of a trajectory (violation, energy) and a divergence flag.

Works on the output of any solver, under jit and vmap (everything is array arithmetic, no Python branching on
values).
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import jax.numpy as jnp

from ._diagnostics import energy, kinetic_energy, nan_max, violation
from ._model import Model, State, Trajectory

Array = Any

#: A trajectory is diverged when some constraint is off its rest length by more than this fraction of it
#: (``jc.violation`` > 1.0: a rod stretched to twice its length or collapsed to a point).
VIOLATION_LIMIT = 1.0
#: ... or when its total energy rose above the initial energy by more than this many energy scales, the scale
#: being ``KE_0 + M |g| sum(L)`` (the initial kinetic energy plus the potential energy all free mass would
#: release by falling the total rest length of the model), floored at the machine tiny.
ENERGY_LIMIT = 10.0


class Diagnosis(NamedTuple):
    """Result of `diagnose` for one trajectory (for a batch of rollouts, ``jax.vmap`` it).

      violation:   [steps] largest relative constraint violation (``jc.violation``) of each step.
      energy:      [steps] total mechanical energy (J) after each step.
      energy_gain: [steps] (E - E_0) / energy scale (see ENERGY_LIMIT).
      bad:         [steps] bool, the step is non-finite, over VIOLATION_LIMIT or over ENERGY_LIMIT.
      diverged:    bool, some step is bad.
      first_bad:   int, index of the first bad step, or -1.
    """

    violation: Array
    energy: Array
    energy_gain: Array
    bad: Array
    diverged: Array
    first_bad: Array


def diagnose(model: Model, traj: Trajectory, state0: Optional[State] = None) -> Diagnosis:
    """Diagnose a rollout: `traj` as returned by ``jc.rollout`` (x, v [steps, n, dim], lam [steps, m]).

    `state0` (the rollout's initial state) sets the reference energy E_0 and its kinetic energy; without it
    the first recorded step is the reference. A step is *bad* when any of its x, v, lam is non-finite, when
    its largest relative violation exceeds VIOLATION_LIMIT (1.0), or when its energy exceeds E_0 by more than
    ENERGY_LIMIT (10) energy scales. NaNs compare as bad. Callable under jax.jit.
    """
    if not isinstance(model, Model):
        raise TypeError(f"diagnose: `model` must be a jaxcon Model, got {type(model).__name__}")
    if not isinstance(traj, Trajectory):
        raise TypeError(f"diagnose: `traj` must be a jaxcon Trajectory, got {type(traj).__name__}")
    if state0 is not None and not isinstance(state0, State):
        raise TypeError(f"diagnose: `state0` must be a jaxcon State or None, got {type(state0).__name__}")
    t = model.topology
    if jnp.ndim(traj.x) != 3:
        raise ValueError(f"diagnose: `traj.x` must be [steps, n, dim] (vmap diagnose over batches), got shape {jnp.shape(traj.x)}")
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
    x, v = traj.x, traj.v
    viol = nan_max(violation(model, x), axis=-1)
    e = energy(model, x, v)
    x0, v0 = (x[0], v[0]) if state0 is None else (state0.x, state0.v)
    e0 = energy(model, x0, v0)
    w = jnp.asarray(model.inv_mass)
    free = w > 0
    mass = jnp.sum(jnp.where(free, 1 / jnp.where(free, w, 1), 0))
    ke0 = kinetic_energy(model, v0)
    scale = ke0 + mass * jnp.linalg.norm(model.gravity) * jnp.sum(model.rest_length)
    scale = jnp.maximum(scale, jnp.finfo(jnp.result_type(scale)).tiny)
    gain = (e - e0) / scale
    finite = (jnp.all(jnp.isfinite(x), axis=(-1, -2)) & jnp.all(jnp.isfinite(v), axis=(-1, -2))
              & jnp.all(jnp.isfinite(traj.lam), axis=-1))
    ok = finite & (viol <= VIOLATION_LIMIT) & (gain <= ENERGY_LIMIT)
    bad = ~ok
    first = jnp.where(jnp.any(bad), jnp.argmax(bad), -1)
    return Diagnosis(viol, e, gain, bad, jnp.any(bad), first)
