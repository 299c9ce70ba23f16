"""Box2D v3's "soft step": substepping with soft constraints and relaxation (Erin Catto, Solver2D, 2024)."""
from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.substeps import substepped
from jaxcon.core.system import Solver
from jaxcon.solvers.common import apply_impulses, clamp_ropes, frames


def soft_coefficients(hertz, damping_ratio, h):
    """Box2D's b2MakeSoft: (bias_rate, mass_scale, impulse_scale) of a constraint that behaves like a
    spring-damper of natural frequency `hertz` and damping ratio `damping_ratio`, integrated implicitly over a
    substep h: omega = 2 pi hertz, a1 = 2 zeta + h omega, a2 = h omega a1, a3 = 1 / (1 + a2),
    bias_rate = omega / a1, mass_scale = a2 a3, impulse_scale = a3."""
    omega = 2 * math.pi * hertz
    a1 = 2 * damping_ratio + h * omega
    a2 = h * omega * a1
    a3 = 1 / (1 + a2)
    return omega / a1, a2 * a3, a3


@pytree_dataclass
class SoftStep(Solver):
    """Soft step (Box2D v3): per substep of length h = dt / substeps,

      1. integrate velocities: v += h g;
      2. warm start: apply the previous substep's impulses;
      3. solve, one sweep over the colours with soft constraints:
           dlam = mass_scale (n . (v_j - v_i) + bias_rate C) / (w_i + w_j) - impulse_scale lam
         (coefficients from `soft_coefficients(hertz, damping_ratio, h)`);
      4. integrate positions: x += h v;
      5. relax: `relax_iterations` sweeps without bias (rigid, dlam = n . (v_j - v_i) / (w_i + w_j), directions
         at the new positions), removing the velocity the bias added.

    Ropes (unilateral): the accumulated impulse is clamped to >= 0; a slack rope (C < 0) uses the speculative
    bias C / h with mass_scale 1 and impulse_scale 0 in both the solve and the relax sweeps, as Box2D does for
    a distance joint's length limit.

    Box2D's own joint softness is hertz = 60, damping_ratio = 2 at 4 substeps of a 60 Hz step (and it keeps
    hertz <= 0.5 / h); as hertz h grows the constraint turns rigid (bias_rate -> 1 / h, mass_scale -> 1,
    impulse_scale -> 0), so large values stay stable.

    Args:
      substeps: substeps per step, static, >= 1.
      hertz: constraint stiffness as a frequency (Hz), > 0, a differentiable leaf.
      damping_ratio: >= 0, a differentiable leaf.
      relax_iterations: rigid sweeps after the position update, static, >= 0.
    """

    substeps: int = static_field(default=4)
    hertz: Any = 60.0
    damping_ratio: Any = 2.0
    relax_iterations: int = static_field(default=1)

    def __post_init__(self):
        check_int("SoftStep", "substeps", self.substeps, 1)
        check_int("SoftStep", "relax_iterations", self.relax_iterations, 0)
        check_scalar("SoftStep", "hertz", self.hertz, 0.0, positive=True)
        check_scalar("SoftStep", "damping_ratio", self.damping_ratio, 0.0)

    def _step(self, sys, x, v, lam, dt):
        dtype = x.dtype
        hertz = jnp.asarray(self.hertz, dtype)
        zeta = jnp.asarray(self.damping_ratio, dtype)
        topo = sys.topology

        def sweep(v, lam, fr, bias, mass_scale, impulse_scale, inv_h):
            lam = list(lam)
            for c, (blk, f) in enumerate(zip(topo.blocks, fr)):
                vi, vj = L.gather_pair(topo, blk, v)
                rel = jnp.sum((vj - vi) * f.n, axis=0)
                ms, isc, b = mass_scale, impulse_scale, bias(f)
                if blk.has_rope:  # slack rope: speculative, rigid
                    slack = f.C < 0 if blk.all_rope else (f.C < 0) & blk.rope.array
                    b = jnp.where(slack, f.C * inv_h, b)
                    ms = jnp.where(slack, 1, ms)
                    isc = jnp.where(slack, 0, isc)
                new = clamp_ropes(blk, lam[c] + ms * f.k * (rel + b) - isc * lam[c])
                p = f.n * (new - lam[c])
                lam[c] = new
                v = v + L.scatter_pair(topo, blk, f.wi * p, -f.wj * p)
            return v, tuple(lam)

        def substep(x, v, lam, h):
            bias_rate, mass_scale, impulse_scale = soft_coefficients(hertz, zeta, h)
            v = sys.apply_gravity(v, h)
            fr = frames(sys, x)
            lam = tuple(clamp_ropes(blk, l) * (f.k > 0).astype(l.dtype) for blk, f, l in zip(topo.blocks, fr, lam))
            v = apply_impulses(sys, v, fr, lam)
            inv_h = 1 / h
            v, lam = sweep(v, lam, fr, lambda f: bias_rate * f.C, mass_scale, impulse_scale, inv_h)
            x = x + h * v
            if self.relax_iterations:
                fr = frames(sys, x)
                v, lam = lax.fori_loop(
                    0, self.relax_iterations,
                    lambda _, c: sweep(*c, fr, lambda f: jnp.zeros_like(f.C), 1.0, 0.0, inv_h), (v, lam))
            return x, v, lam

        return substepped(substep, self.substeps, x, v, lam, dt)
