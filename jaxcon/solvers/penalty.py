"""Penalty (stiff spring) solver: every rod and rope is a damped spring, integrated by symplectic Euler."""
from __future__ import annotations

import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import contact_rows
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.contact import Impulses, zero_impulses
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.solvers import contact
from jaxcon.solvers.common import refuse_hard_sets, run_substeps, split_contacts, with_found

#: The spring tension is clipped to +- STRETCH_CLIP * stiffness * rest_length (constraints with rest length
#: > 0). A stable run never comes near it (it is a 1000% stretch, ten times `jc.diagnose`'s violation limit);
#: above the stability limit it keeps forces bounded, so an unstable run grows only polynomially, stays
#: finite and is reported by `jc.diagnose` instead of overflowing to inf / NaN; once any spring is stretched
#: past the clip, the forces stop carrying gradient (stop_gradient), so derivatives stay finite too.
STRETCH_CLIP = 10.0


@pytree_dataclass
class Penalty(Solver):
    """Rods and ropes as stiff damped springs (no constraint solve), symplectic Euler.

    Per substep of length h = dt / substeps, with n the unit vector from a constraint's first particle to its
    second, C = |x_j - x_i| - L and u = n . (v_j - v_i) the stretching speed, the tension is

        T = stiffness C + damping u         (rod: pulls when T > 0, pushes when T < 0)
        T = max(T, 0) where C > 0, else 0   (rope: resists stretching only)

    then v += h g + h M^-1 J^T T (v_i += w_i n T h, v_j -= w_j n T h) and x += h v.

    Explicit integration is stable only for h below about 2 / omega, omega = sqrt(stiffness (w_i + w_j)) for
    a lone spring, higher for connected ones (see `stability_limit`), and 2 / (damping (w_i + w_j)) for the
    damping term. Above it the run diverges; the tension is clipped
    (see STRETCH_CLIP) so that the blow-up stays finite and `jc.diagnose` flags it as diverged.

    The returned lam is the spring impulse over the step, sum of T h (N s, > 0 tension); the warm start passed
    in is not used (a spring has no iteration to warm start).

    Contacts (a model with `planes`, `spheres` or `collide`) are penalty forces too, from the positions and
    velocities at the start of the substep, except friction, which reads the velocity after gravity and the
    springs (so that a contact can hold exactly): with C the gap, n the contact normal, vn the normal relative
    velocity and m = 1 / (w_i + w_j) the contact's effective mass,

        f_n = max(stiffness (-C) - (damping + 2 zeta sqrt(stiffness m)) vn, 0)   where C < 0, else 0
        impulse_t = -v_t min(mu f_n h / max(|v_t|, slip_velocity), m)            (regularised Coulomb)

    The normal force never pulls (clamped >= 0). zeta is the damping ratio at which such a clamped linear
    spring-dashpot rebounds with the model's `restitution` e (Schwager and Poeschel 2007); it cannot rebound
    with less than exp(-2) = 0.135 at critical damping, so e below that gets zeta = 1 and bounces with about
    0.12 (a ball dropped with e = 0 rebounds to about 1.4% of its height). Gravity during the contact and the
    explicit integration shift the bounce a little (first bounce of a ball dropped from 0.9 m, measured:
    0.293, 0.497, 0.7998, 0.9001 for e = 0.3, 0.5, 0.8, 0.9); the solver's `damping`, if any, is added on top
    and lowers it. `restitution_threshold` is not used. Friction is Coulomb's, regularised below
    `slip_velocity` and capped so that one substep never reverses the slip: where mu f_n h / slip_velocity
    exceeds m, a sticking contact holds exactly; below it, a contact that should stick creeps at up to about
    `slip_velocity`. Pairs are all evaluated at once (no sweep). Contact impulses are reported as sum of
    f h over the substeps (N s, contact_n >= 0, |contact_t| <= mu contact_n). The stiffness also sets the
    penetration: a resting mass m sinks m g / stiffness into the floor, and an impact at speed u about
    u sqrt(m / stiffness). Kinetic energy is not monotone through contacts, as some of it is held in the
    contact springs (the 16-ball break at dt 1/60 gains up to 4.7% of its initial kinetic energy in a step
    with stiffness 1e5 and 30 substeps, its balls overlapping by up to 5.5% of a diameter; 0.45% and 0.2%
    with 1e6 and 100 substeps). `stability_limit` counts the contacts too. A hard constraint set (compliance 0)
    in a model with contacts is refused before tracing (`_check_stability`): it would be a spring of
    `stiffness` in the set's own units, squeezed by the contacts' load (docs/constraints.md).

    Args:
      stiffness: spring constant k, N/m, a differentiable leaf, > 0 (rods, ropes and contacts).
      damping: damping coefficient c along the constraint, N s/m, a differentiable leaf, >= 0 (rods, ropes,
        and added to the contacts' normal damping).
      substeps: substeps per step, static, >= 1.
      slip_velocity: regularisation speed of contact friction, m/s, a differentiable leaf, > 0.
    """

    stiffness: Any = 1e5
    damping: Any = 0.0
    substeps: int = static_field(default=1)
    slip_velocity: Any = 1e-3

    supports_contacts = True

    def __post_init__(self):
        check_int("Penalty", "substeps", self.substeps, 1)
        check_scalar("Penalty", "stiffness", self.stiffness, 0.0, positive=True)
        check_scalar("Penalty", "damping", self.damping, 0.0)
        check_scalar("Penalty", "slip_velocity", self.slip_velocity, 0.0, positive=True)

    def stability_limit(self, model) -> float:
        """A substep h below which the undamped springs of `model` are stable: 2 / omega_bound (s), with
        omega_bound^2 = stiffness * max over constraints of (w_i deg_i + w_j deg_j) (deg: constraints at the
        particle), a Gershgorin bound on the largest eigenvalue of stiffness J M^-1 J^T. For a single
        spring it is the exact 2 / sqrt(stiffness (w_i + w_j)); for chains it is within a factor sqrt(2) of
        the true limit. Concrete values only (NumPy). `rollout` and `step` warn when dt / substeps is above it."""
        t = model.topology
        w = np.asarray(model.inv_mass, np.float64)
        ends = [t.i, t.j] + [info.particles.reshape(-1) for info in t.sets]
        deg = np.bincount(np.concatenate(ends), minlength=t.n)
        if model.contact is not None:
            return self._contact_stability_limit(model, w, deg)
        k = float(self.stiffness)
        bound = k * float(np.max(w[t.i] * deg[t.i] + w[t.j] * deg[t.j], initial=0.0))
        bound = max([bound] + [self._set_bound(c, info, w, deg) for c, info in zip(model.constraints, t.sets)])
        omega = np.sqrt(bound)
        return float(2 / omega) if omega > 0 else float("inf")

    def _set_bound(self, con, info, w, deg) -> float:
        """A constraint set's rows in `stability_limit`'s bound, estimated as for unit gradients (|dC/dx_p| = 1,
        true of distances; an angle's is 1 / length, an area's a length): stiffness (1 / alpha for compliant
        rows) times sum_p w_p deg_p over the row's particles."""
        a = np.broadcast_to(np.asarray(concrete(con.compliance) if concrete(con.compliance) is not None else 0.0,
                                       np.float64), (info.m,))
        k = np.where(a > 0, 1 / np.where(a > 0, a, 1), float(self.stiffness))
        return float(np.max(k * np.sum(w[info.particles] * deg[info.particles], axis=1), initial=0.0))

    def _contact_stability_limit(self, model, w, deg):
        """`stability_limit` of a model with contacts: each particle's degree also counts the contacts it can
        have at once (its candidate pairs, at most 6 in 2-D and 12 in 3-D, plus one per obstacle up to dim),
        obstacle contacts are springs to a fixed body, and the limit is scaled by sqrt(1 + zeta^2) - zeta for
        the contacts' damping ratio zeta (from `restitution` and `damping`), the stability limit of symplectic
        Euler for a damped oscillator."""
        t, ct = model.topology, model.contact
        kiss = 6 if t.dim == 2 else 12
        if ct.has_grid:             # any two particles may touch: each has up to `kiss` contacts
            touch = np.full(t.n, kiss if t.n > 1 else 0) + min(ct.n_obstacles, t.dim)
            deg = deg + touch
            top = float(np.max(w * deg, initial=0.0))
            bound = max(float(np.max(w[t.i] * deg[t.i] + w[t.j] * deg[t.j], initial=0.0)), 2 * top)
            w_pair = np.array([2 * float(np.max(w, initial=0.0))])
        else:
            pairs = np.asarray(ct.pairs.array).reshape(-1, 2)
            touch = np.minimum(np.bincount(pairs.reshape(-1), minlength=t.n), kiss) + min(ct.n_obstacles, t.dim)
            deg = deg + touch
            i = np.concatenate([t.i, pairs[:, 0], np.arange(t.n)])
            j = np.concatenate([t.j, pairs[:, 1], np.arange(t.n)])
            wj = np.concatenate([w[t.j], w[pairs[:, 1]], np.zeros(t.n if ct.n_obstacles else 0)])
            i, j = i[: len(wj)], j[: len(wj)]
            bound = float(np.max(w[i] * deg[i] + wj * deg[j], initial=0.0))
            w_pair = np.concatenate([w[pairs[:, 0]] + w[pairs[:, 1]], w if ct.n_obstacles else np.zeros(0)])
        k = float(self.stiffness)
        omega = np.sqrt(k * bound)
        if omega <= 0:
            return float("inf")
        e = float(np.asarray(model.restitution))
        zeta = _damping_ratio_now(e)
        zeta += float(self.damping) * float(np.sqrt(np.max(w_pair, initial=0.0) / k)) / 2
        return float(2 / omega * (np.sqrt(1 + zeta ** 2) - zeta))

    def _check_stability(self, owner, model, dt) -> None:
        """Refuse hard constraint sets under contacts (`common.refuse_hard_sets`); warn (before tracing, where the values
        are known) when a substep is above `stability_limit`: the springs will then blow up. A warning, not an
        error: the limit is a sufficient bound, and an unstable run is something one may want to see."""
        refuse_hard_sets(owner, "Penalty", model, "it would be a spring of `stiffness` in the set's own units, "
                         "squeezed by the contacts' load (a hard volume pressed to 70% of its height lost 8.4%)")
        vals = [concrete(a) for a in (self.stiffness, model.inv_mass, dt)]
        if any(a is None for a in vals):
            return
        if model.contact is not None and any(concrete(a) is None for a in (model.restitution, self.damping)):
            return
        h = float(vals[2]) / self.substeps
        limit = self.stability_limit(model)
        if h > limit:
            need = int(np.ceil(float(vals[2]) / limit))
            warnings.warn(
                f"{owner}: Penalty substep dt / substeps = {h:.3g} s is above this model's stability limit "
                f"{limit:.3g} s (stiffness {float(vals[0]):g} N/m): the springs are likely to "
                f"oscillate and diverge. Use substeps >= {need}, a smaller dt, or a lower stiffness.",
                RuntimeWarning, stacklevel=4)

    def _step(self, sys, x, v, lam, dt):
        topo, cs = sys.topology, sys.contact
        dtype = x.dtype
        k = jnp.asarray(self.stiffness, dtype)
        c = jnp.asarray(self.damping, dtype)

        def substep(x, v, ws, h, found=None):
            """Springs, then with contacts (after moving start overlaps out, `_start_overlaps`) the contacts'
            penalty impulses and the speculative rows that keep a fast particle from passing through a sphere or
            another particle (`contact.speculative_pass`). A grid model's step (`grid_substepped`) hands every substep the step's candidate
            pairs `found`."""
            ws, prev = split_contacts(sys, ws)
            partners = None
            if cs is not None:
                if found is not None:
                    partners = found[0]
                    pn, pt = contact.carry_slots(prev, partners)
                    prev = prev._replace(pair_n=pn, pair_t=pt)
                x = _start_overlaps(cs, sys.w, x, v, prev, h, k, c, partners)
            if topo.blocks:
                x1, v1, imp_b = _springs(sys, x, v, h, k, c)
            else:                    # no springs
                v1 = sys.apply_gravity(v, h)
                x1, imp_b = x + h * v1, ()
            if cs is None:
                return x1, v1, imp_b
            dv, imp_c = _contact_impulses(topo, cs, sys.w, x, v, v1, h, k, c, jnp.asarray(self.slip_velocity, dtype),
                                          partners)
            v2, spec = contact.speculative_pass(topo, cs, sys.w, x, v1 + dv, h, partners)
            imp_c = imp_c._replace(obs_n=imp_c.obs_n + spec.obs_n, pair_n=imp_c.pair_n + spec.pair_n)
            return x1 + h * (v2 - v1), v2, (imp_b, with_found(imp_c, found))

        return run_substeps(sys, substep, self.substeps, x, v, lam, dt)


def _springs(sys, x, v, h, k, c):
    """One substep of the constraints as springs of stiffness k and damping c (Penalty's docstring; a set's
    compliant rows as their own springs, `_set_springs`): (x, v, impulses per block)."""
    topo = sys.topology
    geo = []
    for blk, rest in zip(topo.blocks, sys.rest):
        if blk.generic is not None:
            geo.append((jnp.zeros((), bool), None, None))
            continue
        xi, xj = L.gather_pair(topo, blk, x)
        wi, wj = L.gather_pair(topo, blk, sys.w)
        C = L.safe_norm(xj - xi, axis=0)[0] - rest
        geo.append(((rest > 0) & (C > STRETCH_CLIP * rest), wi[0], wj[0]))
    # Past the clip the run has diverged (diagnose flags it). Such a substep passes no derivative
    # back, so the gradient of a diverged run stays finite instead of overflowing through the blow-up.
    blown = jnp.any(jnp.stack([jnp.any(b) for b, _, _ in geo]))
    x = jnp.where(blown, lax.stop_gradient(x), x)
    v = jnp.where(blown, lax.stop_gradient(v), v)
    for b, (blk, rest) in enumerate(zip(topo.blocks, sys.rest)):
        if blk.generic is not None:
            geo[b] = _set_springs(sys, blk, x, v, k, c)
            continue
        xi, xj = L.gather_pair(topo, blk, x)
        vi, vj = L.gather_pair(topo, blk, v)
        dist, n = L.safe_norm(xj - xi, axis=0)
        geo[b] = (n, geo[b][1], geo[b][2], dist - rest, jnp.sum((vj - vi) * n, axis=0), rest)
    imp = []
    for blk, g in zip(topo.blocks, geo):
        if blk.generic is not None:
            imp.append(g[1] * h)
            continue
        n, wi, wj, C, u, rest = g
        T = k * C + c * u
        cap = STRETCH_CLIP * k * rest
        T = jnp.where(rest > 0, jnp.clip(T, -cap, cap), T)
        if blk.has_rope:
            taut = jnp.where(C > 0, jnp.maximum(T, 0), 0)
            T = taut if blk.all_rope else jnp.where(blk.rope.array, taut, T)
        imp.append(T * h)
    v = sys.apply_gravity(v, h)
    for blk, g, p in zip(topo.blocks, geo, imp):
        if blk.generic is not None:
            v = R.apply(topo, blk, g[0], v, p)
            continue
        n, wi, wj = g[:3]
        q = n * p
        v = L.add_pair(topo, blk, v, wi * q, -wj * q)
    return x + h * v, v, tuple(imp)


def _set_springs(sys, blk, x, v, k, c):
    """A constraint set's rows as springs: (their frame, tension T): T = k C_lib + c rel for hard rows (the
    solver's stiffness and damping), C_lib / alpha for compliant rows (their own spring: potential energy
    C^2 / (2 alpha)); a unilateral row only while violated, and then only pushing C up."""
    f = R.set_frame(sys.topology, blk, *sys.set_of(blk), x, sys.w)
    soft = f.alpha > 0
    T = jnp.where(soft, f.C / jnp.where(soft, f.alpha, 1), k * f.C) + c * R.rel(sys.topology, blk, f, v)
    if blk.all_rope:
        T = jnp.where(f.C > 0, jnp.maximum(T, 0), 0)
    return f, T * (f.k > 0).astype(T.dtype)


#: The least restitution a contact with no tensile force can have at critical damping, exp(-2) (below it Penalty
#: uses critical damping and bounces with about this restitution).
MIN_RESTITUTION = float(np.exp(-2.0))


def _log_restitution(zeta, xp=jnp):
    """ln e of a linear spring-dashpot with damping ratio zeta in [0, 1) whose force is clamped >= 0 (the
    contact ends when the force vanishes, before the overlap does): Schwager and Poeschel 2007, Granular
    Matter 9, 465, written with one atan2 for both of their ranges of zeta. `xp`: jax.numpy or numpy."""
    s = xp.sqrt(1 - zeta * zeta)
    return -(zeta / s) * (xp.pi - xp.arctan2(2 * zeta * s, 1 - 2 * zeta * zeta))


def _damping_ratio_now(e: float) -> float:
    """`_restitution_damping_ratio` of a concrete e, in NumPy (for `stability_limit`)."""
    if e <= MIN_RESTITUTION:
        return 1.0
    lo, hi = 0.0, 1 - 1e-6
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _log_restitution(mid, np) > np.log(e) else (lo, mid)
    return (lo + hi) / 2


def _restitution_damping_ratio(e):
    """The damping ratio zeta at which a clamped linear spring-dashpot rebounds with restitution e (inverting
    `_log_restitution` by bisection, then one Newton step that carries the derivative d zeta / d e); 1
    (critical damping) for e <= MIN_RESTITUTION."""
    top = 1 - 1e-6
    target = jnp.log(jnp.maximum(e, MIN_RESTITUTION))

    def bisect(_, lo_hi):
        lo, hi = lo_hi
        mid = (lo + hi) / 2
        above = _log_restitution(mid) > target        # still too elastic: more damping
        return jnp.where(above, mid, lo), jnp.where(above, hi, mid)

    lo, hi = lax.fori_loop(0, 60, bisect, (jnp.zeros_like(target), jnp.full_like(target, top)))
    z0 = lax.stop_gradient((lo + hi) / 2)
    value, slope = jax.value_and_grad(_log_restitution)(z0)
    zeta = z0 - (value - target) / slope
    return jnp.where(e > MIN_RESTITUTION, zeta, 1.0)


def _penalty_row(vrel0, vrel, n, C, m, k, c, two_zeta, mu, slip, h):
    """(normal impulse, friction impulse [dim, ...] on the second body) of penalty contacts over a substep h;
    m: effective mass (0: no contact). The damping reads the relative velocity at the start of the substep,
    `vrel0`, friction the one after gravity and the springs, `vrel`."""
    vn = jnp.sum(vrel0 * n, 0)
    live = m > 0
    root = jnp.where(live, jnp.sqrt(jnp.where(live, k * m, 1)), 0)
    f_n = jnp.where((C < 0) & live, jnp.maximum(-k * C - (c + two_zeta * root) * vn, 0), 0)
    p_n = f_n * h
    vt = vrel - n * jnp.sum(vrel * n, 0)
    speed, _ = L.safe_length(vt)
    return p_n, -vt * jnp.minimum(mu * p_n / jnp.maximum(speed, slip), m)


def _excess(C, vn, m, prev_n, h, k, c, two_zeta, tol):
    """The part of a contact's overlap -C that no spring stored (`_start_overlaps`): 0 where the contact pushed
    in the previous substep (prev_n > 0) or has no effective mass m; else what exceeds twice the deepest a
    contact can be in its first substep, h |vn| (it was apart one substep ago), or when its force has just
    vanished with the overlap not yet gone, (c + 2 zeta sqrt(k m)) |vn| / k."""
    root = jnp.where(m > 0, jnp.sqrt(jnp.where(m > 0, k * m, 1)), 0)
    legit = 2 * (h + (c + two_zeta * root) / k) * jnp.abs(vn) + tol
    return jnp.where((prev_n <= 0) & (m > 0), jnp.maximum(-C - legit, 0), 0)


def _start_overlaps(cs, w, x, v, prev, h, k, c, partners=None):
    """Positions x [dim, *view] with every start overlap moved out at position level, along its contact's
    normal (`contact_rows.direction`: upwards from a sphere's exact centre or between coincident particles), with no
    change of velocity. A start overlap is an overlap that no spring can have stored: the contact did not push
    in the previous substep (the impulses `prev`), yet it is deeper than one substep's approach (`_excess`): a
    particle that starts inside an obstacle or another particle. Its spring would store (k / 2) depth^2 and fling
    the particle out (a 1 kg particle started 0.3 R off a 1 m sphere's centre left at 100 m/s); moved out, it
    leaves with the velocity it had. Pairs are moved apart in inverse proportion to their masses (a grid
    model's: its `partners` [n, K], with `prev` in their slots)."""
    ct, dim = cs.ct, x.shape[0]
    two_zeta = 2 * _restitution_damping_ratio(cs.restitution)
    r = cs.radius[0]
    if ct.n_obstacles:
        m = L.safe_reciprocal(w[0])
        size = jnp.sum(jnp.abs(x), 0) + r
        def one(x, q, sphere, prev_n):
            n, C = contact_rows.obstacle_gap(cs, q, x, sphere=sphere)
            tol = contact_rows.tolerance(size + contact_rows.obstacle_size(cs, q, sphere))
            return x + n * _excess(C, jnp.sum(n * v, 0), m, prev_n, h, k, c, two_zeta, tol), None
        x = contact_rows.each_obstacle(ct, one, x, prev.obs_n)[0]
    if ct.n_pairs or ct.has_grid:
        xf, vf, wf, rf = x.reshape(dim, -1), v.reshape(dim, -1), w.reshape(-1), cs.radius_flat
        ia, ja, valid, index = contact_rows.pair_slots(ct, xf.shape[1], partners)
        dist, n = contact_rows.direction(xf[:, ja] - xf[:, ia])
        m = L.safe_reciprocal(wf[ia] + wf[ja]) * jnp.asarray(valid, x.dtype)
        tol = contact_rows.tolerance(jnp.sum(jnp.abs(xf[:, ia]) + jnp.abs(xf[:, ja]), 0) + rf[ia] + rf[ja])
        vn = jnp.sum(n * (vf[:, ja] - vf[:, ia]), 0)
        e = _excess(dist - rf[ia] - rf[ja], vn, m, prev.pair_n, h, k, c, two_zeta, tol)
        x = x + contact_rows.pair_total(ct, w, n * (e * m), -1.0, index).reshape(x.shape)
    return x


def _contact_impulses(topo, cs, w, x, v0, v, h, k, c, slip, partners=None):
    """Penalty contact impulses of one substep (Penalty's docstring): (velocity change [dim, *view], the
    substep's contact `Impulses`). x, v0: positions and velocities at the start of the substep, v: velocities
    after gravity and the springs; `partners` [n, K]: a grid model's candidate pairs."""
    ct, mu, dim = cs.ct, cs.friction, x.shape[0]
    two_zeta = 2 * _restitution_damping_ratio(cs.restitution)
    on = ot = pn = pt = None
    dv = jnp.zeros_like(v)
    if ct.n_obstacles:
        m = L.safe_reciprocal(w[0])
        def one(dv, q, sphere, _):
            n, C = contact_rows.obstacle_gap(cs, q, x, sphere=sphere)
            p_n, p_t = _penalty_row(v0, v, n, C, m, k, c, two_zeta, mu, slip, h)
            return dv + w * (n * p_n + p_t), (p_n, p_t)
        dv, (on, ot) = contact_rows.each_obstacle(ct, one, dv)
    if ct.n_pairs or ct.has_grid:
        xf, vf, v0f, wf = x.reshape(dim, -1), v.reshape(dim, -1), v0.reshape(dim, -1), w.reshape(-1)
        ia, ja, valid, index = contact_rows.pair_slots(ct, xf.shape[1], partners)
        dist, n = contact_rows.direction(xf[:, ja] - xf[:, ia])
        C = dist - cs.radius_flat[ia] - cs.radius_flat[ja]
        m = L.safe_reciprocal(wf[ia] + wf[ja]) * jnp.asarray(valid, x.dtype)
        pn, pt = _penalty_row(v0f[:, ja] - v0f[:, ia], vf[:, ja] - vf[:, ia], n, C, m, k, c, two_zeta, mu, slip, h)
        dv = dv + contact_rows.pair_total(ct, w, n * pn + pt, -1.0, index).reshape(v.shape)
    zero = zero_impulses(topo, ct, x.dtype)
    return dv, Impulses(zero.obs_n if on is None else on, zero.obs_t if ot is None else ot,
                                zero.pair_n if pn is None else pn, zero.pair_t if pt is None else pt)
