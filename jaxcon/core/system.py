"""The solver interface: `System` (a model in the solvers' internal layout) and the `Solver` base class."""
from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.contact import ContactSystem
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
    contact: Any = None          # a ContactSystem (jaxcon.core.contact) for models with contacts
    accel: Any = None            # the step's external acceleration w F [dim, *view], or None
    sets: tuple = ()             # per block of a jc.Constraint set: its leaves in its layout (`rows.SetSystem`)
    cons: tuple = static_field(default=())   # the sets' `Constraint`s with their leaves dropped (fn, kind, name)

    @classmethod
    def from_model(cls, model: Model, dtype) -> "System":
        t = model.topology
        w = L.per_particle_in(t, jnp.asarray(model.inv_mass, dtype))
        rest = jnp.asarray(model.rest_length, dtype)
        if t.has_sets:         # rest lengths are the pairs'; a set block's entries are unused zeros
            rest = jnp.concatenate([rest, jnp.zeros(t.m - t.m_pairs, dtype)])
        rest = L.constraints_in(t, rest)
        firsts = np.cumsum([t.m_pairs] + [c.m for c in model.constraints]).tolist()
        sets = [R.set_system(model.constraints[b.generic], b, firsts[b.generic], dtype)
                for b in t.blocks if b.generic is not None]
        cons = tuple(_static(c) for c in model.constraints)
        return cls(w, rest, jnp.asarray(model.gravity, dtype), t, ContactSystem.from_model(model, dtype), None,
                   tuple(sets), cons)

    def set_of(self, block):
        """(the `Constraint`, its `SetSystem`) of a set's block (or `SetRow`)."""
        return self.cons[block.generic], self.sets[block.set_block]

    def apply_gravity(self, v, h):
        """v + h (g + w F): gravity on the free particles, and the step's external forces (`accel`) if any."""
        g = self.gravity.reshape((-1,) + (1,) * len(self.topology.view))
        v = v + h * g * (self.w > 0).astype(v.dtype)
        return v if self.accel is None else v + h * self.accel


class _StaticConstraint:
    """A `Constraint` without its leaves, hashable by its function, kind and name (jit metadata)."""

    __slots__ = ("fn", "grad", "unilateral", "name", "m")

    def __init__(self, c):
        self.fn, self.grad, self.unilateral, self.name, self.m = c.fn, c.grad, c.unilateral, c.name, c.m

    def _key(self):
        return self.fn, self.grad, self.unilateral, self.name, self.m

    def __hash__(self):
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, _StaticConstraint) and self._key() == other._key()


def _static(c):
    return _StaticConstraint(c)


class Solver:
    """Base class. A solver advances the internal carry ``(x, v, lam)`` by one step of length dt.

    Subclasses implement `_step(sys, x, v, lam, dt) -> (x, v, lam_step)`, where x, v are [dim, *view] and lam
    is a tuple of per-block impulses accumulated over the step (used as the next step's warm start). For a
    model with contacts lam is the pair (block impulses, contact `Impulses`), and only solvers whose
    `supports_contacts` is True are given one.
    """

    supports_contacts = False

    def _step(self, sys: System, x, v, lam, dt):
        raise NotImplementedError
