"""Physical diagnostics on user-layout arrays; they broadcast over leading (time, batch) axes."""
from __future__ import annotations

import jax.numpy as jnp

from ._layout import safe_norm
from ._model import Model


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
    return 0.5 * jnp.sum(_masses(model) * jnp.sum(v * v, -1), -1)


def energy(model: Model, x, v):
    """Total mechanical energy (J) of the free particles: kinetic + gravitational. x, v: [..., n, dim]."""
    check_particles("energy", model, "x", x)
    pe = -jnp.sum(_masses(model) * jnp.sum(x * model.gravity, -1), -1)
    return kinetic_energy(model, v) + pe


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
    """Relative constraint violation [..., m]: |d - L| / L for rods, max(d - L, 0) / L for ropes (a slack rope
    is not violated). Where L = 0 the absolute violation is returned. x: [..., n, dim]."""
    check_particles("violation", model, "x", x)
    t = model.topology
    d, _ = safe_norm(x[..., t.j, :] - x[..., t.i, :], axis=-1)
    err = d - model.rest_length
    err = jnp.where(t.is_rope, jnp.maximum(err, 0), jnp.abs(err))
    L = jnp.asarray(model.rest_length)
    return err / jnp.where(L > 0, L, 1)
