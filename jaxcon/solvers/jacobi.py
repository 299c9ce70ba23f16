"""Jacobi solver: velocity-level impulses like PGS, but every constraint solved from the same velocities."""
from __future__ import annotations

import functools
from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_bool, check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.substeps import substepped
from jaxcon.core.system import Solver
from jaxcon.solvers import contact_jacobi
from jaxcon.solvers.common import (
    check_stabilization,
    clamp_ropes,
    contact_begin,
    contact_end,
    frames,
    gamma,
    contact_substepped,
    restitution_phases,
    row_solve,
    split_position_pass,
    split_slop,
    velocity_bias,
    warm_start,
)


def max_degree(topo) -> int:
    """Largest number of constraints (of every kind) sharing one free particle (static, from the topology; a
    fixed particle takes no velocity change, so its constraints do not compete); at least 1."""
    ends = [topo.i, topo.j] + [info.particles.reshape(-1) for info in topo.sets]
    deg = np.bincount(np.concatenate(ends), minlength=topo.n) * ~topo.fixed
    return max(int(deg.max(initial=0)), 1)


@pytree_dataclass
class Jacobi(Solver):
    """Projected Jacobi at velocity level with Baumgarte stabilisation.

    Per (sub)step of length h: v += h g; warm start with the previous impulses (ropes clamped >= 0); then each
    iteration computes, for every constraint from the *same* velocities v,

        dlam = relaxation (n . (v_j - v_i) + bias) / (w_i + w_j)      (bias as in `PGS`)

    clamps the accumulated lam + dlam of ropes to >= 0 and applies all the impulse changes at once (summed per
    particle); finally x += h v. The fixed point is the one PGS converges to (every constraint's velocity
    equation holds), but it is reached more slowly; relaxation < 2 / max particle degree always converges
    (Gershgorin bound on the scaled Delassus matrix), so the default is 1 / max degree.

    Contacts (`planes`, `spheres`, `collide`; jaxcon.solvers.contact_jacobi): PGS's rows, warm start,
    time-of-impact correction and position pass, with every contact (all obstacles and all pair slots at once)
    and every rod updated from the same velocities in each iteration. With `relaxation=None` a model with contacts
    is relaxed by mass splitting: a row between particles i and j takes the effective mass
    1 / (c_i w_i + c_j w_j), c the number of rods and pushing contacts at each particle in that iteration
    (convergent, and momentum-conserving: every impulse acts equally and oppositely). On the 16-ball break it
    needs 8 to 10 times PGS's iterations to converge (e.g. `Jacobi(20, substeps=2)` where `PGS(20)` suffices).

    Args:
      iterations: Jacobi iterations per (sub)step, static, >= 1.
      beta: Baumgarte factor in [0, 1], a differentiable leaf; with split impulses only the contacts' push-out
        rate.
      relaxation: scale of the summed impulse in (0, 2], a differentiable leaf; None: 1 / (largest number of
        constraints at one particle) of the model being solved, or mass splitting for a model with contacts
        (a fixed value there scales every rod and contact row alike).
      warm_start: start from the previous step's impulses (static); a constraint set's compliant rows from a
        share of theirs, none where the spring is stiff for the step (`common.warm_rows`).
      substeps: (sub)steps per step, static, >= 1.
      stabilization: 'baumgarte' (default) or 'split' (static): split impulses as in `PGS`, the position
        projection by Jacobi sweeps with the rods' relaxation (1 / largest degree by default).
      slop: split impulses' slop, as in `PGS`.
    """

    iterations: int = static_field(default=20)
    beta: Any = 0.2
    relaxation: Any = None
    warm_start: bool = static_field(default=True)
    substeps: int = static_field(default=1)
    stabilization: str = static_field(default="baumgarte")
    slop: Any = 0.005

    def __post_init__(self):
        check_stabilization("Jacobi", self.stabilization)
        check_scalar("Jacobi", "slop", self.slop, 0.0, 1.0)
        check_int("Jacobi", "iterations", self.iterations, 1)
        check_int("Jacobi", "substeps", self.substeps, 1)
        check_bool("Jacobi", "warm_start", self.warm_start)
        check_scalar("Jacobi", "beta", self.beta, 0.0, 1.0)
        if self.relaxation is not None:
            check_scalar("Jacobi", "relaxation", self.relaxation, 0.0, 2.0, positive=True)

    supports_contacts = True

    def _step(self, sys, x, v, lam, dt):
        if sys.contact is not None:
            return contact_substepped(sys, functools.partial(self._substep_contacts, sys), self.substeps, x, v, lam,
                                      dt)
        topo = sys.topology
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        relax = (jnp.asarray(1.0 / max_degree(topo), dtype) if self.relaxation is None
                 else jnp.asarray(self.relaxation, dtype))
        share = jnp.asarray(self.slop, dtype)

        def substep(x, v, lam_ws, h):
            v = sys.apply_gravity(v, h)
            split = self.stabilization == "split"
            fr = frames(sys, x)
            slop = split_slop(sys, fr, v, h, beta, share) if split else None
            bias = velocity_bias(topo, fr, beta, h, slop)
            if self.warm_start:
                v, lam = warm_start(sys, v, fr, lam_ws, h)
            else:
                lam = tuple(jnp.zeros_like(f.C) for f in fr)

            gs = tuple(gamma(f, h) for f in fr)

            def iterate(_, carry):
                v, lam = carry
                new = []
                dv = jnp.zeros_like(v)
                for blk, f, b, g, l in zip(topo.blocks, fr, bias, gs, lam):
                    rel = R.rel(topo, blk, f, v)
                    step = (rel + b) * f.k if g is None else row_solve(topo, blk, f, rel + b, l, g)
                    nl = clamp_ropes(blk, l + relax * step)
                    dv = R.apply(topo, blk, f, dv, nl - l)
                    new.append(nl)
                return v + dv, tuple(new)

            v, lam = lax.fori_loop(0, self.iterations, iterate, (v, lam))
            if split:
                return split_position_pass(sys, x + h * v, self.iterations, slop, relax), v, lam
            return x + h * v, v, lam

        return substepped(substep, self.substeps, x, v, lam, dt)

    def _substep_contacts(self, sys, x, v, lam_ws, h, found=None):
        """One (sub)step of a model with contacts (jaxcon.solvers.contact_jacobi): PGS's contact rows, warm start,
        time-of-impact correction and position safety pass, with rods and contacts solved in the same Jacobi
        iterations. `relaxation=None` relaxes by mass splitting (per-particle counts of the rows that push).
        A grid model's step goes through `grid_substepped`, which calls this with its candidate pairs `found`."""
        topo = sys.topology
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        relax = None if self.relaxation is None else jnp.asarray(self.relaxation, dtype)
        split = self.stabilization == "split"
        share = jnp.asarray(self.slop, dtype)
        v_free, v, fr, bias, obs, pairs, lam, imp, slop = contact_begin(sys, x, v, lam_ws, beta, h, share if split else None,
                                                                  self.warm_start, found=found)

        def run(obs, pairs):
            return functools.partial(contact_jacobi.iteration(sys, fr, bias, obs, pairs, relax), 0)

        v, lam, imp = restitution_phases(sys, v_free, obs, pairs, self.iterations, (v, lam, imp), run)
        rods_pass = None
        if split and fr:
            rod_relax = jnp.asarray(1.0 / max_degree(topo), dtype) if relax is None else relax
            rods_pass = lambda x: split_position_pass(sys, x, self.iterations, slop, rod_relax)  # noqa: E731
        return contact_end(sys, x, v, v_free, obs, pairs, imp, h, rods_pass=rods_pass), v, (lam, imp)
