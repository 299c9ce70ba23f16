"""Solver interface, the shared per-constraint geometry, and the PGS / sequential-impulse solver."""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.system import System
from jaxcon.core.topology import Topology
from jaxcon.solvers import contact

Array = Any


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
        v = L.add_pair(sys.topology, blk, v, f.wi * p, -f.wj * p)
    return v


def curvature_rate(n, dist, u, h, axis=0):
    """The rate at which moving along the constraint's tangent for h opens a distance constraint: for relative
    velocity u whose part across the unit normal n is u_t, |d + h u_t| = sqrt(d^2 + h^2 |u_t|^2), so the
    distance grows by (sqrt(d^2 + h^2 |u_t|^2) - d) / h = h |u_t|^2 / (sqrt(d^2 + h^2 |u_t|^2) + d) per unit
    time (written without cancellation; 0 where d and u_t are both 0). `axis`: the vector axis of n and u.

    This is the discrete form of the velocity constraint's curvature term (J-dot v = |u_t|^2 / d). A velocity
    solve that asks J v = 0 moves the particles along the tangent, so every step lengthens a rotating rod by
    about h^2 |u_t|^2 / (2 d) and the next step's solve removes the outward velocity that this rotation leaves,
    losing (h |u_t|^2 / d)^2 / 2 of kinetic energy per unit mass and step. Asking J v = -curvature_rate moves
    them along the chord instead. Baumgarte stabilisation gets there indirectly (its steady position error
    h^2 |u_t|^2 / (2 d beta) supplies that inward velocity); split impulses, whose velocity solve sees no
    position error, need it explicitly."""
    ut = u - n * jnp.sum(u * n, axis=axis, keepdims=True)
    ut2 = jnp.sum(ut * ut, axis=axis)
    return h * ut2 * L.safe_reciprocal(jnp.sqrt(dist * dist + h * h * ut2) + dist)


def velocity_bias(topo: Topology, fr: tuple, beta, h, v=None) -> tuple:
    """Per-block velocity bias: (beta / h) C for rods and taut ropes, the speculative C / h for slack ropes (the
    rope may close the gap within this (sub)step but no further). Split impulses pass the velocities `v`
    [dim, *view] and beta = 0: rods and taut ropes then get the `curvature_rate` of their motion instead of a
    position correction, so the velocity solve keeps C(x + h v) = C(x) to second order."""
    out = []
    for blk, f in zip(topo.blocks, fr):
        b = beta / h * f.C
        if blk.has_rope:
            slack = jnp.where(f.C > 0, b, f.C / h)
            b = slack if blk.all_rope else jnp.where(blk.rope.array, slack, b)
        if v is not None:       # every row, a slack rope's too: its speculative C(x + h v) <= 0 includes it, and
            vi, vj = L.gather_pair(topo, blk, v)      # a rope just at its length gets the same target either way
            b = b + curvature_rate(f.n, f.dist, vj - vi, h)
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


class _Rows(NamedTuple):
    """What `layout.block_solve` reads of a colour's rows."""

    n: Any
    wi: Any
    wj: Any
    k: Any


def position_sweep(sys: System, rest: tuple, alpha, jacobi_relaxation=None):
    """One pass of position-level projection over the rod and rope colours, (_, (p, mu)) -> (p, mu): each
    constraint, with d = p_j - p_i, moves its particles along d by dmu = (|d| - rest - alpha mu) / (w_i + w_j +
    alpha) (p_i += w_i n dmu, p_j -= w_j n dmu; mu > 0 pulls), its accumulated mu clamped >= 0 for ropes (a rope
    never pushes). Gauss-Seidel colour by colour (XPBD, split impulses' position pass), or, with
    `jacobi_relaxation`, every constraint from the same p, the changes scaled by it and summed (Jacobi). `rest`:
    per-block target lengths; `alpha`: compliance / h^2 (0: a rigid projection)."""
    topo = sys.topology
    w_pairs = []
    for blk in topo.blocks:
        wi, wj = L.gather_pair(topo, blk, sys.w)
        wi, wj = wi[0], wj[0]
        w_pairs.append((wi, wj, L.safe_reciprocal(wi + wj + alpha)))

    def update(p, blk, rows):
        rest, wi, wj, k, mu = rows
        pi, pj = L.gather_pair(topo, blk, p)
        d = pj - pi
        # n (new - mu) with n = d / |d| is written as d times one scalar per constraint, built from
        # |d|^2 and 1/|d| (rods need no clamp: 1/|d| is 0 at zero length). `safe_length` keeps |d|^2
        # a reduction: on CPU, XLA stores d and |d|^2 as arrays before it, so the update below reads
        # them instead of recomputing the projection per particle. Written as an elementwise dot
        # (L.dot0), the update kernels were split and re-summed every colour: 8 to 16x slower
        # on the 64x64 cloth.
        dist, inv = L.safe_length(d)
        if jacobi_relaxation is None:
            dmu = L.block_solve(topo, blk, _Rows(d * inv, wi, wj, k), dist - rest - alpha * mu, alpha)
        else:
            dmu = jacobi_relaxation * (dist - rest - alpha * mu) * k
        new = clamp_ropes(blk, mu + dmu * (inv > 0).astype(inv.dtype))
        q = d * (((new - mu) if blk.has_rope else dmu) * inv)
        return wi * q, -wj * q, new

    def colour(p, blk, rows):
        qi, qj, new = update(p, blk, rows)
        return L.add_pair(topo, blk, p, qi, qj), new

    def sweep(_, carry):
        p, mu = carry
        mu = list(mu)
        dp = jnp.zeros_like(p)
        for c, (blk, r, (wi, wj, k)) in enumerate(zip(topo.blocks, rest, w_pairs)):
            if jacobi_relaxation is None:
                p, mu[c] = L.each_colour(blk, colour, p, (r, wi, wj, k, mu[c]))
            else:
                qi, qj, mu[c] = update(p, blk, (r, wi, wj, k, mu[c]))
                dp = L.add_pair(topo, blk, dp, qi, qj)
        return (p if jacobi_relaxation is None else p + dp), tuple(mu)
    return sweep


def split_position_pass(sys: System, x, iterations: int, jacobi_relaxation=None):
    """Split impulses' position pass: positions `x`, after the velocity step, are projected onto the rest lengths
    by `iterations` rigid `position_sweep`s from mu = 0 (a rope only while stretched). Velocities are not
    touched, so the correction adds no kinetic energy, and the whole error can go in one step: this is Box2D
    v2's position solver (nonlinear Gauss-Seidel) and Cline and Pai's post-stabilisation.

    Measured (tests/test_split_impulses.py; float64, dt 1/240): a 20-link chain with a 20:1 end mass whose links
    start 25% too long is 0.02% stretched after 1 s with PGS(20). The linear pseudo-velocity solve it replaces
    (J v_p = -(beta / h) C at the start of the step, from v_p = 0, and x += h (v + v_p)) left it 82% stretched,
    and 66 to 92% when warm started or taking the step's own drift into account: it corrects the error the step
    started with, not the one the unconverged velocity sweeps make, and a warm-started correction overshoots once
    it has worked."""
    mu0 = tuple(jnp.zeros(b.shape, x.dtype) for b in sys.topology.blocks)
    sweep = position_sweep(sys, sys.rest, jnp.zeros((), x.dtype), jacobi_relaxation)
    return lax.fori_loop(0, iterations, sweep, (x, mu0))[0]


# ---- the start and end of a velocity-level (sub)step with contacts (PGS, Jacobi) ------------------------------
#: Solves a grid model's step may take (`grid_step`): the first, and one again with the pairs it missed.
GRID_ATTEMPTS = 2


def grid_step(sys, x, v, h, solve):
    """A (sub)step of a model with a neighbour grid, `solve(found) -> (x, v, (lam, imp))` being the solver's
    step with the candidate pairs `found` = (partners, overflow) (`contact.neighbours`).

    The search takes the velocities after gravity, but an impact within the step can send a particle into one
    that was no candidate: three discs in a row, B hitting A at 30 m/s with A 5 cm from C, moved A through C
    in one step. The candidates cover every pair that can touch on straight paths at those velocities, with
    a skin of GRID_SKIN (r_i + r_j); so if no particle's displacement in the step differs from its free one,
    h v_free, by more than GRID_SKIN min(r) from a common offset (the middle of their range: a pile that
    stops as one keeps it), no other pair can have touched, and the step stands. Otherwise a second search
    lists the pairs that touch on the straight lines from the start to the end positions
    (`contact.path_search`); if one was not solved (`contact.unsolved`), the step is solved again from its
    start with both lists' pairs (`contact.merge_partners`), up to GRID_ATTEMPTS solves, and what the last
    check still finds is counted in the overflow, with the touching pairs the second search had no slot for.
    One traced copy of the solve, in a loop of `lax.cond`s (under `vmap` every branch runs: GRID_ATTEMPTS
    solves per step)."""
    cs = sys.contact
    v_free = sys.apply_gravity(v, h)
    r_min = lax.stop_gradient(jnp.min(cs.radius_flat))
    found, scan = contact.grid_search(cs, x, v_free, h)

    def run(i, carry):
        partners, over, _, _ = carry
        out = solve((partners, over))
        dev = lax.stop_gradient(out[0] - x - h * v_free).reshape(x.shape[0], -1)
        dev = dev - (jnp.max(dev, 1, keepdims=True) + jnp.min(dev, 1, keepdims=True)) / 2
        stays = jnp.max(jnp.sum(dev * dev, 0)) <= (contact.GRID_SKIN * r_min) ** 2

        def verify(_):
            wide = contact.path_search(cs, x, out[0], h, scan)
            missed = contact.unsolved(wide[0], partners)
            last = i == GRID_ATTEMPTS - 1
            both, dropped = contact.merge_partners(partners, wide[0])
            return both, over + dropped, wide[1] + jnp.where(last, missed, 0), (missed > 0) & ~last

        partners, over, count, again = lax.cond(stays, lambda _: (partners, over, over, jnp.zeros((), bool)),
                                                verify, None)
        lam, imp = out[2]
        return partners, over, out[:2] + ((lam, imp._replace(overflow=count)),), again

    def attempt(i, carry):
        return lax.cond(carry[3], lambda c: run(i, c), lambda c: c, carry)

    out = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(solve, found))
    return lax.fori_loop(0, GRID_ATTEMPTS, attempt, found + (out, jnp.ones((), bool)))[2]


def contact_begin(sys, x, v, lam_ws, beta, h, split: bool, warm: bool, factor=1.0, gradient: bool = True,
                  found=None, slop=0.0):
    """Gravity, the rods' frames and biases (no Baumgarte bias when `split`), the contact rows, and the warm
    start of rods and contacts (scaled by `factor`; no gradient through it unless `gradient`). A grid model
    passes its candidate pairs `found` = (partners, overflow) (`grid_step`).
    Returns (v_free, v, fr, bias, obs, pairs, lam, imp): v_free is the velocity after gravity, before any
    impulse (what the time-of-impact correction compares with)."""
    topo, cs = sys.topology, sys.contact
    lam_ws, imp_ws = lam_ws
    v0, v = v, sys.apply_gravity(v, h)
    v_free = v
    fr = frames(sys, x)
    bias = velocity_bias(topo, fr, jnp.zeros((), x.dtype), h, v) if split else velocity_bias(topo, fr, beta, h)
    partners, overflow = (None, None) if found is None else found
    obs, pairs = contact.rows(cs, sys.w, x, v0, v, beta, h, partners, slop)
    if not warm:
        lam, imp = tuple(jnp.zeros_like(f.C) for f in fr), contact.zero_impulses(topo, cs.ct, x.dtype)
    else:
        if not gradient:
            imp_ws = lax.stop_gradient(imp_ws)
        v, lam = warm_start(sys, v, fr, lam_ws, factor, gradient)
        v, imp = contact.warm_start(cs, sys.w, v, obs, pairs, imp_ws, factor)
    if partners is not None:
        imp = imp._replace(partners=partners, overflow=overflow)
    return v_free, v, fr, bias, obs, pairs, lam, imp


def restitution_phases(sys, v_free, obs, pairs, iterations: int, carry, body):
    """The contact solve in two phases sharing `iterations` (at least one each): compression (every target
    without restitution), then restitution, continued from it; the restitution phase's change is scaled back
    where it would raise the kinetic energy (contact.restitution_scale). `body(obs, pairs)` returns one
    iteration, carry = (v, ...) -> carry. One loop, whose rows switch targets between the phases, so the
    iteration is traced and compiled once. Returns the carry mixed leaf by leaf."""
    first = max(iterations // 2, 1)
    total = first + max(iterations - first, 1)

    def phase_rows(f, late):
        return None if f is None else f._replace(target=jnp.where(late, f.target, f.target_c))

    def one(i, state):
        carry, saved = state
        late = i >= first
        carry = body(phase_rows(obs, late), phase_rows(pairs, late))(carry)
        saved = jax.tree.map(lambda new, old: jnp.where(i == first - 1, new, old), carry, saved)
        return carry, saved

    bounced, compressed = lax.fori_loop(0, total, one, (carry, carry))
    s = contact.restitution_scale(sys.w, v_free, compressed[0], bounced[0], contact.bouncing(obs, pairs))

    def mix(a, b):       # integer leaves (a neighbour grid's partners and overflow) are the same in both phases
        return a + s * (b - a) if jnp.issubdtype(a.dtype, jnp.floating) else b

    return jax.tree.map(mix, compressed, bounced)


def contact_end(sys, x, v, v_free, obs, pairs, imp, h, passes=1, rods_pass=None, slop=0.0):
    """New positions: x + h v with the time-of-impact correction (a particle whose velocity changed at tau within
    the step moved at its old velocity until then: x' = x + tau v_free + (h - tau) v'), then `rods_pass` (split
    impulses' position pass of the rods, x -> x, or None), then the position safety pass of the contacts
    (`passes`, `slop`: see contact.project_overlaps)."""
    cs = sys.contact
    dx = -contact.impact_times(cs, obs, pairs, imp, x.shape) * (v - v_free)
    x = x + h * v + dx
    if rods_pass is not None:
        x = rods_pass(x)
    return contact.project_overlaps(cs, sys.w, x, passes, pairs, slop)
