"""Time stepping: `step` and `rollout`, jit-compiled, differentiable and batchable."""
from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcon.core import layout as L
from jaxcon.core.checks import check_int, check_real, check_values, describe_shape
from jaxcon.core.model import Model, State, Trajectory, check_model, check_state
from jaxcon.core.pytree import concrete
from jaxcon.core.system import Solver, System
from jaxcon.core import contact as C


def _check_call(owner, model, state, solver, dt, steps=None):
    if not isinstance(model, Model):
        raise TypeError(f"{owner}: `model` must be a jaxcon Model, got {type(model).__name__}")
    if not isinstance(solver, Solver):
        raise TypeError(f"{owner}: `solver` must be a jaxcon solver (e.g. jc.PGS()), got {type(solver).__name__}")
    check_x64(owner, model, state)
    check_model(owner, model, "model.")
    check_solver(owner, solver)
    check_state(owner, model, state)
    check_dt(owner, dt, _dtype(state), getattr(solver, "substeps", 1))
    if steps is not None:
        check_int(owner, "steps", steps, 1)
    if model.contact is not None and not solver.supports_contacts:
        raise ValueError(
            f"{owner}: {type(solver).__name__} does not support contacts, and the model has some ({model.contact!r}); "
            "use jc.PGS (sequential impulses) for models with `planes`, `spheres` or `collide`")
    warn = getattr(solver, "_check_stability", None)
    if warn is not None:
        warn(owner, model, dt)


def check_solver(owner, solver):
    """The solver's own checks (its `__post_init__`) run again on its leaves where they are known now: a solver
    rebuilt from leaves (`jax.tree.map`, an optimiser's update) bypasses its constructor."""
    post = getattr(solver, "__post_init__", None)
    if post is None:
        return
    try:
        post()
    except ValueError as e:
        raise ValueError(f"{owner}: `solver`: {e}") from None


def check_x64(owner, model, state):
    """Refuse a model or state holding 64-bit JAX arrays while `jax_enable_x64` is off: they were made with x64 on,
    and JAX would silently compute them in 32 bits. (32-bit models run in their own dtype under x64.)"""
    if jax.config.jax_enable_x64:
        return
    for what, obj in (("model", model), ("state", state)):
        if not isinstance(obj, (Model, State)):
            continue
        for leaf in jax.tree.leaves(obj):
            if isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer) and leaf.dtype.itemsize == 8:
                raise ValueError(
                    f"{owner}: the {what} holds {leaf.dtype} arrays, made while jax_enable_x64 was on, but "
                    "jax_enable_x64 is off now, so JAX would compute them in 32 bits. Rebuild the model and state "
                    "with the current setting (jc.build or a scene), or turn x64 back on with "
                    "jax.config.update('jax_enable_x64', True)")


def check_dt(owner, dt, dtype, substeps=1):
    """`dt` (seconds) must be a real scalar; where known now, finite, > 0, and such that a (sub)step
    h = dt / substeps keeps h^2 and 1 / h^2 normal, finite numbers in the state's dtype (the solvers use both:
    a float32 dt of 1e-45 is 0 there, and 1e30 overflows h^2 g). Values only known inside jit are not checked."""
    check_real(owner, "dt", dt)
    if np.ndim(dt) != 0:
        raise ValueError(f"{owner}: `dt` must be a scalar, got shape {np.shape(dt)}")
    d = concrete(dt)
    if d is None:
        return
    d = float(d)
    if not (np.isfinite(d) and d > 0):
        raise ValueError(f"{owner}: `dt` must be finite and > 0, got {d}")
    fi = np.finfo(dtype)
    h = np.float64(d) / substeps
    lo, hi = float(np.sqrt(fi.tiny)) * 1e3, float(np.sqrt(fi.max)) * 1e-3
    if not lo <= h <= hi:
        per = "" if substeps == 1 else f" / {substeps} substeps"
        raise ValueError(f"{owner}: `dt` = {d:g} s{per} is outside the range {fi.dtype} can step with "
                         f"({lo:.1e} to {hi:.1e} s per (sub)step: h^2 and 1 / h^2 must stay normal numbers)")


def _dtype(state):
    return jnp.result_type(state.x)


def _enter(model, state):
    """(System, x, v, lam) in the internal layout; for a model with contacts lam is (blocks, contact Impulses),
    a state without contact impulses starting from zero."""
    t = model.topology
    dtype = _dtype(state)
    sys = System.from_model(model, dtype)
    x = L.particles_in(t, jnp.asarray(state.x, dtype))
    v = hold_fixed(t, L.particles_in(t, jnp.asarray(state.v, dtype)))
    lam = L.constraints_in(t, jnp.asarray(state.lam, dtype))
    if model.contact is not None:
        ct = model.contact
        if state.contact_n is None:
            imp = C.zero_impulses(t, ct, dtype)
        else:
            cn = jnp.asarray(state.contact_n, dtype)
            ctan = (jnp.zeros(cn.shape + (t.dim,), dtype) if state.contact_t is None
                    else jnp.asarray(state.contact_t, dtype))
            imp = C.contacts_in(t, ct, cn, ctan)
        if ct.has_grid:
            imp = imp._replace(partners=C.partners_in(ct, state.contact_partners), reuse=C.no_reuse(t, ct, dtype))
        lam = (lam, imp)
    return sys, x, v, lam


def _impulses_out(model, lam, like):
    """(lam [..., m], contact_n, contact_t, contact_partners) in user order from the internal carry (contacts
    None without, partners None without a grid)."""
    t = model.topology
    if model.contact is None:
        return L.constraints_out(t, lam, like), None, None, None
    blocks, imp = lam
    cn, ctan = C.contacts_out(t, model.contact, imp)
    partners = C.partners_out(model.contact, imp.partners) if model.contact.has_grid else None
    return L.constraints_out(t, blocks, like), cn, ctan, partners


def _record_sys(sys, lam, like):
    """One step's impulses as recorded in the time loop: rods flat in block order, contacts in user order."""
    t = sys.topology
    if sys.contact is None:
        return L.constraints_concat(t, lam, like)
    blocks, imp = lam
    ct = sys.contact.ct
    grid = (C.partners_out(ct, imp.partners), imp.overflow) if ct.has_grid else (None, None)
    return (L.constraints_concat(t, blocks, like),) + C.contacts_out(t, ct, imp) + grid


def _state_out(model, x, v, lam):
    t = model.topology
    return State(L.particles_out(t, x), L.particles_out(t, v), *_impulses_out(model, lam, x))


@jax.jit
def _step_jit(model, state, solver, dt, forces=None, targets=None):
    sys, x, v, lam = _enter(model, state)
    u = drive_in(model.topology, forces, targets, x.dtype)
    x, v, lam = driven_step(sys, solver, (x, v, lam), jnp.asarray(dt, x.dtype), u)
    return _state_out(model, x, v, lam)


def step(model: Model, state: State, solver: Solver, dt, *, forces=None, targets=None) -> State:
    """Advance `state` by one step of length `dt` seconds. Returns the new State (its lam: the step's
    constraint impulses, N s, > 0 pulling).

    forces: None or [n, dim] external forces (N) held during the step (ignored on fixed particles).
    targets: None or [n_fixed, dim] positions of the fixed particles after the step, in increasing index order;
      they move there at constant velocity. Without targets the fixed particles stay where they are.
    """
    _check_call("step", model, state, solver, dt)
    forces, targets = check_drive("step", model, forces, targets)
    return _step_jit(model, state, solver, dt, forces, targets)


def _time_loop(sys, solver, carry, dt, steps, save_every, checkpoint=None, remat=True, drive=None):
    """Run `steps` steps of `solver` from the internal carry (x, v, lam). Returns (carry, (xs, vs, lams)), the
    records stacked over steps // save_every, lams flat in block order. `drive`: None, or the internal inputs
    (forces, targets) of every step (`drive_in`), each None or with a leading axis of `steps`."""
    # Reverse mode recomputes each step from its carry instead of storing the step's intermediates: a step
    # holds dozens of small per-colour arrays (frames, biases, warm start), and stacking each of them over the
    # time loop made the gradient's program 2x larger and slower to compile (docs/performance.md). A rollout
    # that is not differentiated is unaffected.
    def advance(carry, u):
        return solver._step(sys, *carry, dt) if u is None else driven_step(sys, solver, carry, dt, u)

    step = jax.checkpoint(advance, prevent_cse=False, policy=jax.checkpoint_policies.nothing_saveable) if remat \
        else advance
    if drive is not None and all(a is None for a in drive):
        drive = None
    grid = sys.contact is not None and sys.contact.ct.has_grid
    between = _between_records(step, save_every, grid)

    def body(carry, us):
        carry = between(carry, us)
        x, v, lam = carry
        # The step's impulses are recorded as one flat array (block order), not one stacked output per colour
        # block: with ten stacked outputs per step, XLA:CPU's two worker threads took turns running the time
        # loop, and recording cost XPBD on the 64x64 cloth about 30% per step, none of it on one thread
        # (NPROC=1 or taskset). Flat, the recording figure fell by 12% (docs/performance.md).
        return carry, (x, v, _record_sys(sys, lam, x))

    def records(carry, n, us):
        if n == 1:          # one record (the final state): no outer loop around the steps
            carry, rec = body(carry, _index(us, 0))
            return carry, jax.tree.map(lambda a: a[None], rec)
        return lax.scan(body, carry, us, length=n)

    n_rec = steps // save_every
    us = _split_steps(drive, (n_rec, save_every))           # [records, save_every, ...] or None
    if checkpoint is None:
        return records(carry, n_rec, us)
    # Outer scan over chunks of `checkpoint` steps, each chunk rematerialised in the backward pass: reverse mode
    # keeps the carry at every chunk boundary plus one chunk's residuals.
    per = checkpoint // save_every
    n_chunks, rest = divmod(n_rec, per)
    chunk = jax.checkpoint(lambda c, u: records(c, per, u))
    parts = []
    if n_chunks:
        head = _split_steps(_index(us, slice(0, n_chunks * per)), (n_chunks, per))
        carry, recs = lax.scan(chunk, carry, head, length=n_chunks)
        parts.append(jax.tree.map(lambda a: a.reshape((n_chunks * per,) + a.shape[2:]), recs))
    if rest:
        carry, recs = jax.checkpoint(lambda c, u: records(c, rest, u))(carry, _index(us, slice(n_chunks * per,
                                                                                                None)))
        parts.append(recs)
    return carry, (parts[0] if len(parts) == 1 else jax.tree.map(lambda *a: jnp.concatenate(a), *parts))


def _between_records(step, save_every, grid):
    """(carry, us) -> carry: the `save_every` steps between two records, `us` their inputs ([save_every, ...]
    or None). A grid model's contact overflow is summed over them."""
    def one(carry, u):
        if not grid:
            return step(carry, u)
        carry, total = carry
        carry = step(carry, u)
        return carry, total + carry[2][1].overflow

    def run(carry, us):
        if save_every == 1:
            return step(carry, _index(us, 0))
        if grid:
            carry = (carry, jnp.zeros((), jnp.int32))
        if us is None:
            carry = lax.fori_loop(0, save_every, lambda _, c: one(c, None), carry)
        else:
            carry = lax.scan(lambda c, u: (one(c, u), None), carry, us)[0]
        if grid:
            (x, v, (blocks, imp)), total = carry
            carry = x, v, (blocks, imp._replace(overflow=total))
        return carry
    return run


def _index(tree, i):
    """tree[i] on every leaf's leading axis (None stays None)."""
    return None if tree is None else jax.tree.map(lambda a: a[i], tree)


def _split_steps(tree, shape):
    """Every leaf's leading axis reshaped to `shape` (None stays None)."""
    return None if tree is None else jax.tree.map(lambda a: a.reshape(shape + a.shape[1:]), tree)


# ---- driven systems: per-step external forces and targets of the fixed particles -----------------------------
def fixed_slots(topo) -> np.ndarray:
    """Flat positions, in the internal view (an internal particle array reshaped to [dim, -1]), of the fixed
    particles in increasing user index: the order of `targets`. On a batch-minor topology copy b of fixed
    particle p comes at p * B + b, so the slots run particle-major, copy-minor."""
    idx = np.flatnonzero(topo.fixed)
    return idx if topo.pos is None else np.asarray(topo.pos)[idx]


def fixed_mask(topo) -> np.ndarray:
    """[1, *view] bool, True at the fixed particles (static)."""
    mask = np.zeros(int(np.prod(topo.view)), bool)
    mask[fixed_slots(topo)] = True
    return mask.reshape((1,) + topo.view)


def hold_fixed(topo, v):
    """The fixed particles' velocities set to 0: a fixed particle without a target never moves, whatever
    velocity its state holds (every solver moves every particle by h v, impulses none with inverse mass 0)."""
    return jnp.where(fixed_mask(topo), jnp.zeros((), v.dtype), v) if topo.fixed.any() else v


def drive_in(topo, forces, targets, dtype):
    """User inputs -> internal: forces [..., n, dim] -> [..., dim, *view]; targets [..., n_fixed, dim] ->
    [..., dim, n_fixed] (in `fixed_slots` order). Either may be None."""
    f = None if forces is None else L.particles_in(topo, jnp.asarray(forces, dtype))
    t = None if targets is None else jnp.swapaxes(jnp.asarray(targets, dtype), -1, -2)
    return f, t


def driven_step(sys, solver, carry, dt, u):
    """One step under the inputs u = (forces [dim, *view], targets [dim, k]), either None. Forces enter as the
    acceleration w F that `System.apply_gravity` adds (every solver, every substep and half kick; 0 on fixed
    particles). The fixed particles move along the straight path to their targets: velocity
    (target - x) / dt during the step, which every solver keeps (their inverse mass is 0) and integrates
    (x + h v per (sub)step), so the constraints see a moving anchor; after the step their positions are set to
    the targets exactly (no rounding drift), and their velocities to that path velocity."""
    force, target = u
    x, v, lam = carry
    if force is not None:
        sys = sys.replace(accel=sys.w * force)
    if target is None:
        return solver._step(sys, x, v, lam, dt)
    slots, shape = fixed_slots(sys.topology), x.shape

    def put(a, vals):
        return a.reshape(shape[0], -1).at[:, slots].set(vals).reshape(shape)

    path = (target - x.reshape(shape[0], -1)[:, slots]) / dt
    x, v, lam = solver._step(sys, x, put(v, path), lam, dt)
    return put(x, target), put(v, path), lam


@functools.partial(jax.jit, static_argnames=("steps", "save_every", "checkpoint", "remat"))
def _rollout_jit(model, state, solver, dt, steps, save_every, checkpoint=None, remat=True, forces=None,
                 targets=None):
    sys, x, v, lam = _enter(model, state)
    t = model.topology
    drive = drive_in(t, forces, targets, x.dtype)
    carry, recs = _time_loop(sys, solver, (x, v, lam), jnp.asarray(dt, x.dtype), steps, save_every, checkpoint,
                             remat, drive)
    (x, v, lam), (xs, vs, lams) = carry, recs
    final = _state_out(model, x, v, lam)
    if model.contact is None:
        return final, Trajectory(L.particles_out(t, xs), L.particles_out(t, vs), L.constraints_unpermute(t, lams))
    lams, cns, cts, partners, overflow = lams
    return final, Trajectory(L.particles_out(t, xs), L.particles_out(t, vs), L.constraints_unpermute(t, lams),
                             cns, cts, partners, overflow)


def available_memory() -> tuple[int, str] | None:
    """(bytes, where) the default device can still allocate: free accelerator memory from its memory stats,
    else the host's available memory (/proc/meminfo MemAvailable, or free physical pages); None if unknown."""
    dev = jax.devices()[0]
    stats = None
    try:
        stats = dev.memory_stats()
    except Exception:  # noqa: BLE001 - backends without memory stats
        pass
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)), f"{dev.platform} device memory"
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "host memory"
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "host memory"
    except (ValueError, OSError, AttributeError):
        return None


def record_bytes(model, state, rows, batch=1) -> int:
    """Bytes of a recorded trajectory of `rows` rows: x, v [n, dim] and lam [m] in the state's dtype; with
    contacts contact_n [k] and contact_t [k, dim]; with a neighbour grid contact_partners [n, K] and
    contact_overflow (int32)."""
    itemsize = np.dtype(_dtype(state)).itemsize
    t, c = model.topology, model.contact
    floats = 2 * t.n * t.dim + t.m
    ints = 0
    if c is not None:
        floats += c.k * (1 + t.dim)
        if c.has_grid:
            ints += t.n * c.grid_k + 1
    return batch * rows * (floats * itemsize + ints * 4)


def drive_bytes(model, state, steps, forces=None, targets=None, batch=1) -> int:
    """Bytes of the internal copy of a rollout's `forces` [steps, n, dim] and `targets` [steps, n_fixed, dim]."""
    t = model.topology
    per = (t.n if forces is not None else 0) + (int(t.fixed.sum()) if targets is not None else 0)
    return batch * steps * per * t.dim * np.dtype(_dtype(state)).itemsize


def check_record_memory(owner, model, state, steps, save_every, batch=1, inputs=0):
    """Refuse, before compiling, a rollout whose recorded trajectory cannot fit in memory. The record holds
    steps // save_every rows of every recorded array (`record_bytes`); putting it back into the user's particle
    and constraint order makes one more copy, so twice its size must fit, plus `inputs` bytes (the internal
    copy of `forces` and `targets`, `drive_bytes`). Inside `jax.vmap` the batch size is not known here and is
    not counted."""
    rows = steps // save_every
    need = 2 * record_bytes(model, state, rows, batch) + inputs
    avail = available_memory()
    if avail is not None and need > avail[0]:
        gb = 1024 ** 3
        fit = max(1, int(np.ceil(need / avail[0])))
        raise ValueError(
            f"{owner}: recording {batch * rows:,} states needs about {need / gb:.1f} GiB (the trajectory and one "
            f"reordered copy), more than the {avail[0] / gb:.1f} GiB of {avail[1]} available. Record less: pass "
            f"`save_every` >= {save_every * fit} (every k-th step is kept), or run fewer `steps` per call.")


def check_drive(owner, model, forces, targets, steps=None, batch=None, steps_name="steps", copy="copy"):
    """Refuse, before tracing, `forces` / `targets` that are not real numbers, have the wrong shape or hold values
    that are not finite (where known now), and `targets` for a model without fixed particles. `steps` None: one
    step's values, forces [n, dim] and targets [n_fixed, dim]; else a leading axis of `steps`; `batch`: a
    batched call, which takes a leading batch axis too, or arrays without one shared by the whole batch.
    `steps_name` and `copy` name the steps axis and a member of the batch in the error.
    Returns (forces, targets), lists turned into NumPy arrays (a list would reach jit as a pytree of scalars)."""
    t = model.topology
    forces, targets = (a if a is None or hasattr(a, "dtype") else np.asarray(a) for a in (forces, targets))
    fixed = np.flatnonzero(t.fixed)
    if targets is not None and not len(fixed):
        raise ValueError(f"{owner}: `targets` gives the paths of the fixed particles, but the model has no fixed "
                         "particles (build it with `fixed=`; use `forces` to push free particles)")
    lead = () if steps is None else (steps,)
    lead_name = () if steps is None else (steps_name,)
    shown = ", ".join(map(str, fixed[:8])) + (", ..." if len(fixed) > 8 else "")
    for name, arr, per, per_name, what in (
            ("forces", forces, (t.n, t.dim), ("n", "dim"), "an external force (N) on every particle"),
            ("targets", targets, (len(fixed), t.dim), ("n_fixed", "dim"),
             f"a position (m) of every fixed particle (particles {shown}, in that order)")):
        if arr is None:
            continue
        check_real(owner, name, arr)
        shape = tuple(np.shape(arr))
        want = [(lead_name + per_name, lead + per)]
        if batch is not None:
            want.insert(0, (("batch",) + lead_name + per_name, (batch,) + lead + per))
        if shape not in [w for _, w in want]:
            forms = " or ".join(f"({', '.join(k)}) = {w}" for k, w in want)
            shared = f" (without the batch axis: shared by every {copy})" if batch is not None else ""
            raise ValueError(f"{owner}: `{name}` must have shape {forms}{shared}, {what}"
                             f"{' after each step' if name == 'targets' else ''}; got {describe_shape(shape)}")
        check_values(owner, name, arr)
    return forces, targets


def rollout(model: Model, state: State, solver: Solver, dt, steps: int, *, save_every: int = 1,
            checkpoint: int | None = None, forces=None, targets=None):
    """Run `steps` steps of length `dt` seconds.

    Returns (final_state, traj): traj.x, traj.v [steps // save_every, n, dim] and traj.lam
    [steps // save_every, m], recorded after every `save_every`-th step (default: every step; lam is the
    impulse of that step, N s, > 0 pulling). Works under jax.jit, jax.grad and jax.vmap.

    The recorded trajectory's memory is estimated before compiling; a rollout whose record cannot fit in the
    device's free memory is refused with an error naming `save_every`.

    checkpoint: None (default) or a number of steps K, a multiple of `save_every`. The rollout then runs as
      an outer scan over chunks of K steps whose body is wrapped in `jax.checkpoint`, so reverse mode stores
      the state at every chunk boundary and one chunk's intermediates (O(steps / K + K) per-step residuals
      instead of O(steps)), at the price of recomputing each chunk once in the backward pass. Values and
      gradients are unchanged. sqrt(steps) is a good K. A last partial chunk is allowed.

    forces: None or [steps, n, dim] external forces (N), entry k held during step k (ignored on fixed
      particles). A differentiable input.
    targets: None or [steps, n_fixed, dim] positions of the fixed particles after each step, in increasing
      index order. In step k a fixed particle moves at constant velocity (target_k - x) / dt, so the
      constraints see a moving anchor, and ends exactly at target_k; its recorded velocity is that one.
      A differentiable input. Without targets the fixed particles never move, whatever their velocity.
      Both hold one entry per simulated step, whatever `save_every`.
    """
    _check_call("rollout", model, state, solver, dt, steps)
    check_int("rollout", "save_every", save_every, 1)
    if steps % save_every:
        raise ValueError(f"rollout: `steps` ({steps}) must be a multiple of `save_every` ({save_every})")
    if checkpoint is not None:
        check_int("rollout", "checkpoint", checkpoint, 1)
        if checkpoint % save_every:
            raise ValueError(
                f"rollout: `checkpoint` ({checkpoint}) must be a multiple of `save_every` ({save_every})")
        if checkpoint >= steps:
            checkpoint = steps
    forces, targets = check_drive("rollout", model, forces, targets, steps)
    check_record_memory("rollout", model, state, steps, save_every,
                        inputs=drive_bytes(model, state, steps, forces, targets))
    return _rollout_jit(model, state, solver, dt, steps, save_every, checkpoint, True, forces, targets)
