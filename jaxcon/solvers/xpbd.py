"""XPBD: extended position-based dynamics (Macklin, Mueller, Chentanez 2016) with substeps."""
from __future__ import annotations

from typing import Any

import jax.numpy as jnp
from jax import lax

from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.contact import zero_impulses
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import position_sweep, run_substeps, with_contacts, with_found


@pytree_dataclass
class XPBD(Solver):
    """Position-level projection of compliant distance constraints, Gauss-Seidel over the colours.

    Per substep of length h = dt / substeps, in displacement form (dp = p - x, the substep's displacement, is
    what the sweeps carry and update; every constraint and contact reads p_j - p_i as (x_j - x_i) + (dp_j - dp_i),
    so h v + h^2 g keeps its precision however large x is):

        v += h g;  dp = h v;  mu = 0
        repeat `iterations` times, colour by colour (constraints of a colour together):
            n = unit(p_j - p_i),  C = |p_j - p_i| - L,  alpha = compliance / h^2
            dmu = (C - alpha mu) / (w_i + w_j + alpha)        (mu > 0: tension, the library's sign)
            mu_new = mu + dmu, clamped to >= 0 for ropes (a rope never pushes)
            p_i += w_i n (mu_new - mu),  p_j -= w_j n (mu_new - mu)
        v = dp / h;  x = x + dp

    mu is the position-level multiplier (kg m); the substep's constraint impulse is mu / h (N s), and the
    returned lam is its sum over the substeps, an impulse over dt (a mass m hanging at rest gives
    lam / dt = m g). The warm start passed in is not used: XPBD restarts mu at 0 every substep.

    Args:
      iterations: Gauss-Seidel sweeps per substep, static, >= 1 (with many substeps, 1 is usual).
      compliance: inverse stiffness, m/N, a differentiable leaf, >= 0; 0 is a rigid rod.
      substeps: substeps per step, static, >= 1.

    Contacts (a model with `planes`, `spheres` or `collide`; `contact.position_pass`, Mueller et al.
    2020): in each iteration, after the colours, every contact with gap C(p) < 0 is projected out at position
    level (rigid, lam_n accumulated >= 0; obstacles for all particles at once, pairs round by round; a contact
    whose predicted path passes the other body keeps the normal at its time of impact, and a start overlap is
    held, not projected: `contact.push_out` moves it out at the substep's start, at most 3 m/s, with no
    velocity), with
    *static* friction cancelling the substep's relative tangential displacement while |lam_t| <= mu lam_n.
    After v = dp / h, a velocity pass over the contacts that pushed (lam_n > 0) sets the normal
    relative velocity to the bounce of sequential impacts from the start of the substep after gravity
    (`contact_rows.chain_bounces`; -e vn for a lone contact, e = 0 at or below `restitution_threshold`) and
    applies *dynamic* friction, the tangential velocity removed by an impulse inside the Coulomb disc of the
    substep's normal impulse; the positions follow that friction (`contact.position_velocity_pass`; dp += h dv,
    in the displacement form), so that what it holds does not creep. The model's single `friction` is used for both
    static and dynamic friction. The reported contact impulses are lam / h plus the velocity pass's impulses,
    summed over the substeps (N s, contact_n >= 0, |contact_t| <= mu contact_n). There is no time-of-impact
    correction (unlike PGS): an impact is resolved at the end of the substep it falls in, so positions after
    a bounce are off by up to a substep's travel and d(final state)/d(initial state) across a bounce is the
    slope of that piecewise map, with jumps where the impact moves to another substep.
    """

    iterations: int = static_field(default=1)
    compliance: Any = 0.0
    substeps: int = static_field(default=10)

    def __post_init__(self):
        check_int("XPBD", "iterations", self.iterations, 1)
        check_int("XPBD", "substeps", self.substeps, 1)
        check_scalar("XPBD", "compliance", self.compliance, 0.0)

    supports_contacts = True

    def _step(self, sys, x, v, lam, dt):
        """Every substep: the predicted displacement dp = h (v + h g) (`position_sweep`'s displacement form);
        `iterations` sweeps, each projecting the
        constraint colours, then the contacts (`contact.position_pass`); v = dp / h, then with contacts
        one velocity pass of restitution and dynamic friction (`contact.position_velocity_pass`), whose friction
        the displacement follows (dp += h dv) before x + dp. Returns the
        impulses summed over the substeps: the blocks', paired with the contacts' `Impulses` where the model has
        contacts. A grid model's substeps share one search for the whole step (`grid_substepped`)."""
        topo, cs = sys.topology, sys.contact
        dtype = x.dtype
        compliance = jnp.asarray(self.compliance, dtype)

        def substep(x, v, _, h, found=None):
            partners = None if found is None else found[0]
            if cs is not None:
                x = contact.push_out(cs, sys.w, x, h, partners)
            sweep_colours = position_sweep(sys, sys.rest, compliance / (h * h), set_alpha=lambda a: a / (h * h),
                                           base=x)
            v_before = sys.apply_gravity(v, h)

            def sweep(i, c):
                dp, mu, imp = c
                dp, mu = sweep_colours(i, (dp, mu))
                if cs is not None:
                    dp, imp = contact.position_pass(cs, sys.w, x, dp, imp, partners, ahead, h)
                return dp, mu, imp

            zero = tuple(jnp.zeros(b.shape, dtype) for b in topo.blocks)
            imp = None if cs is None else zero_impulses(topo, cs.ct, dtype)
            ahead = h * v_before
            dp, mu, imp = lax.fori_loop(0, self.iterations, sweep, (ahead, zero, imp), unroll=topo.unroll)
            v = dp / h
            if cs is not None:
                v, imp, follow = contact.position_velocity_pass(cs, sys.w, x + dp, v_before, v, imp, h, partners, True,
                                                                (x, dp, ahead))
                dp = dp + follow                 # the positions follow the velocity pass's friction
                imp = with_found(imp, found)
            return x + dp, v, with_contacts(sys, tuple(m / h for m in mu), imp)

        return run_substeps(sys, substep, self.substeps, x, v, lam, dt)
