"""Model (static topology + differentiable physical parameters), State and Trajectory, and `build`."""
from __future__ import annotations

from typing import Any, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from jaxcon.core import layout as _layout
from jaxcon.core.checks import check_real, check_shape, check_values, resolve_dtype
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.topology import Topology, check_colouring, greedy_colouring

Array = Any


@pytree_dataclass
class Model:
    """A constrained particle system.

    Leaves (differentiable, batchable):
      inv_mass:    [n] 1/kg; 0 marks a fixed particle.
      rest_length: [m] metres, one per constraint in the order given to `build` (rods first, then ropes).
      gravity:     [dim] m/s^2.
    Static: `topology` (index pairs, kinds, colouring, layout).
    """

    inv_mass: Array
    rest_length: Array
    gravity: Array
    topology: Topology = static_field()

    def __post_init__(self):
        t = self.topology
        if not isinstance(t, Topology):
            raise TypeError(f"Model: `topology` must be a Topology, got {type(t).__name__}")
        check_shape("Model", "inv_mass", self.inv_mass, (t.n,))
        check_shape("Model", "rest_length", self.rest_length, (t.m,))
        check_shape("Model", "gravity", self.gravity, (t.dim,))
        check_values("Model", "inv_mass", self.inv_mass, nonneg=True)
        check_values("Model", "rest_length", self.rest_length, nonneg=True)
        check_values("Model", "gravity", self.gravity)

    # convenience, all static
    @property
    def n_particles(self) -> int:
        return self.topology.n

    @property
    def n_constraints(self) -> int:
        return self.topology.m

    @property
    def dim(self) -> int:
        return self.topology.dim

    @property
    def pairs(self) -> np.ndarray:
        """[m, 2] particle indices of each constraint (user order)."""
        return np.stack([self.topology.i, self.topology.j], -1)

    @property
    def is_rope(self) -> np.ndarray:
        """[m] bool, True for unilateral (rope) constraints."""
        return self.topology.is_rope

    def __repr__(self):
        """Particles (how many fixed, when the masses are concrete), constraints by kind, colours, dim, dtype."""
        t = self.topology
        plural = lambda k, word: f"{k} {word}{'' if k == 1 else 's'}"      # noqa: E731
        w = concrete(self.inv_mass)
        fixed = "" if w is None else f" ({int(np.sum(w == 0))} fixed)"
        ropes = int(t.is_rope.sum())
        kinds = ", ".join(plural(k, kind) for k, kind in ((t.m - ropes, "rod"), (ropes, "rope")) if k)
        dtype = jnp.result_type(self.rest_length if t.m else self.inv_mass)
        return (f"Model({plural(t.n, 'particle')}{fixed}, {plural(t.m, 'constraint')}"
                f"{f' ({kinds})' if kinds else ''}, {plural(t.n_colours, 'colour')}, dim={t.dim}, dtype={dtype})")


@pytree_dataclass
class State:
    """What changes in time.

      x:   [n, dim] positions (m).
      v:   [n, dim] velocities (m/s).
      lam: [m] constraint impulse of the last step (N s; > 0 pulls the two particles together), the
           warm start of the next step.
    """

    x: Array
    v: Array
    lam: Array

    def __repr__(self):
        return (f"State(x={jnp.shape(self.x)}, v={jnp.shape(self.v)}, lam={jnp.shape(self.lam)}, "
                f"dtype={jnp.result_type(self.x)})")


@pytree_dataclass
class Trajectory:
    """Per-step record of a rollout (after each step): x, v [steps, n, dim]; lam [steps, m]."""

    x: Array
    v: Array
    lam: Array


def check_state(owner: str, model: Model, state: State) -> None:
    t = model.topology
    if not isinstance(state, State):
        raise TypeError(f"{owner}: `state` must be a jaxcon State, got {type(state).__name__}")
    for name in ("x", "v", "lam"):
        a = getattr(state, name)
        if not hasattr(a, "dtype"):
            raise TypeError(f"{owner}: `state.{name}` must be an array (jax or NumPy), got {type(a).__name__}; "
                            "make states with jc.build or a scene, or wrap values in jnp.asarray")
        if not jnp.issubdtype(jnp.result_type(a), jnp.floating):
            raise TypeError(f"{owner}: `state.{name}` must hold floating-point numbers, got dtype {jnp.result_type(a)}")
    check_shape(owner, "state.x", state.x, (t.n, t.dim))
    check_shape(owner, "state.v", state.v, (t.n, t.dim))
    check_shape(owner, "state.lam", state.lam, (t.m,))
    for name in ("x", "v", "lam"):
        check_values(owner, f"state.{name}", getattr(state, name))


def _fixed_mask(fixed, n: int) -> np.ndarray:
    """`fixed` as a bool mask [n]: None, integer indices, or a boolean mask of length n."""
    if fixed is None:
        return np.zeros(n, bool)
    try:
        a = np.asarray(fixed)
    except ValueError:
        raise ValueError("build: `fixed` must be a list of particle indices or a boolean mask of length n") from None
    if a.size == 0:
        return np.zeros(n, bool)
    if a.dtype.kind == "b":
        if a.shape != (n,):
            raise ValueError(f"build: a boolean `fixed` is a mask and must have shape ({n},) (one entry per "
                             f"particle), got {a.shape}")
        return a.copy()
    if a.dtype.kind == "f" and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise ValueError(f"build: `fixed` must hold integer particle indices (or be a boolean mask of length {n}), "
                         f"got {fixed!r}")
    idx = a.astype(np.int64).reshape(-1)
    bad = (idx < 0) | (idx >= n)
    if bad.any():
        raise ValueError(f"build: `fixed` index {int(idx[bad][0])} is out of range (there are {n} particles)")
    mask = np.zeros(n, bool)
    mask[idx] = True
    return mask


def _pairs(name: str, pairs, n: int) -> np.ndarray:
    if pairs is None:
        return np.zeros((0, 2), np.int64)
    try:
        a = np.asarray(pairs)
    except ValueError:
        raise ValueError(f"build: `{name}` must be a list of (i, j) particle index pairs; some entries are not "
                         "pairs (ragged list)") from None
    if a.size == 0:
        return np.zeros((0, 2), np.int64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"build: `{name}` must be a list of (i, j) particle index pairs, got shape {a.shape}")
    if a.dtype.kind not in "iu":
        if a.dtype.kind == "f" and np.all(a == np.round(a)):
            a = a.astype(np.int64)
        else:
            raise ValueError(f"build: `{name}` must hold integer particle indices, got dtype {a.dtype}")
    a = a.astype(np.int64)
    bad = (a < 0) | (a >= n)
    if bad.any():
        k = int(np.argwhere(bad)[0][0])
        raise ValueError(
            f"build: `{name}[{k}]` = {tuple(a[k].tolist())} has a particle index out of range "
            f"(there are {n} particles, indices 0..{n - 1})"
        )
    same = a[:, 0] == a[:, 1]
    if same.any():
        k = int(np.argmax(same))
        raise ValueError(f"build: `{name}[{k}]` joins particle {int(a[k, 0])} to itself")
    return a


def build(
    positions,
    masses,
    rods: Optional[Sequence] = None,
    ropes: Optional[Sequence] = None,
    fixed=None,
    rest_lengths=None,
    velocities=None,
    gravity=None,
    *,
    colouring=None,
    grid_shape: Optional[tuple] = None,
    dtype=None,
):
    """Build a model and its initial state from arrays.

    Topology (`rods`, `ropes`, `fixed`, `colouring`, `grid_shape`) is static and must be concrete. The physical
    values (`positions`, `masses`, `rest_lengths`, `velocities`, `gravity`) may be traced: `build` works inside
    `jax.grad`, `jax.jit` and `jax.vmap`, and gradients flow through it. Values known now are checked; traced
    ones cannot be, so a traced negative mass or scalar gravity is not caught.

    Args:
      positions: [n, dim] initial positions (m), dim 2 or 3.
      masses: [n] (or a scalar) masses in kg; finite and > 0 for particles that are not fixed, and such that
        1 / mass is a normal number in the model's dtype (a mass of 1e39 in float32 would otherwise become an
        inverse mass of 0, i.e. a fixed particle). The masses of fixed particles are ignored.
      rods: (i, j) pairs joined by bilateral distance constraints (push or pull).
      ropes: (i, j) pairs joined by unilateral distance constraints (pull only, lambda >= 0).
      fixed: the fixed particles (inverse mass 0): a list of indices, or a boolean mask of shape [n].
      rest_lengths: [n_rods + n_ropes] rest lengths (m, rods first, then ropes); None: initial distances.
      velocities: [n, dim] initial velocities (m/s); None: zero.
      gravity: [dim] acceleration vector (m/s^2), or a scalar magnitude >= 0 pointing along the negative last
        axis; None: 9.81 m/s^2 along the negative last axis.
      colouring: optional [m] colour per constraint; default greedy in the given order. It is checked:
        constraints of one colour may not share a particle.
      grid_shape: optional shape whose product is n, used as the internal particle layout (lets regular
        structures solve colours with strided slices instead of gathers). When a colour steps by 2 along its
        last axis and that axis is even, the layout stores that axis as even entries then odd ones; states
        stay in your particle order either way.
      dtype: float dtype of the model and state. None: the dtype of `positions` when it is a floating-point
        array, else JAX's default float dtype (float64 under `jax_enable_x64`, float32 otherwise).

    Returns:
      (model, state).
    """
    check_real("build", "positions", positions)
    dtype = resolve_dtype("build", dtype, positions)
    x = jnp.asarray(positions).astype(dtype)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"build: `positions` must have shape [n, 2] or [n, 3], got {tuple(x.shape)}")
    n, dim = x.shape
    if n < 1:
        raise ValueError("build: `positions` must hold at least one particle")
    check_values("build", "positions", x)
    is_fixed = _fixed_mask(fixed, n)
    inv_mass = _inverse_masses(masses, is_fixed, dtype)

    rod_pairs = _pairs("rods", rods, n)
    rope_pairs = _pairs("ropes", ropes, n)
    pairs = np.concatenate([rod_pairs, rope_pairs], 0)
    is_rope = np.concatenate([np.zeros(len(rod_pairs), bool), np.ones(len(rope_pairs), bool)])
    m = len(pairs)
    if m == 0:
        raise ValueError("build: the model needs at least one constraint (`rods` or `ropes`)")
    i, j = pairs[:, 0], pairs[:, 1]

    if rest_lengths is None:
        xc = concrete(positions)
        if xc is not None:      # known now: the distances in float64, rounded once
            xc = np.asarray(xc, np.float64)
            rest = jnp.asarray(np.linalg.norm(xc[j] - xc[i], axis=-1), dtype)
        else:
            rest = _layout.safe_norm(x[j] - x[i], axis=-1)[0]
    else:
        check_real("build", "rest_lengths", rest_lengths)
        check_shape("build", "rest_lengths", rest_lengths, (m,))
        check_values("build", "rest_lengths", rest_lengths, nonneg=True)
        rest = jnp.asarray(rest_lengths).astype(dtype)

    if velocities is None:
        v = jnp.zeros_like(x)
    else:
        check_real("build", "velocities", velocities)
        check_shape("build", "velocities", velocities, (n, dim))
        check_values("build", "velocities", velocities)
        v = jnp.asarray(velocities).astype(dtype)

    g = _gravity("build", gravity, dim, dtype)
    topo = Topology(n, dim, i, j, is_rope, _colouring(colouring, i, j, n), _view(grid_shape, n))
    model = Model(inv_mass, rest, g, topo)
    state = State(x, v, jnp.zeros(m, dtype))
    return model, state


def _inverse_masses(masses, is_fixed, dtype):
    """[n] inverse masses in `dtype`: 0 for fixed particles, 1 / mass otherwise (traced masses welcome)."""
    n = len(is_fixed)
    check_real("build", "masses", masses)
    if np.ndim(masses) not in (0, 1):
        raise ValueError(f"build: `masses` must be a scalar or have shape ({n},), got {np.shape(masses)}")
    m = jnp.broadcast_to(jnp.asarray(masses).astype(dtype), (n,)) if np.ndim(masses) == 0 else masses
    check_shape("build", "masses", m, (n,))
    m = jnp.asarray(m).astype(dtype)
    mc = concrete(masses)
    if mc is not None:
        mc = np.broadcast_to(np.asarray(mc, np.float64), (n,))
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            inv = 1 / mc
            stored = inv.astype(dtype)
            bad = ~is_fixed & ~(np.isfinite(mc) & (mc > 0))
            tiny = np.finfo(dtype).tiny
            representable = np.isfinite(stored) & (stored >= tiny) & np.isfinite(mc.astype(dtype))
            unrepresentable = ~is_fixed & ~bad & ~representable
        if bad.any():
            p = int(np.argmax(bad))
            raise ValueError(f"build: `masses` must be finite and > 0 for particles that are not in `fixed`; "
                             f"particle {p} has mass {mc[p]}")
        if unrepresentable.any():
            p = int(np.argmax(unrepresentable))
            raise ValueError(
                f"build: `masses`: particle {p} has mass {mc[p]:g} kg, whose inverse is not a normal {np.dtype(dtype)} "
                f"number (it would be stored as {stored[p]:g}, and an inverse mass of 0 fixes a particle); use masses "
                f"between {1 / np.finfo(dtype).max:.3g} and {1 / tiny:.3g} kg, a wider dtype, or `fixed`")
        return jnp.asarray(np.where(is_fixed, 0.0, inv), dtype)     # known now: 1 / mass in float64, rounded once
    safe = jnp.where(is_fixed, jnp.ones((), dtype), m)
    return jnp.where(is_fixed, jnp.zeros((), dtype), 1 / safe)


def _gravity(owner, gravity, dim, dtype):
    """[dim] gravity vector from None, a scalar magnitude >= 0 (downward along the last axis) or a vector."""
    if gravity is None:
        return jnp.zeros(dim, dtype).at[-1].set(-9.81)
    check_real(owner, "gravity", gravity)
    if np.ndim(gravity) == 0:
        check_values(owner, "gravity", gravity)
        g = concrete(gravity)
        if g is not None and float(g) < 0:
            raise ValueError(
                f"{owner}: a scalar `gravity` is a magnitude (m/s^2) pointing along the negative last axis and must "
                f"be >= 0, got {float(g)}; for gravity along another direction pass a [{dim}] vector")
        return jnp.zeros(dim, dtype).at[-1].set(-jnp.asarray(gravity).astype(dtype))
    check_shape(owner, "gravity", gravity, (dim,))
    check_values(owner, "gravity", gravity)
    return jnp.asarray(gravity).astype(dtype)


def _colouring(colouring, i, j, n):
    if colouring is None:
        return greedy_colouring(i, j, n)
    colour = np.asarray(colouring)
    check_shape("build", "colouring", colour, (len(i),))
    if colour.dtype.kind not in "iu" or (colour < 0).any():
        raise ValueError("build: `colouring` must hold non-negative integers")
    check_colouring(i, j, colour, n)
    return colour


def _view(grid_shape, n):
    if grid_shape is None:
        return (n,)
    view = tuple(int(s) for s in grid_shape)
    if int(np.prod(view)) != n or any(s < 1 for s in view):
        raise ValueError(f"build: `grid_shape` {view} must multiply to the number of particles {n}")
    return view
