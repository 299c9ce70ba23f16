"""Penalty (stiff spring) solver: every rod and rope is a damped spring, integrated by symplectic Euler."""
from __future__ import annotations

import warnings
from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.substeps import substepped
from jaxcon.core.system import Solver

#: The spring tension is clipped to +- STRETCH_CLIP * stiffness * rest_length (constraints with rest length
#: > 0). A stable run never comes near it (it is a 1000% stretch, ten times `jc.diagnose`'s violation limit);
#: above the stability limit it keeps forces bounded, so an unstable run grows only polynomially, stays
#: finite and is reported by `jc.diagnose` instead of overflowing to inf / NaN; once any spring is stretched
#: past the clip, the forces stop carrying gradient (stop_gradient), so derivatives stay finite too.
STRETCH_CLIP = 10.0


@pytree_dataclass
class Penalty(Solver):
    """Rods and ropes as stiff damped springs (no constraint solve), symplectic Euler.

    Per substep of length h = dt / substeps, with n the unit vector from a constraint's first particle to its
    second, C = |x_j - x_i| - L and u = n . (v_j - v_i) the stretching speed, the tension is

        T = stiffness C + damping u         (rod: pulls when T > 0, pushes when T < 0)
        T = max(T, 0) where C > 0, else 0   (rope: resists stretching only)

    then v += h g + h M^-1 J^T T (v_i += w_i n T h, v_j -= w_j n T h) and x += h v.

    Explicit integration is stable only for h below about 2 / omega, omega = sqrt(stiffness (w_i + w_j)) for
    a lone spring, higher for connected ones (see `stability_limit`), and 2 / (damping (w_i + w_j)) for the
    damping term. Above it the run diverges; the tension is clipped
    (see STRETCH_CLIP) so that the blow-up stays finite and `jc.diagnose` flags it as diverged.

    The returned lam is the spring impulse over the step, sum of T h (N s, > 0 tension); the warm start passed
    in is not used (a spring has no iteration to warm start).

    Args:
      stiffness: spring constant k, N/m, a differentiable leaf, > 0.
      damping: damping coefficient c along the constraint, N s/m, a differentiable leaf, >= 0.
      substeps: substeps per step, static, >= 1.
    """

    stiffness: Any = 1e5
    damping: Any = 0.0
    substeps: int = static_field(default=1)

    def __post_init__(self):
        check_int("Penalty", "substeps", self.substeps, 1)
        check_scalar("Penalty", "stiffness", self.stiffness, 0.0, positive=True)
        check_scalar("Penalty", "damping", self.damping, 0.0)

    def stability_limit(self, model) -> float:
        """A substep h below which the undamped springs of `model` are stable: 2 / omega_bound (s), with
        omega_bound^2 = stiffness * max over constraints of (w_i deg_i + w_j deg_j) (deg: constraints at the
        particle), a Gershgorin bound on the largest eigenvalue of stiffness J M^-1 J^T. For a single
        spring it is the exact 2 / sqrt(stiffness (w_i + w_j)); for chains it is within a factor sqrt(2) of
        the true limit. Concrete values only (NumPy). `rollout` and `step` warn when dt / substeps is above it."""
        t = model.topology
        w = np.asarray(model.inv_mass, np.float64)
        deg = np.bincount(np.concatenate([t.i, t.j]), minlength=t.n)
        bound = float(np.max(w[t.i] * deg[t.i] + w[t.j] * deg[t.j]))
        omega = np.sqrt(float(self.stiffness) * bound)
        return float(2 / omega) if omega > 0 else float("inf")

    def _check_stability(self, owner, model, dt) -> None:
        """Warn (before tracing, where the values are known) when a substep is above `stability_limit`: the
        springs will then blow up. A warning, not an error: the limit is a sufficient bound, and an unstable run
        is something one may want to see."""
        vals = [concrete(a) for a in (self.stiffness, model.inv_mass, dt)]
        if any(a is None for a in vals):
            return
        h = float(vals[2]) / self.substeps
        limit = self.stability_limit(model)
        if h > limit:
            need = int(np.ceil(float(vals[2]) / limit))
            warnings.warn(
                f"{owner}: Penalty substep dt / substeps = {h:.3g} s is above this model's stability limit "
                f"{limit:.3g} s (stiffness {float(vals[0]):g} N/m): the springs are likely to "
                f"oscillate and diverge. Use substeps >= {need}, a smaller dt, or a lower stiffness.",
                RuntimeWarning, stacklevel=4)

    def _step(self, sys, x, v, lam, dt):
        topo = sys.topology
        dtype = x.dtype
        k = jnp.asarray(self.stiffness, dtype)
        c = jnp.asarray(self.damping, dtype)

        def substep(x, v, _, h):
            geo = []
            for blk, rest in zip(topo.blocks, sys.rest):
                xi, xj = L.gather_pair(topo, blk, x)
                wi, wj = L.gather_pair(topo, blk, sys.w)
                C = L.safe_norm(xj - xi, axis=0)[0] - rest
                geo.append(((rest > 0) & (C > STRETCH_CLIP * rest), wi[0], wj[0]))
            # Past the clip the run has diverged (diagnose flags it). Such a substep passes no derivative
            # back, so the gradient of a diverged run stays finite instead of overflowing through the blow-up.
            blown = jnp.any(jnp.stack([jnp.any(b) for b, _, _ in geo]))
            x = jnp.where(blown, lax.stop_gradient(x), x)
            v = jnp.where(blown, lax.stop_gradient(v), v)
            for b, (blk, rest) in enumerate(zip(topo.blocks, sys.rest)):
                xi, xj = L.gather_pair(topo, blk, x)
                vi, vj = L.gather_pair(topo, blk, v)
                dist, n = L.safe_norm(xj - xi, axis=0)
                geo[b] = (n, geo[b][1], geo[b][2], dist - rest, jnp.sum((vj - vi) * n, axis=0), rest)
            imp = []
            for blk, (n, wi, wj, C, u, rest) in zip(topo.blocks, geo):
                T = k * C + c * u
                cap = STRETCH_CLIP * k * rest
                T = jnp.where(rest > 0, jnp.clip(T, -cap, cap), T)
                if blk.has_rope:
                    taut = jnp.where(C > 0, jnp.maximum(T, 0), 0)
                    T = taut if blk.all_rope else jnp.where(blk.rope.array, taut, T)
                imp.append(T * h)
            v = sys.apply_gravity(v, h)
            for blk, (n, wi, wj, *_), p in zip(topo.blocks, geo, imp):
                q = n * p
                v = v + L.scatter_pair(topo, blk, wi * q, -wj * q)
            return x + h * v, v, tuple(imp)

        return substepped(substep, self.substeps, x, v, lam, dt)
