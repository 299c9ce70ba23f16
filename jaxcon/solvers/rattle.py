"""RATTLE: velocity Verlet with position (SHAKE) and velocity constraints, solved by coloured sweeps."""
from __future__ import annotations

import functools
import operator
from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.core.contact import zero_impulses
from jaxcon.solvers import contact
from jaxcon.solvers.common import frames, run_substeps, shake_sweep, with_contacts, with_found

# A sweep loop is unrolled when it has at most _UNROLL_ITERATIONS iterations and iterations times the code blocks
# one sweep emits (one per topology block: a colour each in the unrolled layout; a table, star or constraint set
# one scan) is at most _UNROLL_BLOCKS. Unrolling lets XLA fuse the small per-sweep ops (a few times faster on
# small systems, same result); on many blocks it costs compile time and run time: RATTLE(5) on the unrolled 32x32
# cloth (8 blocks) compiled in 23 s and ran at 157 ms/step unrolled, against 1.6 s and 0.72 ms/step as a loop
# (docs/performance.md).
_UNROLL_ITERATIONS = 8
_UNROLL_BLOCKS = 16


def _unroll(iterations: int, topo) -> bool:
    return iterations <= _UNROLL_ITERATIONS and iterations * max(len(topo.blocks), 1) <= _UNROLL_BLOCKS


@pytree_dataclass
class RATTLE(Solver):
    """RATTLE (Andersen 1983): symplectic, time-reversible, second-order velocity Verlet on the constraint
    manifold.

    Per step of length h, with n0 the constraint directions at the start of the step:

      1. half kick and drift: v' = v + h/2 g, x' = x + h v'; then SHAKE: sweeps over the colours, each
         constraint moved along n0 (x_i += w_i n0 mu, x_j -= w_j n0 mu,
         mu = (|d|^2 - L^2) / (2 (w_i + w_j) d . n0)) until |x_j - x_i| = L; v' gets the same correction / h.
      2. half kick: v = v' + h/2 g; then sweeps projecting the velocities onto J(x') v = 0 (directions n1 at
         the new positions): dlam = n1 . (v_j - v_i) / (w_i + w_j).

    Both stages run exactly `iterations` Gauss-Seidel sweeps (static; reverse-mode differentiable). The
    `tolerance` is an early-out by masking: in a sweep, a constraint whose residual is already at or below
    `tolerance` gets no update (position residual |d^2 - L^2| / (2 L^2) ~ relative stretch; velocity residual
    |n1 . (v_j - v_i)| h / L ~ relative stretch the velocity would cause over one step). It saves no time
    (the sweep is still computed) but stops updating converged constraints, as SHAKE's classic loop does.

    Ropes: a rope takes part only while it is taut; its accumulated impulse of each stage is clamped >= 0
    (a slack rope is free). The returned lam is the constraint impulse over the step (mu / h + the velocity
    stage's impulse; lam > 0: tension; a hanging mass gives m g h). The warm-start input is not used.

    Contacts (`planes`, `spheres`, `collide`) are unilateral rows in both stages, as XPBD's (docs/contacts.md;
    the step starts with XPBD's `contact.push_out` of start overlaps):
    every SHAKE sweep ends with the contacts' position pass (`contact.position_pass`: overlaps pushed out along
    the normal with lam_n >= 0, static friction), whose correction / h goes into v' as the constraints' does; the
    velocity stage ends with their velocity pass (`contact.position_velocity_pass`: restitution from the
    approach velocity v + h/2 g, dynamic friction). Contact impulses are not symmetric in time, so a model with
    contacts loses RATTLE's time reversibility at every contact (not elsewhere). The velocity pass comes after
    the constraints' velocity projection, so in a step with an impact the rods at the particles it moves end
    with J v != 0 (up to 0.5 m/s on a 6-link chain landing at dt 1/240, against XPBD's 0.03), which the next
    step's SHAKE removes; running the contacts inside the projection sweeps instead gained kinetic energy on
    the break. A neighbour grid's step searches
    its pairs once (`common.grid_substepped`).

    Args:
      iterations: Gauss-Seidel sweeps per stage, static, >= 1.
      tolerance: residual below which a constraint is no longer updated, >= 0 (a leaf; 0: always update).
    """

    iterations: int = static_field(default=10)
    tolerance: Any = 1e-12

    def __post_init__(self):
        check_int("RATTLE", "iterations", self.iterations, 1)
        check_scalar("RATTLE", "tolerance", self.tolerance, 0.0)

    supports_contacts = True

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), 1, x, v, lam, dt)

    def _substep(self, sys, x, v, lam, h, found=None):
        """One step (module docstring); a grid model's `found` = (partners, overflow) from its search."""
        topo, cs = sys.topology, sys.contact
        partners = None if found is None else found[0]
        dtype = x.dtype
        tol = jnp.asarray(self.tolerance, dtype)
        tiny = jnp.finfo(dtype).tiny
        if cs is not None:
            x = contact.push_out(cs, sys.w, x, h, partners)
        fr0 = frames(sys, x)
        zero = tuple(jnp.zeros_like(f.C) for f in fr0)

        v, spring0 = _spring_kick(sys, fr0, v, h / 2)
        v = sys.apply_gravity(v, h / 2)
        x0, v_approach = x, v
        x = x + h * v

        shake = shake_sweep(sys, fr0, h, tol)

        def shake_contacts(i, carry):           # the contacts' position pass after each SHAKE sweep
            x, v, mu, imp = carry
            x, v, mu = shake(i, (x, v, mu))
            if cs is None:
                return x, v, mu, imp
            dp = x - x0
            moved, imp = contact.position_pass(cs, sys.w, x0, dp, imp, partners, h * v_approach, h)
            return x + (moved - dp), v + (moved - dp) / h, mu, imp

        carry = (x, v, zero, None if cs is None else zero_impulses(topo, cs.ct, dtype))
        unroll = cs is None and _unroll(self.iterations, topo)      # a sweep with contacts stays a loop
        x, v, mu, imp = lax.fori_loop(0, self.iterations, shake_contacts, carry, unroll=unroll)

        fr1 = frames(sys, x)
        v, spring1 = _spring_kick(sys, fr1, v, h / 2)
        v = sys.apply_gravity(v, h / 2)

        def project_colour(v, blk, rows):
            f, r, mu, lam = rows
            rel = R.rel(topo, blk, f, v)
            if getattr(blk, "generic", None) is not None:      # a set's hard rows: J(x) v = 0; compliant rows are springs
                live = f.alpha == 0
                if blk.has_rope:    # a unilateral row constrains the velocity only where the position stage held it
                    held = (mu > 0) | (f.C >= 0)
                    live = live & (held if blk.all_rope else (held | ~blk.rope.array))
                step = jnp.where(live, rel * f.k, 0)
                new = R.accumulate(blk, lam, step)
                return R.apply(topo, blk, f, v, new - lam), new
            active = jnp.abs(rel) * h > tol * r
            if blk.has_rope:  # a rope that is slack after the drift does not constrain the velocity
                taut = f.C > -tol * jnp.maximum(r, tiny)
                active = active & (taut if blk.all_rope else (taut | ~blk.rope.array))
            step = L.block_solve(topo, blk, f, rel) if getattr(blk, "star", False) else jnp.where(active, rel * f.k, 0)
            new = R.accumulate(blk, lam, step)
            return R.apply(topo, blk, f, v, new - lam), new

        def project(_, carry):
            v, lam = carry
            lam = list(lam)
            for c, (blk, f, r) in enumerate(zip(topo.blocks, fr1, sys.rest)):
                v, lam[c] = L.each_colour(blk, project_colour, v, (f, r, mu[c], lam[c]))
            return v, tuple(lam)

        v, lam2 = lax.fori_loop(0, self.iterations, project, (v, zero), unroll=_unroll(self.iterations, topo))
        lam = tuple(map(operator.add, (m / h for m in mu), lam2))
        lam = tuple(l + s0 + s1 for l, s0, s1 in zip(lam, spring0, spring1))
        if cs is None:
            return x, v, lam
        v, imp = contact.position_velocity_pass(cs, sys.w, x, v_approach, v, imp, h, partners)
        return x, v, with_contacts(sys, lam, with_found(imp, found))


def _spring_kick(sys, fr, v, dt):
    """A half kick of the constraint sets' compliant rows, which RATTLE integrates as the springs they are: the
    force -(C / alpha) dC/dx (potential energy C^2 / (2 alpha)) held for `dt`. Returns (v, per-block impulses:
    C_lib / alpha dt for compliant rows, 0 elsewhere)."""
    out = []
    for blk, f in zip(sys.topology.blocks, fr):
        if blk.generic is None:
            out.append(0)
            continue
        soft = (f.alpha > 0) & (f.k > 0)
        imp = jnp.where(soft, f.C / jnp.where(soft, f.alpha, 1), 0) * dt
        v = R.apply(sys.topology, blk, f, v, imp)
        out.append(imp)
    return v, tuple(out)
