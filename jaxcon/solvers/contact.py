"""The contact rows' updates in every solver that takes contacts (docs/contacts.md): Gauss-Seidel (`sweep`, with
SoftStep's soft rows from `soft_rows`), Jacobi with mass splitting (`jacobi_pass`), the position level of XPBD
(`position_pass`, `position_velocity_pass`), the warm start, the restitution phases' energy bound, the
time-of-impact correction and the position safety pass (`project_overlaps`). The rows themselves are the contact
kind's (`jaxcon.core.contact_rows`), and a grid model's pairs come from `jaxcon.core.grid`.

Each contact row has a unit normal n, a target velocity and an accumulated normal impulse lam_n >= 0 with a
friction impulse lam_t in the tangent plane, |lam_t| <= mu lam_n. Its normal update is the one every
sequential-impulse solver uses: lam_n += k (target - vn), clamped >= 0; friction follows, solved as a 2-D or
3-D vector clamped to the Coulomb disc.
"""
from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.contact import ContactSystem, Impulses, zero_impulses
from jaxcon.core.contact_rows import (
    CONTACT_SLOP,
    PUSH_OUT_SPEED,
    UNILATERAL,
    ObstacleBlock,
    ObstacleColour,
    Rows,
    direction,
    each_obstacle,
    dot as _dot,
    is_in_solve,
    length as _length,
    obstacle_gap,
    obstacle_reach,
    obstacle_moved_gap,
    overlap_normal,
    pair_block,
    pair_index,
    pair_partners,
    pair_total,
    phase_target,
    slot_rows,
    speculative_rows as contact_rows_speculative,
    velocity_rows,
)


Array = Any


#: PGS's position safety passes for a grid model. Its slot-by-slot passes converge more slowly than the rounds'
#: Gauss-Seidel ones: on 18 discs in 4 staggered rows landing on a floor (PGS(10), dt 1/120) the deepest overlap
#: was 0.86% of a diameter with 8 passes, 0.30% with 16 and 0.12% with 32 (all pairs: 0.03% with 8); a pass
#: costs K small steps over n particles, against n - 1 rounds for all pairs. `PGS(contact_passes=k)` overrides
#: it: with substeps, the passes' lifts kept a deep pile flowing, and one pass lets it rest (docs/contacts.md).
GRID_OVERLAP_PASSES = 32

#: A grid model's position passes stop after one that moved no particle by more than this fraction of the slop
#: times the smallest radius (`project_overlaps`). Measured on the 1024-disc box (docs/contacts.md): 0.1 with
#: the push-out beyond two slops (`PUSH_SLOPS`) rests by 5 s at 12 ms per step; 0.1 with the push-out beyond one
#: slop did not rest in 8 s (1.1 m/s); 0.001 rested at 28 ms per step (most steps ran all 32 passes). With the
#: push-out beyond six slops, 0.5 and 1.0 saved no time (6.5 and 6.6 ms per step against 6.4) and left deeper
#: overlaps (3.9% and 4.5% of R at 8 s against 1.9%).
GRID_PASS_STOP = 0.1


def _solve_row(vrel, f: Rows, mu, ln, lt, soft=None):
    """One contact row at velocity level: the normal impulse by the row update of every kind (`rows.solve` with
    rel = -vn, the rate of C_lib = -gap, and bias = the row's target: lam_n += k (target - vn); `rows.accumulate`:
    clamped >= 0), then friction (`finish_row`). `soft` = (mass_scale, impulse_scale), each of the rows' shape,
    makes it a soft row (SoftStep, `soft_rows`) as SoftStep's constraint rows are: the change is mass_scale times
    that minus impulse_scale lam_n. Returns (impulse change P [dim, ...] on the second body, new lam_n, new
    lam_t)."""
    step = R.solve(None, UNILATERAL, f, f.target - _dot(vrel, f.n), ln, None)
    if soft is not None:
        mass_scale, impulse_scale = soft
        step = mass_scale * step - impulse_scale * ln
    return finish_row(vrel, f, mu, ln, R.accumulate(UNILATERAL, ln, step), lt)


# SoftStep's contacts, Box2D v3 style (Erin Catto, "Solver2D", 2024; box2d/src/contact_solver.c).
#
# The rows are PGS's (`rows` with no Baumgarte term): speculative contacts, swept time of
# impact and restitution. Per substep of length h:
#
# * **Solve** (with bias, one Gauss-Seidel sweep after the rods): a separated contact (C > 0: speculative, or an
#   impact within the substep) is rigid, with its row's target. A touching or overlapping one (C <= 0) is a soft
#   constraint that pushes the overlap out like a spring-damper of `contact_hertz` and `contact_damping_ratio`:
#   target min(-bias_rate C, push_velocity), the update scaled by mass_scale and softened by
#   -impulse_scale lam_n (Box2D's b2MakeSoft coefficients; obstacles, Box2D's static bodies, at twice the
#   hertz), with no restitution, as Box2D. One difference from Box2D: an impact within the substep keeps its
#   row's bounce target here already (Box2D bounces only after relaxing), so that the time-of-impact correction
#   moves the particle on its bounced velocity for the rest of the substep, as PGS does.
# * positions x += h v, with PGS's time-of-impact correction.
# * **Relax** (without bias): every row rigid with its row's target, which for touching contacts is
#   max(e u + dv, 0): the push-out velocity is removed and restitution is applied here (Box2D applies it after
#   the relax iterations, to contacts whose approach speed exceeded the threshold; a row with a positive target
#   does the same within the relax sweeps).
#
# Friction is rigid in both stages (as Box2D's), clamped to mu lam_n.


def soft_rows(rows: Optional[Rows], soft, push_velocity):
    """SoftStep's solve-stage rows and their softness (Box2D v3's soft contacts): (rows, (mass_scale,
    impulse_scale)), each of the rows' shape. Touching or overlapping rows (gap <= 0, or within rounding of
    touching and no impact: `_gap`) get the push-out target min(-bias_rate C, push_velocity) and the soft
    coefficients `soft` = (bias_rate, mass_scale, impulse_scale); separated rows, and impacts, stay rigid."""
    if rows is None:
        return None, None
    bias_rate, mass_scale, impulse_scale = soft
    touching = (rows.gap <= 0) | (rows.near & (rows.toi == 0))
    target = jnp.where(touching, jnp.minimum(-bias_rate * rows.gap, push_velocity), rows.target)
    one = jnp.ones_like(rows.gap)
    return rows._replace(target=target), (jnp.where(touching, mass_scale * one, one),
                                          jnp.where(touching, impulse_scale * one, 0 * one))


def finish_row(vrel, f: Rows, mu, ln, new_n, lt):
    """The rest of a contact row once its new normal impulse `new_n` is known: friction on the relative
    velocity after that impulse, clamped to the disc mu new_n. Returns (P, new_n, new_t) as `_solve_row`."""
    dn = new_n - ln
    vrel = vrel + (f.winv * dn) * f.n
    vt = vrel - f.n * _dot(vrel, f.n)
    new_t = lt - vt * f.k
    length, inv = _length(new_t)
    limit = mu * new_n
    new_t = new_t * jnp.where(length >= limit, limit * inv, 1)
    return f.n * dn + (new_t - lt), new_n, new_t


def sweep(cs: Optional[ContactSystem], w, v, obs: Rows, pairs: Rows, imp: Impulses, soft=(None, None)):
    """One Gauss-Seidel pass over every contact: the obstacles' rows, then the pairs', each a block whose colours
    `layout.each_colour` runs in order (obstacle by obstacle; round by round, or a grid model's slot by slot:
    `contact_rows.ObstacleBlock`, `pair_block`). Each colour's rows update together from the same v
    (`_solve_row`); a grid slot's rows, which may share particles, are relaxed by mass splitting: each takes the
    effective mass 1 / (c_i w_i + c_j w_j), c the slot's rows that push at each particle (as `jacobi_pass`
    does). Returns (v, imp); a model without contacts (`cs` None) returns them unchanged.

    `soft` = (obstacle softness, pair softness): SoftStep's (mass_scale, impulse_scale) per row
    (`soft_rows`), each None for rigid rows (`_solve_row`)."""
    if cs is None:
        return v, imp
    mu = cs.friction

    def colour(w):
        def update(v, c, rows):
            (f, s), (ln, lt) = rows
            vrel = c.rel(v)
            if c.split:
                act = ((ln > 0) | (ln + (f.target - _dot(vrel, f.n)) * f.k > 0)) & (f.k > 0)
                f = f._replace(k=c.split_mass(w, act.astype(v.dtype)) * (f.k > 0).astype(v.dtype))
            P, ln, lt = L.computed_once(_solve_row, (vrel, f, mu, ln, lt, s), getattr(c, "partner", None))
            return c.apply(w, v, P), (ln, lt)
        return update

    on, ot = imp.obs_n, imp.obs_t
    if obs is not None and obs.sel is not None:
        v, (on, ot) = _selected_obstacles(cs.ct, colour, w, v, obs, soft[0], on, ot)
    elif obs is not None:
        v, (on, ot) = L.each_colour(ObstacleBlock(cs.ct), colour(w), v, ((obs, soft[0]), (on, ot)))
    pn, pt = imp.pair_n, imp.pair_t
    if pairs is not None:
        dim, shape = v.shape[0], v.shape
        block = pair_block(cs.ct, pairs.j, is_in_solve(pairs), pairs.slots)   # j: a grid's partners, None if listed
        vf, (pn, pt) = L.each_colour(block, colour(w.reshape(-1)), v.reshape(dim, -1),
                                     ((pairs._replace(slots=None), soft[1]), (pn, pt)))
        v = vf.reshape(shape)
    return v, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def _selected_obstacles(ct, colour, w, v, obs: Rows, soft, on, ot):
    """The obstacles' part of `sweep` where `obs.sel` picks the rows within reach (`contact_rows.select_obstacles`):
    obstacle by obstacle, if every row left out would not change (no impulse, and an update that asks for none:
    k (target - vn) <= 0), only the picked rows are solved, gathered into `idx`'s order and written back; else
    the whole obstacle, as without a selection. The same updates either way, on fewer rows: the 1024-disc box
    has 3072 plane rows, of which about 100 touch."""
    dim, vshape = v.shape[0], v.shape
    nview = len(vshape) - 1
    vf, wf = v.reshape(dim, -1), w.reshape(1, -1)
    n = vf.shape[1]

    def flat(a):
        return a.reshape(a.shape[: a.ndim - nview] + (-1,))

    planes = obs.sel.planes          # inside a solve that split the impulses per obstacle (`solve_phases`)

    def one(vf, q):
        f = jax.tree.map(lambda a: flat(a[q]), obs._replace(sel=None)) if planes is None else \
            phase_target(planes[q][0], obs.sel.late)
        s = None if soft is None else jax.tree.map(lambda a: flat(a[q]), soft)
        ln, lt = (flat(on[q]), flat(ot[q])) if planes is None else (on[q], ot[q])
        idx, inside = obs.sel.idx[q], obs.sel.inside[q]
        # a row `_solve_row` would leave as it is (no impulse, and k (target - vn) <= 0 asks for none): a change to
        # the row update must change this test too
        still = (ln == 0) & jnp.all(lt == 0, 0) & ((f.target - _dot(vf, f.n)) * f.k <= 0)

        def picked(args):
            vf, ln, lt = args
            live = idx < n

            def take(a):
                return jnp.take(a, jnp.minimum(idx, n - 1), axis=-1)

            if planes is None:
                fs = jax.tree.map(take, f)
                fs = fs._replace(k=fs.k * live.astype(fs.k.dtype))        # an unused entry: no row
            else:
                fs = phase_target(planes[q][1], obs.sel.late)
            ss = None if s is None else jax.tree.map(take, s)
            ws = take(wf) if planes is None else planes[q][2]
            vs, (lns, lts) = colour(ws)(take(vf), ObstacleColour(q), ((fs, ss), (take(ln), take(lt))))

            def put(a, b):
                return a.at[..., idx].set(b, mode="drop")
            return put(vf, vs), put(ln, lns), put(lt, lts)

        def every(args):
            vf, ln, lt = args
            vf, (ln, lt) = colour(wf)(vf, ObstacleColour(q), ((f, s), (ln, lt)))
            return vf, ln, lt

        vf, ln, lt = lax.cond(jnp.all(inside | still), picked, every, (vf, ln, lt))
        return vf, (ln, lt)

    if planes is not None:           # split per obstacle: at most UNROLL_OBSTACLES of them (`solve_phases`)
        ons, ots = [], []
        for q in range(obs.gap.shape[0]):
            vf, (ln, lt) = one(vf, q)
            ons.append(ln)
            ots.append(lt)
        return vf.reshape(vshape), (tuple(ons), tuple(ots))
    vf, (ons, ots) = each_obstacle(ct, lambda vf, q, sphere, _: one(vf, q), vf)
    return vf.reshape(vshape), (ons.reshape(on.shape), ots.reshape(ot.shape))


def _obstacle_frame(obs: Rows):
    """Obstacle rows with the dim axis first ([dim, Q, *view]), as `_solve_row` wants."""
    return obs._replace(n=jnp.moveaxis(obs.n, 1, 0))


def jacobi_counts(cs: ContactSystem, v, obs: Rows, pairs: Rows, imp: Impulses, base):
    """Mass splitting's counts (`jacobi_pass`): `base` [1, *view] (the other rows at each particle) plus, per
    particle, the contact rows that push on it in this iteration: those that hold an impulse, or whose
    unrelaxed update from the velocities `v` would give one."""
    ct, c = cs.ct, base
    if obs is not None:
        f = _obstacle_frame(obs)
        vn = _dot(v[:, None], f.n)
        act = ((imp.obs_n > 0) | (imp.obs_n + (obs.target - vn) * obs.k > 0)) & (obs.k > 0)
        c = c + jnp.sum(act.astype(c.dtype), 0)[None]
    if pairs is not None:
        ia, ja = pair_index(ct, pairs)
        vf = v.reshape(v.shape[0], -1)
        vn = _dot((vf[:, ja] - vf[:, ia]).reshape(pairs.n.shape), pairs.n)
        act = ((imp.pair_n > 0) | (imp.pair_n + (pairs.target - vn) * pairs.k > 0)) & (pairs.k > 0)
        act = act.astype(c.dtype).reshape(-1)
        flat = c.reshape(-1).at[ia].add(act).at[ja].add(act)
        c = flat.reshape(c.shape)
    return c


def jacobi_pass(cs: ContactSystem, w, v, obs: Rows, pairs: Rows, imp: Impulses, count, relax):
    """Every contact row updated from the same `v` (Jacobi), each by `_solve_row`: (dv, imp). A row between
    particles i and j takes the effective mass 1 / (c_i w_i + c_j w_j) with the per-particle counts `count`
    [1, *view] (mass splitting, `jacobi_counts`; an obstacle has no inverse mass: 1 / (c_i w_i)), or relax * k
    with a fixed relaxation (`count` None).

    Mass splitting (Tonge, Benevolenski and Voroshilov 2012, "Mass splitting for jitter-free parallel rigid body
    simulation") is the momentum-conserving form of the constraint averaging of Macklin et al. 2014. A particle
    touched by c rows in this iteration (its constraint rows, plus its contacts that push or are about to) lends
    each of them 1 / c of its mass, and the impulse is applied with the true masses. Every row's impulse acts
    equally and oppositely on its two particles, so momentum is conserved exactly (per-particle averaging of the
    velocity changes is not: c_i != c_j). Since the Delassus matrix is bounded by this diagonal
    (A = J W J^T <= diag(c_i w_i + c_j w_j), each particle's rows forming a Gram matrix of unit normals), the
    iteration converges for any fixed active set. The counts are recomputed in every iteration, so a particle
    free of contacts keeps its full mass and a ball wedged in a rack splits it six ways."""
    dv = jnp.zeros_like(v)
    ct, mu = cs.ct, cs.friction
    on, ot, pn, pt = imp[:4]
    if obs is not None:
        f = _obstacle_frame(obs)
        k = relax * obs.k if count is None else L.safe_reciprocal(count * obs.winv) * (obs.k > 0).astype(v.dtype)
        vrel = jnp.broadcast_to(v[:, None], f.n.shape)
        P, on, ot = _solve_row(vrel, f._replace(k=k), mu, on, jnp.moveaxis(ot, 1, 0))
        ot = jnp.moveaxis(ot, 0, 1)
        dv = dv + w * jnp.sum(P, 1)
    if pairs is not None:
        index = pair_index(ct, pairs)
        ia, ja = index
        vf = v.reshape(v.shape[0], -1)
        shape = pairs.k.shape
        if count is None:
            k = relax * pairs.k
        else:
            cf, wf = count.reshape(-1), w.reshape(-1)
            k = L.safe_reciprocal(cf[ia] * wf[ia] + cf[ja] * wf[ja]).reshape(shape) * (pairs.k > 0).astype(v.dtype)
        vrel = (vf[:, ja] - vf[:, ia]).reshape(pairs.n.shape)
        partners = pair_partners(pairs)
        P, pn, pt = L.computed_once(_solve_row, (vrel, pairs._replace(k=k), mu, pn, pt), partners)
        dv = dv + pair_total(ct, w, P, -1.0, index, partners).reshape(v.shape)
    return dv, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def carry_slots(prev: Impulses, partners):
    """A grid model's pair impulses `prev` (made with prev.partners) moved to the slots of `partners` [n, K]:
    (pair_n [n, K], pair_t [dim, n, K]). A slot keeps an impulse only if it lists the same partner again (each
    pair always sits in the row of its lower-numbered particle, so a pair that stays a candidate stays in the
    same row); a new pair starts from 0."""
    # Each new slot's previous slot (K: none; at most one matches) is an integer reduction, and the impulses a
    # gather from it. Written as K selects of the impulses instead, XLA's CPU backend fused the select chain into
    # each of the four fusions that read the warm start (its projection, the scatter of its impulses, the
    # slot-major copy for the solve), recomputing it in each: on the settled 1024-disc box 1.5 to 2.5% of the
    # step, measured against a sum of selects over [n, K, K] and 5% against the chain (docs/contacts.md).
    K = partners.shape[1]
    same = (partners[:, :, None] >= 0) & (partners[:, :, None] == prev.partners[:, None, :])    # [n, new, old]
    idx = jnp.sum(jnp.where(same, jnp.arange(-K, 0, dtype=jnp.int32), 0), -1) + K
    pn = jnp.take_along_axis(prev.pair_n, idx, 1, mode="fill", fill_value=0)
    pt = jnp.take_along_axis(prev.pair_t, jnp.broadcast_to(idx, prev.pair_t.shape), 2, mode="fill", fill_value=0)
    return pn, pt


def warm_start(cs: ContactSystem, w, v, obs: Rows, pairs: Rows, prev: Impulses, factor=1.0):
    """Apply last step's contact impulses to contacts that touch or will touch within this step, re-projected
    on the new normals (lam_n >= 0, friction inside the new cone). Returns (v, imp)."""
    ct, mu = cs.ct, cs.friction

    def project(f: Rows, ln, lt):
        active = f.warm & (f.k > 0)
        ln = jnp.maximum(ln, 0) * factor * active.astype(ln.dtype)
        lt = (lt - f.n * _dot(lt, f.n)) * factor
        length, inv = _length(lt)
        limit = mu * ln
        return ln, lt * jnp.where(length >= limit, limit * inv, 1) * active.astype(ln.dtype)

    on, ot = prev.obs_n, prev.obs_t
    if obs is not None:
        on, ot = project(_obstacle_frame(obs), on, jnp.moveaxis(ot, 1, 0))
        ot = jnp.moveaxis(ot, 0, 1)          # back to [Q, dim, *view]
        P = obs.n * on[:, None] + ot
        v = each_obstacle(ct, lambda v, q, sphere, Pq: (v + w * Pq, None), v, P)[0]   # obstacle by obstacle (see
        # `carry_slots`), written out up to `UNROLL_OBSTACLES`
    pn, pt = prev.pair_n, prev.pair_t
    partners = pair_partners(pairs)
    if partners is not None:
        pn, pt = carry_slots(prev, partners)
    if pairs is not None:
        # projected once (`layout.computed_once`): the slot-major move of the impulses for the solve, the scatter of
        # their impulses and the sum over each particle's own slots each computed the projection again
        pn, pt = L.computed_once(project, (pairs, pn, pt), partners)
        P = pairs.n * pn + pt
        v = v + pair_total(ct, w, P, -1.0, pair_index(ct, pairs), partners).reshape(v.shape)
    return v, prev._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def restitution_scale(w, v_free, v_c, v_n, bounce):
    """The largest s in [0, 1] for which v_c + s (v_n - v_c) has no more kinetic energy than the larger of the
    velocity before any impulse (`v_free`) and the compression phase's (`v_c`); 1 where no row bounces.

    Newton's restitution applied to several coupled impacts at once (a ball that hits a cluster which is also
    hitting a cushion) can end with more kinetic energy than before the impacts; a single impact, or one into a
    cluster whose other contacts are inelastic, cannot. The compression phase (every contact inelastic) only
    removes energy (or adds what Baumgarte push-out adds), so scaling the restitution phase's change back to
    that bound keeps the non-penetration targets of the compression phase, the cone, lam_n >= 0 (a convex
    combination of two solutions that satisfy them) and the momentum, and never raises the kinetic energy."""
    m = L.safe_reciprocal(w)
    d = v_n - v_c
    kc, b, c = jnp.sum(m * v_c * v_c), jnp.sum(m * v_c * d), jnp.sum(m * d * d)
    e = jnp.maximum(jnp.sum(m * v_free * v_free), kc)
    e = e * (1 + 16 * jnp.finfo(e.dtype).eps)
    within = ~bounce | (kc + 2 * b + c <= e)
    # Where `within`, the root below is not used, but reverse mode still multiplies its (zero) cotangent by its
    # partial derivatives: with the phases' velocities a rounding error apart, c ~ 1e-27 and d s / d c ~ 1 / c^2
    # overflows float32, and 0 * inf is NaN (the falling chain's friction gradient). So the root only ever sees
    # safe values there (b = 0, c = slack = 1), and its square root never sees 0.
    b, c = jnp.where(within, 0, b), jnp.where(within, 1, c)
    slack = jnp.where(within, 1, jnp.maximum(e - kc, 0))
    disc = b * b + c * slack
    root = jnp.where(disc > 0, jnp.sqrt(jnp.where(disc > 0, disc, 1)), 0)
    den = b + root                        # two cancellation-free forms of the larger root of K(s) = e
    # For b < 0 the root is (|b| + root) / c, at most 1 when not `within` (K(1) > e), i.e. c >= |b| + root: the
    # maximum changes nothing there and keeps the quotient and its derivatives bounded when c underflows.
    s = jnp.where(b >= 0, slack / jnp.where(den > 0, den, 1),
                  (root - b) / jnp.where(b < 0, jnp.maximum(c, root - b), 1))
    return jnp.where(within, 1, jnp.clip(s, 0, 1))


#: Contact-only Gauss-Seidel sweeps of the restitution stage (`restitution_stage`).
RESTITUTION_SWEEPS = 16


def restitution_stage(cs: Optional[ContactSystem], w, v, obs: Rows, pairs: Rows, imp: Impulses):
    """The restitution stage of every solver, after its own solve (Box2D v3's restitution stage): in a step
    where some row bounces (its target above its compression target, or any positive target where rows have
    no compression target: XPBD's and RATTLE's velocity pass), `RESTITUTION_SWEEPS` Gauss-Seidel sweeps over
    the contact rows alone (`sweep`) with their restitution targets (`contact_rows.chain_bounces`); otherwise
    nothing (the same values and derivatives). A solver's own sweeps carry a hit through a chain of touching
    bodies by about one contact per sweep (two with the rounds' order), too few at one or two sweeps per
    substep (SoftStep, XPBD's velocity pass) or with mass splitting (Jacobi) for a cradle's end ball to leave
    with the hit ball's speed. Returns (v, imp)."""
    if cs is None:
        return v, imp
    bounce = jnp.zeros((), bool)
    for f in (obs, pairs):
        if f is not None:
            bounce = bounce | jnp.any(f.target > (0 if f.target_c is None else f.target_c))

    def run(c):
        return lax.fori_loop(0, RESTITUTION_SWEEPS, lambda _, c: sweep(cs, w, c[0], obs, pairs, c[1]), c)

    return lax.cond(bounce, run, lambda c: c, (v, imp))


#: Passes that carry a time of impact across touching contacts (a ball hit in a rack passes the impulse on
#: through up to this many touching neighbours within the same step).
TOI_PASSES = 8


def impact_times(cs: ContactSystem, obs: Rows, pairs: Rows, imp: Impulses, shape):
    """Per-particle time [1, *view] at which its velocity changed within the step: the time of impact of the
    impacts it takes part in (with an impulse), carried on through contacts that touch at the start of the step
    and push (a rack hit by the cue ball: the whole cluster's velocities change at the cue ball's impact), 0 for
    particles no impact reaches."""
    tau = jnp.zeros(shape[1:], obs.toi.dtype if obs is not None else pairs.toi.dtype)
    if obs is not None:
        hit = (obs.toi > 0) & (imp.obs_n > 0)
        tau = jnp.max(jnp.where(hit, obs.toi, 0), axis=0)
    if pairs is None:
        return tau[None]
    ia, ja = pair_index(cs.ct, pairs)
    push = (imp.pair_n > 0).reshape(-1)
    toi = jnp.where(push, pairs.toi.reshape(-1), 0)
    flat = tau.reshape(-1)
    flat = flat.at[ia].max(toi).at[ja].max(toi)
    touching = push & ((pairs.toi == 0) | pairs.near).reshape(-1)       # not an impact of separated balls

    def carry(_, t):
        across = jnp.where(touching, jnp.maximum(t[ia], t[ja]), 0)
        return t.at[ia].max(across).at[ja].max(across)

    # Without an impact nothing is carried (the same values and derivatives): a pile at rest skips the passes.
    flat = lax.cond(jnp.any(flat > 0), lambda t: lax.fori_loop(0, TOI_PASSES, carry, t), lambda t: t, flat)
    return flat.reshape((1,) + shape[1:])


#: PGS's passes of the position safety pass when particles collide with each other (one pass leaves half of an
#: overlap between a ball and one it is pressed against on a cushion; 8 bring the worst off-axis billiards
#: break from 12% of a diameter to 0.14%). Obstacles alone need one. Jacobi keeps one: its under-converged
#: stacks leave overlap every step, and removing all of it at position level, with no velocity change, makes
#: a resting column jitter (0.05 m/s).
OVERLAP_PASSES = 8


def project_overlaps(cs: ContactSystem, w, x, passes: Optional[int] = None, pairs: Optional[Rows] = None, slop=0.0,
                     cap=None, partners=None, beyond=None):
    """Move overlapping contacts apart at position level (non-linear Gauss-Seidel, as Box2D v2's position
    solver), `passes` times (default: `OVERLAP_PASSES` with pairs, `GRID_OVERLAP_PASSES` with a grid, else 1):
    pair rounds, then obstacles (which cannot move, so they have the last word; a heavy ball on light ones
    is then pushed out of them without pushing the bottom one into the floor). Velocities
    are not touched, so no kinetic energy or momentum is added; it only acts where the velocity solve left an
    overlap (an under-converged cluster, or the time-of-impact correction of a particle whose velocity was
    also changed by a later contact). A grid model's pairs (the rows `pairs` of this step) are projected
    slot by slot instead (the overlaps of one slot together, each split between the overlaps at its particles).
    `slop`: the overlaps are projected onto `slop` times the contact distance, not onto 0 (`CONTACT_SLOP`).
    `cap` (m): a pass moves each contact out by at most this much (`push_out`). `partners` [n, K]: a grid
    model's pairs where there are no `pairs` rows (`push_out`). `beyond` (m): a pass moves only contacts that
    overlap by more than this (at least `CONTACT_SLOP` of the contact distance), the others not at all
    (`push_out`)."""
    ct = cs.ct
    dim, shape = x.shape[0], x.shape
    r = cs.radius[0]
    k = L.safe_reciprocal(w[0])

    def obstacles(x):
        def one(x, q, sphere, _):                # planes, then spheres
            n, C = obstacle_gap(cs, q, x, sphere=sphere)
            size = obstacle_reach(cs, q, sphere)                                 # the contact distance
            return x + n * (_capped(jnp.maximum(-C - slop * r, 0), cap, beyond, size) * (k > 0)), None
        return each_obstacle(ct, one, x)[0]

    def pairs_pass(x):           # round by round, or slot by slot (mass splitting over a slot's overlaps)
        wf, rf = w.reshape(-1), cs.radius_flat

        def colour(xf, c, rows):
            dist, n = direction(c.rel(xf))
            over = _capped(jnp.maximum((1 - slop) * c.both(rf) - dist, 0), cap, beyond, c.both(rf))
            if c.split:
                over = over * (rows[0] > 0)
                P = L.computed_once(lambda n, over, k: n * (over * k),
                                    (n, over, c.split_mass(wf, (over > 0).astype(xf.dtype))), c.partner)
            else:
                P = n * (over * L.safe_reciprocal(c.both(wf)) * c.valid)
            return c.apply(wf, xf, P), None

        return L.each_colour(block, colour, x.reshape(dim, -1), (kk, None))[0].reshape(shape)

    if pair_partners(pairs) is not None:          # a grid's slots, read by every pass: moved once
        block, kk = slot_rows(pairs.j, pairs.k, pairs.slots)
    elif partners is not None:
        block, kk = slot_rows(partners, (partners >= 0).astype(x.dtype))
    else:
        block, kk = pair_block(ct), None

    def one_pass(_, x):
        if ct.n_pairs or ct.has_grid:
            x = pairs_pass(x)
        return obstacles(x) if ct.n_obstacles else x

    if passes is None:
        passes = GRID_OVERLAP_PASSES if ct.has_grid else OVERLAP_PASSES if ct.n_pairs else 1
    if passes == 1:
        return one_pass(0, x)
    if not ct.has_grid:
        return lax.fori_loop(0, passes, one_pass, x)
    # A grid model's passes stop once one moves no particle by more than GRID_PASS_STOP of the slop (of the
    # smallest radius; with no slop, once one moves nothing): a pile at rest, whose velocity solve leaves no
    # overlap beyond the slop, takes one pass instead of GRID_OVERLAP_PASSES.
    limit = lax.stop_gradient(GRID_PASS_STOP * slop * jnp.min(cs.radius_flat))

    def gated(_, carry):
        def run(x):
            y = one_pass(0, x)
            return y, lax.stop_gradient(jnp.max(jnp.abs(y - x))) > limit
        return lax.cond(carry[1], run, lambda x: (x, carry[1]), carry[0])

    return lax.fori_loop(0, passes, gated, (x, jnp.ones((), bool)))[0]


def speculative_pass(topo, cs: ContactSystem, w, x, v, h, partners=None):
    """One Gauss-Seidel pass of `contact_rows.speculative_rows` on the velocities `v` at the end of a spring
    solver's (sub)step of length h from positions `x` (Penalty): no contact passes more than half its contact
    distance into a sphere or another particle, however fast (a particle that would otherwise move through a
    wall of discs or a sphere within one substep). Returns (v, the rows' normal `Impulses`)."""
    obs, pairs = contact_rows_speculative(cs, w, x, v, h, partners)
    zero = zero_impulses(topo, cs.ct, x.dtype)
    if obs is None and pairs is None:
        return v, zero
    return sweep(cs.replace(friction=jnp.zeros_like(cs.friction)), w, v, obs, pairs, zero)


def _capped(a, cap, beyond=None, size=None):
    """Overlaps `a` moved by at most `cap`, and only where deeper than `beyond`, at least CONTACT_SLOP `size`
    (`project_overlaps`)."""
    moved = a if cap is None else jnp.minimum(a, cap)
    return moved if beyond is None else jnp.where(a > jnp.maximum(beyond, CONTACT_SLOP * size), moved, 0)


def push_out(cs: ContactSystem, w, x, h, partners=None):
    """The start overlaps of a position-level (sub)step of length h (XPBD, RATTLE) that are deeper than
    PUSH_OUT_SPEED h (at least `CONTACT_SLOP` of the contact distance), pushed out at position level, each contact
    by at most `contact_rows.PUSH_OUT_SPEED` h in all, with no change of velocity (`project_overlaps`,
    OVERLAP_PASSES passes where particles collide with each other, as PGS's position pass; a grid model's
    `partners` [n, K]). These are the overlaps the position pass holds (`contact_rows.overlap_normal`'s floor:
    it keeps such a contact from getting deeper than it starts instead of pushing it out, which v = dp / h
    would make velocity); a shallower one is the position pass's, projected within the substep at no more than
    PUSH_OUT_SPEED. The two take disjoint sets: what a substep's sweeps leave (a resting pile's overlaps) is not
    moved here. Removed here as well, a resting column of discs sank and was lifted again every substep (|v|
    0.011 m/s instead of 0), and a 100 kg ball on two 1 kg balls pushed the upper one through the lower with
    XPBD."""
    passes = OVERLAP_PASSES if cs.ct.n_pairs or cs.ct.has_grid else 1
    hold = PUSH_OUT_SPEED * h
    return project_overlaps(cs, w, x, passes, None, 0.0, hold / passes, partners, hold)


# ---- contacts at position level (XPBD, Penalty) ------------------------------------------------------------
# Contacts at position level, for XPBD (Mueller et al. 2020, "Detailed rigid body simulation with extended
# position based dynamics"; Macklin et al. 2019, "Small steps in physics simulation").
#
# Per substep of length h, from positions x and predicted positions p = x + h (v + h g):
#
# * `position_pass` (once per solver iteration, after the rod and rope colours): every contact with gap C(p) is a
#   rigid (compliance 0) unilateral constraint. Its position multiplier lam_n (kg m, accumulated over the
#   iterations, clamped >= 0) changes by -C / (w_i + w_j): an overlap is pushed out, and a contact pushed out
#   too far by an earlier row gives some of it back. Then **static friction**: the relative tangential
#   displacement of the two bodies over the substep, dx_t, is cancelled (lam_t -= dx_t / (w_i + w_j)) when the
#   resulting |lam_t| <= mu lam_n; otherwise nothing is added (the kinetic part is the velocity pass's), and a
#   lam_t left above a cone that shrank is scaled back onto it. Obstacles are solved one after another, each
#   for all particles at once; pairs round by round (a loop over the rounds, as `sweep`), a grid
#   model's pairs slot by slot (mass splitting over a slot's rows that push or overlap).
# * `position_velocity_pass` (once, after v = (p - x) / h): each contact with lam_n > 0 gets one velocity row, solved by
#   `sweep` starting from the position impulses lam / h: the normal velocity is set to
#   max(-e vn_before, 0) (restitution; vn_before is the normal relative velocity at the start of the substep
#   after gravity, e = 0 when |vn_before| <= the restitution threshold), with the total normal impulse of the
#   substep kept >= 0, then **dynamic friction** removes the tangential relative velocity with a total friction
#   impulse clamped to the Coulomb disc mu * (total normal impulse). Where the velocity row adds no normal impulse
#   and static friction did not hold, that is Mueller et al.'s eq. 30, |dv_t| = min(mu lam_n / h (w_i + w_j),
#   |v_t|); the clamp on the total makes every reported impulse satisfy |lam_t| <= mu lam_n.
#
# The substep's reported impulses (N s) are the velocity pass's totals: lam / h plus the velocity rows.


def _position_row(disp, n, C, floor, k, mu, ln, lt):
    """One contact at position level: normal multiplier (accumulated, >= 0) projecting the gap C onto `floor`
    (0, or what is left of a start overlap after this substep's push-out, `contact_rows.overlap_normal`), then
    static friction. `disp` is the second body's displacement over the substep relative to the first,
    k = 1 / (w_i + w_j) (0: no row). Returns (position impulse change P [dim, ...] on the second body, new lam_n,
    new lam_t)."""
    new_n = R.accumulate(UNILATERAL, ln, (floor - C) * k)        # the row update of every kind, at position level
    disp_t = disp - n * _dot(disp, n)
    stick = lt - disp_t * k
    limit = mu * new_n
    length, _ = L.safe_length(stick)
    held, inv = L.safe_length(lt)
    kept = lt * jnp.where(held > limit, limit * inv, 1)
    new_t = jnp.where(length <= limit, stick, kept)
    return n * (new_n - ln) + (new_t - lt), new_n, new_t


def position_pass(cs: ContactSystem, w, x, dp, imp: Impulses, partners=None, ahead=None, h=None):
    """One position-level pass over every contact (the section's comment above): obstacles, then the pairs, each
    block colour by colour (`layout.each_colour`: round by round, or a grid model's `partners` [n, K] slot by
    slot, where the rows of one slot, whose particles may repeat, are relaxed by mass splitting over those that
    push or overlap). x: positions at the start of the substep, dp: the displacement since, so
    that the current positions are x + dp [dim, *view] (kept apart: every gap is computed as the start's plus
    the displacement's part, `contact_rows.overlap_normal`, which also gives the speculative normal of a contact
    whose path passes through the other body, and the floor: no contact gets deeper than it starts); imp: position
    multipliers (kg m) accumulated in this substep; `ahead`: the substep's predicted displacement, which decides
    the speculative normals (default dp); h: the substep's length, a start overlap deeper than PUSH_OUT_SPEED h
    is held, not projected (`push_out` moves it; shallower ones, what the last substep's sweeps left, are
    projected, so at most PUSH_OUT_SPEED per contact becomes velocity). Returns (dp, imp)."""
    ct, mu = cs.ct, cs.friction
    hold = 0.0 if h is None else PUSH_OUT_SPEED * h
    on, ot = imp.obs_n, imp.obs_t
    if ct.n_obstacles:
        k = L.safe_reciprocal(w[0])

        def obstacle(dp, c, lam):
            n, C, floor = obstacle_moved_gap(cs, c.q, x, dp, ahead, hold, sphere=c.sphere)
            P, ln, lt = _position_row(dp, n, C, floor, k, mu, *lam)
            return dp + w * P, (ln, lt)

        dp, (on, ot) = L.each_colour(ObstacleBlock(ct), obstacle, dp, (on, ot))
    pn, pt = imp.pair_n, imp.pair_t
    if ct.n_pairs or ct.has_grid:
        dim, shape = dp.shape[0], dp.shape
        wf, xf, r = w.reshape(-1), x.reshape(dim, -1), cs.radius_flat
        af = None if ahead is None else ahead.reshape(dim, -1)

        def pair(df, c, rows):
            _, (ln, lt) = rows
            disp = c.rel(df)
            n, C, floor = overlap_normal(c.rel(xf), disp, c.both(r), None if af is None else c.rel(af), hold)
            if c.split:
                act = ((c.partner >= 0) & ((C < floor) | (ln > 0))).astype(df.dtype)
                k = c.split_mass(wf, act) * act
            else:
                k = L.safe_reciprocal(c.both(wf)) * c.valid
            P, ln, lt = L.computed_once(_position_row, (disp, n, C, floor, k, mu, ln, lt),
                                        getattr(c, "partner", None))
            return c.apply(wf, df, P), (ln, lt)

        df, (pn, pt) = L.each_colour(pair_block(ct, partners), pair, dp.reshape(dim, -1), (None, (pn, pt)))
        dp = df.reshape(shape)
    return dp, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


#: Gauss-Seidel sweeps of the position solvers' velocity pass (`position_velocity_pass`). Measured on the 55-disc
#: pyramid (friction 0.6, dt 1/60, 5 s, XPBD at its defaults): its base spread by 1.8% of R with 4 sweeps and
#: 0.75% with 8 (docs/contacts.md).
VELOCITY_PASS_SWEEPS = 8


def position_velocity_pass(cs: ContactSystem, w, p, v_before, v, imp: Impulses, h, partners=None, follow=False,
                           moved=None):
    """Restitution and dynamic friction (the section's comment above) on v = (p - x) / h, `VELOCITY_PASS_SWEEPS`
    sweeps, then the restitution stage (`restitution_stage`). `imp` holds the substep's position multipliers
    (kg m). Returns (v, the substep's contact impulses in N s), and with `follow` the positions' change as well.
    `moved` = (x, dp, ahead), the position pass's start, displacement and prediction (p = x + dp): the rows
    take the position pass's normals (`contact_rows.velocity_rows`).

    `follow` (XPBD): the positions follow the friction of the velocity pass, p += h w (change of the friction
    impulses); that change is returned on its own, for the caller to add to its displacement (XPBD's
    displacement form: dp += h dv keeps it in full precision however large p is). The
    position pass's static friction cancels a contact's tangential displacement only within its substep, and
    one cold Gauss-Seidel iteration leaves some of it at every substep (a later row moves a particle that an
    earlier row held); the velocity pass removed that velocity but the displacement stayed, so a pyramid of
    discs crept apart by a constant step every substep (XPBD: 31% of R in 5 s). With the displacement taken
    back as the velocity is, what the friction holds at velocity level stays put."""
    obs, pairs = velocity_rows(cs, w, p, v_before, imp, partners, moved)
    start = imp._replace(**{f: getattr(imp, f) / h for f in ("obs_n", "obs_t", "pair_n", "pair_t")})
    v, imp = lax.fori_loop(0, VELOCITY_PASS_SWEEPS, lambda _, c: sweep(cs, w, c[0], obs, pairs, c[1]), (v, start))
    v, imp = restitution_stage(cs, w, v, obs, pairs, imp)
    if not follow:
        return v, imp
    dv = jnp.zeros_like(v)
    if obs is not None:
        dv = dv + w * jnp.sum(imp.obs_t - start.obs_t, 0)
    if pairs is not None:
        dv = dv + pair_total(cs.ct, w, imp.pair_t - start.pair_t, -1.0, pair_index(cs.ct, pairs),
                             pair_partners(pairs)).reshape(v.shape)
    return v, imp, h * dv
