"""Jacobi solver: velocity-level impulses like PGS, but every constraint solved from the same velocities."""
from __future__ import annotations

import functools
import warnings
from typing import Any

import jax.numpy as jnp

from jaxcon.core import contact_rows
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_bool, check_int, check_scalar
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import (
    check_stabilization,
    run_substeps,
    solve_phases,
    split_position_pass,
    step_begin,
    step_end,
    with_contacts,
)


def max_degree(topo) -> int:
    """Largest number of blocks solved together that share one free particle (static, from the topology; a fixed
    particle takes no velocity change, so its constraints do not compete): a constraint counts at each of its
    particles, a hub's star once (`Topology.block_degree`: its rows are solved together); at least 1."""
    return max(int((topo.block_degree() * ~topo.fixed).max(initial=0)), 1)


@pytree_dataclass
class Jacobi(Solver):
    """Projected Jacobi at velocity level with Baumgarte stabilisation.

    Per (sub)step of length h: v += h g; warm start with the previous impulses (ropes clamped >= 0); then each
    iteration computes, for every constraint from the *same* velocities v,

        dlam = relaxation (n . (v_j - v_i) + bias) / (w_i + w_j)      (bias as in `PGS`)

    clamps the accumulated lam + dlam of ropes to >= 0 and applies all the impulse changes at once (summed per
    particle); finally x += h v. The fixed point is the one PGS converges to (every constraint's velocity
    equation holds), but it is reached more slowly; relaxation < 2 / max particle degree always converges
    (Gershgorin bound on the scaled Delassus matrix), so the default is 1 / max degree. A hub's constraints (a
    star of rods or of a set's rows) are solved together as one block (block Jacobi, `layout.block_solve`) and
    count once at the hub in that degree (`max_degree`).

    Contacts (`planes`, `spheres`, `collide`; `contact.jacobi_pass`): PGS's rows, warm start,
    time-of-impact correction and position pass, with every contact (all obstacles and all pair slots at once)
    and every rod updated from the same velocities in each iteration. With `relaxation=None` a model with contacts
    is relaxed by mass splitting: a row between particles i and j takes the effective mass
    1 / (c_i w_i + c_j w_j), c the number of constraint rows and pushing contacts at each particle in that
    iteration (a compliant row adds its gamma = alpha / h^2 to that; convergent, and momentum-conserving: every
    impulse acts equally and oppositely; `contact.jacobi_pass`). On the 16-ball break it
    needs 8 to 10 times PGS's iterations to converge (e.g. `Jacobi(20, substeps=2)` where `PGS(20)` suffices).

    Args:
      iterations: Jacobi iterations per (sub)step, static, >= 1.
      beta: Baumgarte factor in [0, 1], a differentiable leaf; with split impulses only the contacts' push-out
        rate.
      relaxation: scale of the summed impulse in (0, 2], a differentiable leaf; None: 1 / (largest number of
        constraints at one particle, a hub's star counting once) of the model being solved, or mass splitting for a model with contacts
        (a fixed value there scales every rod and contact row alike).
      warm_start: start from the previous step's impulses (static); a constraint set's compliant rows from a
        share of theirs, none where the spring is stiff for the step (`common.warm_rows`).
      substeps: (sub)steps per step, static, >= 1.
      stabilization: 'baumgarte' (default) or 'split' (static): split impulses as in `PGS`, the position
        projection by Jacobi sweeps with the rods' relaxation (1 / largest degree by default).
      slop: split impulses' slop, as in `PGS`.
      contact_slop: the overlap left to the contacts, as `PGS.contact_slop` (default
        `contact_rows.CONTACT_SLOP`). Without it a pile of discs does not rest: its contacts, left at C = 0 by the
        position pass, are taken for separated and solved cold in some steps, without friction (docs/contacts.md).
    """

    iterations: int = static_field(default=20)
    beta: Any = 0.2
    relaxation: Any = None
    warm_start: bool = static_field(default=True)
    substeps: int = static_field(default=1)
    stabilization: str = static_field(default="baumgarte")
    slop: Any = 0.005
    contact_slop: Any = contact_rows.CONTACT_SLOP

    def __post_init__(self):
        check_stabilization("Jacobi", self.stabilization)
        check_scalar("Jacobi", "contact_slop", self.contact_slop, 0.0, 0.5)
        check_scalar("Jacobi", "slop", self.slop, 0.0, 1.0)
        check_int("Jacobi", "iterations", self.iterations, 1)
        check_int("Jacobi", "substeps", self.substeps, 1)
        check_bool("Jacobi", "warm_start", self.warm_start)
        check_scalar("Jacobi", "beta", self.beta, 0.0, 1.0)
        if self.relaxation is not None:
            check_scalar("Jacobi", "relaxation", self.relaxation, 0.0, 2.0, positive=True)

    supports_contacts = True

    def _check_stability(self, owner, model, dt) -> None:
        """Warn (before tracing, where the value is known) when a fixed `relaxation` is at or above
        2 / (largest number of constraints at one particle): the bound below which the iteration converges for
        every set of constraints (Gershgorin), and above which a cloth's corrections overshoot and grow until
        the run is NaN (a draped 6x6 cloth, 8 rods at a particle, with relaxation 0.5). A warning, not an error:
        the bound is sufficient, not necessary. With contacts, which add rows at a particle as they touch, staying
        below it is not enough: there the bound counts the constraints only."""
        r = None if self.relaxation is None else concrete(self.relaxation)
        if r is None:
            return
        deg = max_degree(model.topology)
        if float(r) >= 2.0 / deg:
            warnings.warn(
                f"{owner}: Jacobi relaxation={float(r):g} is at or above 2 / {deg} = {2.0 / deg:.3g}, where {deg} "
                "is the largest number of constraints at one particle of this model: the iterations may diverge "
                f"(to NaN). Use relaxation < {2.0 / deg:.3g}, or relaxation=None (1 / {deg} without contacts, "
                "mass splitting with them). Contacts add rows at a particle that this bound does not count.",
                RuntimeWarning, stacklevel=4)

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)

    def _substep(self, sys, x, v, lam_ws, h, found=None):
        """One (sub)step: gravity, the rows and warm start of every kind (`common.step_begin`); then iterations
        that update every constraint row and every contact row (`contact.jacobi_pass`) from the same v and apply
        the sum, in the contacts' restitution phases (`common.solve_phases`); then x += h v with the contacts'
        time-of-impact correction and position pass (`common.step_end`). `relaxation=None` relaxes by
        1 / largest degree without contacts, by mass splitting with them. A grid model's step goes through
        `grid_substepped`, which calls this with its candidate pairs `found`."""
        topo, cs = sys.topology, sys.contact
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        if self.relaxation is not None:
            relax = jnp.asarray(self.relaxation, dtype)
        else:
            relax = jnp.asarray(1.0 / max_degree(topo), dtype) if cs is None else None
        split = self.stabilization == "split"
        share = jnp.asarray(self.slop, dtype)
        contact_slop = jnp.asarray(self.contact_slop, dtype)
        b = step_begin(sys, x, v, lam_ws, beta, h, share if split else None, self.warm_start, found=found,
                       contact_slop=contact_slop)
        base = None if relax is not None else row_counts(topo, b.fr, sys.w)
        springs = tuple(R.gamma(f, h) for f in b.fr)

        def iterations(obs, pairs):
            def iterate(carry):
                v, lam, imp = carry
                count = None if relax is not None else contact.jacobi_counts(cs, v, obs, pairs, imp, base)
                dv, lam = rows_pass(topo, b.fr, b.bias, springs, v, lam, count, relax)
                if cs is None:
                    return v + dv, lam, imp
                dv_contacts, imp = contact.jacobi_pass(cs, sys.w, v, obs, pairs, imp, count, relax)
                return v + dv + dv_contacts, lam, imp
            return iterate

        v, lam, imp = solve_phases(sys, b.v_free, b.obs, b.pairs, self.iterations, (b.v, b.lam, b.imp), iterations)
        rods_pass = None
        if split and b.fr:
            rod_relax = jnp.asarray(1.0 / max_degree(topo), dtype) if relax is None else relax
            rods_pass = lambda x: split_position_pass(sys, x, self.iterations, b.slop, rod_relax)  # noqa: E731
        x = step_end(sys, x, v, b.v_free, b.obs, b.pairs, imp, h, rods_pass=rods_pass, contact_slop=contact_slop)
        return x, v, with_contacts(sys, lam, imp)


def row_counts(topo, fr, like):
    """Number of constraint rows at each particle, [1, *view] (rows with no effective mass left out): the
    base of mass splitting's counts (`contact.jacobi_counts`)."""
    c = jnp.zeros((1,) + like.shape[1:], like.dtype)
    for blk, f in zip(topo.blocks, fr):
        one = (f.k > 0).astype(like.dtype)[None]
        if blk.generic is not None:          # a set's row counts at each of its particles, a star's once at its hub
            per = jnp.broadcast_to(one[:, None], (1,) + f.w.shape)
            if blk.hub_slot is not None:
                hub = blk.hub_slot.array
                per = jnp.where(hub, (one / _star_rows(blk, one))[:, None], per)
            c = L.add_rows(topo, blk, c, per)
            continue
        hub = one / _star_rows(blk, one) if blk.star else one
        c = L.add_pair(topo, blk, c, hub, one)
    return c


def _star_rows(blk, one):
    """Per row of a star block (rods' [..., S] or a set's [..., H S]), the number of live rows of its star (at
    least 1), so that a star counts once at its hub."""
    S = one.shape[-1] if blk.star else blk.spokes
    per = one.reshape(one.shape[:-1] + (one.shape[-1] // S, S))
    n = jnp.maximum(jnp.sum(per, axis=-1, keepdims=True), 1)
    return jnp.broadcast_to(n, per.shape).reshape(one.shape)


def _split_frame(topo, blk, f, count):
    """The rows `f` with each particle's inverse mass multiplied by its count (mass splitting): J M^-1 J^T and
    the effective mass k of the split masses."""
    if blk.generic is not None:
        w = L.gather_rows(topo, blk, count)[0] * f.w
        s = jnp.sum(w * jnp.sum(f.J * f.J, axis=0), axis=0)
        return f._replace(w=w, s=s, k=L.safe_reciprocal(s) * (f.k > 0).astype(s.dtype))
    ci, cj = L.gather_pair(topo, blk, count)
    wi, wj = ci[0] * f.wi, cj[0] * f.wj
    return f._replace(wi=wi, wj=wj, k=L.safe_reciprocal(wi + wj) * (f.k > 0).astype(wi.dtype))


def rows_pass(topo, fr, bias, springs, v, lam, count, relax):
    """Jacobi update of every constraint row from the same `v`: (dv, lam), each row's change
    `rows.solve` (a set's compliant rows as implicit springs) scaled by `relax`, or, with the
    per-particle counts `count` [1, *view] (mass splitting), the same update with the effective mass
    1 / (c_i w_i + c_j w_j) (a set's rows: J M^-1 J^T with each inverse mass multiplied by its count)."""
    dv = jnp.zeros_like(v)
    new = []
    for blk, f, b, g, l in zip(topo.blocks, fr, bias, springs, lam):
        rhs = R.rel(topo, blk, f, v) + b
        if count is None:
            step = relax * R.solve(topo, blk, f, rhs, l, g)
        else:
            fs = _split_frame(topo, blk, f, count)
            step = R.solve(topo, blk, fs, rhs, l, None if g is None else R.Spring(
                g.g, L.safe_reciprocal(fs.s + g.g) * (f.k > 0).astype(g.g.dtype)))
        nl = R.accumulate(blk, l, step)
        dv = R.apply(topo, blk, f, dv, nl - l)
        new.append(nl)
    return dv, tuple(new)
