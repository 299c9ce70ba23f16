"""Direct solver: all multipliers of a (sub)step at once from one linear solve."""
from __future__ import annotations

import functools
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.lax.linalg import tridiagonal_solve

from jaxcon.core import contact_rows
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import (check_stabilization, run_substeps, solve_phases, split_contacts, step_begin,
                                   step_end, with_contacts)

_METHODS = ("auto", "dense", "tridiagonal")

# Chains shorter than this use the dense solve of the same (tridiagonal) matrix, whatever the method: at
# these sizes it costs nothing, and it avoids an XLA CPU bug in jaxlib 0.10.2, where reverse mode through
# the tridiagonal path of a 3-constraint, 2-D, float64 chain compiles a fused pad kernel that segfaults
# (found by tests/test_gradients_all_solvers.py; the dense path of the same system is fine).
_TRIDIAGONAL_FROM = 9


def is_simple_chain(topo) -> bool:
    """True when constraint k joins particles k and k+1 (either orientation) for every k, in user order."""
    k = np.arange(topo.m)
    lo, hi = np.minimum(topo.i, topo.j), np.maximum(topo.i, topo.j)
    return topo.m == topo.n - 1 and bool(np.all(lo == k)) and bool(np.all(hi == k + 1))


def _regularisation(value, dtype):
    # Relative diagonal regularisation of J M^-1 J^T, at least 1e3 machine epsilons (2e-13 in float64,
    # 1.2e-4 in float32). It keeps redundant constraints (a duplicated rod: a singular matrix) solvable,
    # splitting the impulse equally between the copies, damps the nearly redundant directions of
    # over-constrained meshes (cloth with shear rods: with 2e-13 the float64 solve blows up at dt = 1/60,
    # with 1e-6 it behaves like PGS) and changes a well-posed solution by about that relative amount only.
    return jnp.maximum(jnp.asarray(value, dtype), 1e3 * jnp.finfo(dtype).eps)


@pytree_dataclass
class Direct(Solver):
    """Exact per-(sub)step impulses from one linear solve (velocity level, Baumgarte-stabilised).

    Per (sub)step of length h: v += h g; with J the constraint Jacobian at the current positions (row k:
    n_k . (v_j - v_i), n_k the unit vector from the first to the second particle of constraint k) and
    C = |x_j - x_i| - L,

        (J M^-1 J^T) lam = J v + (beta / h) C,     v += -M^-1 J^T lam,     x += h v

    so that every constraint ends the substep with J v = -(beta / h) C (lam > 0: tension).

    The matrix is assembled from the static index pairs. When the topology is a simple chain (constraint k
    joins particles k and k+1 in user order, as in `jc.scenes.chain`) it is tridiagonal and solved in O(n)
    with `jax.lax.linalg.tridiagonal_solve`; otherwise densely with `jnp.linalg.solve` (O(m^3): meant for
    small systems). Guards: a constraint with no defined direction (coincident particles) or no mobility
    (both particles fixed) gets an identity row and lam = 0; the diagonal is scaled by 1 + `regularisation`
    (at least 1e3 machine epsilons) so redundant constraints (a duplicated rod, cloth shear rods) stay
    solvable.

    Unilateral rows (ropes, a unilateral `jc.Constraint` set) make the solve a linear complementarity problem:
    lam >= 0 on those rows, the residual A lam - b >= 0 where lam = 0, and one of the two zero on each. It is
    solved exactly by block principal pivoting (Judice and Pires, with Murty's single pivots when the block
    pivots stop making progress): each pivot is a solve of the same matrix restricted to the rows held active.
    The pivoting runs without gradient; the impulses are the solve of the final active set, differentiated as
    such (the active set is piecewise constant in the inputs). A slack unilateral row's bias is the speculative
    C / h, as in `PGS`: it may close the gap within the (sub)step and no further. Cost: one solve per
    right-hand side where every row may stay active (all ropes taut, every floor pressed), else two more and one
    per pivot; under `vmap` every element takes the slowest one's pivots. At most 4 u + 8 pivots (u unilateral
    rows): a review's random complementarity problems of up to 250 rows (condition numbers to 1e8) took at most
    69; were the limit reached, the last active set's solve would be used, clamped to lam >= 0, with no report.

    The warm-start input is not used (the solve is exact).

    Contacts (a model with `planes`, `spheres` or `collide`): the contact rows are PGS's (speculative contacts,
    restitution in two phases, friction in the Coulomb cone, the time-of-impact correction and the position
    pass; warm started from the previous step), and they have no exact solve here: friction's cone makes the
    problem no linear complementarity problem. Each (sub)step alternates, block by block (block Gauss-Seidel),
    the exact solve of every constraint row given the contact impulses so far, and one sweep over the contact
    rows (`contact.sweep`) given the constraint impulses: `contact_iterations` sweeps (at least one in each of
    the two restitution phases, as in `PGS`), each followed by the exact solve, which comes first as well, and
    once more after the restitution guard has mixed the two phases. So the constraints end the (sub)step
    exactly as above, and the contacts are as converged as that many PGS sweeps over them with the
    constraints solved exactly in between. With `stabilization='split'` each exact solve also gives its position correction, and the
    last one moves the positions before the contacts' position pass.

    Args:
      beta: Baumgarte factor in [0, 1], a differentiable leaf.
      substeps: (sub)steps per step, static, >= 1.
      method: 'auto' (tridiagonal for a simple chain, else dense), 'dense' or 'tridiagonal' (static).
        Chains of fewer than 9 constraints are always solved densely (same system, same result).
      regularisation: relative diagonal regularisation (constraint force mixing), >= 0, a leaf; values below
        1e3 machine epsilons are raised to that.
      stabilization: 'baumgarte' (default, above) or 'split' (static): split impulses, as in `PGS`, with exact
        linear corrections: the same matrix is solved for J v + (beta / h) C over the constraints within their
        adaptive slop (lam, the physical impulse), and for beta C over those beyond it, a position correction
        that moves the positions of the substep and does not touch the velocities.
      slop: split impulses' slop, as in `PGS`.
      contact_iterations: sweeps over the contact rows per (sub)step, each followed by the exact solve of the
        constraints (static, >= 1; at least 2 run, one per restitution phase; a model without contacts ignores
        it).
      contact_slop: the overlap left to the contacts, as `PGS.contact_slop`.
      contact_passes: passes of the contacts' position pass, as `PGS.contact_passes`.
    """

    #: assembles its matrices in user particle order, so `jc.batched_rollout` batches it with `jax.vmap`
    batch_minor = False


    beta: Any = 0.2
    substeps: int = static_field(default=1)
    method: str = static_field(default="auto")
    regularisation: Any = 1e-6
    stabilization: str = static_field(default="baumgarte")
    slop: Any = 0.005
    contact_iterations: int = static_field(default=10)
    contact_slop: Any = contact_rows.CONTACT_SLOP
    contact_passes: Optional[int] = static_field(default=None)

    supports_contacts = True

    def __post_init__(self):
        check_stabilization("Direct", self.stabilization)
        check_int("Direct", "contact_iterations", self.contact_iterations, 1)
        check_scalar("Direct", "contact_slop", self.contact_slop, 0.0, 0.5)
        if self.contact_passes is not None:
            check_int("Direct", "contact_passes", self.contact_passes, 1)
        check_scalar("Direct", "slop", self.slop, 0.0, 1.0)
        check_scalar("Direct", "beta", self.beta, 0.0, 1.0)
        check_int("Direct", "substeps", self.substeps, 1)
        check_scalar("Direct", "regularisation", self.regularisation, 0.0, 1.0)
        if self.method not in _METHODS:
            raise ValueError(f"Direct: `method` must be one of {_METHODS}, got {self.method!r}")

    def _use_tridiagonal(self, topo) -> bool:
        chain = is_simple_chain(topo)
        if self.method == "tridiagonal" and not chain:
            raise ValueError(
                "Direct: method='tridiagonal' needs a simple chain (constraint k joining particles k and "
                "k+1 for every k); use method='dense' or 'auto' for this model"
            )
        return chain and self.method != "dense" and topo.m >= _TRIDIAGONAL_FROM

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), self.substeps, x, v, lam, dt)

    def _exact(self, sys, h):
        """The exact solve of every constraint row over a (sub)step of length h: (xu, vu) [n, dim], user order,
        -> (lam [m] user order, (velocity change, and with split impulses the position correction) [n, dim] user
        order); None without constraints. Rods and ropes alone: the tridiagonal chain or dense pair solve; with
        constraint sets, every row's Jacobian assembled densely in user order (`_rows_solve`): rods as above, a
        set's compliant rows with alpha / h^2 on their diagonal (implicit springs) and bias C / h."""
        topo = sys.topology
        if not topo.m:
            return None
        dtype = sys.w.dtype
        beta = jnp.asarray(self.beta, dtype)
        w = L.per_particle_out(topo, sys.w)
        rest = L.constraints_out(topo, sys.rest)
        eps = _regularisation(self.regularisation, dtype)
        slop = jnp.asarray(self.slop, dtype) if self.stabilization == "split" else None
        if topo.has_sets:
            sets = _user_sets(sys)
            return lambda xu, vu: _rows_solve(xu, vu, w, rest[: topo.m_pairs], sets, topo, beta, h, eps, slop)
        solve = _chain_solve if self._use_tridiagonal(topo) else functools.partial(_dense_solve, topo=topo)
        return lambda xu, vu: solve(xu, vu, w, rest, beta / h, eps, h, _unilateral(topo), slop=slop)

    def _substep(self, sys, x, v, lam_ws, h, found=None):
        """One (sub)step for every model: gravity, the exact solve of every constraint row (no warm start: the
        solve is exact), and x += h v (with split impulses, plus the last solve's position correction). With
        contacts, the contact kind's stages as in `PGS` (`common.step_begin`, `solve_phases`, `step_end`; a grid
        model's candidate pairs `found` from `grid_substepped`), their sweeps alternating with the exact solve
        (class docstring). Without contacts the solve runs once, and the positions are those of the step
        before contacts existed."""
        topo, cs = sys.topology, sys.contact
        dtype = x.dtype
        slop = jnp.asarray(self.contact_slop, dtype)
        blocks, imp_ws = split_contacts(sys, lam_ws)
        cold = with_contacts(sys, jax.tree.map(jnp.zeros_like, blocks), imp_ws)      # no constraint warm start
        b = step_begin(sys, x, v, cold, jnp.asarray(self.beta, dtype), h, None, cs is not None, 1.0, True, found,
                       slop)
        exact, xu = self._exact(sys, h), L.particles_out(topo, x)

        def project(v, dvs):
            """v less the last exact solve's velocity change dvs[0], solved again: (v, lam, dvs)."""
            if exact is None:
                return v, None, dvs
            free = L.particles_out(topo, v) - dvs[0]
            lam_u, dvs = exact(xu, free)
            return L.particles_in(topo, free + dvs[0]), lam_u, dvs

        v, lam_u, dvs = project(b.v, (jnp.zeros_like(xu),))
        imp = b.imp
        if cs is not None:
            def sweeps(obs, pairs):
                def sweep(carry):
                    v, lam_u, dvs, imp = carry
                    v, imp = contact.sweep(cs, sys.w, v, obs, pairs, imp)
                    return project(v, dvs) + (imp,)
                return sweep

            v, lam_u, dvs, imp = solve_phases(sys, b.v_free, b.obs, b.pairs, self.contact_iterations,
                                              (v, lam_u, dvs, imp), sweeps, slot_major=True)
            # the restitution guard mixes the two phases' ends: exact for rods (the rows are linear), not for a
            # unilateral row whose activity differs between them, so the constraints are solved once more
            v, lam_u, dvs = project(v, dvs)
        lam = b.lam if lam_u is None else L.constraints_in(topo, lam_u)
        if cs is None:              # split impulses: the excess's correction, as a velocity over the step
            move = v if len(dvs) < 2 else v + L.particles_in(topo, dvs[1] / h)
            return x + h * move, v, lam
        moved = None if len(dvs) < 2 else (lambda x: x + L.particles_in(topo, dvs[1]))
        x = step_end(sys, x, v, b.v_free, b.obs, b.pairs, imp, h, passes=self.contact_passes, rods_pass=moved,
                     contact_slop=slop)
        return x, v, with_contacts(sys, lam, imp)


def _user_sets(sys):
    """Per constraint set: ((fn, grad), particles [m, k] user indices, params {[m, ...]}, compliance [m]) in user
    order, from the system's layout (a table, or one block per colour)."""
    out = []
    blocks = [b for b in sys.topology.blocks if b.generic is not None]
    for s, (info, con) in enumerate(zip(sys.topology.sets, sys.cons)):
        mine = [(b, ssys) for b, ssys in zip(blocks, sys.sets) if b.generic == s]
        src = np.concatenate([b.src.array.reshape(-1)[b.flat.array] for b, _ in mine])
        order = np.argsort(src, kind="stable")                   # user order within the set

        def user(*a):
            flat = [x.reshape(x.shape[: x.ndim - len(b.shape)] + (-1,))[..., b.flat.array]
                    for x, (b, _) in zip(a, mine)]
            return jnp.moveaxis(jnp.concatenate(flat, axis=-1)[..., order], -1, 0)
        out.append(((con.fn, con.grad), info.particles, jax.tree.map(user, *[ssys.params for _, ssys in mine]),
                    user(*[ssys.compliance for _, ssys in mine])))
    return out


def _rows_solve(xu, vu, w, rest, sets, topo, beta, h, eps, slop):
    """One dense solve over every row (rods and sets) of (J M^-1 J^T + Gamma) lam = J v + bias, Gamma =
    alpha / h^2 on a set's compliant rows (their bias C / h; the others beta / h C; a slack unilateral row C / h),
    a complementarity solve where some rows are unilateral (`_complementarity`). With split impulses' `slop`
    (the share), a rod's C beyond its adaptive slop (`_rhs`) moves to a second right-hand side, h beta / h C, the
    position correction; a set's rows have no length scale and keep Baumgarte's bias. Returns (lam [m] user
    order, velocity changes as `_dense_solve`)."""
    n, dim = xu.shape
    J, C, alpha = _all_rows(xu, rest, sets, topo)
    J = J.reshape(-1, n * dim)
    wd = jnp.repeat(w, dim)
    A = (J * wd) @ J.T
    diag = jnp.diagonal(A)
    ok = diag > 0
    g = alpha / (h * h)
    A = jnp.where(ok[:, None] & ok[None, :], A, 0) + jnp.diag(jnp.where(ok, eps * diag + g, 1))
    rel = -(J @ vu.reshape(-1))
    corr = jnp.where(alpha > 0, C / h, beta / h * C)
    uni = _unilateral(topo)
    slack = _slack(uni, C)
    corr = jnp.where(slack, C / h, corr)
    if slop is None:
        cols = [rel + corr]
    else:
        inside = jnp.ones(C.shape, bool)
        if topo.m_pairs:
            i, j, mp = topo.i, topo.j, topo.m_pairs
            dist, nrm = L.safe_norm(xu[j] - xu[i], axis=-1)
            u = vu[j] - vu[i]
            ut = u - nrm * jnp.sum(u * nrm, -1, keepdims=True)
            steady = h * h * jnp.sum(ut * ut, -1) * L.safe_reciprocal(dist * jnp.maximum(beta, 1e-3))
            rod_in = jnp.abs(C[:mp]) <= jnp.clip(steady, slop * rest, 0.1 * rest)
            inside = inside.at[:mp].set(rod_in)
        inside = inside | slack
        cols = [rel + jnp.where(inside, corr, 0), h * jnp.where(inside, 0, corr)]
    lams = _columns(_dense_on, jnp.matmul, jnp.diagonal, A, [jnp.where(ok, c, 0) for c in cols], uni, slack & ok, h)
    changes = tuple((J.T @ lams[:, c]).reshape(n, dim) * w[:, None] for c in range(lams.shape[1]))
    return lams[:, 0], changes


def _unilateral(topo):
    """bool [m] in user order: the unilateral rows (ropes, then each unilateral set's rows), or None if none."""
    uni = np.concatenate([topo.is_rope] + [np.full(len(s.particles), s.unilateral) for s in topo.sets])
    return uni if uni.any() else None


def _slack(uni, C):
    """The slack unilateral rows: `uni` (`_unilateral`, or None) where C_lib < 0; they get the speculative bias
    C / h, and in split impulses' position correction what the velocity solve leaves of their slack
    (`_columns`)."""
    return np.zeros(C.shape, bool) if uni is None else jnp.asarray(uni) & (C < 0)


def _columns(solve_on, mul, diag, A, cols, uni, slack, h):
    """`_complementarity` of the right-hand sides `cols`; with split impulses' two (velocity, position), the
    position one is solved after the velocity one, and a slack unilateral row (`slack`) may take in it the slack
    the velocity solve leaves it, C_lib + h (rate after the velocity impulses) = -h r_v (r_v = A lam_v - b_v >= 0
    where the velocity solve leaves it inactive, 0 where it closes the gap): the position correction may close
    what is left of the gap and no more. (It was 0, so a slack row resisted any stretching in the position
    correction as if taut: with a unilateral set, a chain landing on the floor diverged, a review's case.)"""
    if len(cols) == 1 or uni is None:
        return _complementarity(solve_on, mul, diag, A, cols, uni)
    lam_v = _complementarity(solve_on, mul, diag, A, cols[:1], uni)
    r_v = mul(A, lam_v[:, 0]) - cols[0]
    lam_p = _complementarity(solve_on, mul, diag, A, [jnp.where(slack, -h * r_v, cols[1])], uni)
    return jnp.concatenate([lam_v, lam_p], 1)


def _dense_on(A, act, b):
    """Solve the dense system A lam = b restricted to the rows `act` (lam = 0 on the others)."""
    if act is None:
        return jnp.linalg.solve(A, b)
    A = jnp.where(act[:, None] & act[None, :], A, 0) + jnp.diag(jnp.where(act, 0, 1).astype(A.dtype))
    return jnp.linalg.solve(A, jnp.where(act, b, 0))


def _tridiagonal_on(A, act, b):
    """`_dense_on` for a tridiagonal A = (dl, d, du) (`lax.linalg.tridiagonal_solve`'s bands)."""
    dl, d, du = A
    if act is not None:
        up, down = jnp.roll(act, -1), jnp.roll(act, 1)
        dl, d, du = jnp.where(act & down, dl, 0), jnp.where(act, d, 1), jnp.where(act & up, du, 0)
        b = jnp.where(act, b, 0)
    return tridiagonal_solve(dl, d, du, b[:, None])[:, 0]


def _tridiagonal_mul(A, lam):
    dl, d, du = A
    zero = jnp.zeros((1,), lam.dtype)
    return d * lam + dl * jnp.concatenate([zero, lam[:-1]]) + du * jnp.concatenate([lam[1:], zero])


def _complementarity(solve_on, mul, diag, A, cols, uni):
    """lam [m, len(cols)]: per right-hand side b in `cols`, the solution of A lam = b where no row is unilateral
    (`uni` None), else of the linear complementarity problem on the unilateral rows: lam >= 0, r = A lam - b
    >= 0 and lam r = 0 there, A lam = b on the others. `solve_on(A, act, b)` solves on the rows `act` with
    lam = 0 elsewhere; `mul(A, lam)` is A lam; `diag(A)` is A's diagonal. A row counts as infeasible when its lam
    or residual is negative beyond 1e3 machine epsilons of its own terms' size.

    Block principal pivoting (Judice and Pires 1994): start with every row active, and swap every infeasible
    unilateral row (an active one with lam < 0, an inactive one with r < 0) at once while that lowers the count of
    infeasible rows, or did within the last 3 pivots; otherwise swap only the infeasible row of largest index
    (Murty's rule, finite for the P-matrix A is: symmetric positive definite with its regularisation). The
    pivoting carries no gradient; the returned lam solves the final active set, differentiably. The first solve
    (every row active) is differentiable itself and is the answer where it is feasible: one solve."""
    if uni is None:
        return jnp.stack([solve_on(A, None, b) for b in cols], -1)
    limit = 4 * int(np.sum(uni)) + 8                  # pivots at most (uni: static)
    uni = jnp.asarray(uni)
    m = uni.shape[0]
    As = jax.tree.map(lax.stop_gradient, A)

    absA = jax.tree.map(jnp.abs, As)
    eps, tiny = 1e3 * jnp.finfo(cols[0].dtype).eps, jnp.finfo(cols[0].dtype).tiny

    def infeasible(act, b, lam=None):
        lam = solve_on(As, act, b) if lam is None else lam
        r = mul(As, lam) - b
        # per row, against the size of the terms the row's residual sums (|b| + |A| |lam|): one scale for the
        # whole model let a float32 rope stretch to its whole length beside an unrelated row of large values
        scale = jnp.abs(b) + mul(absA, jnp.abs(lam)) + tiny
        return uni & jnp.where(act, lam * diag(absA) < -eps * scale, r < -eps * scale)

    def pivoted(b, bad):
        """The final active set's solve, pivoting from every row active (whose infeasible rows are `bad`)."""
        bs = lax.stop_gradient(b)

        def pivot(carry):
            it, act, bad, best, grace = carry
            count = jnp.sum(bad)
            block = (count < best) | (grace > 0)
            last = jnp.arange(m) == jnp.max(jnp.where(bad, jnp.arange(m), -1))
            act = act ^ jnp.where(block, bad, last)
            grace = jnp.where(count < best, 3, grace - 1)
            return it + 1, act, infeasible(act, bs), jnp.minimum(best, count), grace

        carry = (0, jnp.ones(m, bool), bad, m + 1, 3)
        act = lax.while_loop(lambda c: (c[0] < limit) & jnp.any(c[2]), pivot, carry)[1]
        return solve_on(A, act, b)

    lams = []
    for b in cols:
        # every row active first, solved with its gradient: where that is feasible (a taut rope, a pressed floor)
        # it is the answer, one solve; else the pivoting (`lax.cond`: under `vmap` both run)
        lam = solve_on(A, None, b)
        bad = infeasible(jnp.ones(m, bool), lax.stop_gradient(b), lax.stop_gradient(lam))
        lam = lax.cond(jnp.any(bad), lambda bad: pivoted(b, bad), lambda _: lam, bad)
        lams.append(jnp.where(uni, jnp.maximum(lam, 0), lam))
    return jnp.stack(lams, -1)


def _all_rows(xu, rest, sets, topo, values=False):
    """Every row at positions xu [n, dim], user order: (J [m, n, dim] of each row's C_user (a rod's
    L - |x_j - x_i|), C_lib [m], compliance [m]); with `values`, C_lib alone."""
    n, dim = xu.shape
    rows_J, rows_C, rows_a = [], [], []
    if topo.m_pairs:
        i, j = topo.i, topo.j
        dist, nrm = L.safe_norm(xu[j] - xu[i], axis=-1)
        rows_C.append(dist - rest)
        if not values:
            Jp = jnp.zeros((topo.m_pairs, n, dim), xu.dtype).at[np.arange(topo.m_pairs), i].set(nrm)
            rows_J.append(Jp.at[np.arange(topo.m_pairs), j].set(-nrm))
            rows_a.append(jnp.zeros(topo.m_pairs, xu.dtype))
    for (fn, grad), parts, params, comp in sets:
        C, J, _ = R.evaluate(fn, xu[parts], params, grad)
        rows_C.append(-C)
        if not values:
            rows_J.append(jnp.zeros((len(parts), n, dim), xu.dtype).at[np.arange(len(parts))[:, None], parts].add(J))
            rows_a.append(comp)
    if values:
        return jnp.concatenate(rows_C)
    return jnp.concatenate(rows_J), jnp.concatenate(rows_C), jnp.concatenate(rows_a)


@functools.lru_cache(maxsize=64)
def _coupling(topo):
    """Static sparsity of J M^-1 J^T: every (a, b, p, sign) with constraints a and b both touching particle p,
    sign = s_ap s_bp where s = -1 at a constraint's first endpoint and +1 at its second. Computed once per
    topology (topologies hash by content), not at every trace."""
    i, j, m = topo.i, topo.j, topo.m
    ends = np.concatenate([i, j])
    cons = np.concatenate([np.arange(m), np.arange(m)])
    sgn = np.concatenate([-np.ones(m), np.ones(m)])
    order = np.argsort(ends, kind="stable")
    ends, cons, sgn = ends[order], cons[order], sgn[order]
    a, b, p, s = [], [], [], []
    starts = np.flatnonzero(np.r_[True, ends[1:] != ends[:-1]])
    stops = np.r_[starts[1:], len(ends)]
    for lo, hi in zip(starts, stops):
        ca, sa = cons[lo:hi], sgn[lo:hi]
        a.append(np.repeat(ca, hi - lo))
        b.append(np.tile(ca, hi - lo))
        s.append(np.repeat(sa, hi - lo) * np.tile(sa, hi - lo))
        p.append(np.full((hi - lo) ** 2, ends[lo]))
    return tuple(np.concatenate(x) for x in (a, b, p, s))


def _dense_solve(xu, vu, w, rest, rate, eps, h, uni, *, topo, slop=None):
    """One dense solve of J W J^T lam = b (a complementarity solve where `uni` marks unilateral rows). The matrix
    is assembled entry by entry from the pairs of constraints that share a particle (O(sum of squared degrees),
    not O(m^2 n)); the solve is O(m^3). Returns (lam, velocity changes): one change (-W J^T lam) for Baumgarte,
    or, with split impulses' `slop`, the velocity change (the bias of C clipped to the slop) and the correction of
    the rest (a position change), each its own right-hand side (`_rhs`)."""
    i, j, m = topo.i, topo.j, topo.m
    dist, nrm = L.safe_norm(xu[j] - xu[i], axis=-1)          # [m], [m, dim]
    ok = ((w[i] + w[j]) > 0) & (dist > 0)
    ca, cb, cp, sg = _coupling(topo)
    vals = jnp.asarray(sg, xu.dtype) * w[cp] * jnp.sum(nrm[ca] * nrm[cb], -1)
    A = jnp.zeros((m, m), xu.dtype).at[ca, cb].add(vals)   # J W J^T (no sqrt(w): finite gradients at w = 0)
    both = ok[:, None] & ok[None, :]
    diag = jnp.diagonal(A)
    A = jnp.where(both, A, 0) + jnp.diag(jnp.where(ok, eps * diag, 1))
    cols = _rhs(ok, nrm, vu[j] - vu[i], dist - rest, rest, rate, h, uni, slop)
    slack = _slack(uni, dist - rest) & ok
    lams = _columns(_dense_on, jnp.matmul, jnp.diagonal, A, cols, uni, slack, h)              # [m, 1 or 2]

    def change(lam):
        p = nrm * lam[:, None]                                   # J^T lam: -p at i, +p at j
        return -w[:, None] * jnp.zeros_like(vu).at[i].add(-p).at[j].add(p)

    return lams[:, 0], tuple(change(lams[:, c]) for c in range(lams.shape[1]))


def _rhs(ok, nrm, u, C, rest, rate, h, uni, slop):
    """The right-hand sides [[m]]: J v + rate C (u: the relative velocities [m, dim]; rate = beta / h), or with
    split impulses' `slop` (the share) two: J v + rate C where |C| is within each rod's slop (as
    `common.split_slop`: twice its rotation's steady Baumgarte error, at least share L, at most L / 10), and
    beta C where it is beyond (a position change: the exact linear correction, at Baumgarte's rate, gentler
    where J M^-1 J^T is nearly singular, as on a cloth with shear rods). A slack rope (`uni`, C < 0) has the
    speculative bias C / h, and in the position column what the velocity solve leaves of its slack
    (`_columns`)."""
    rel = jnp.sum(u * nrm, -1)
    slack = _slack(uni, C)
    bias = jnp.where(slack, C / h, rate * C)
    if slop is None:
        cols = [rel + bias]
    else:
        ut = u - nrm * jnp.sum(u * nrm, -1, keepdims=True)
        dist = C + rest
        steady = h * jnp.sum(ut * ut, -1) * L.safe_reciprocal(dist * jnp.maximum(rate, 1e-3 / h))
        inside = (jnp.abs(C) <= jnp.clip(steady, slop * rest, 0.1 * rest)) | slack
        cols = [rel + jnp.where(inside, bias, 0), h * rate * jnp.where(inside, 0, C)]
    return [jnp.where(ok, c, 0) for c in cols]


def _chain_solve(xu, vu, w, rest, rate, eps, h, uni, *, slop=None):
    """`_dense_solve` for a simple chain, in O(n) (tridiagonal)."""
    # Constraint k joins particle k and k+1; n_k points from k to k+1 (lam is orientation-independent).
    dist, nrm = L.safe_norm(xu[1:] - xu[:-1], axis=-1)        # [m], [m, dim]
    ok = ((w[:-1] + w[1:]) > 0) & (dist > 0)
    diag = w[:-1] + w[1:]
    off = -w[1:-1] * jnp.sum(nrm[:-1] * nrm[1:], -1)          # A[k, k+1] = A[k+1, k]
    off = jnp.where(ok[:-1] & ok[1:], off, 0)
    zero = jnp.zeros((1,), xu.dtype)
    bands = (jnp.concatenate([zero, off]), jnp.where(ok, diag * (1 + eps), 1), jnp.concatenate([off, zero]))
    cols = _rhs(ok, nrm, vu[1:] - vu[:-1], dist - rest, rest, rate, h, uni, slop)
    lams = _columns(_tridiagonal_on, _tridiagonal_mul, lambda a: a[1], bands, cols, uni,
                    _slack(uni, dist - rest) & ok, h)

    def change(lam):
        p = nrm * lam[:, None]                                     # [m, dim]
        pad = jnp.zeros((1, p.shape[1]), p.dtype)
        return w[:, None] * (jnp.concatenate([p, pad]) - jnp.concatenate([pad, p]))

    return lams[:, 0], tuple(change(lams[:, c]) for c in range(lams.shape[1]))
