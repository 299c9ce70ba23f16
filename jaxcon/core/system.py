"""The solver interface: `System` (a model in the solvers' internal layout) and the `Solver` base class."""
from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from jaxcon.core import layout as L
from jaxcon.core.model import Model
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.topology import Topology

Array = Any


@pytree_dataclass
class System:
    """A model in the solver's internal layout (built once per rollout, outside the time loop).

      w:       [1, *view] inverse masses.
      rest:    tuple, per block, of rest lengths [*block.shape].
      gravity: [dim].
      accel:   None, or this step's external acceleration w F [dim, *view] from the user's `forces` (set by the
               time loop for each step; `apply_gravity` adds it, so every solver and substep sees it).
    """

    w: Array
    rest: tuple
    gravity: Array
    topology: Topology = static_field()
    contact: Any = None          # a ContactSystem (jaxcon.solvers.contact) for models with contacts
    accel: Any = None            # the step's external acceleration w F [dim, *view], or None

    @classmethod
    def from_model(cls, model: Model, dtype) -> "System":
        from jaxcon.solvers.contact import ContactSystem
        t = model.topology
        w = L.per_particle_in(t, jnp.asarray(model.inv_mass, dtype))
        rest = L.constraints_in(t, jnp.asarray(model.rest_length, dtype))
        return cls(w, rest, jnp.asarray(model.gravity, dtype), t, ContactSystem.from_model(model, dtype))

    def apply_gravity(self, v, h):
        """v + h (g + w F): gravity on the free particles, and the step's external forces (`accel`) if any."""
        g = self.gravity.reshape((-1,) + (1,) * len(self.topology.view))
        v = v + h * g * (self.w > 0).astype(v.dtype)
        return v if self.accel is None else v + h * self.accel


class Solver:
    """Base class. A solver advances the internal carry ``(x, v, lam)`` by one step of length dt.

    Subclasses implement `_step(sys, x, v, lam, dt) -> (x, v, lam_step)`, where x, v are [dim, *view] and lam
    is a tuple of per-block impulses accumulated over the step (used as the next step's warm start). For a
    model with contacts lam is the pair (block impulses, contact `Impulses`), and only solvers whose
    `supports_contacts` is True are given one.
    """

    supports_contacts = False
    #: Whether the solver can step a model whose pairs come from the neighbour grid (PGS and Jacobi).
    supports_grid = False

    def _step(self, sys: System, x, v, lam, dt):
        raise NotImplementedError
