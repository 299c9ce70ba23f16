"""RATTLE: velocity Verlet with position (SHAKE) and velocity constraints, solved by coloured sweeps."""
from __future__ import annotations

import operator
from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers.common import clamp_ropes, frames

# Sweep loops of at most this many iterations are unrolled (lets XLA fuse the small per-sweep ops; a few
# times faster on small systems, same result).
_UNROLL = 8


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

    Args:
      iterations: Gauss-Seidel sweeps per stage, static, >= 1.
      tolerance: residual below which a constraint is no longer updated, >= 0 (a leaf; 0: always update).
    """

    iterations: int = static_field(default=10)
    tolerance: Any = 1e-12

    def __post_init__(self):
        check_int("RATTLE", "iterations", self.iterations, 1)
        check_scalar("RATTLE", "tolerance", self.tolerance, 0.0)

    def _step(self, sys, x, v, lam, h):
        topo = sys.topology
        dtype = x.dtype
        tol = jnp.asarray(self.tolerance, dtype)
        tiny = jnp.finfo(dtype).tiny
        fr0 = frames(sys, x)
        rest2 = tuple(r * r for r in sys.rest)
        zero = tuple(jnp.zeros_like(f.C) for f in fr0)

        v, spring0 = _spring_kick(sys, fr0, v, h / 2)
        v = sys.apply_gravity(v, h / 2)
        x = x + h * v

        def shake_set(xv, blk, rows):
            """SHAKE for a set's rows: C_lib(x) moved to 0 along the start-of-step gradient J0 (the row's
            mu = C_lib / (J(x) M^-1 J0^T), at least half of sqrt(J M^-1 J^T J0 M^-1 J0^T) as for a rod);
            compliant rows are springs (`_spring_kick`) and take no part."""
            x, v = xv
            f0, ssys, mu = rows
            f = R.set_frame(topo, blk, sys.cons[blk.generic], ssys, x, sys.w)
            along = jnp.sum(f.w * jnp.sum(f.J * f0.J, axis=0), axis=0)
            live = (f0.k > 0) & (f.k > 0) & (along > 0) & (f0.alpha == 0)
            floor = 0.5 * jnp.sqrt(f.s * f0.s)
            new = clamp_ropes(blk, mu + jnp.where(live, f.C / jnp.where(live, jnp.maximum(along, floor), 1), 0))
            q = f0.J * (f0.w * (new - mu))
            return (L.add_rows(topo, blk, x, q), L.add_rows(topo, blk, v, q / h)), new

        def shake_colour(xv, blk, rows):
            if getattr(blk, "generic", None) is not None:
                return shake_set(xv, blk, rows)
            x, v = xv
            f, r2, mu = rows
            xi, xj = L.gather_pair(topo, blk, x)
            d = xj - xi
            dist, _ = L.safe_length(d)
            res = jnp.sum(d * d, axis=0) - r2
            # SHAKE moves along the start-of-step direction n0 by res / (2 (w_i + w_j) d . n0). A rod of rest
            # length 0 (or one that turned far within the step) has d . n0 near 0 and would be flung (1e44 m):
            # d . n0 is taken as at least |d| / 2, which bounds the move by |d| and leaves other rods unchanged.
            along = jnp.sum(d * f.n, axis=0)
            live = (f.k > 0) & (along > 0)
            rhs = jnp.where(live, res / (2 * jnp.where(live, jnp.maximum(along, 0.5 * dist), 1)), 0)
            if getattr(blk, "star", False):        # a star's rows share the hub: solved together, every row updated
                upd = L.block_solve(topo, blk, f, rhs)
            else:
                upd = jnp.where(live & (jnp.abs(res) > tol * 2 * r2), rhs * f.k, 0)
            new = clamp_ropes(blk, mu + upd)
            p = f.n * (new - mu)
            pi, pj = f.wi * p, -f.wj * p
            return (L.add_pair(topo, blk, x, pi, pj), L.add_pair(topo, blk, v, pi / h, pj / h)), new

        def shake(_, carry):
            x, v, mu = carry
            mu = list(mu)
            for c, (blk, f, r2) in enumerate(zip(topo.blocks, fr0, rest2)):
                extra = sys.sets[blk.generic] if blk.generic is not None else r2
                (x, v), mu[c] = L.each_colour(blk, shake_colour, (x, v), (f, extra, mu[c]))
            return x, v, tuple(mu)

        x, v, mu = lax.fori_loop(0, self.iterations, shake, (x, v, zero), unroll=self.iterations <= _UNROLL)

        fr1 = frames(sys, x)
        v, spring1 = _spring_kick(sys, fr1, v, h / 2)
        v = sys.apply_gravity(v, h / 2)

        def project_colour(v, blk, rows):
            f, r, lam = rows
            rel = R.rel(topo, blk, f, v)
            if getattr(blk, "generic", None) is not None:      # a set's hard rows: J(x) v = 0; compliant rows are springs
                step = jnp.where(f.alpha == 0, rel * f.k, 0)
                new = clamp_ropes(blk, lam + step)
                return R.apply(topo, blk, f, v, new - lam), new
            active = jnp.abs(rel) * h > tol * r
            if blk.has_rope:  # a rope that is slack after the drift does not constrain the velocity
                taut = f.C > -tol * jnp.maximum(r, tiny)
                active = active & (taut if blk.all_rope else (taut | ~blk.rope.array))
            step = L.block_solve(topo, blk, f, rel) if getattr(blk, "star", False) else jnp.where(active, rel * f.k, 0)
            new = clamp_ropes(blk, lam + step)
            return R.apply(topo, blk, f, v, new - lam), new

        def project(_, carry):
            v, lam = carry
            lam = list(lam)
            for c, (blk, f, r) in enumerate(zip(topo.blocks, fr1, sys.rest)):
                v, lam[c] = L.each_colour(blk, project_colour, v, (f, r, lam[c]))
            return v, tuple(lam)

        v, lam2 = lax.fori_loop(0, self.iterations, project, (v, zero), unroll=self.iterations <= _UNROLL)
        lam = tuple(map(operator.add, (m / h for m in mu), lam2))
        return x, v, tuple(l + s0 + s1 for l, s0, s1 in zip(lam, spring0, spring1))


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
