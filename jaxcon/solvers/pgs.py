"""Sequential impulses / projected Gauss-Seidel (`jc.PGS`)."""
from __future__ import annotations

import functools
from typing import Any, Optional

import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import contact_rows
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_bool, check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import (
    apply_impulses,
    check_stabilization,
    run_substeps,
    solve_phases,
    split_position_pass,
    step_begin,
    step_end,
    with_contacts,
)


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
      beta: Baumgarte factor in [0, 1], a differentiable leaf (0.1 to 0.3 is usual); with split impulses only
        the contacts' push-out rate.
      warm_start: start each step from the previous step's impulses (static); a constraint set's compliant rows
        from the share of theirs that leaves the least kinetic energy, all of it at rest
        (`common.spring_share`).
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
      stabilization: 'baumgarte' (default, the textbook method above) or 'split' (static): split impulses.
        Baumgarte within an adaptive slop, projection beyond it: each rod and rope gets a slop
        s = clip(h^2 |u_t|^2 / (d max(beta, 1e-3)), slop L, 0.1 L), twice the steady error Baumgarte leaves on a
        rod rotating at tangential speed u_t (`common.split_slop`). Where |C| <= s the velocity sweeps see the
        Baumgarte bias as usual; where |C| > s they see none, and after the step `iterations` nonlinear
        Gauss-Seidel sweeps project those constraints' positions back to their rest lengths, velocities
        untouched (Box2D v2's position solver, `common.split_position_pass`). A system without position
        error moves as with Baumgarte (a double pendulum matches it to the digit at 240 and 960 Hz); a
        stretched start, or a heavy chain the sweeps cannot hold, is corrected without its error being turned
        into kinetic energy. lam is the velocity impulse, the physical constraint impulse. Not with
        `implicit=True`.
      slop: split impulses' smallest slop, a share of each rod's and rope's rest length in [0, 1), a
        differentiable leaf (default 0.005). Not used by Baumgarte.
      contact_slop: the overlap, as a fraction of the contact distance (r_i + r_j; r for a plane or sphere),
        that contacts keep without being pushed out (Box2D's linear slop), a differentiable leaf in [0, 0.5];
        default `contact_rows.CONTACT_SLOP` = 0.005, half a percent of a diameter. The Baumgarte term pushes out
        only the overlap beyond six of it (`contact_rows.PUSH_SLOPS`), the position safety pass projects onto it, and
        pairs within it of touching are warm-started: what lets a pile come to rest (docs/contacts.md, piles at
        rest). 0 is the method before (resting contacts at C = 0, solved cold every other step).
      contact_passes: passes of the contacts' position safety pass per (sub)step (static, >= 1), or None for
        the default: `contact.GRID_OVERLAP_PASSES` (32, stopping early once a pass moves almost nothing) with a
        neighbour grid, `contact.OVERLAP_PASSES` with listed pairs, 1 with obstacles only. The pass moves
        positions without touching velocities, so it lifts a deep pile against gravity each step; with
        several substeps that energy kept the 4096-disc box flowing, and one pass lets it rest
        (`PGS(10, substeps=4, contact_passes=1)`, docs/contacts.md).
      warm_start_gradient: if False, no gradient flows through the warm-start impulses (static). The forward
        pass is unchanged and the gradient becomes a truncated one. Measured on a swinging 16x16 cloth it does
        not stop long-horizon gradient growth (that growth is the physics: the motion is chaotic, and a
        converged XPBD grows as fast); windowed losses (`jc.fit(window=...)`) are what bound it. See
        docs/fitting.md.
    """

    iterations: int = static_field(default=10)
    beta: Any = 0.2
    warm_start: bool = static_field(default=True)
    substeps: int = static_field(default=1)
    warm_start_factor: Any = 1.0
    warm_start_gradient: bool = static_field(default=True)
    implicit: bool = static_field(default=False)
    stabilization: str = static_field(default="baumgarte")
    slop: Any = 0.005
    contact_slop: Any = contact_rows.CONTACT_SLOP
    contact_passes: Optional[int] = static_field(default=None)

    def __post_init__(self):
        check_stabilization("PGS", self.stabilization)
        check_scalar("PGS", "slop", self.slop, 0.0, 1.0)
        if self.implicit and self.stabilization == "split":
            raise ValueError("PGS: `implicit=True` is not available with stabilization='split' (its position "
                             "projection has no implicit derivative here); use implicit=False")
        check_int("PGS", "iterations", self.iterations, 1)
        check_int("PGS", "substeps", self.substeps, 1)
        check_bool("PGS", "warm_start", self.warm_start)
        check_bool("PGS", "warm_start_gradient", self.warm_start_gradient)
        check_bool("PGS", "implicit", self.implicit)
        check_scalar("PGS", "beta", self.beta, 0.0, 1.0)
        check_scalar("PGS", "warm_start_factor", self.warm_start_factor, 0.0, 1.0)
        check_scalar("PGS", "contact_slop", self.contact_slop, 0.0, 0.5)
        if self.contact_passes is not None:
            check_int("PGS", "contact_passes", self.contact_passes, 1)

    supports_contacts = True

    def _factor(self, dtype):
        factor = self.warm_start_factor
        return factor if isinstance(factor, (int, float)) else jnp.asarray(factor, dtype)

    def _substep(self, sys, x, v, lam_ws, h, found=None):
        """One (sub)step: gravity, the rows and warm start of every kind (`common.step_begin`); each sweep
        solves the constraint colours, then the contacts (`contact.sweep`, nothing without contacts), in the
        contacts' restitution phases (`common.solve_phases`); then x += h v with the contacts' time-of-impact
        correction and position pass (`common.step_end`). Contacts push out overlap with `beta`. A grid model's
        step goes through `grid_substepped`, which calls this with its candidate pairs `found`."""
        topo, cs = sys.topology, sys.contact
        if self.implicit and cs is not None:
            raise ValueError("PGS(implicit=True) does not support contacts (an inequality); use implicit=False")
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        contact_slop = jnp.asarray(self.contact_slop, dtype)
        split = self.stabilization == "split"
        share = jnp.asarray(self.slop, dtype)
        b = step_begin(sys, x, v, lam_ws, beta, h, share if split else None, self.warm_start, self._factor(dtype),
                       self.warm_start_gradient, found, contact_slop)
        v, lam, imp = b.v, b.lam, b.imp
        if self.implicit:
            return self._implicit(sys, x, v, lam, b.fr, b.bias, h)
        if topo.packed and topo.blocks and cs is None:
            # the warm start's impulses, as `warm_start` applied them to v_free: the first colour's impulse
            # change is computed from them (`layout.gather_after`) rather than from the stored v
            ws = [(blk, f.wi * (f.n * l), -f.wj * (f.n * l)) for blk, f, l in zip(topo.blocks, b.fr, lam)] \
                if self.warm_start else []
            v, lam = packed_sweeps(topo, b.fr, b.bias, v, lam, self.iterations, b.v_free, ws)
        else:
            block_sweep = self._block_sweep(topo, b.fr, b.bias, h)

            def sweeps(obs, pairs):
                def sweep(carry):
                    v, lam, imp = carry
                    v, lam = block_sweep(v, lam)
                    v, imp = contact.sweep(cs, sys.w, v, obs, pairs, imp)
                    return v, lam, imp
                return sweep

            v, lam, imp = solve_phases(sys, b.v_free, b.obs, b.pairs, self.iterations, (v, lam, imp), sweeps,
                                       slot_major=True)
        rods_pass = (lambda x: split_position_pass(sys, x, self.iterations, b.slop)) if split and b.fr else None
        x = step_end(sys, x, v, b.v_free, b.obs, b.pairs, imp, h, passes=self.contact_passes, rods_pass=rods_pass,
                     contact_slop=contact_slop)
        return x, v, with_contacts(sys, lam, imp)

    @staticmethod
    def _block_sweep(topo, fr, bias, h):
        """One Gauss-Seidel pass over the constraint colours: (v, lam) -> (v, lam). Every kind's rows through
        `rows.rel` / `rows.apply` (`rows.solve`: a set's compliant rows as implicit springs; `rows.accumulate`)."""
        def colour(v, blk, rows):
            f, b, g, lam = rows
            new = R.accumulate(blk, lam, R.solve(topo, blk, f, R.rel(topo, blk, f, v) + b, lam, g))
            return R.apply(topo, blk, f, v, new - lam), new

        springs = tuple(R.gamma(f, h) for f in fr)          # once per (sub)step, outside the sweeps

        def sweep(v, lam):
            lam = list(lam)
            for c, (blk, f, b, g) in enumerate(zip(topo.blocks, fr, bias, springs)):
                v, lam[c] = L.each_colour(blk, colour, v, (f, b, g, lam[c]))
            return v, tuple(lam)
        return sweep

    def _implicit(self, sys, x, v, lam0, fr, bias, h):
        """Converged multipliers with implicit derivatives: lam solves G lam = rel(v) + bias, where
        G lam = -J (M^-1 J^T lam) is J M^-1 J^T in the tension convention (symmetric), and v is the velocity
        before any impulse. `lam0` (the warm start, already applied to v) is the solver's initial guess only."""
        topo = sys.topology
        if topo.has_ropes or any(info.unilateral for info in topo.sets):
            raise ValueError("PGS(implicit=True): implicit differentiation needs equality constraints; the model "
                             "has ropes or unilateral constraints (inequalities). Use implicit=False for them.")
        v_free = apply_impulses(sys, v, fr, tuple(-l for l in lam0))     # undo the warm start
        zero_v = jnp.zeros_like(v)
        gs = tuple(R.gamma(f, h) for f in fr)

        def relative(u):
            return tuple(R.rel(topo, blk, f, u) for blk, f in zip(topo.blocks, fr))

        def matvec(l):          # (J M^-1 J^T + gamma) l, gamma for a set's compliant rows
            return tuple(-r if g is None else g.g * li - r
                         for r, g, li in zip(relative(apply_impulses(sys, zero_v, fr, l)), gs, l))

        def solve(_, rhs, guess=lax.stop_gradient(lam0)):
            def colour(u, blk, rows):
                f, r, g, l = rows
                d = R.solve(topo, blk, f, R.rel(topo, blk, f, u) + r, l, g)
                return R.apply(topo, blk, f, u, d), l + d

            def sweep(_, carry):
                u, l = carry
                l = list(l)
                for c, (blk, f, g) in enumerate(zip(topo.blocks, fr, gs)):
                    u, l[c] = L.each_colour(blk, colour, u, (f, rhs[c], g, l[c]))
                return u, tuple(l)

            u0 = apply_impulses(sys, zero_v, fr, guess)
            return lax.fori_loop(0, self.iterations, sweep, (u0, guess))[1]

        rhs = tuple(r + b for r, b in zip(relative(v_free), bias))
        lam = lax.custom_linear_solve(matvec, rhs, solve, symmetric=True)
        v = apply_impulses(sys, v_free, fr, lam)
        return x + h * v, v, lam

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)


def packed_sweeps(topo, fr, bias, v, lam, iterations, v_free, ws):
    """PGS's `iterations` Gauss-Seidel sweeps over the colours of a batch-minor topology (`topo.batch` copies,
    `topo.packed`), carried in one array: (v, lam) -> (v, lam), what the plain sweeps compute.

    The plain sweep writes two arrays per colour: the impulses (lam, a row per constraint and copy) and the
    velocities (v, which the next colour reads at other rows). XLA on CPU has no multi-output fusion, so that
    is two kernels per colour and sweep, plus a copy of lam per colour in the sweep loop. Here the velocities,
    every colour's impulses and the next colour's impulse change dl are rows of one array S
    [dim * n + m + max colour size, B], and each colour is one kernel that reads S and writes S: the colour's
    update from its dl (new = clamp(lam + dl), v += M^-1 J^T (new - lam)), then the next colour's dl from the
    updated velocities of its endpoints (`layout.gather_after`: no padded arrays stored between). An
    optimization barrier after each colour keeps XLA from splitting S back into its parts. Each value is
    computed by the plain sweep's operations in its order; XLA compiles them into other kernels, so results
    agree with the plain sweeps to rounding (1.4e-17 after one step in float64, 3e-14 after 240 chaotic
    double-pendulum steps; tests/test_batching.py).

    For the double pendulum (PGS(10), float32) this is 36 kernels per step against 74 for the plain sweeps
    and 32 for the hand-written reference (`bench.references.batch_minor_pgs`), whatever the batch size. On
    CPU the plain sweeps still run faster (1.3 to 1.7x here), which is why the CPU default (pieces) keeps
    them (`jaxcon.core.batch.packs`); `jaxcon.core.batch.packing_pays` says which models pack.

    `v_free`, `ws`: the velocities before the warm start and its impulses as `layout.add_pair` terms, from
    which the first colour's dl is computed (v is v_free after them)."""
    blocks = topo.blocks
    B, C = topo.batch, len(blocks)
    shapes = [a.shape for a in lam]
    rows = [int(np.prod(sh)) // B for sh in shapes]
    off = np.cumsum([0] + rows).tolist()
    nv, M, D = v.size // B, off[-1], max(rows)
    v_shape = v.shape

    def solve(c, ends):
        blk, f = blocks[c], fr[c]
        vi, vj = ends
        return L.block_solve(topo, blk, f, L.dot(blk, vj - vi, f.n) + bias[c])

    def pack(v, lm, dl):
        dl = dl.reshape(-1, B)
        parts = [v.reshape(nv, B), lm, dl] + ([jnp.zeros((D - dl.shape[0], B), v.dtype)] if dl.shape[0] < D else [])
        return lax.optimization_barrier(jnp.concatenate(parts))

    def colour(c, S):
        blk, f = blocks[c], fr[c]
        v, lm = S[:nv].reshape(v_shape), S[nv:nv + M]
        dl = S[nv + M:nv + M + rows[c]].reshape(shapes[c])
        old = lm[off[c]:off[c + 1]].reshape(shapes[c])
        new = R.accumulate(blk, old, dl)
        p = f.n * (new - old)
        upd = (blk, f.wi * p, -f.wj * p)
        nxt = (c + 1) % C
        dl_next = solve(nxt, L.gather_after(topo, blocks[nxt], v, [upd]))
        lm = jnp.concatenate([a for a in (lm[:off[c]], new.reshape(-1, B), lm[off[c + 1]:]) if a.shape[0]])
        return pack(L.add_pair(topo, blk, v, *upd[1:]), lm, dl_next)

    def sweep(_, S):
        for c in range(C):
            S = colour(c, S)
        return S

    lm = jnp.concatenate([a.reshape(-1, B) for a in lam])
    S = pack(v, lm, solve(0, L.gather_after(topo, blocks[0], v_free, ws)))
    S = lax.fori_loop(0, iterations, sweep, S, unroll=topo.unroll)
    v = S[:nv].reshape(v_shape)
    return v, tuple(S[nv + off[c]:nv + off[c + 1]].reshape(shapes[c]) for c in range(C))
