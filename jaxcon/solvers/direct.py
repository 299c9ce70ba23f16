"""Direct solver: all multipliers of a (sub)step at once from one linear solve."""
from __future__ import annotations

import functools

import jax
from typing import Any

import jax.numpy as jnp
import numpy as np
from jax.lax.linalg import tridiagonal_solve

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import pytree_dataclass, static_field
from jaxcon.core.substeps import substepped
from jaxcon.core.system import Solver
from jaxcon.solvers.common import check_stabilization

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
    solvable. Ropes are not supported
    (a unilateral constraint needs a complementarity solve): use PGS, SoftStep or RATTLE for ropes.

    The warm-start input is not used (the solve is exact).

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
    """

    #: assembles its matrices in user particle order, so `jc.batched_rollout` batches it with `jax.vmap`
    batch_minor = False


    beta: Any = 0.2
    substeps: int = static_field(default=1)
    method: str = static_field(default="auto")
    regularisation: Any = 1e-6
    stabilization: str = static_field(default="baumgarte")
    slop: Any = 0.005

    def __post_init__(self):
        check_stabilization("Direct", self.stabilization)
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
        topo = sys.topology
        if topo.has_ropes or any(info.unilateral for info in topo.sets):
            raise ValueError(
                "Direct: the model has ropes or unilateral constraints, which Direct does not take (an "
                "inequality needs a complementarity solve); use jc.PGS, jc.SoftStep or jc.RATTLE"
            )
        if topo.has_sets:
            return self._step_rows(sys, x, v, lam, dt)
        tri = self._use_tridiagonal(topo)
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        w = L.per_particle_out(topo, sys.w)       # user order, like the states below
        rest = L.constraints_out(topo, sys.rest)
        eps = _regularisation(self.regularisation, dtype)

        split = self.stabilization == "split"
        share = jnp.asarray(self.slop, dtype)

        def substep(x, v, _lam, h):
            v = sys.apply_gravity(v, h)
            xu, vu = L.particles_out(topo, x), L.particles_out(topo, v)  # [n, dim], user order
            solve = _chain_solve if tri else functools.partial(_dense_solve, topo=topo)
            lam_u, dvs = solve(xu, vu, w, rest, beta / h, eps, slop=(share, h) if split else None)
            v = L.particles_in(topo, vu + dvs[0])
            move = v if not split else v + L.particles_in(topo, dvs[1] / h)    # split: the excess's correction
            return x + h * move, v, L.constraints_in(topo, lam_u)

        return substepped(substep, self.substeps, x, v, lam, dt)


    def _step_rows(self, sys, x, v, lam, dt):
        """The step of a model with constraint sets: every row's Jacobian assembled densely in user order
        (`_rows_solve`); rods as above, a set's compliant rows with alpha / h^2 on their diagonal (implicit
        springs) and bias C / h."""
        topo = sys.topology
        dtype = x.dtype
        beta = jnp.asarray(self.beta, dtype)
        w = L.per_particle_out(topo, sys.w)
        rest = L.constraints_out(topo, sys.rest)[: topo.m_pairs]
        eps = _regularisation(self.regularisation, dtype)
        split = self.stabilization == "split"
        share = jnp.asarray(self.slop, dtype)
        sets = _user_sets(sys)

        def substep(x, v, _lam, h):
            v = sys.apply_gravity(v, h)
            xu, vu = L.particles_out(topo, x), L.particles_out(topo, v)
            lam_u, dvs = _rows_solve(xu, vu, w, rest, sets, topo, beta, h, eps, share if split else None)
            v = L.particles_in(topo, vu + dvs[0])
            move = v if not split else v + L.particles_in(topo, dvs[1] / h)
            return x + h * move, v, L.constraints_in(topo, lam_u)

        return substepped(substep, self.substeps, x, v, lam, dt)


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
    alpha / h^2 on a set's compliant rows (their bias C / h; the others beta / h C). With split impulses' `slop`
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
        cols = [rel + jnp.where(inside, corr, 0), h * jnp.where(inside, 0, corr)]
    lams = jnp.linalg.solve(A, jnp.stack([jnp.where(ok, c, 0) for c in cols], -1))
    changes = tuple((J.T @ lams[:, c]).reshape(n, dim) * w[:, None] for c in range(lams.shape[1]))
    return lams[:, 0], changes


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


def _dense_solve(xu, vu, w, rest, rate, eps, *, topo, slop=None):
    """One dense solve of J W J^T lam = b. The matrix is assembled entry by entry from the pairs of
    constraints that share a particle (O(sum of squared degrees), not O(m^2 n)); the solve is O(m^3).
    Returns (lam, velocity changes): one change (-W J^T lam) for Baumgarte, or, with split impulses' `slop`, the
    velocity change (the bias of C clipped to the slop) and the correction of the rest (a position change),
    from one solve with two right-hand sides (`_rhs`)."""
    i, j, m = topo.i, topo.j, topo.m
    dist, nrm = L.safe_norm(xu[j] - xu[i], axis=-1)          # [m], [m, dim]
    ok = ((w[i] + w[j]) > 0) & (dist > 0)
    ca, cb, cp, sg = _coupling(topo)
    vals = jnp.asarray(sg, xu.dtype) * w[cp] * jnp.sum(nrm[ca] * nrm[cb], -1)
    A = jnp.zeros((m, m), xu.dtype).at[ca, cb].add(vals)   # J W J^T (no sqrt(w): finite gradients at w = 0)
    both = ok[:, None] & ok[None, :]
    diag = jnp.diagonal(A)
    A = jnp.where(both, A, 0) + jnp.diag(jnp.where(ok, eps * diag, 1))
    lams = jnp.linalg.solve(A, _rhs(ok, nrm, vu[j] - vu[i], dist - rest, rest, rate, slop))     # [m, 1 or 2]

    def change(lam):
        p = nrm * lam[:, None]                                   # J^T lam: -p at i, +p at j
        return -w[:, None] * jnp.zeros_like(vu).at[i].add(-p).at[j].add(p)

    return lams[:, 0], tuple(change(lams[:, c]) for c in range(lams.shape[1]))


def _rhs(ok, nrm, u, C, rest, rate, slop):
    """[m, 1] right-hand side J v + rate C (u: the relative velocities [m, dim]; rate = beta / h), or with split
    impulses' `slop` = (share, h) [m, 2]: J v + rate C where |C| is within each rod's slop (as
    `common.split_slop`: twice its rotation's steady Baumgarte error, at least share L, at most L / 10), and
    beta C where it is beyond (a position change: the exact linear correction, at Baumgarte's rate, gentler
    where J M^-1 J^T is nearly singular, as on a cloth with shear rods)."""
    rel = jnp.sum(u * nrm, -1)
    if slop is None:
        cols = [rel + rate * C]
    else:
        share, h = slop
        ut = u - nrm * jnp.sum(u * nrm, -1, keepdims=True)
        dist = C + rest
        steady = h * jnp.sum(ut * ut, -1) * L.safe_reciprocal(dist * jnp.maximum(rate, 1e-3 / h))
        inside = jnp.abs(C) <= jnp.clip(steady, share * rest, 0.1 * rest)
        cols = [rel + rate * jnp.where(inside, C, 0), h * rate * jnp.where(inside, 0, C)]
    return jnp.stack([jnp.where(ok, c, 0) for c in cols], -1)


def _chain_solve(xu, vu, w, rest, rate, eps, *, slop=None):
    """`_dense_solve` for a simple chain, in O(n) (tridiagonal)."""
    # Constraint k joins particle k and k+1; n_k points from k to k+1 (lam is orientation-independent).
    dist, nrm = L.safe_norm(xu[1:] - xu[:-1], axis=-1)        # [m], [m, dim]
    ok = ((w[:-1] + w[1:]) > 0) & (dist > 0)
    diag = w[:-1] + w[1:]
    off = -w[1:-1] * jnp.sum(nrm[:-1] * nrm[1:], -1)          # A[k, k+1] = A[k+1, k]
    off = jnp.where(ok[:-1] & ok[1:], off, 0)
    zero = jnp.zeros((1,), xu.dtype)
    dl = jnp.concatenate([zero, off])
    du = jnp.concatenate([off, zero])
    d = jnp.where(ok, diag * (1 + eps), 1)
    lams = tridiagonal_solve(dl, d, du, _rhs(ok, nrm, vu[1:] - vu[:-1], dist - rest, rest, rate, slop))

    def change(lam):
        p = nrm * lam[:, None]                                     # [m, dim]
        pad = jnp.zeros((1, p.shape[1]), p.dtype)
        return w[:, None] * (jnp.concatenate([p, pad]) - jnp.concatenate([pad, p]))

    return lams[:, 0], tuple(change(lams[:, c]) for c in range(lams.shape[1]))
