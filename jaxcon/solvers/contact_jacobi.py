"""Contacts for `jc.Jacobi`: every contact row and every rod read the same velocities in an iteration.

The rows, warm start, time-of-impact correction and position safety pass are those of PGS
(`jaxcon.solvers.contact`); only the iteration differs. Each Jacobi iteration computes, from the same v, the
update of every rod, every obstacle contact (all obstacles at once) and every pair slot (all rounds at once),
and applies the sum of the impulse changes.

Relaxation (the default, `relaxation=None`): mass splitting (Tonge, Benevolenski and Voroshilov 2012, "Mass
splitting for jitter-free parallel rigid body simulation"), the momentum-conserving form of the constraint
averaging of Macklin et al. 2014. A particle touched by c rows in this iteration (its rods, plus its contacts
that push or are about to) lends each of them 1 / c of its mass: a row between particles i and j takes the
effective mass 1 / (c_i w_i + c_j w_j) instead of 1 / (w_i + w_j), and its impulse is applied with the true
masses. Every row's impulse acts equally and oppositely on its two particles, so momentum is conserved
exactly (per-particle averaging of the velocity changes is not: c_i != c_j). Since the Delassus matrix is
bounded by this diagonal (A = J W J^T <= diag(c_i w_i + c_j w_j), each particle's rows forming a Gram matrix
of unit normals), the iteration converges for any fixed active set. The counts are recomputed in every
iteration, so a particle free of contacts keeps its full mass and a ball wedged in a rack splits it six ways.
A fixed `relaxation` instead scales every row's update (rods and contacts) by that one factor.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.solvers.common import clamp_ropes
from jaxcon.solvers.contact import Impulses, Rows, _pair_total, _solve_row, pair_index


def rod_degree(topo, fr, like):
    """Number of rods and ropes at each particle, [1, *view] (rows with no effective mass left out)."""
    c = jnp.zeros((1,) + like.shape[1:], like.dtype)
    for blk, f in zip(topo.blocks, fr):
        one = (f.k > 0).astype(like.dtype)[None]
        if blk.generic is not None:          # a set's row counts at each of its particles
            c = L.add_rows(topo, blk, c, jnp.broadcast_to(one[:, None], (1,) + f.w.shape))
            continue
        c = L.add_pair(topo, blk, c, one, one)
    return c


def _obstacle_frame(obs: Rows):
    """Obstacle rows with the dim axis first ([dim, Q, *view]), as `_solve_row` wants."""
    return obs._replace(n=jnp.moveaxis(obs.n, 1, 0))


def contact_counts(cs, v, obs: Rows, pairs: Rows, imp: Impulses, base):
    """`base` [1, *view] plus, per particle, the contact rows that push on it in this iteration: those that
    hold an impulse, or whose unrelaxed update from the velocities `v` would give one."""
    ct, c = cs.ct, base
    if obs is not None:
        f = _obstacle_frame(obs)
        vn = jnp.sum(v[:, None] * f.n, 0)
        act = ((imp.obs_n > 0) | (imp.obs_n + (obs.target - vn) * obs.k > 0)) & (obs.k > 0)
        c = c + jnp.sum(act.astype(c.dtype), 0)[None]
    if pairs is not None:
        ia, ja = pair_index(ct, pairs)
        vf = v.reshape(v.shape[0], -1)
        vn = jnp.sum((vf[:, ja] - vf[:, ia]).reshape(pairs.n.shape) * pairs.n, 0)
        act = ((imp.pair_n > 0) | (imp.pair_n + (pairs.target - vn) * pairs.k > 0)) & (pairs.k > 0)
        act = act.astype(c.dtype).reshape(-1)
        flat = c.reshape(-1).at[ia].add(act).at[ja].add(act)
        c = flat.reshape(c.shape)
    return c


def rod_pass(topo, fr, bias, v, lam, count, relax):
    """Jacobi update of every rod and rope from the same `v`: (dv, lam). A row's effective mass is
    1 / (c_i w_i + c_j w_j) with the per-particle counts `count` [1, *view] (mass splitting), or relax * k with
    a fixed relaxation (`count` None)."""
    dv = jnp.zeros_like(v)
    new = []
    for blk, f, b, l in zip(topo.blocks, fr, bias, lam):
        if blk.generic is not None:          # a set's rows: the same update through rows.rel / rows.apply
            if count is None:
                k = relax * f.k
            else:
                c = L.gather_rows(topo, blk, count)[0]
                k = L.safe_reciprocal(jnp.sum(c * f.w * jnp.sum(f.J * f.J, axis=0), axis=0)) * (f.k > 0)
            nl = clamp_ropes(blk, l + (R.rel(topo, blk, f, v) + b) * k)
            dv = R.apply(topo, blk, f, dv, nl - l)
            new.append(nl)
            continue
        vi, vj = L.gather_pair(topo, blk, v)
        rel = jnp.sum((vj - vi) * f.n, axis=0)
        if count is None:
            k = relax * f.k
        else:
            ci, cj = L.gather_pair(topo, blk, count)
            k = L.safe_reciprocal(ci[0] * f.wi + cj[0] * f.wj) * (f.k > 0).astype(f.k.dtype)
        nl = clamp_ropes(blk, l + (rel + b) * k)
        p = f.n * (nl - l)
        dv = L.add_pair(topo, blk, dv, f.wi * p, -f.wj * p)
        new.append(nl)
    return dv, tuple(new)


def contact_pass(cs, w, v, obs: Rows, pairs: Rows, imp: Impulses, count, relax):
    """Jacobi update of every contact row (normal, then friction, as `contact._solve_row`) from the same `v`:
    (dv, imp). Effective masses as in `rod_pass` (an obstacle has no inverse mass: 1 / (c_i w_i))."""
    ct, mu = cs.ct, cs.friction
    dv = jnp.zeros_like(v)
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
        P, pn, pt = _solve_row(vrel, pairs._replace(k=k), mu, pn, pt)
        dv = dv + _pair_total(ct, w, P, -1.0, index).reshape(v.shape)
    return dv, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def iteration(sys, fr, bias, obs: Rows, pairs: Rows, relax):
    """The body of one Jacobi iteration over rods and contacts, (i, (v, lam, imp)) -> (v, lam, imp), for
    `lax.fori_loop`. `relax` None: mass splitting with counts recomputed each iteration; else a fixed factor."""
    topo, cs, w = sys.topology, sys.contact, sys.w
    base = None if relax is not None else rod_degree(topo, fr, w)

    def body(_, carry):
        v, lam, imp = carry
        count = None if relax is not None else contact_counts(cs, v, obs, pairs, imp, base)
        dv_rods, lam = rod_pass(topo, fr, bias, v, lam, count, relax)
        dv_contacts, imp = contact_pass(cs, w, v, obs, pairs, imp, count, relax)
        return v + dv_rods + dv_contacts, lam, imp

    return body
