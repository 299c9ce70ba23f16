"""What the solvers share: the constraints' frames, the row update, biases, warm start, split impulses, the position and
SHAKE sweeps, and the frame of a (sub)step for every kind (contacts included) with the neighbour grid's step."""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import contact_rows
from jaxcon.core.contact import Impulses, zero_impulses
from jaxcon.core import grid
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.pytree import concrete
from jaxcon.core.substeps import substepped
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
    """Per-block constraint geometry of positions `x` ([dim, *view]): a `Frame` per rod and rope block, a
    `rows.SetFrame` per constraint set's block."""
    out = []
    for blk, rest in zip(sys.topology.blocks, sys.rest):
        if blk.generic is not None:
            out.append(R.set_frame(sys.topology, blk, *sys.set_of(blk), x, sys.w))
            continue
        xi, xj = L.gather_pair(sys.topology, blk, x)
        wi, wj = L.gather_pair(sys.topology, blk, sys.w)
        wi, wj = wi[0], wj[0]
        dist, n = L.safe_norm(xj - xi, axis=0, elementwise=sys.topology.batch is not None)
        k = L.safe_reciprocal(wi + wj) * (dist > 0).astype(dist.dtype)
        out.append(Frame(n, dist, dist - rest, wi, wj, k))
    return tuple(out)


def apply_impulses(sys: System, v, fr: tuple, lam: tuple):
    """v + M^-1 J^T lam for every block (tension convention: lam > 0 pulls the endpoints together)."""
    for blk, f, l in zip(sys.topology.blocks, fr, lam):
        v = R.apply(sys.topology, blk, f, v, l)
    return v


def velocity_bias(topo: Topology, fr: tuple, beta, h, slop=None) -> tuple:
    """Per-block velocity bias: (beta / h) C for rods and taut ropes, the speculative C / h for slack ropes (the
    rope may close the gap within this (sub)step but no further); a constraint set's unilateral rows as ropes, its
    compliant rows C / h (`rows.solve` softens them). Split impulses pass `slop` (`split_slop`), per block the
    error up to which Baumgarte corrects it; a larger C gets no bias (`split_position_pass` removes it without
    touching the velocities)."""
    out = []
    for k, (blk, f) in enumerate(zip(topo.blocks, fr)):
        C = f.C if slop is None else jnp.where(jnp.abs(f.C) <= slop[k], f.C, 0)
        b = beta / h * C
        if R.compliant(f) is not None:          # a compliant row is a spring: the whole C, softened by gamma
            b = jnp.where(f.alpha > 0, f.C / h, b)
        if blk.has_rope:
            slack = jnp.where(f.C > 0, b, f.C / h)
            b = slack if blk.all_rope else jnp.where(blk.rope.array, slack, b)
        out.append(b)
    return tuple(out)


def spring_rows(fr: tuple) -> tuple:
    """Per block, where its rows are compliant springs (a constraint set's rows of compliance > 0), or None for
    a block without compliance (rods, ropes)."""
    return tuple(None if R.compliant(f) is None else f.alpha > 0 for f in fr)


def spring_share(sys: System, v, dv):
    """The share t in [0, 1] of the compliant rows' warm-start velocity change `dv` to apply to `v`: the one that
    leaves the least kinetic energy, t = -v.M dv / dv.M dv (a line search along the warm start), capped at the
    whole. One share per model (per copy of a batch-minor model). At rest under a load the warm start removes the
    load's velocity exactly, so t = 1 there: the last impulses are kept in full and the static stretch is alpha
    times the force for any number of sweeps. A share that would raise the kinetic energy is never taken, so the
    last step's impulses, which sweeps that do not converge leave lagging behind a stiff spring's motion, are not
    fed back into it (docs/constraints.md, compliant rows and the warm start)."""
    m = L.safe_reciprocal(sys.w)
    axes = tuple(range(v.ndim - 1)) if sys.topology.batch is not None else None
    a = jnp.sum(m * v * dv, axis=axes)
    b = jnp.sum(m * dv * dv, axis=axes)
    return jnp.where(b > 0, jnp.clip(-a * L.safe_reciprocal(b), 0, 1), 1)


def warm_start(sys: System, v, fr: tuple, lam_ws: tuple, h, factor=1.0, gradient: bool = True, others=None):
    """Apply `factor` times the previous impulses (ropes clamped, undefined constraints dropped) to `v`; then
    `others(v) -> (v, extra)` (the contacts' warm start, or None); last a constraint set's compliant rows
    together, by the share of theirs that leaves the least kinetic energy after everything else's warm start
    (`spring_share`). Returns (v, lam, extra): the velocities after the warm start, the accumulated impulses to
    iterate from and what `others` returned (None without it). (`h` is the (sub)step, unused.)"""
    del h
    if not gradient:
        lam_ws = lax.stop_gradient(lam_ws)
    if not (isinstance(factor, (int, float)) and factor == 1):     # a plain 1 costs nothing
        lam_ws = tuple(l * factor for l in lam_ws)
    lam = tuple(R.clamp(blk, l) * (f.k > 0).astype(f.k.dtype)
                for blk, f, l in zip(sys.topology.blocks, fr, lam_ws))
    springs = spring_rows(fr)
    held = tuple(l if sp is None else jnp.where(sp, 0, l) for l, sp in zip(lam, springs))
    v = apply_impulses(sys, v, fr, held)
    v, extra = (v, None) if others is None else others(v)
    if all(sp is None for sp in springs):
        return v, lam, extra
    soft = tuple(jnp.zeros_like(l) if sp is None else jnp.where(sp, l, 0) for l, sp in zip(lam, springs))
    dv = apply_impulses(sys, jnp.zeros_like(v), fr, soft)
    t = spring_share(sys, v, dv)
    return v + t * dv, tuple(hl + t * sl for hl, sl in zip(held, soft)), extra


def refuse_hard_sets(owner, solver: str, model, why: str) -> None:
    """Refuse, before tracing, a model with contacts and a constraint set of compliance 0 (where the compliance is
    known) for a solver whose hard rows give way under load (`why`): a ValueError naming the solvers that hold a
    hard set against contacts (PGS, Direct and XPBD: docs/constraints.md, hard sets under contacts)."""
    if model.contact is None:
        return
    for con in model.constraints:
        a = concrete(con.compliance)
        if a is not None and np.any(np.asarray(a) == 0):
            raise ValueError(
                f"{owner}: {solver} does not hold the hard constraint set {con.name!r} (compliance 0) against "
                f"contacts: {why}. Use jc.PGS, jc.Direct or jc.XPBD, which hold it within 1%, or give the set a "
                "compliance > 0")


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


def position_sweep(sys: System, rest: tuple, alpha, jacobi_relaxation=None, set_alpha=None, sets: bool = True,
                   base=None):
    """One pass of position-level projection over the rod and rope colours, (_, (p, mu)) -> (p, mu): each
    constraint, with d = p_j - p_i, moves its particles along d by dmu = (|d| - rest - alpha mu) / (w_i + w_j +
    alpha) (p_i += w_i n dmu, p_j -= w_j n dmu; mu > 0 pulls), its accumulated mu clamped >= 0 for ropes (a rope
    never pushes). Gauss-Seidel colour by colour (XPBD, split impulses' position pass), or, with
    `jacobi_relaxation`, every constraint from the same p, the changes scaled by it and summed (Jacobi). `rest`:
    per-block target lengths; `alpha`: compliance / h^2 (0: a rigid projection).

    A constraint set's rows are evaluated at the current positions (nonlinear Gauss-Seidel) and move by
    dmu = (C_lib - a mu) / (J M^-1 J^T + a), p += M^-1 J^T dmu, with a = `set_alpha(compliance)` (XPBD: the
    set's compliance / h^2); `set_alpha` None keeps a set's compliant rows out of the pass (split impulses: a
    compliant row's stretch is its spring's, not an error to correct). `sets=False` leaves the sets' rows out
    (split impulses: Baumgarte corrects them through the velocities).

    `base`: displacement form (XPBD). The carry's p is then the displacement from the positions `base` (the
    substep's start), and a rod's d is (base_j - base_i) + (p_j - p_i): the displacement h v + h^2 g stays in
    full precision however far from the origin the particles are (in float32, base + h^2 g rounds h^2 g away
    once it is below half an ulp of the position). A constraint set's fn is evaluated at base + p."""
    topo = sys.topology
    w_pairs = []
    for blk in topo.blocks:
        if blk.generic is not None:
            w_pairs.append(None)
            continue
        wi, wj = L.gather_pair(topo, blk, sys.w)
        wi, wj = wi[0], wj[0]
        d0 = None
        if base is not None:
            bi, bj = L.gather_pair(topo, blk, base)
            d0 = bj - bi
        w_pairs.append((wi, wj, L.safe_reciprocal(wi + wj + alpha), d0))

    def update(p, blk, rows):
        rest, wi, wj, k, d0, mu = rows
        pi, pj = L.gather_pair(topo, blk, p)
        d = pj - pi if d0 is None else d0 + (pj - pi)
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
        new = R.accumulate(blk, mu, dmu * (inv > 0).astype(inv.dtype))
        q = d * (((new - mu) if blk.has_rope else dmu) * inv)
        return wi * q, -wj * q, new

    def update_set(p, blk, rows):
        ssys, mu = rows
        f = R.set_frame(topo, blk, sys.cons[blk.generic], ssys, p if base is None else base + p, sys.w)
        a = jnp.zeros_like(f.C) if set_alpha is None else set_alpha(f.alpha)
        if getattr(blk, "hub_slot", None) is not None:      # a set's stars: their rows solved together
            dmu = L.block_solve(topo, blk, f, f.C - a * mu, a)
        else:
            dmu = (f.C - a * mu) * L.safe_reciprocal(f.s + a) * (f.k > 0).astype(f.C.dtype)
        if set_alpha is None:
            dmu = dmu * (f.alpha == 0).astype(dmu.dtype)
        if jacobi_relaxation is not None:
            dmu = jacobi_relaxation * dmu
        new = R.accumulate(blk, mu, dmu)
        return f.Jw * (new - mu), new

    def colour(p, blk, rows):
        qi, qj, new = update(p, blk, rows)
        return L.add_pair(topo, blk, p, qi, qj), new

    def colour_set(p, blk, rows):
        q, new = update_set(p, blk, rows)
        return L.add_rows(topo, blk, p, q), new

    def sweep(_, carry):
        p, mu = carry
        mu = list(mu)
        dp = jnp.zeros_like(p)
        for c, (blk, r, wk) in enumerate(zip(topo.blocks, rest, w_pairs)):
            if blk.generic is not None:
                if not sets:
                    continue
                rows = (sys.set_of(blk)[1], mu[c])
                if jacobi_relaxation is None:
                    p, mu[c] = L.each_colour(blk, colour_set, p, rows)
                else:
                    q, mu[c] = update_set(p, blk, rows)
                    dp = L.add_rows(topo, blk, dp, q)
            elif jacobi_relaxation is None:
                p, mu[c] = L.each_colour(blk, colour, p, (r, *wk, mu[c]))
            else:
                qi, qj, mu[c] = update(p, blk, (r, *wk, mu[c]))
                dp = L.add_pair(topo, blk, dp, qi, qj)
        return (p if jacobi_relaxation is None else p + dp), tuple(mu)
    return sweep


def split_slop(sys: System, fr: tuple, v, h, beta, share) -> tuple:
    """Per block, split impulses' slop (m): the position error each constraint may keep and have Baumgarte
    correct through the velocities. Twice the steady error that its rotation leaves with Baumgarte,
    h^2 |u_t|^2 / (2 d beta) (u_t the relative velocity across it): that error is the rotation's
    centripetal correction, not an error to remove; and at least `share` times the rest length, at most a tenth
    of it. Whatever is beyond it is not rotation (a stretched start, sweeps that cannot hold a chain) and is
    projected away without touching the velocities (`split_position_pass`)."""
    topo = sys.topology
    out = []
    for blk, f, r in zip(topo.blocks, fr, sys.rest):
        if blk.generic is not None:     # a constraint set has no length scale: Baumgarte corrects all of it
            out.append(jnp.full_like(f.C, jnp.inf))
            continue
        vi, vj = L.gather_pair(topo, blk, v)
        u = vj - vi
        ut = u - f.n * jnp.sum(u * f.n, axis=0)
        steady = h * h * jnp.sum(ut * ut, axis=0) * L.safe_reciprocal(f.dist * jnp.maximum(beta, 1e-3))
        out.append(jnp.clip(steady, share * r, 0.1 * r))
    return tuple(out)


def split_position_pass(sys: System, x, iterations: int, slop: tuple, jacobi_relaxation=None):
    """Split impulses' position pass: positions `x` (after the velocity step) projected by `iterations` rigid
    `position_sweep`s from mu = 0 onto lengths within `slop` (a share of each rest length) of the rest lengths
    (a rope only while stretched beyond it); velocities untouched, so the correction adds no kinetic energy.
    Box2D v2's position solver (nonlinear Gauss-Seidel), or Jacobi sweeps with the given relaxation.

    Split impulses are Baumgarte stabilisation within the slop (`velocity_bias` clips C to it) and this
    projection beyond it (docs/solvers.md, "Split impulses"). Inside the slop the step is exactly Baumgarte's, so
    a system without position error moves as with Baumgarte: a rotating rod's centripetal correction comes from
    its steady error h^2 |u_t|^2 / (2 d beta), which the slop must hold (0.5% holds a double pendulum at 240 Hz;
    0.25% left it 3.8x less accurate). A larger error (a stretched start, a chain the sweeps cannot hold) is
    removed here without becoming kinetic energy."""
    topo = sys.topology
    rest = []
    for blk, r, s in zip(topo.blocks, sys.rest, slop):
        if blk.generic is not None:     # not projected (its slop is unbounded): `position_sweep(sets=False)`
            rest.append(r)
            continue
        xi, xj = L.gather_pair(topo, blk, x)
        dist = L.safe_length(xj - xi)[0]
        rest.append(jnp.where(jnp.abs(dist - r) > s, r, dist))
    mu0 = tuple(jnp.zeros(b.shape, x.dtype) for b in topo.blocks)
    sweep = position_sweep(sys, tuple(rest), jnp.zeros((), x.dtype), jacobi_relaxation, sets=False)
    return lax.fori_loop(0, iterations, sweep, (x, mu0))[0]


def shake_sweep(sys: System, fr0: tuple, h, tol=0.0, set_alpha=None):
    """One SHAKE pass over the constraint colours, (_, (x, v, mu)) -> (x, v, mu) (RATTLE's position stage):
    each constraint moves along its start-of-step direction n0 (`fr0`) by dmu = (|d|^2 - L^2) / (2 (w_i + w_j)
    d . n0), x_i += w_i n0 dmu, x_j -= w_j n0 dmu, and the velocities by the same divided by h; a rope's
    accumulated mu clamped >= 0; Gauss-Seidel colour by colour. A constraint whose residual is at or below `tol`
    (|d^2 - L^2| / (2 L^2)) is not updated. Moving along n0 rather than the current direction is what keeps a
    rotating rod's kinetic energy: the kick is then orthogonal to its velocity. A constraint set's rows move
    C_lib(x) to a mu along their start-of-step gradient J0 (`shake_set`), a = `set_alpha(compliance)` (None: 0,
    every row hard)."""
    topo = sys.topology
    rest2 = tuple(r * r for r in sys.rest)

    def update(x, blk, f, r2, mu):
        xi, xj = L.gather_pair(topo, blk, x)
        d = xj - xi
        dist, inv = L.safe_length(d)
        res = jnp.sum(d * d, axis=0) - r2
        # a rod of rest length 0 holds its particles together and has no direction at its solution: it moves along
        # the current d, by all of it (the exact projection onto x_j = x_i; along n0 it crept, 0.26 m in 1 s)
        zero = r2 == 0
        f = f._replace(n=jnp.where(zero, d * inv, f.n),
                       k=jnp.where(zero, L.safe_reciprocal(f.wi + f.wj) * (dist > 0).astype(dist.dtype), f.k))
        # a rod that turned far within the step has d . n0 near 0 and would be flung (1e44 m): d . n0 is taken as
        # at least |d| / 2, which bounds the move by |d| and leaves others unchanged
        along = jnp.sum(d * f.n, axis=0)
        live = (f.k > 0) & (along > 0)
        rhs = jnp.where(live, res / (2 * jnp.where(live, jnp.maximum(along, 0.5 * dist), 1)), 0)
        rhs = jnp.where(zero, dist, rhs)
        if getattr(blk, "star", False):        # a star's rows share the hub: solved together, every row updated
            upd = L.block_solve(topo, blk, f, rhs)
        else:
            upd = jnp.where(live & (jnp.abs(res) > tol * 2 * r2), rhs * f.k, 0)
        new = R.accumulate(blk, mu, upd)
        p = f.n * (new - mu)
        return f.wi * p, -f.wj * p, new

    def colour(xv, blk, rows):
        x, v = xv
        pi, pj, new = update(x, blk, *rows)
        return (L.add_pair(topo, blk, x, pi, pj), L.add_pair(topo, blk, v, pi / h, pj / h)), new

    def shake_set(xv, blk, rows):
        """C_lib(x) moved to a mu along the start-of-step gradient J0: dmu = (C_lib - a mu) / (J(x) M^-1 J0^T + a)
        (J M^-1 J0^T at least half of sqrt(J M^-1 J^T J0 M^-1 J0^T) as for a rod), a = `set_alpha(compliance)`:
        a compliant row is an implicit spring, as XPBD's, and a hard row (a = 0) is SHAKE's."""
        x, v = xv
        f0, ssys, mu = rows
        f = R.set_frame(topo, blk, sys.cons[blk.generic], ssys, x, sys.w)
        along = jnp.sum(f.w * jnp.sum(f.J * f0.J, axis=0), axis=0)
        live = (f0.k > 0) & (f.k > 0) & (along > 0)
        ss = f.s * f0.s                  # 0 where a row has no gradient: sqrt's derivative there is infinite
        floor = 0.5 * jnp.sqrt(jnp.where(ss > 0, ss, 1)) * (ss > 0).astype(ss.dtype)
        a = jnp.zeros_like(f.C) if set_alpha is None else set_alpha(f0.alpha)
        if getattr(blk, "hub_slot", None) is not None:      # a set's stars: along J0, J0 M^-1 J0^T (+ a) together
            step = L.block_solve(topo, blk, f0._replace(k=f0.k * live), jnp.where(live, f.C - a * mu, 0), a)
        else:
            step = jnp.where(live, (f.C - a * mu) / jnp.where(live, jnp.maximum(along, floor) + a, 1), 0)
        new = R.accumulate(blk, mu, step)
        q = f0.Jw * (new - mu)
        return (L.add_rows(topo, blk, x, q), L.add_rows(topo, blk, v, q / h)), new

    def sweep(_, carry):
        x, v, mu = carry
        mu = list(mu)
        for c, (blk, f, r2) in enumerate(zip(topo.blocks, fr0, rest2)):
            if blk.generic is not None:
                (x, v), mu[c] = L.each_colour(blk, shake_set, (x, v), (f, sys.set_of(blk)[1], mu[c]))
            else:
                (x, v), mu[c] = L.each_colour(blk, colour, (x, v), (f, r2, mu[c]))
        return x, v, tuple(mu)
    return sweep


# ---- the (sub)step of every solver: the rows of every kind, contacts among them ----------------------------------
# A solver writes one (sub)step, `substep(x, v, lam_ws, h, found=None)`, and runs it through `run_substeps`. The
# contact kind's stages (its rows and warm start in `step_begin`, its sweep beside the constraint colours, the
# restitution phases of `solve_phases`, the time-of-impact correction and position pass of `step_end`) are
# no-ops for a model without contacts, which then computes what it computed before contacts existed.
#: Solves a grid model's step may take (`grid_step`): the first, and one again with the pairs it missed.
GRID_ATTEMPTS = 2


def run_substeps(sys, substep, substeps: int, x, v, lam, dt):
    """`substepped` for any model, `substep(x, v, lam_ws, h, found=None)`: through `grid_substepped` where the
    model's pairs come from a neighbour grid."""
    if sys.contact is not None and sys.contact.ct.has_grid:
        return grid_substepped(sys, substep, substeps, x, v, lam, dt)
    return substepped(substep, substeps, x, v, lam, dt, unroll=sys.topology.unroll)


def with_contacts(sys, lam, imp):
    """A (sub)step's impulses as the solvers carry them: the constraint blocks' `lam`, paired with the contact
    `Impulses` where the model has contacts."""
    return lam if sys.contact is None else (lam, imp)


def split_contacts(sys, lam):
    """The inverse of `with_contacts`: (the constraint blocks' impulses, the contact `Impulses` or None)."""
    return (lam, None) if sys.contact is None else lam


def grid_substepped(sys, substep, substeps: int, x, v, lam, dt):
    """A step of a model with a neighbour grid: `substep(x, v, lam_ws, h, found=...) -> (x, v, lam_h)` run
    `substeps` times (`substepped`) with the candidate pairs `found` = (partners, overflow) of one search made
    for the whole step (`grid_step`). The contact slots are the same in every substep of a step, so their
    impulses add up over the step as any other impulse, and the next step's warm start matches them slot by
    slot as after a single substep."""
    blocks, imp = lam
    lam = (blocks, imp._replace(reuse=None))

    def solve(found):
        return substepped(functools.partial(substep, found=found), substeps, x, v, lam, dt, path=True)
    x, v, (blocks, imp), reuse = grid_step(sys, x, v, dt, solve, substeps, imp.reuse)
    return x, v, (blocks, imp._replace(reuse=reuse))


def grid_step(sys, x, v, dt, solve, substeps: int = 1, reuse=None):
    """A step of a model with a neighbour grid, `solve(found) -> (x, v, (lam, imp), trail)` being the solver's
    step (all its substeps, `substepped`) with the candidate pairs `found` = (partners, overflow)
    (`grid.neighbours`), and `trail` [substeps, *x.shape] the positions after each substep.

    The search takes the velocities after the step's gravity, but an impact within the step can send a
    particle into one that was no candidate: three discs in a row, B hitting A at 30 m/s with A 5 cm from C,
    moved A through C in one step. The candidates cover every pair that can touch on straight paths at those
    velocities over the whole step, with a skin of GRID_SKIN (r_i + r_j); so if no particle's position after
    any substep k differs from its free one (x + k h v plus gravity's share, h = dt / substeps) by more than
    GRID_SKIN min(r) from a common offset (the middle of their range: a pile that stops as one keeps it), no
    other pair can have touched, and the step stands. Otherwise a second search lists the pairs that come
    within r_i + r_j of each other on the straight lines from the start to the end positions
    (`grid.path_search`). With substeps a particle's path is the polyline through its positions after each
    substep, straight within a substep: its distance from the chord at equal times is largest at a vertex, so
    each particle's r is widened by its largest vertex distance from the chord (0 for one substep; a cloth that
    lands keeps it small, where the distance from the free path is its whole fall in the step). If such a pair
    was not solved (`grid.unsolved`), the step is solved again from its start with both lists' pairs
    (`grid.merge_partners`), up to GRID_ATTEMPTS solves, and what the last check still finds is counted in
    the overflow, with the touching pairs the second search had no slot for (an upper bound). One traced copy
    of the solve, in a loop of `lax.cond`s (under `vmap` every branch runs: GRID_ATTEMPTS solves per step).

    `reuse`: the wider candidate list a rollout carries between steps (`core.contact.Reuse`), from which the
    step takes its candidates where it may instead of searching (`grid.reused_search`), or None (search).
    Returns (x, v, lam, reuse), reuse None where it was."""
    cs = sys.contact
    h = dt / substeps
    dim = x.shape[0]
    v_free = sys.apply_gravity(v, dt)
    r_min = lax.stop_gradient(jnp.min(cs.radius_flat))
    if reuse is None:
        (found, scan), floor = grid.grid_search(cs, x, v_free, dt), None
    else:
        found, reuse, floor = grid.reused_search(cs, x, v_free, dt, reuse)
        scan = None
    x0, v0 = lax.stop_gradient(x), lax.stop_gradient(v)
    g = lax.stop_gradient(sys.apply_gravity(jnp.zeros_like(v), 1.0))
    k = jnp.arange(1, substeps + 1, dtype=x.dtype).reshape((substeps,) + (1,) * x.ndim)
    free = x0 + (k * h) * v0 + (h * h) * (k * (k + 1) / 2) * g      # after each substep, without any impulse

    def spread(dev):
        """Per-particle length of dev [substeps, dim, ...] less, per substep, a common offset (the middle of its
        range over the particles), its largest over the substeps: [n]."""
        dev = dev.reshape(substeps, dim, -1)
        dev = dev - (jnp.max(dev, 2, keepdims=True) + jnp.min(dev, 2, keepdims=True)) / 2
        return jnp.max(jnp.sqrt(jnp.sum(dev * dev, 1)), 0)

    def run(i, carry):
        partners, over, _, _ = carry
        out = solve((partners, over))
        trail = out[3]
        stays = jnp.max(spread(trail - free)) <= grid.GRID_SKIN * r_min

        def verify(_):
            margin = None
            if substeps > 1:
                chord = x0 + (k / substeps) * (trail[-1] - x0)
                margin = jnp.max(jnp.sqrt(jnp.sum((trail - chord).reshape(substeps, dim, -1) ** 2, 1)), 0)
            wide = grid.path_search(cs, x, out[0], dt, scan, margin, floor)
            missed = grid.unsolved(wide[0], partners)
            last = i == GRID_ATTEMPTS - 1
            both, dropped = grid.merge_partners(partners, wide[0])
            return both, over + dropped, wide[1] + jnp.where(last, missed, 0), (missed > 0) & ~last

        partners, over, count, again = lax.cond(stays, lambda _: (partners, over, over, jnp.zeros((), bool)),
                                                verify, None)
        lam, imp = out[2]
        return partners, over, out[:2] + ((lam, imp._replace(overflow=count)),), again

    def attempt(i, carry):
        return lax.cond(carry[3], lambda c: run(i, c), lambda c: c, carry)

    out = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(lambda f: solve(f)[:3], found))
    return lax.fori_loop(0, GRID_ATTEMPTS, attempt, found + (out, jnp.ones((), bool)))[2] + (reuse,)


class Begin(NamedTuple):
    """What `step_begin` prepares: v_free, the velocity after gravity and before any impulse (what the
    time-of-impact correction compares with); v after the warm start; the constraint frames `fr`, biases and
    impulses `lam`; the contact rows `obs` and `pairs` and impulses `imp` (None without contacts); split
    impulses' slop (`split_slop`) or None."""
    v_free: Any
    v: Any
    fr: tuple
    bias: tuple
    obs: Any
    pairs: Any
    lam: tuple
    imp: Any
    slop: Any


def step_begin(sys, x, v, lam_ws, beta, h, split, warm: bool, factor=1.0, gradient: bool = True,
               found=None, contact_slop=0.0) -> Begin:
    """Gravity, the constraints' frames and biases (`split`: split impulses' slop share, or None), the contact
    rows (which keep `contact_slop` of overlap, `contact_rows.rows`) where the model has contacts, and the warm start
    of every row (scaled by `factor`; no gradient through it unless `gradient`). `lam_ws` is what the solver
    carries (`with_contacts`). A grid model passes its candidate pairs `found` = (partners, overflow)
    (`grid_step`)."""
    topo, cs = sys.topology, sys.contact
    lam_ws, imp_ws = split_contacts(sys, lam_ws)
    v0, v = v, sys.apply_gravity(v, h)
    fr = frames(sys, x)
    slop = None if split is None else split_slop(sys, fr, v, h, beta, split)
    bias = velocity_bias(topo, fr, beta, h, slop)
    v_free = v
    obs = pairs = imp = None
    if cs is not None:
        obs, pairs = contact_rows.rows(cs, sys.w, x, v0, v, beta, h, None if found is None else found[0], contact_slop)
    if not warm:
        lam = tuple(jnp.zeros_like(f.C) for f in fr)
        if cs is not None:
            imp = zero_impulses(topo, cs.ct, x.dtype)
    else:
        others = None if cs is None else functools.partial(
            contact.warm_start, cs, sys.w, obs=obs, pairs=pairs,
            prev=imp_ws if gradient else lax.stop_gradient(imp_ws), factor=factor)
        v, lam, imp = warm_start(sys, v, fr, lam_ws, h, factor, gradient, others)
    if cs is not None:
        imp = with_found(imp, found)
    return Begin(v_free, v, fr, bias, obs, pairs, lam, imp, slop)


def with_found(imp, found):
    """Contact impulses `imp` carrying a grid step's candidate pairs `found` = (partners, overflow) (None: a
    model without a grid, unchanged)."""
    return imp if found is None else imp._replace(partners=found[0], overflow=found[1])


def solve_phases(sys, v_free, obs, pairs, iterations: int, carry, body, slot_major: bool = False):
    """The velocity solve, `iterations` of `body(obs, pairs)`, which returns one iteration carry = (v, ...) ->
    carry. A model without contacts runs them in one loop. With contacts it runs in two phases sharing the
    iterations (at least one each): compression (every target without restitution), then restitution,
    continued from it, ending with the contacts' restitution stage (`contact.restitution_stage`, where the carry
    ends with the contact `Impulses`); the restitution phase's change is scaled back where it would raise the
    kinetic energy (contact.restitution_scale). One loop, whose rows switch targets between the phases, so the iteration is
    traced and compiled once. Returns the carry mixed leaf by leaf.

    `slot_major`: `body` reads the contact rows only through `contact.sweep`, so the carry's pair impulses of a grid
    are moved slot-major once here (`contact_rows.in_solve`) rather than in every sweep, and back; and where the
    sweeps pick obstacle rows (`Rows.sel`), the obstacle impulses are split per obstacle and each obstacle's
    picked rows gathered once here (`contact_rows.obstacles_in_solve`)."""
    if sys.contact is None:
        one_iteration = body(None, None)
        return lax.fori_loop(0, iterations, lambda _, c: one_iteration(c), carry, unroll=sys.topology.unroll)
    major = slot_major and contact_rows.pair_partners(pairs) is not None
    split = (slot_major and obs is not None and obs.sel is not None
             and obs.gap.shape[0] <= contact_rows.UNROLL_OBSTACLES)     # more: scanned, not split
    if major or split:
        view = obs.gap.shape[1:] if split else None

        def enter(imp):
            imp = contact_rows.impulses_slot_major(imp) if major else imp
            return contact_rows.obstacle_impulses_split(imp) if split else imp

        def leave(imp):
            imp = contact_rows.impulses_slot_minor(imp) if major else imp
            return contact_rows.obstacle_impulses_joined(imp, view) if split else imp

        out = solve_phases(sys, v_free, contact_rows.obstacles_in_solve(obs, sys.w) if split else obs,
                           contact_rows.in_solve(pairs) if major else pairs, iterations, _on_impulses(enter, carry),
                           body)
        return _on_impulses(leave, out)
    first = max(iterations // 2, 1)
    total = first + max(iterations - first, 1)

    def one(i, state):
        carry, saved = state
        late = i >= first
        carry = body(contact_rows.phase(obs, late), contact_rows.phase(pairs, late))(carry)
        saved = jax.tree.map(lambda new, old: jnp.where(i == first - 1, new, old), carry, saved)
        return carry, saved

    bounced, compressed = lax.fori_loop(0, total, one, (carry, carry))
    if isinstance(bounced[-1], Impulses):       # the contacts' restitution stage, shared with every solver
        v, imp = contact.restitution_stage(sys.contact, sys.w, bounced[0], contact_rows.phase(obs, True),
                                           contact_rows.phase(pairs, True), bounced[-1])
        bounced = (v,) + tuple(bounced[1:-1]) + (imp,)
    s = contact.restitution_scale(sys.w, v_free, compressed[0], bounced[0], contact_rows.bouncing(obs, pairs))

    def mix(a, b):       # integer leaves (a neighbour grid's partners and overflow) are the same in both phases
        return a + s * (b - a) if jnp.issubdtype(a.dtype, jnp.floating) else b

    return jax.tree.map(mix, compressed, bounced)


def _on_impulses(fn, tree):
    """`tree` with fn applied to each of its contact `Impulses`."""
    def is_imp(a):
        return isinstance(a, Impulses)
    return jax.tree.map(lambda a: fn(a) if is_imp(a) else a, tree, is_leaf=is_imp)


def step_end(sys, x, v, v_free, obs, pairs, imp, h, passes=1, rods_pass=None, contact_slop=0.0):
    """New positions: x + h v, with contacts the time-of-impact correction (a particle whose velocity changed at
    tau within the step moved at its old velocity until then: x' = x + tau v_free + (h - tau) v'), then
    `rods_pass` (split impulses' position pass of the constraints, x -> x, or None), then the position safety
    pass of the contacts (`passes`, `contact_slop`: see contact.project_overlaps)."""
    cs = sys.contact
    if cs is None:
        x = x + h * v
        return x if rods_pass is None else rods_pass(x)
    dx = -contact.impact_times(cs, obs, pairs, imp, x.shape) * (v - v_free)
    x = x + h * v + dx
    if rods_pass is not None:
        x = rods_pass(x)
    return contact.project_overlaps(cs, sys.w, x, passes, pairs, contact_slop)
