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

    def update(vp, blk, f, b, k, lam):
        ui, uj = L.gather_pair(topo, blk, vp)
        step = (jnp.sum((uj - ui) * f.n, axis=0) + b) * k
        new = clamp_ropes(blk, lam + (step if jacobi_relaxation is None else jacobi_relaxation * step))
        p = f.n * (new - lam)
        return f.wi * p, -f.wj * p, new

    def colour(vp, blk, rows):              # Gauss-Seidel: each colour reads the previous colours' changes
        pi, pj, new = update(vp, blk, *rows)
        return L.add_pair(topo, blk, vp, pi, pj), new

    def sweep(_, carry):
        vp, lam = carry
        lam = list(lam)
        dv = jnp.zeros_like(vp)          # Jacobi: every block reads the same vp, the changes are summed
        for c, (blk, f, (b, k)) in enumerate(zip(topo.blocks, fr, correction)):
            if jacobi_relaxation is None:
                vp, lam[c] = L.each_colour(blk, colour, vp, (f, b, k, lam[c]))
            else:
                pi, pj, lam[c] = update(vp, blk, f, b, k, lam[c])
                dv = L.add_pair(topo, blk, dv, pi, pj)
        return vp + dv, tuple(lam)

    return lax.fori_loop(0, iterations, sweep, (vp0, lam0))[0]


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
                  found=None):
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
    bias = velocity_bias(topo, fr, jnp.zeros((), x.dtype) if split else beta, h)
    partners, overflow = (None, None) if found is None else found
    obs, pairs = contact.rows(cs, sys.w, x, v0, v, beta, h, partners)
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


def contact_end(sys, x, v, v_free, obs, pairs, imp, h, v_pseudo=None, passes=1):
    """New positions: x + h (v + v_pseudo) with the time-of-impact correction (a particle whose velocity
    changed at tau within the step moved at its old velocity until then: x' = x + tau v_free + (h - tau) v'),
    then the position safety pass (`passes`: see contact.project_overlaps). `v_pseudo`: split impulses'
    pseudo-velocity (moves, then is discarded)."""
    cs = sys.contact
    dx = -contact.impact_times(cs, obs, pairs, imp, x.shape) * (v - v_free)
    move = v if v_pseudo is None else v + v_pseudo
    return contact.project_overlaps(cs, sys.w, x + h * move + dx, passes, pairs)
