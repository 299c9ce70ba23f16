"""Contacts at position level, for XPBD (Mueller et al. 2020, "Detailed rigid body simulation with extended
position based dynamics"; Macklin et al. 2019, "Small steps in physics simulation").

Per substep of length h, from positions x and predicted positions p = x + h (v + h g):

* `project` (once per solver iteration, after the rod and rope colours): every contact with gap C(p) is a
  rigid (compliance 0) unilateral constraint. Its position multiplier lam_n (kg m, accumulated over the
  iterations, clamped >= 0) changes by -C / (w_i + w_j): an overlap is pushed out, and a contact pushed out
  too far by an earlier row gives some of it back. Then **static friction**: the relative tangential
  displacement of the two bodies over the substep, dx_t, is cancelled (lam_t -= dx_t / (w_i + w_j)) when the
  resulting |lam_t| <= mu lam_n; otherwise nothing is added (the kinetic part is the velocity pass's), and a
  lam_t left above a cone that shrank is scaled back onto it. Obstacles are solved one after another, each
  for all particles at once; pairs round by round (a loop over the rounds, as `contact.sweep`), a grid
  model's pairs slot by slot (`_grid_project`).
* `velocity_pass` (once, after v = (p - x) / h): each contact with lam_n > 0 gets one velocity row, solved by
  `contact.sweep` starting from the position impulses lam / h: the normal velocity is set to
  max(-e vn_before, 0) (restitution; vn_before is the normal relative velocity at the start of the substep
  after gravity, e = 0 when |vn_before| <= the restitution threshold), with the total normal impulse of the
  substep kept >= 0, then **dynamic friction** removes the tangential relative velocity with a total friction
  impulse clamped to the Coulomb disc mu * (total normal impulse). Where the velocity row adds no normal impulse
  and static friction did not hold, that is Mueller et al.'s eq. 30, |dv_t| = min(mu lam_n / h (w_i + w_j),
  |v_t|); the clamp on the total makes every reported impulse satisfy |lam_t| <= mu lam_n.

The substep's reported impulses (N s) are the velocity pass's totals: lam / h plus the velocity rows.
"""
from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from jaxcon.core import layout as L
from jaxcon.solvers import contact
from jaxcon.solvers.contact import ContactSystem, Impulses, Rows


def obstacle_gap(cs: ContactSystem, q: int, p, x=None):
    """(unit normal [dim, *view], gap [*view]) of every particle at `p` against obstacle q (planes first).
    With the substep's start positions `x`, a particle that started inside a sphere keeps the normal it had
    there (`contact.overlap_normal`)."""
    dim, nview = p.shape[0], p.ndim - 1
    r = cs.radius[0]
    if q < cs.ct.n_planes:
        nrm = jnp.broadcast_to(cs.plane_normal[q].reshape((dim,) + (1,) * nview), p.shape)
        return nrm, jnp.sum(nrm * p, 0) - cs.plane_offset[q] - r
    s = q - cs.ct.n_planes
    c = cs.sphere_centre[s].reshape((dim,) + (1,) * nview)
    if x is not None:
        return contact.overlap_normal(x - c, p - c, cs.sphere_radius[s] + r)
    dist, nrm = contact.direction(p - c)
    return nrm, dist - cs.sphere_radius[s] - r


def _pair_gap(cs: ContactSystem, pf, r, xf):
    """(unit normal [dim, S] from i to j, gap [S]) of pair round r at flat positions pf [dim, n], the substep
    having started at xf (`contact.overlap_normal`)."""
    ct = cs.ct
    i, j = jnp.asarray(ct.i.array)[r], jnp.asarray(ct.j.array)[r]
    return contact.overlap_normal(xf[:, j] - xf[:, i], pf[:, j] - pf[:, i], cs.radius_flat[i] + cs.radius_flat[j])


def _position_row(disp, n, C, k, mu, ln, lt):
    """One contact at position level: normal multiplier (accumulated, >= 0), then static friction. `disp` is
    the second body's displacement over the substep relative to the first, k = 1 / (w_i + w_j) (0: no row).
    Returns (position impulse change P [dim, ...] on the second body, new lam_n, new lam_t)."""
    new_n = jnp.maximum(ln - C * k, 0)
    disp_t = disp - n * jnp.sum(disp * n, 0)
    stick = lt - disp_t * k
    limit = mu * new_n
    length, _ = L.safe_length(stick)
    held, inv = L.safe_length(lt)
    kept = lt * jnp.where(held > limit, limit * inv, 1)
    new_t = jnp.where(length <= limit, stick, kept)
    return n * (new_n - ln) + (new_t - lt), new_n, new_t


def project(cs: ContactSystem, w, x, p, imp: Impulses, partners=None):
    """One position-level pass over every contact (module docstring): obstacles, then the pair rounds (a grid
    model's `partners` [n, K]: its slots, `_grid_project`). x: positions at the start of the substep, p:
    current positions [dim, *view]; imp: position multipliers (kg m) accumulated in this substep. Returns
    (p, imp)."""
    ct, mu = cs.ct, cs.friction
    on, ot = imp.obs_n, imp.obs_t
    if ct.n_obstacles:
        on, ot = list(on), list(ot)
        k = L.safe_reciprocal(w[0])
        for q in range(ct.n_obstacles):
            n, C = obstacle_gap(cs, q, p, x)
            P, on[q], ot[q] = _position_row(p - x, n, C, k, mu, on[q], ot[q])
            p = p + w * P
        on, ot = jnp.stack(on), jnp.stack(ot)
    pn, pt = imp.pair_n, imp.pair_t
    if ct.n_pairs:
        dim, shape = p.shape[0], p.shape
        ia, ja = jnp.asarray(ct.i.array), jnp.asarray(ct.j.array)
        valid = jnp.asarray(ct.valid.array, p.dtype)
        wf, xf = w.reshape(-1), x.reshape(dim, -1)

        def one_round(r, carry):
            pf, pn, pt = carry
            i, j = ia[r], ja[r]
            n, C = _pair_gap(cs, pf, r, xf)
            disp = (pf[:, j] - xf[:, j]) - (pf[:, i] - xf[:, i])
            k = L.safe_reciprocal(wf[i] + wf[j]) * valid[r]
            P, ln, lt = _position_row(disp, n, C, k, mu, pn[r], pt[:, r])
            pf = contact._pair_apply(ct, pf, r, wf[i], wf[j], P)
            return pf, pn.at[r].set(ln), pt.at[:, r].set(lt)

        pf, pn, pt = lax.fori_loop(0, ct.rounds, one_round, (p.reshape(dim, -1), pn, pt))
        p = pf.reshape(shape)
    elif ct.has_grid:
        p, pn, pt = _grid_project(cs, w, x, p, partners, pn, pt)
    return p, imp._replace(obs_n=on, obs_t=ot, pair_n=pn, pair_t=pt)


def _grid_project(cs: ContactSystem, w, x, p, partners, pn, pt):
    """`project`'s pass over a grid model's pairs, slot by slot as `contact.grid_pass`: the rows of one slot
    (one per particle, whose partners may repeat) are projected together from the same positions, relaxed by
    mass splitting (k = 1 / (c_i w_i + c_j w_j), c the slot's rows at each particle that push or overlap), and
    the slots follow one another in a `lax.scan`; a slot no particle uses is skipped. Returns (p, pair_n
    [n, K], pair_t [dim, n, K])."""
    dim, shape = p.shape[0], p.shape
    wf, xf, r = w.reshape(-1), x.reshape(dim, -1), cs.radius_flat

    def one_slot(pf, xs):
        j, ln, lt = xs

        def solve(pf):
            jc = jnp.maximum(j, 0)
            n, C = contact.overlap_normal(xf[:, jc] - xf, pf[:, jc] - pf, r + r[jc])
            disp = (pf[:, jc] - xf[:, jc]) - (pf - xf)
            act = ((j >= 0) & ((C < 0) | (ln > 0))).astype(pf.dtype)
            c = act + jnp.zeros_like(act).at[jc].add(act)
            k = L.safe_reciprocal(c * wf + c[jc] * wf[jc]) * act
            P, new_n, new_t = _position_row(disp, n, C, k, cs.friction, ln, lt)
            return pf.at[:, jc].add(wf[jc] * P) - wf * P, (new_n, new_t)

        return lax.cond(jnp.any(j >= 0), solve, lambda pf: (pf, (ln, lt)), pf)

    xs = (contact.slot_major(partners), contact.slot_major(pn), contact.slot_major(pt))
    pf, (pn, pt) = lax.scan(one_slot, p.reshape(dim, -1), xs)
    return pf.reshape(shape), jnp.moveaxis(pn, 0, -1), jnp.moveaxis(pt, 0, -1)


def _target(cs: ContactSystem, vn_before):
    """Restitution target of the velocity pass: max(-e vn_before, 0), e = 0 at or below the threshold."""
    e = jnp.where(jnp.abs(vn_before) > cs.threshold, cs.restitution, 0)
    return jnp.maximum(-e * vn_before, 0)


def velocity_rows(cs: ContactSystem, w, p, v_before, imp: Impulses, partners=None):
    """Velocity rows (obstacle Rows or None, pair Rows or None) at the end of the position solve: normals and
    gaps at `p`, restitution targets from `v_before` (start of the substep, after gravity), and effective
    masses only for contacts that pushed in this substep (lam_n > 0; the others get k = 0, no impulse). A grid
    model's pair rows are its `partners`' slots [n, K]."""
    ct, dim = cs.ct, p.shape[0]
    obs = pairs = None
    if ct.n_obstacles:
        ns, Cs = zip(*(obstacle_gap(cs, q, p) for q in range(ct.n_obstacles)))
        n, C = jnp.stack(ns), jnp.stack(Cs)
        winv = jnp.broadcast_to(w[0], C.shape)
        k = L.safe_reciprocal(winv) * (imp.obs_n > 0).astype(C.dtype)
        obs = Rows(n, _target(cs, jnp.sum(n * v_before[None], 1)), k, winv, jnp.zeros_like(C), C)
    if ct.n_pairs or ct.has_grid:
        pf, vf, wf = p.reshape(dim, -1), v_before.reshape(dim, -1), w.reshape(-1)
        ia, ja, valid, _ = contact.pair_slots(ct, pf.shape[1], partners)
        dist, n = contact.direction(pf[:, ja] - pf[:, ia])
        C = dist - cs.radius_flat[ia] - cs.radius_flat[ja]
        winv = wf[ia] + wf[ja]
        k = L.safe_reciprocal(winv) * jnp.asarray(valid, winv.dtype) * (imp.pair_n > 0).astype(C.dtype)
        vn = jnp.sum(n * (vf[:, ja] - vf[:, ia]), 0)
        pairs = Rows(n, _target(cs, vn), k, winv, jnp.zeros_like(C), C)
        if partners is not None:
            pairs = pairs._replace(i=ia, j=partners)
    return obs, pairs


def velocity_pass(cs: ContactSystem, w, p, v_before, v, imp: Impulses, h, partners=None):
    """Restitution and dynamic friction (module docstring) on v = (p - x) / h. `imp` holds the substep's
    position multipliers (kg m). Returns (v, the substep's contact impulses in N s)."""
    obs, pairs = velocity_rows(cs, w, p, v_before, imp, partners)
    start = imp._replace(**{f: getattr(imp, f) / h for f in ("obs_n", "obs_t", "pair_n", "pair_t")})
    return contact.sweep(cs, w, v, obs, pairs, start)
