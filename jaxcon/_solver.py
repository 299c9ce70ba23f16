"""Solver interface, the shared per-constraint geometry, and the PGS / sequential-impulse solver."""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _layout as L
from ._model import Model, check_real
from ._pytree import concrete, pytree_dataclass, static_field
from ._substeps import substepped
from ._topology import Topology

Array = Any


@pytree_dataclass
class System:
    """A model in the solver's internal layout (built once per rollout, outside the time loop).

      w:       [1, *view] inverse masses.
      rest:    tuple, per block, of rest lengths [*block.shape].
      gravity: [dim].
    """

    w: Array
    rest: tuple
    gravity: Array
    topology: Topology = static_field()

    @classmethod
    def from_model(cls, model: Model, dtype) -> "System":
        t = model.topology
        w = L.per_particle_in(t, jnp.asarray(model.inv_mass, dtype))
        rest = L.constraints_in(t, jnp.asarray(model.rest_length, dtype))
        return cls(w, rest, jnp.asarray(model.gravity, dtype), t)

    def apply_gravity(self, v, h):
        g = self.gravity.reshape((-1,) + (1,) * len(self.topology.view))
        return v + h * g * (self.w > 0).astype(v.dtype)


class Frame(NamedTuple):
    """Geometry of one block of constraints at the start of a (sub)step. Arrays are [*block.shape] unless
    noted; `n` is [dim, *block.shape] and points from the first endpoint to the second."""

    n: Array
    dist: Array
    C: Array      # dist - rest
    wi: Array
    wj: Array
    k: Array      # 1 / (J M^-1 J^T) = 1 / (wi + wj); 0 where undefined (both fixed, or coincident)


def frames(sys: System, x) -> tuple:
    """Per-block constraint geometry of positions `x` ([dim, *view])."""
    out = []
    for blk, rest in zip(sys.topology.blocks, sys.rest):
        xi, xj = L.gather_pair(sys.topology, blk, x)
        wi, wj = L.gather_pair(sys.topology, blk, sys.w)
        wi, wj = wi[0], wj[0]
        dist, n = L.safe_norm(xj - xi, axis=0)
        k = L.safe_reciprocal(wi + wj) * (dist > 0).astype(dist.dtype)
        out.append(Frame(n, dist, dist - rest, wi, wj, k))
    return tuple(out)


def clamp_ropes(blk, lam):
    """Project accumulated impulses of a block onto lam >= 0 where the constraint is a rope."""
    if blk.all_rope:
        return jnp.maximum(lam, 0)
    if blk.rope is not None:
        return jnp.where(blk.rope.array, jnp.maximum(lam, 0), lam)
    return lam


def apply_impulses(sys: System, v, fr: tuple, lam: tuple):
    """v + M^-1 J^T lam for every block (tension convention: lam > 0 pulls the endpoints together)."""
    for blk, f, l in zip(sys.topology.blocks, fr, lam):
        p = f.n * l
        v = v + L.scatter_pair(sys.topology, blk, f.wi * p, -f.wj * p)
    return v


def velocity_bias(topo: Topology, fr: tuple, beta, h) -> tuple:
    """Per-block velocity bias: (beta / h) C for rods and taut ropes, the speculative C / h for slack ropes (the
    rope may close the gap within this (sub)step but no further)."""
    out = []
    for blk, f in zip(topo.blocks, fr):
        b = beta / h * f.C
        if blk.has_rope:
            slack = jnp.where(f.C > 0, b, f.C / h)
            b = slack if blk.all_rope else jnp.where(blk.rope.array, slack, b)
        out.append(b)
    return tuple(out)


def warm_start(sys: System, v, fr: tuple, lam_ws: tuple, factor=1.0, gradient: bool = True):
    """Apply `factor` times the previous impulses (ropes clamped, undefined constraints dropped) to `v`.
    Returns (v, lam): the velocities after the warm start and the accumulated impulses to iterate from."""
    if not gradient:
        lam_ws = lax.stop_gradient(lam_ws)
    if not (isinstance(factor, (int, float)) and factor == 1):     # a plain 1 costs nothing
        lam_ws = tuple(l * factor for l in lam_ws)
    lam = tuple(clamp_ropes(blk, l) * (f.k > 0).astype(f.k.dtype) for blk, f, l in zip(sys.topology.blocks, fr, lam_ws))
    return apply_impulses(sys, v, fr, lam), lam


STABILIZATIONS = ("baumgarte", "split")


def check_stabilization(owner, value) -> None:
    if value not in STABILIZATIONS:
        raise ValueError(f"{owner}: `stabilization` must be 'baumgarte' or 'split', got {value!r}")


def position_correction(topo: Topology, fr: tuple, beta, h) -> tuple:
    """Split impulses: per block (bias, k) of the pseudo-velocity solve J v_p = -(beta / h) C. Rods always take
    part; a rope only while stretched (C > 0), with its pseudo-impulse clamped >= 0 like its impulse; a slack
    rope gets k = 0 (no correction: a rope never pushes)."""
    out = []
    for blk, f in zip(topo.blocks, fr):
        b, k = beta / h * f.C, f.k
        if blk.has_rope:
            stretched = f.C > 0
            active = stretched if blk.all_rope else (stretched | ~blk.rope.array)
            k = k * active.astype(k.dtype)
        out.append((b, k))
    return tuple(out)


def pseudo_velocities(sys: System, fr: tuple, correction: tuple, iterations: int, jacobi_relaxation=None):
    """Solve the split-impulse pseudo-velocity problem from v_p = 0: `iterations` Gauss-Seidel sweeps over the
    colours (or Jacobi sweeps with the given relaxation), dlam_p = (n . (vp_j - vp_i) + bias) k, rope
    pseudo-impulses clamped >= 0. Returns v_p [dim, *view]: it moves the positions of one (sub)step and is then
    discarded, so the position correction adds no kinetic energy. Not warm-started."""
    topo = sys.topology
    vp0 = jnp.zeros((topo.dim,) + topo.view, fr[0].n.dtype)
    lam0 = tuple(jnp.zeros_like(f.C) for f in fr)

    def sweep(_, carry):
        vp, lam = carry
        lam = list(lam)
        dv = jnp.zeros_like(vp)          # Jacobi: every block reads the same vp, the changes are summed
        for c, (blk, f, (b, k)) in enumerate(zip(topo.blocks, fr, correction)):
            ui, uj = L.gather_pair(topo, blk, vp)
            step = (jnp.sum((uj - ui) * f.n, axis=0) + b) * k
            new = clamp_ropes(blk, lam[c] + (step if jacobi_relaxation is None else jacobi_relaxation * step))
            p = f.n * (new - lam[c])
            lam[c] = new
            d = L.scatter_pair(topo, blk, f.wi * p, -f.wj * p)
            if jacobi_relaxation is None:
                vp = vp + d
            else:
                dv = dv + d
        return vp + dv, tuple(lam)

    return lax.fori_loop(0, iterations, sweep, (vp0, lam0))[0]


def _check_int(owner, name, value, minimum):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{owner}: `{name}` must be a Python int (it is static), got {value!r}")
    if value < minimum:
        raise ValueError(f"{owner}: `{name}` must be >= {minimum}, got {value}")


def _check_bool(owner, name, value):
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{owner}: `{name}` must be a bool, got {value!r}")


def _check_scalar(owner, name, value, lo=None, hi=None, *, positive=False):
    """Scalar, finite, within [lo, hi] and (if `positive`) > 0, for values known now; tracers are skipped."""
    check_real(owner, name, value)
    if np.ndim(value) != 0:
        raise ValueError(f"{owner}: `{name}` must be a scalar, got shape {np.shape(value)}")
    a = concrete(value)
    if a is None:
        return
    a = float(a)
    if not np.isfinite(a):
        raise ValueError(f"{owner}: `{name}` must be finite, got {a}")
    if lo is not None and a < lo:
        raise ValueError(f"{owner}: `{name}` must be >= {lo}, got {a}")
    if hi is not None and a > hi:
        raise ValueError(f"{owner}: `{name}` must be <= {hi}, got {a}")
    if positive and not a > 0:
        raise ValueError(f"{owner}: `{name}` must be > 0, got {a}")


class Solver:
    """Base class. A solver advances the internal carry ``(x, v, lam)`` by one step of length dt.

    Subclasses implement `_step(sys, x, v, lam, dt) -> (x, v, lam_step)`, where x, v are [dim, *view] and lam
    is a tuple of per-block impulses accumulated over the step (used as the next step's warm start).
    """

    def _step(self, sys: System, x, v, lam, dt):
        raise NotImplementedError


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
      beta: Baumgarte factor in [0, 1], a differentiable leaf (0.1 to 0.3 is usual).
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
      stabilization: 'baumgarte' (default, the textbook method above) or 'split' (static): split impulses
        (Catto's pseudo-velocities, Box2D v2's and Bullet's split impulse). The velocity sweeps then run with no
        Baumgarte bias (rods: J v = 0; a slack rope keeps its speculative C / h, which is not a correction), and
        a second set of `iterations` sweeps from v_p = 0 solves J v_p = -(beta / h) C for rods and stretched
        ropes (pseudo-impulses >= 0 for ropes, not warm-started). Positions advance by x += h (v + v_p) and v_p
        is discarded: position error is corrected without turning into kinetic energy. lam is the velocity
        impulse only, the physical constraint impulse. Not with `implicit=True`.
      warm_start_gradient: if False, no gradient flows through the warm-start impulses (static). The forward
        pass is unchanged and the gradient becomes a truncated one. Measured on a swinging 16x16 cloth it does
        not stop long-horizon gradient growth (that growth is the physics: the motion is chaotic, and a
        converged XPBD grows as fast); windowed losses (`jc.fit(window=...)`) are what bound it. See
        docs/notebooks.md.
    """

    iterations: int = static_field(default=10)
    beta: Any = 0.2
    warm_start: bool = static_field(default=True)
    substeps: int = static_field(default=1)
    warm_start_factor: Any = 1.0
    warm_start_gradient: bool = static_field(default=True)
    implicit: bool = static_field(default=False)
    stabilization: str = static_field(default="baumgarte")

    def __post_init__(self):
        check_stabilization("PGS", self.stabilization)
        if self.implicit and self.stabilization == "split":
            raise ValueError("PGS: `implicit=True` is not available with stabilization='split' (the pseudo-velocity "
                             "solve has no implicit derivative here); use implicit=False")
        _check_int("PGS", "iterations", self.iterations, 1)
        _check_int("PGS", "substeps", self.substeps, 1)
        _check_bool("PGS", "warm_start", self.warm_start)
        _check_bool("PGS", "warm_start_gradient", self.warm_start_gradient)
        _check_bool("PGS", "implicit", self.implicit)
        _check_scalar("PGS", "beta", self.beta, 0.0, 1.0)
        _check_scalar("PGS", "warm_start_factor", self.warm_start_factor, 0.0, 1.0)

    def _substep(self, sys, x, v, lam_ws, h):
        topo = sys.topology
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        v = sys.apply_gravity(v, h)
        fr = frames(sys, x)
        split = self.stabilization == "split"
        bias = velocity_bias(topo, fr, jnp.zeros((), dtype) if split else beta, h)
        if self.warm_start:
            factor = self.warm_start_factor
            factor = factor if isinstance(factor, (int, float)) else jnp.asarray(factor, dtype)
            v, lam = warm_start(sys, v, fr, lam_ws, factor, self.warm_start_gradient)
        else:
            lam = tuple(jnp.zeros_like(f.C) for f in fr)

        def sweep(_, carry):
            v, lam = carry
            lam = list(lam)
            for c, (blk, f, b) in enumerate(zip(topo.blocks, fr, bias)):
                vi, vj = L.gather_pair(topo, blk, v)
                rel = L.dot0(vj - vi, f.n)
                new = clamp_ropes(blk, lam[c] + (rel + b) * f.k)
                p = f.n * (new - lam[c])
                lam[c] = new
                v = v + L.scatter_pair(topo, blk, f.wi * p, -f.wj * p)
            return v, tuple(lam)

        if self.implicit:
            return self._implicit(sys, x, v, lam, fr, bias, h)
        v, lam = lax.fori_loop(0, self.iterations, sweep, (v, lam))
        if split:
            vp = pseudo_velocities(sys, fr, position_correction(topo, fr, beta, h), self.iterations)
            return x + h * (v + vp), v, lam
        return x + h * v, v, lam

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
            def sweep(_, carry):
                u, l = carry
                l = list(l)
                for c, (blk, f) in enumerate(zip(topo.blocks, fr)):
                    ui, uj = L.gather_pair(topo, blk, u)
                    d = (jnp.sum((uj - ui) * f.n, axis=0) + rhs[c]) * f.k
                    l[c] = l[c] + d
                    p = f.n * d
                    u = u + L.scatter_pair(topo, blk, f.wi * p, -f.wj * p)
                return u, tuple(l)

            u0 = apply_impulses(sys, zero_v, fr, guess)
            return lax.fori_loop(0, self.iterations, sweep, (u0, guess))[1]

        rhs = tuple(r + b for r, b in zip(relative(v_free), bias))
        lam = lax.custom_linear_solve(matvec, rhs, solve, symmetric=True)
        v = apply_impulses(sys, v_free, fr, lam)
        return x + h * v, v, lam

    def _step(self, sys, x, v, lam, dt):
        return substepped(functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)
