"""Sequential impulses / projected Gauss-Seidel (`jc.PGS`)."""
from __future__ import annotations

import functools
from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.checks import check_bool, check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.substeps import substepped
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import (
    apply_impulses,
    check_stabilization,
    clamp_ropes,
    contact_begin,
    contact_end,
    frames,
    grid_step,
    restitution_phases,
    split_position_pass,
    velocity_bias,
    warm_start,
)


@pytree_dataclass
class PGS(Solver):
    """Sequential impulses / projected Gauss-Seidel at velocity level with Baumgarte stabilisation.

    Per (sub)step of length h: v += h g; for each constraint, with n the unit vector from its first to its
    second particle and C = |x_j - x_i| - L,

        dlam = (n . (v_j - v_i) + bias) / (w_i + w_j),   bias = (beta / h) C   (rod, or taut rope)
                                                         bias = C / h          (slack rope: speculative)

    applied at once (v_i += w_i n dlam, v_j -= w_j n dlam), the accumulated lam of a rope clamped to >= 0;
    colours in sequence, the constraints of one colour together; then x += h v (symplectic Euler).

    Args:
      iterations: sweeps over all colours per (sub)step, static, >= 1.
      beta: Baumgarte factor in [0, 1], a differentiable leaf (0.1 to 0.3 is usual); with split impulses only
        the contacts' push-out rate.
      warm_start: start each step from the previous step's impulses (static).
      substeps: (sub)steps per step, static, >= 1.
      warm_start_factor: scale in [0, 1] of the warm-start impulses, a differentiable leaf. 1 is the textbook
        method. With few iterations on long chains, full warm starting plus the Baumgarte bias feeds the
        previous step's correction impulse back in faster than the sweeps remove it, and the chain gains
        energy until it explodes (a 50-link chain hanging at rest, 10 iterations, beta 0.2: 1e2 stretch
        after 1 s). 0.85 (Bullet's default) keeps it bounded at a small cost in convergence.
      implicit: differentiate the multipliers implicitly (static; rods only). The forward pass is the same
        sweeps; reverse mode solves the adjoint system (J M^-1 J^T)^T mu = g with the same `iterations`
        sweeps instead of storing and unrolling every sweep. Exact when the sweeps have converged and lambda is
        unique (tested against finite differences to 1e-7); 7 to 34x less reverse-mode memory measured. Not for
        redundant structures (a cloth with shear rods: J M^-1 J^T is singular, lambda is not unique and the
        adjoint sweeps do not converge: the gradient is then meaningless), nor for under-converged sweeps on
        long horizons (20-link chain, 50 sweeps, 240 steps: 60% off the unrolled gradient). Ropes (an
        inequality) are refused with a clear error.
      stabilization: 'baumgarte' (default, the textbook method above) or 'split' (static): split impulses,
        position error kept out of the velocities (Box2D v2's position solver, Cline and Pai's
        post-stabilisation). The velocity sweeps see no position error: rods and taut ropes ask for
        n . (v_j - v_i) = -(the rate at which rotating about each other opens them,
        `common.curvature_rate`), so the step x += h v moves along the chord and keeps C(x + h v) = C(x) to
        second order (J v = 0 would move along the tangent and lose energy to the next step's projection);
        a slack rope keeps its speculative C / h. Then `iterations` nonlinear Gauss-Seidel sweeps project the
        positions onto the rest lengths (a rope only while stretched), velocities untouched: the whole error
        goes in one step without turning into kinetic energy, so `beta` does not act on rods and ropes (it is
        still the contacts' push-out rate). lam is the velocity impulse only, the physical constraint
        impulse. Not with `implicit=True`.
      contact_slop: the overlap, as a fraction of the contact distance (r_i + r_j; r for a plane or sphere),
        that contacts keep without being pushed out (Box2D's linear slop), a differentiable leaf in [0, 0.5];
        default `contact.CONTACT_SLOP` = 0.005, half a percent of a diameter. The Baumgarte term pushes out
        only the overlap beyond two of it, the position safety pass projects onto it, and pairs within it of touching
        are warm-started: what lets a pile come to rest (docs/contacts.md, piles at rest). 0 is the method
        before (resting contacts at C = 0, solved cold every other step).
      warm_start_gradient: if False, no gradient flows through the warm-start impulses (static). The forward
        pass is unchanged and the gradient becomes a truncated one. Measured on a swinging 16x16 cloth it does
        not stop long-horizon gradient growth (that growth is the physics: the motion is chaotic, and a
        converged XPBD grows as fast); windowed losses (`jc.fit(window=...)`) are what bound it. See
        docs/fitting.md.
    """

    iterations: int = static_field(default=10)
    beta: Any = 0.2
    warm_start: bool = static_field(default=True)
    substeps: int = static_field(default=1)
    warm_start_factor: Any = 1.0
    warm_start_gradient: bool = static_field(default=True)
    implicit: bool = static_field(default=False)
    stabilization: str = static_field(default="baumgarte")
    contact_slop: Any = contact.CONTACT_SLOP

    def __post_init__(self):
        check_stabilization("PGS", self.stabilization)
        if self.implicit and self.stabilization == "split":
            raise ValueError("PGS: `implicit=True` is not available with stabilization='split' (its position "
                             "projection has no implicit derivative here); use implicit=False")
        check_int("PGS", "iterations", self.iterations, 1)
        check_int("PGS", "substeps", self.substeps, 1)
        check_bool("PGS", "warm_start", self.warm_start)
        check_bool("PGS", "warm_start_gradient", self.warm_start_gradient)
        check_bool("PGS", "implicit", self.implicit)
        check_scalar("PGS", "beta", self.beta, 0.0, 1.0)
        check_scalar("PGS", "warm_start_factor", self.warm_start_factor, 0.0, 1.0)
        check_scalar("PGS", "contact_slop", self.contact_slop, 0.0, 0.5)

    supports_contacts = True
    supports_grid = True

    def _factor(self, dtype):
        factor = self.warm_start_factor
        return factor if isinstance(factor, (int, float)) else jnp.asarray(factor, dtype)

    def _substep(self, sys, x, v, lam_ws, h):
        if sys.contact is not None:
            return self._substep_contacts(sys, x, v, lam_ws, h)
        topo = sys.topology
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        v = sys.apply_gravity(v, h)
        fr = frames(sys, x)
        split = self.stabilization == "split"
        bias = velocity_bias(topo, fr, jnp.zeros((), dtype), h, v) if split else velocity_bias(topo, fr, beta, h)
        if self.warm_start:
            v, lam = warm_start(sys, v, fr, lam_ws, self._factor(dtype), self.warm_start_gradient)
        else:
            lam = tuple(jnp.zeros_like(f.C) for f in fr)

        block_sweep = self._block_sweep(topo, fr, bias)

        def sweep(_, carry):
            return block_sweep(*carry)

        if self.implicit:
            return self._implicit(sys, x, v, lam, fr, bias, h)
        v, lam = lax.fori_loop(0, self.iterations, sweep, (v, lam))
        if split:
            return split_position_pass(sys, x + h * v, self.iterations), v, lam
        return x + h * v, v, lam

    def _substep_contacts(self, sys, x, v, lam_ws, h, found=None):
        """The same step with contacts (jaxcon.solvers.contact): each sweep solves the constraint colours, then
        the contacts; positions get the time-of-impact correction. Contacts push out overlap with `beta`. A grid
        model's step goes through `grid_step`, which calls this with its candidate pairs `found`."""
        if self.implicit:
            raise ValueError("PGS(implicit=True) does not support contacts (an inequality); use implicit=False")
        topo, cs = sys.topology, sys.contact
        if cs.ct.has_grid and found is None:
            return grid_step(sys, x, v, h, functools.partial(self._substep_contacts, sys, x, v, lam_ws, h))
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        slop = jnp.asarray(self.contact_slop, dtype)
        split = self.stabilization == "split"
        v_free, v, fr, bias, obs, pairs, lam, imp = contact_begin(
            sys, x, v, lam_ws, beta, h, split, self.warm_start, self._factor(dtype), self.warm_start_gradient,
            found, slop)
        block_sweep = self._block_sweep(topo, fr, bias)

        def sweeps(obs, pairs):
            def sweep(carry):
                v, lam, imp = carry
                v, lam = block_sweep(v, lam)
                v, imp = contact.sweep(cs, sys.w, v, obs, pairs, imp)
                return v, lam, imp
            return sweep

        v, lam, imp = restitution_phases(sys, v_free, obs, pairs, self.iterations, (v, lam, imp), sweeps)
        rods_pass = (lambda x: split_position_pass(sys, x, self.iterations)) if split and fr else None
        x = contact_end(sys, x, v, v_free, obs, pairs, imp, h, passes=None, rods_pass=rods_pass, slop=slop)
        return x, v, (lam, imp)

    @staticmethod
    def _block_sweep(topo, fr, bias):
        """One Gauss-Seidel pass over the constraint colours: (v, lam) -> (v, lam)."""
        def colour(v, blk, rows):
            f, b, lam = rows
            vi, vj = L.gather_pair(topo, blk, v)
            rel = L.dot(blk, vj - vi, f.n)
            new = clamp_ropes(blk, lam + L.block_solve(topo, blk, f, rel + b))
            p = f.n * (new - lam)
            return L.add_pair(topo, blk, v, f.wi * p, -f.wj * p), new

        def sweep(v, lam):
            lam = list(lam)
            for c, (blk, f, b) in enumerate(zip(topo.blocks, fr, bias)):
                v, lam[c] = L.each_colour(blk, colour, v, (f, b, lam[c]))
            return v, tuple(lam)
        return sweep

    def _implicit(self, sys, x, v, lam0, fr, bias, h):
        """Converged multipliers with implicit derivatives: lam solves G lam = rel(v) + bias, where
        G lam = -J (M^-1 J^T lam) is J M^-1 J^T in the tension convention (symmetric), and v is the velocity
        before any impulse. `lam0` (the warm start, already applied to v) is the solver's initial guess only."""
        topo = sys.topology
        if topo.has_ropes:
            raise ValueError("PGS(implicit=True): implicit differentiation needs equality constraints; the model "
                             "has ropes (inequalities). Use implicit=False for ropes.")
        v_free = apply_impulses(sys, v, fr, tuple(-l for l in lam0))     # undo the warm start
        zero_v = jnp.zeros_like(v)

        def relative(u):
            out = []
            for blk, f in zip(topo.blocks, fr):
                ui, uj = L.gather_pair(topo, blk, u)
                out.append(jnp.sum((uj - ui) * f.n, axis=0))
            return tuple(out)

        def matvec(l):
            return tuple(-r for r in relative(apply_impulses(sys, zero_v, fr, l)))

        def solve(_, rhs, guess=lax.stop_gradient(lam0)):
            def colour(u, blk, rows):
                f, r, l = rows
                ui, uj = L.gather_pair(topo, blk, u)
                d = L.block_solve(topo, blk, f, jnp.sum((uj - ui) * f.n, axis=0) + r)
                p = f.n * d
                return L.add_pair(topo, blk, u, f.wi * p, -f.wj * p), l + d

            def sweep(_, carry):
                u, l = carry
                l = list(l)
                for c, (blk, f) in enumerate(zip(topo.blocks, fr)):
                    u, l[c] = L.each_colour(blk, colour, u, (f, rhs[c], l[c]))
                return u, tuple(l)

            u0 = apply_impulses(sys, zero_v, fr, guess)
            return lax.fori_loop(0, self.iterations, sweep, (u0, guess))[1]

        rhs = tuple(r + b for r, b in zip(relative(v_free), bias))
        lam = lax.custom_linear_solve(matvec, rhs, solve, symmetric=True)
        v = apply_impulses(sys, v_free, fr, lam)
        return x + h * v, v, lam

    def _step(self, sys, x, v, lam, dt):
        return substepped(functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)
