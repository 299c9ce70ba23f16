"""RATTLE: velocity Verlet with position (SHAKE) and velocity constraints, solved by coloured sweeps."""
from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxcon.core import contact_rows
from jaxcon.core import layout as L
from jaxcon.core import rows as R
from jaxcon.core.checks import check_int, check_scalar
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.system import Solver
from jaxcon.core.contact import zero_impulses
from jaxcon.solvers import contact
from jaxcon.solvers.common import apply_impulses, frames, run_substeps, shake_sweep, with_contacts, with_found

# A sweep loop is unrolled when it has at most _UNROLL_ITERATIONS iterations and iterations times the code blocks
# one sweep emits (one per topology block: a colour each in the unrolled layout; a table, star or constraint set
# one scan) is at most _UNROLL_BLOCKS. Unrolling lets XLA fuse the small per-sweep ops (a few times faster on
# small systems, same result); on many blocks it costs compile time and run time: RATTLE(5) on the unrolled 32x32
# cloth (8 blocks) compiled in 23 s and ran at 157 ms/step unrolled, against 1.6 s and 0.72 ms/step as a loop
# (docs/performance.md).
_UNROLL_ITERATIONS = 8
_UNROLL_BLOCKS = 16


#: Sweeps to a tolerance are run in chunks of this many, the convergence checked after each chunk: a `lax.cond` per
#: sweep cost more than the sweeps on small systems (docs/solvers.md).
_CHUNK = 4


def _unroll(iterations: int, topo) -> bool:
    return iterations <= _UNROLL_ITERATIONS and iterations * max(len(topo.blocks), 1) <= _UNROLL_BLOCKS


@pytree_dataclass
class RATTLE(Solver):
    """RATTLE (Andersen 1983): symplectic, time-reversible, second-order velocity Verlet on the constraint
    manifold.

    Per step of length h, with n0 the constraint directions at the start of the step:

      1. half kick and drift: v' = v + h/2 g, x' = x + h v'; then SHAKE: sweeps over the colours, each
         constraint moved along n0 (x_i += w_i n0 mu, x_j -= w_j n0 mu,
         mu = (|d|^2 - L^2) / (2 (w_i + w_j) d . n0)) until |x_j - x_i| = L; v' gets the same correction / h.
      2. half kick: v = v' + h/2 g; then sweeps projecting the velocities onto J(x') v = 0 (directions n1 at
         the new positions): dlam = n1 . (v_j - v_i) / (w_i + w_j), started from the position stage's
         impulses mu / h (applied along n1: a constraint at rest needs exactly those).

    A rod of rest length 0 holds its two particles together; it has no direction at its solution, so both
    stages take its current one (the relative position, then the relative velocity) and remove all of it.

    A constraint set's compliant rows (compliance alpha > 0, potential C^2 / (2 alpha)) are implicit springs, as
    XPBD's: SHAKE solves C_lib(x') = a mu with a = alpha / (h^2 / 2) (mu / h is half the step's impulse, so at
    rest C = alpha T). The velocity stage's half kick is split (`_trapezoid`, `_start_force`): a spring the
    step resolves (h omega small) takes it from the step's start, explicitly, which with the position stage is
    the trapezoidal rule, second order and undamped; a spring it does not resolve takes it implicitly at the
    end, C_lib(x') + h rel(v) = a' lam2, damped rather than unstable; alpha -> 0 is the hard row, and a static
    spring rests at alpha T with v = 0 for any alpha.

    Sweeps: Gauss-Seidel, up to `iterations` per stage, stopping once a sweep moves no coordinate by more than
    `tolerance` times the model's extent (position stage; velocity stage: h times the velocity change), checked
    every `_CHUNK` sweeps (`_sweeps`: a static loop of `lax.cond`s, so jax.grad, jax.jvp and jax.vmap work;
    under vmap every sweep runs). `tolerance=None` is dtype-aware (`default_tolerance`); `tolerance=0` runs
    exactly `iterations` sweeps. Within a sweep a rod whose residual is at or below `tolerance` is not updated
    (|d^2 - L^2| / (2 L^2); velocity: |n1 . (v_j - v_i)| h / L).

    Ropes: a rope takes part only while it is taut; its accumulated impulse of each stage is clamped >= 0
    (a slack rope is free). The returned lam is the constraint impulse over the step (mu / h + the velocity
    stage's impulse; lam > 0: tension; a hanging mass gives m g h). The warm-start input is not used.

    Contacts (`planes`, `spheres`, `collide`) are unilateral rows in both stages, as XPBD's (docs/contacts.md;
    the step starts with XPBD's `contact.push_out` of start overlaps):
    every SHAKE sweep ends with the contacts' position pass (`contact.position_pass`: overlaps pushed out along
    the normal with lam_n >= 0, static friction), whose correction / h goes into v' as the constraints' does; the
    velocity stage ends with the contacts' velocity rows swept to the same tolerance (`_contact_velocities`:
    restitution from the approach velocity v + h/2 g, dynamic friction, in a compression and a restitution
    phase). Contact impulses are not symmetric in time, so a model with contacts loses RATTLE's time
    reversibility at every contact (not elsewhere). The contacts' velocity rows come after the constraints'
    velocity projection, so in a step with an impact the rods at the particles they move end with J v != 0,
    which the next step's SHAKE removes; running the contacts inside the projection sweeps instead gained
    kinetic energy on the break. A neighbour grid's step searches its pairs once (`common.grid_substepped`).

    Args:
      iterations: the most Gauss-Seidel sweeps per stage, static, >= 1.
      tolerance: static, >= 0, or None: 1e-8 in float64, 1e-6 in float32 (`default_tolerance`); relative to
        the model's extent. 0: always exactly `iterations` sweeps.
    """

    iterations: int = static_field(default=64)
    tolerance: Any = static_field(default=None)

    def __post_init__(self):
        check_int("RATTLE", "iterations", self.iterations, 1)
        if self.tolerance is not None:
            check_scalar("RATTLE", "tolerance", self.tolerance, 0.0)
            if concrete(self.tolerance) is None:
                raise ValueError("RATTLE: `tolerance` is static (it decides how the sweeps run): pass a Python float, "
                                 "not a traced value")
            object.__setattr__(self, "tolerance", float(self.tolerance))     # hashable, whatever scalar came in

    supports_contacts = True

    def _step(self, sys, x, v, lam, dt):
        return run_substeps(sys, functools.partial(self._substep, sys), 1, x, v, lam, dt)

    def _substep(self, sys, x, v, lam, h, found=None):
        """One step (module docstring); a grid model's `found` = (partners, overflow) from its search."""
        topo, cs = sys.topology, sys.contact
        partners = None if found is None else found[0]
        dtype = x.dtype
        tol = jnp.asarray(default_tolerance(dtype) if self.tolerance is None else self.tolerance, dtype)
        tiny = jnp.finfo(dtype).tiny
        if cs is not None:
            x = contact.push_out(cs, sys.w, x, h, partners)
        fr0 = frames(sys, x)
        zero = tuple(jnp.zeros_like(f.C) for f in fr0)

        v = sys.apply_gravity(v, h / 2)
        x0, v_approach = x, v
        x = x + h * v

        shake = shake_sweep(sys, fr0, h, tol, set_alpha=lambda a: a / (h * h / 2))

        def shake_contacts(i, carry):           # the contacts' position pass after each SHAKE sweep
            x, v, mu, imp = carry
            x, v, mu = shake(i, (x, v, mu))
            if cs is None:
                return x, v, mu, imp
            dp = x - x0
            moved, imp = contact.position_pass(cs, sys.w, x0, dp, imp, partners, h * v_approach, h)
            return x + (moved - dp), v + (moved - dp) / h, mu, imp

        carry = (x, v, zero, None if cs is None else zero_impulses(topo, cs.ct, dtype))
        written = self.tolerance == 0 and _unroll(self.iterations, topo)
        unroll = cs is None and written      # a sweep with contacts stays a loop
        bound = None if self.tolerance == 0 else tol * lax.stop_gradient(_extent(x0))
        x, v, mu, imp = _sweeps(shake_contacts, carry, self.iterations, unroll, lambda a, b: _moved(a[0], b[0]), bound)

        fr1 = frames(sys, x)
        springs = tuple(_trapezoid(f, h) for f in fr1)
        v = sys.apply_gravity(v, h / 2)
        kick = tuple(_start_force(blk, f, h) for blk, f in zip(topo.blocks, fr0))
        v = apply_impulses(sys, v, fr0, kick)

        def project_colour(v, blk, rows):
            f, r, mu, lam, spring = rows
            rel = R.rel(topo, blk, f, v)
            if getattr(blk, "generic", None) is not None:      # a set's rows: J(x) v = 0, compliant ones springs
                live = f.k > 0
                if blk.has_rope:    # a unilateral row constrains the velocity only where the position stage held it
                    held = (mu > 0) | (f.C >= 0)
                    live = live & (held if blk.all_rope else (held | ~blk.rope.array))
                rhs = rel + jnp.where(f.alpha > 0, f.C / h, 0)
                fl = f._replace(k=f.k * live) if blk.hub_slot is not None else f   # a set's stars: live rows only
                step = jnp.where(live, R.solve(topo, blk, fl, rhs, lam, spring), 0)
                new = R.accumulate(blk, lam, step)
                return R.apply(topo, blk, f, v, new - lam), new
            zero = r == 0      # a rod of rest length 0: the whole relative velocity, along itself (`shake_sweep`)
            vi, vj = L.gather_pair(topo, blk, v)
            u, inv = vj - vi, L.safe_length(vj - vi)[1]
            f = f._replace(n=jnp.where(zero, u * inv, f.n),
                           k=jnp.where(zero, L.safe_reciprocal(f.wi + f.wj) * (inv > 0).astype(inv.dtype), f.k))
            rel = R.rel(topo, blk, f, v)
            active = jnp.abs(rel) * h > tol * r
            if blk.has_rope:  # a rope that is slack after the drift does not constrain the velocity
                taut = f.C > -tol * jnp.maximum(r, tiny)
                active = active & (taut if blk.all_rope else (taut | ~blk.rope.array))
            step = L.block_solve(topo, blk, f, rel) if getattr(blk, "star", False) else jnp.where(active, rel * f.k, 0)
            new = R.accumulate(blk, lam, step)
            return R.apply(topo, blk, f, v, new - lam), new

        def project(_, carry):
            v, lam = carry
            lam = list(lam)
            for c, (blk, f, r, g) in enumerate(zip(topo.blocks, fr1, sys.rest, springs)):
                v, lam[c] = L.each_colour(blk, project_colour, v, (f, r, mu[c], lam[c], g))
            return v, tuple(lam)

        lam2 = tuple(R.clamp(blk, m / h) * ((f.k > 0) & ((r != 0) if blk.generic is None else True)).astype(dtype)
                     for blk, m, f, r in zip(topo.blocks, mu, fr1, sys.rest))
        v = apply_impulses(sys, v, fr1, lam2)       # warm started with the position stage's impulses
        v, lam2 = _sweeps(project, (v, lam2), self.iterations, written,
                          lambda a, b: h * _moved(a[0], b[0]), bound)
        lam = tuple(m / h + l2 + e for m, l2, e in zip(mu, lam2, kick))
        if cs is None:
            return x, v, lam
        v_free = sys.apply_gravity(v_approach, h / 2)
        v, imp = _contact_velocities(sys, (x0, x - x0), v_approach, v_free, v, imp, h, partners, self.iterations,
                                     bound)
        return x, v, with_contacts(sys, lam, with_found(imp, found))



def _trapezoid(f, h):
    """A set's compliant rows' spring in the velocity stage (`rows.Spring`), None for rods and ropes.

    With g = alpha / (h^2 / 2) (the position stage's implicit spring at velocity level) and s = J M^-1 J^T, a row
    takes the share theta = (s / (s + g))^2 of its half kick implicitly at the step's end, and 1 - theta
    explicitly from the start (`_start_force`): lam = theta lam_end, where lam_end = (rel + C / h) / g is the
    implicit row's force at the velocities the stage ends with; that is the implicit row with g' = g / theta.
    A soft spring (h omega small, theta -> 0) gets the trapezoidal rule on the velocities: with the position
    stage, x' - 2 x + x_prev = h^2 (a' + a_prev) / 2, second order and without damping. A stiff one
    (theta -> 1) gets the implicit row, stable at any stiffness. At rest C = alpha T either way. The square
    keeps the damping small up to h omega = 0.13 (docs/constraints.md)."""
    g = R.gamma(f, h / math.sqrt(2))
    if g is None:
        return None
    s = jnp.where(f.k > 0, f.s, 1)
    theta = (s / (s + g.g)) ** 2
    ge = g.g / theta
    return R.Spring(ge, L.safe_reciprocal(f.s + ge) * (f.k > 0).astype(ge.dtype))


def _start_force(blk, f, h):
    """The explicit share of a set's compliant rows' second half kick, from the step's start (frames `f`):
    (1 - theta) (h / 2) C / alpha = C (2 s + g) / (h (s + g)^2), g = alpha / (h^2 / 2) (`_trapezoid`), bounded
    as alpha -> 0.
    Zero for hard rows, rods and ropes, and for a unilateral row pushing."""
    a = R.compliant(f)
    if a is None:
        return jnp.zeros_like(f.C)
    g = a / (h * h / 2)
    s = jnp.where(f.k > 0, f.s, 1)
    e = jnp.where((a > 0) & (f.k > 0), f.C * (2 * s + g) / (h * (s + g) ** 2), 0)
    return R.clamp(blk, e)


def default_tolerance(dtype) -> float:
    """RATTLE's default `tolerance` for positions of `dtype`: 1e-8 in float64, 1e-6 in float32 (a few ulps of
    the model's extent: a smaller change is rounding)."""
    return 1e-8 if jnp.finfo(dtype).bits > 32 else 1e-6


def _extent(x):
    """The model's size: the largest range of the positions x [dim, ...] along an axis (m)."""
    flat = x.reshape(x.shape[0], -1)
    return jnp.max(jnp.max(flat, axis=1) - jnp.min(flat, axis=1))


def _moved(a, b):
    """The largest change of one coordinate from a to b."""
    return jnp.max(jnp.abs(b - a))


def _sweeps(body, carry, iterations: int, unroll: bool, change, bound):
    """Up to `iterations` sweeps `body(i, carry) -> carry`. `bound` None: all of them (`unroll`: written out).
    Otherwise in chunks of `_CHUNK` sweeps (the last one's sweeps beyond `iterations` discarded), each chunk the
    taken branch of a `lax.cond` in a static `fori_loop` (reverse-mode differentiable, unlike a `while_loop`):
    once a chunk's last sweep changed the carry by no more than `bound` (`change(old, new)`, a scalar), the
    remaining chunks are no-op branches. One sweep is traced once. Under `jax.vmap` the cond's predicate is
    batched and every sweep runs (the converged ones' results discarded)."""
    if bound is None:
        return lax.fori_loop(0, iterations, body, carry, unroll=unroll)

    def chunk(n, state):
        def sweep(k, pair):
            old, cur = pair
            new = body(k, cur)
            if iterations % _CHUNK:         # the last chunk's sweeps beyond `iterations` change nothing
                new = jax.tree.map(lambda a, b: jnp.where(n * _CHUNK + k < iterations, a, b), new, cur)
            return cur, new

        def run(c):
            old, new = lax.fori_loop(0, _CHUNK, sweep, (c, c))
            return new, change(old, new) <= bound

        return lax.cond(state[1], lambda c: (c, jnp.ones((), bool)), run, state[0])

    return lax.fori_loop(0, -(-iterations // _CHUNK), chunk, (carry, jnp.zeros((), bool)))[0]


def _contact_velocities(sys, moved, v_approach, v_free, v, imp, h, partners, iterations: int, bound):
    """The contacts' velocity stage: each contact that pushed in the position stage (lam_n > 0) gets a velocity
    row (`contact_rows.velocity_rows`: restitution target from the approach velocity, dynamic friction), swept
    from the position stage's impulses imp / h to convergence (`_sweeps`) as the constraints' projection is: the
    end-of-step velocity of a contact at rest is then 0, the second half kick of gravity taken out, as a rod's
    J v = 0. In two phases, as the velocity solvers' (`common.solve_phases`): compression (every target 0), then
    restitution, whose change is scaled back where it would raise the kinetic energy above that of `v_free`
    (the step's velocity without impulses) or of the compression phase (`contact.restitution_scale`). Returns
    (v, the step's contact impulses in N s)."""
    cs, w = sys.contact, sys.w
    x0, dp = moved                 # the position stage's start and displacement: its normals (`velocity_rows`)
    obs, pairs = contact_rows.velocity_rows(cs, w, x0 + dp, v_approach, imp, partners, (x0, dp, h * v_approach))
    obs, pairs = (None if r is None else r._replace(target_c=jnp.zeros_like(r.target), warm=r.k > 0)
                  for r in (obs, pairs))
    fields = ("obs_n", "obs_t", "pair_n", "pair_t")
    start = imp._replace(**{f: getattr(imp, f) / h for f in fields})
    if partners is not None:
        start = start._replace(partners=partners)
    # warm started with the position stage's impulses again (the velocity stage's impulse of a contact at rest)
    v, warm = contact.warm_start(cs, w, v, obs, pairs, start)
    start = start._replace(**{f: getattr(start, f) + getattr(warm, f) for f in fields})

    def solve(late, carry):
        o, p = contact_rows.phase(obs, late), contact_rows.phase(pairs, late)
        return _sweeps(lambda _, c: contact.sweep(cs, w, c[0], o, p, c[1]), carry, iterations, False,
                       lambda a, b: h * _moved(a[0], b[0]), bound)

    compressed = solve(False, (v, start))
    bounced = solve(True, compressed)
    scale = contact.restitution_scale(w, v_free, compressed[0], bounced[0], contact_rows.bouncing(obs, pairs))
    return jax.tree.map(lambda a, b: a + scale * (b - a) if jnp.issubdtype(a.dtype, jnp.floating) else b,
                        compressed, bounced)
