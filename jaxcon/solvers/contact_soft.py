"""Contacts for `jc.SoftStep`, Box2D v3 style (Erin Catto, "Solver2D", 2024; box2d/src/contact_solver.c).

The rows are PGS's (`jaxcon.solvers.contact.rows` with no Baumgarte term): speculative contacts, swept time of
impact and restitution. Per substep of length h:

* **Solve** (with bias, one Gauss-Seidel sweep after the rods): a separated contact (C > 0: speculative, or an
  impact within the substep) is rigid, with its row's target. A touching or overlapping one (C <= 0) is a soft
  constraint that pushes the overlap out like a spring-damper of `contact_hertz` and `contact_damping_ratio`:
  target min(-bias_rate C, push_velocity), the update scaled by mass_scale and softened by
  -impulse_scale lam_n (Box2D's b2MakeSoft coefficients; obstacles, Box2D's static bodies, at twice the
  hertz), with no restitution, as Box2D. One difference from Box2D: an impact within the substep keeps its
  row's bounce target here already (Box2D bounces only after relaxing), so that the time-of-impact correction
  moves the particle on its bounced velocity for the rest of the substep, as PGS does.
* positions x += h v, with PGS's time-of-impact correction.
* **Relax** (without bias): every row rigid with its row's target, which for touching contacts is
  max(e u + dv, 0): the push-out velocity is removed and restitution is applied here (Box2D applies it after
  the relax iterations, to contacts whose approach speed exceeded the threshold; a row with a positive target
  does the same within the relax sweeps).

Friction is rigid in both stages (as Box2D's), clamped to mu lam_n.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxcon.solvers.contact import Impulses, Rows, finish_row, sweep


def solve_rows(rows: Rows, soft, push_velocity):
    """Solve-stage rows and their softness: (rows, (mass_scale, impulse_scale)), each of the rows' shape.
    Touching or overlapping rows (gap <= 0, or within rounding of touching and no impact: `contact._gap`) get
    the soft push-out target min(-bias_rate C, push_velocity) and the soft coefficients `soft` = (bias_rate,
    mass_scale, impulse_scale); separated rows, and impacts, stay rigid."""
    if rows is None:
        return None, None
    bias_rate, mass_scale, impulse_scale = soft
    touching = (rows.gap <= 0) | (rows.near & (rows.toi == 0))
    target = jnp.where(touching, jnp.minimum(-bias_rate * rows.gap, push_velocity), rows.target)
    one = jnp.ones_like(rows.gap)
    return rows._replace(target=target), (jnp.where(touching, mass_scale * one, one),
                                          jnp.where(touching, impulse_scale * one, 0 * one))


def _soft_row(vrel, f: Rows, soft, mu, ln, lt):
    """One soft contact row: lam_n += mass_scale k (target - vn) - impulse_scale lam_n, clamped >= 0, then
    rigid friction clamped to the disc mu lam_n. Returns (impulse change P on the second body, lam_n, lam_t)."""
    mass_scale, impulse_scale = soft
    vn = jnp.sum(vrel * f.n, 0)
    new_n = jnp.maximum(ln + mass_scale * f.k * (f.target - vn) - impulse_scale * ln, 0)
    return finish_row(vrel, f, mu, ln, new_n, lt)


def soft_sweep(cs, w, v, obs: Rows, pairs: Rows, imp: Impulses, obs_soft, pair_soft):
    """One Gauss-Seidel pass over every contact with soft rows: `contact.sweep` with `_soft_row` and the
    per-row soft coefficients. Returns (v, imp)."""
    def row(vrel, f, mu, ln, lt, soft):
        return _soft_row(vrel, f, soft, mu, ln, lt)

    return sweep(cs, w, v, obs, pairs, imp, row=row, extra=(obs_soft, pair_soft))
