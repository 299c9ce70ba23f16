"""Box2D v3's "soft step": substepping with soft constraints and relaxation (Erin Catto, Solver2D, 2024)."""
from __future__ import annotations

import functools
import math
from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import frames, refuse_hard_sets, run_substeps, step_begin, with_contacts


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


def _sweep(topo, v, lam, fr, bias, mass_scale, impulse_scale, inv_h, spring=True):
    """One Gauss-Seidel sweep over the constraint colours with soft (or, mass_scale 1 and impulse_scale 0,
    rigid) rows; a slack rope (or unilateral row) is speculative and rigid. A constraint set's compliant rows
    are their own springs instead (`rows.solve`, bias C / h; warm-started by `common.warm_rows`;
    untouched by the relax sweeps), so a compliance means the same potential energy as in every other solver.
    Returns (v, lam)."""
    def colour(v, blk, rows):
        f, g, lam = rows
        rel = R.rel(topo, blk, f, v)
        ms, isc, b = mass_scale, impulse_scale, bias(f)
        if blk.has_rope:  # slack rope: speculative, rigid
            slack = f.C < 0 if blk.all_rope else (f.C < 0) & blk.rope.array
            b = jnp.where(slack, f.C * inv_h, b)
            ms = jnp.where(slack, 1, ms)
            isc = jnp.where(slack, 0, isc)
        step = ms * L.block_solve(topo, blk, f, rel + b) - isc * lam
        if g is not None:       # the relax sweeps leave compliant rows alone: their spring impulse is the solve's
            own = R.solve(topo, blk, f, rel + f.C * inv_h, lam, g) if spring else jnp.zeros_like(step)
            step = jnp.where(f.alpha > 0, own, step)
        new = R.accumulate(blk, lam, step)
        return R.apply(topo, blk, f, v, new - lam), new

    lam = list(lam)
    for c, (blk, f) in enumerate(zip(topo.blocks, fr)):
        v, lam[c] = L.each_colour(blk, colour, v, (f, R.gamma(f, 1 / inv_h), lam[c]))
    return v, tuple(lam)


@pytree_dataclass
class SoftStep(Solver):
    """Soft step (Box2D v3): per substep of length h = dt / substeps,

      1. integrate velocities: v += h g;
      2. warm start: apply the previous substep's impulses (a constraint set's compliant rows': a share,
         `common.warm_rows`);
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

    Contacts (`planes`, `spheres`, `collide`; `contact.soft_rows`), as Box2D v3: PGS's rows (speculative
    contacts, swept time of impact, restitution) solved after the rods in the same sweeps; a touching or
    overlapping contact is soft in the solve sweep (push-out at `contact_hertz`, `contact_damping_ratio`, at
    most `contact_push_velocity`; obstacles, Box2D's static bodies, at twice the hertz) and rigid, with its
    restitution, in the relax sweeps; positions get PGS's time-of-impact correction. A resting contact sinks by
    its spring's static deflection, (load / effective mass) / (2 pi hertz)^2 (a particle resting on the floor:
    g / (2 pi 60)^2 = 0.07 mm at the defaults and dt 1/60). A fast impact through touching contacts (a
    billiards rack) is only carried as far as one sweep per substep reaches: the 10 m/s break needs 16
    substeps and contact_hertz = 0.25 / h to overlap below 1% of a diameter. A hard constraint set (compliance 0)
    in a model with contacts is refused before tracing (`_check_stability`): its rows are springs of `hertz`
    here, which contacts pressing on it squeeze (docs/constraints.md).

    Args:
      substeps: substeps per step, static, >= 1.
      hertz: constraint stiffness as a frequency (Hz), > 0, a differentiable leaf.
      damping_ratio: >= 0, a differentiable leaf.
      relax_iterations: rigid sweeps after the position update, static, >= 0.
      contact_hertz: contact stiffness (Hz) between particles, > 0, a differentiable leaf; None: Box2D's
        min(30, 0.25 / h) with h the substep. Contacts with planes and spheres use twice it.
      contact_damping_ratio: >= 0, a differentiable leaf (Box2D's default 10).
      contact_push_velocity: the fastest an overlap is pushed out (m/s), > 0, a differentiable leaf (Box2D's
        default 3).
    """

    substeps: int = static_field(default=4)
    hertz: Any = 60.0
    damping_ratio: Any = 2.0
    relax_iterations: int = static_field(default=1)
    contact_hertz: Any = None
    contact_damping_ratio: Any = 10.0
    contact_push_velocity: Any = 3.0

    def __post_init__(self):
        check_int("SoftStep", "substeps", self.substeps, 1)
        check_int("SoftStep", "relax_iterations", self.relax_iterations, 0)
        check_scalar("SoftStep", "hertz", self.hertz, 0.0, positive=True)
        check_scalar("SoftStep", "damping_ratio", self.damping_ratio, 0.0)
        if self.contact_hertz is not None:
            check_scalar("SoftStep", "contact_hertz", self.contact_hertz, 0.0, positive=True)
        check_scalar("SoftStep", "contact_damping_ratio", self.contact_damping_ratio, 0.0)
        check_scalar("SoftStep", "contact_push_velocity", self.contact_push_velocity, 0.0, positive=True)

    supports_contacts = True

    def _check_stability(self, owner, model, dt) -> None:
        """Before tracing: refuse a hard constraint set under contacts (`common.refuse_hard_sets`). A hard row is a
        spring of `hertz` here, so a set pressed by contacts gives way by its load over (2 pi hertz)^2 times its
        effective mass (a hard volume pressed on the floor at 10 g lost 4.2%, 1.6% at 120 Hz)."""
        refuse_hard_sets(owner, "SoftStep", model,
                         f"its hard rows are springs of `hertz` ({self.hertz} Hz), and a set pressed by contacts gives "
                         "way by its load over (2 pi hertz)^2 times the set's effective mass (a hard volume pressed "
                         "on the floor lost 4.2%)")

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)

    def _substep(self, sys, x, v, lam, h, found=None):
        """One substep: warm start; the solve sweep over the constraint colours, then the contacts' (soft
        push-out of overlap, no restitution: `contact.soft_rows`); positions, with the contacts' time-of-impact
        correction; relax sweeps over every row without bias, restitution in the contacts' relax targets. A grid
        model's step goes through `grid_substepped`, which calls this with its candidate pairs `found`."""
        dtype = x.dtype
        topo, cs, w = sys.topology, sys.contact, sys.w
        bias_rate, mass_scale, impulse_scale = soft_coefficients(jnp.asarray(self.hertz, dtype),
                                                                 jnp.asarray(self.damping_ratio, dtype), h)
        zero = jnp.zeros((), dtype)            # no Baumgarte term: the contacts' rows are speculative or soft
        b = step_begin(sys, x, v, lam, zero, h, None, True, found=found)
        v_free, v, fr, lam, obs, pairs, imp = b.v_free, b.v, b.fr, b.lam, b.obs, b.pairs, b.imp
        solve_obs = solve_pairs = None
        softness = (None, None)
        if cs is not None:
            hz = (jnp.minimum(jnp.asarray(30.0, dtype), 0.25 / h) if self.contact_hertz is None
                  else jnp.asarray(self.contact_hertz, dtype))
            zeta = jnp.asarray(self.contact_damping_ratio, dtype)
            push = jnp.asarray(self.contact_push_velocity, dtype)
            solve_obs, obs_soft = contact.soft_rows(obs, soft_coefficients(2 * hz, zeta, h), push)  # static bodies
            solve_pairs, pair_soft = contact.soft_rows(pairs, soft_coefficients(hz, zeta, h), push)
            softness = (obs_soft, pair_soft)
        inv_h = 1 / h
        v, lam = _sweep(topo, v, lam, fr, lambda f: bias_rate * f.C, mass_scale, impulse_scale, inv_h)
        v, imp = contact.sweep(cs, w, v, solve_obs, solve_pairs, imp, softness)
        v, imp = contact.restitution_stage(cs, w, v, obs, pairs, imp)
        x = x + h * v
        if cs is not None:
            x = x - contact.impact_times(cs, obs, pairs, imp, x.shape) * (v - v_free)
        if self.relax_iterations:
            fr = frames(sys, x)

            def relax(_, carry):
                v, lam, imp = carry
                v, lam = _sweep(topo, v, lam, fr, lambda f: jnp.zeros_like(f.C), 1.0, 0.0, inv_h, False)
                v, imp = contact.sweep(cs, w, v, obs, pairs, imp)
                return v, lam, imp

            v, lam, imp = lax.fori_loop(0, self.relax_iterations, relax, (v, lam, imp), unroll=topo.unroll)
        return x, v, with_contacts(sys, lam, imp)
