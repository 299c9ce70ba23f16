"""Model (static topology + differentiable physical parameters), State and Trajectory, and `build`."""
from __future__ import annotations

from typing import Any, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from ._pytree import concrete, pytree_dataclass, static_field
from ._topology import Topology, check_colouring, greedy_colouring

Array = Any


def _check_shape(owner: str, name: str, value, shape: tuple) -> None:
    got = tuple(np.shape(value))
    if got != tuple(shape):
        raise ValueError(f"{owner}: `{name}` must have shape {tuple(shape)}, got {got}")


def _check_values(owner: str, name: str, value, *, nonneg: bool = False, positive: bool = False) -> None:
    """Finite (and optionally >= 0 or > 0) check on values known now; tracers are skipped."""
    a = concrete(value)
    if a is None:
        return
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{owner}: `{name}` must be real numbers, got dtype {a.dtype}")
    bad = ~np.isfinite(a)
    if bad.any():
        idx = np.argwhere(bad)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be finite; entry {idx} is {a[tuple(idx)]}")
    if nonneg and (a < 0).any():
        idx = np.argwhere(a < 0)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be >= 0; entry {idx} is {a[tuple(idx)]}")
    if positive and (a <= 0).any():
        idx = np.argwhere(a <= 0)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be > 0; entry {idx} is {a[tuple(idx)]}")


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
        _check_shape("Model", "inv_mass", self.inv_mass, (t.n,))
        _check_shape("Model", "rest_length", self.rest_length, (t.m,))
        _check_shape("Model", "gravity", self.gravity, (t.dim,))
        _check_values("Model", "inv_mass", self.inv_mass, nonneg=True)
        _check_values("Model", "rest_length", self.rest_length, nonneg=True)
        _check_values("Model", "gravity", self.gravity)

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
        return f"Model({self.topology!r})"


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
        return f"State(x={jnp.shape(self.x)}, v={jnp.shape(self.v)}, lam={jnp.shape(self.lam)})"


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
    _check_shape(owner, "state.x", state.x, (t.n, t.dim))
    _check_shape(owner, "state.v", state.v, (t.n, t.dim))
    _check_shape(owner, "state.lam", state.lam, (t.m,))
    for name in ("x", "v", "lam"):
        _check_values(owner, f"state.{name}", getattr(state, name))


def _float_dtype(a) -> Any:
    dt = jnp.asarray(a).dtype
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def _pairs(name: str, pairs, n: int) -> np.ndarray:
    if pairs is None:
        return np.zeros((0, 2), np.int64)
    a = np.asarray(pairs)
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
    fixed: Optional[Sequence[int]] = None,
    rest_lengths=None,
    velocities=None,
    gravity=None,
    *,
    colouring=None,
    grid_shape: Optional[tuple] = None,
):
    """Build a model and its initial state from arrays.

    Args:
      positions: [n, dim] initial positions (dim 2 or 3). Their dtype sets the model's float dtype.
      masses: [n] (or a scalar) masses in kg; must be finite and > 0 except for fixed particles.
      rods: (i, j) pairs joined by bilateral distance constraints (push or pull).
      ropes: (i, j) pairs joined by unilateral distance constraints (pull only, lambda >= 0).
      fixed: indices of fixed particles (inverse mass 0).
      rest_lengths: [n_rods + n_ropes] rest lengths (rods first, then ropes); None: initial distances.
      velocities: [n, dim] initial velocities; None: zero.
      gravity: [dim] vector or a scalar magnitude along the negative last axis; None: 9.81 m/s^2.
      colouring: optional [m] colour per constraint; default greedy in the given order. It is checked:
        constraints of one colour may not share a particle.
      grid_shape: optional shape whose product is n, used as the internal particle layout (lets regular
        structures solve colours with strided slices instead of gathers). When a colour steps by 2 along its
        last axis and that axis is even, the layout stores that axis as even entries then odd ones; states
        stay in your particle order either way.

    Returns:
      (model, state).
    """
    x = jnp.asarray(positions)
    dtype = _float_dtype(x)
    x = x.astype(dtype)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"build: `positions` must have shape [n, 2] or [n, 3], got {tuple(x.shape)}")
    n, dim = x.shape
    if n < 1:
        raise ValueError("build: `positions` must hold at least one particle")
    _check_values("build", "positions", x)

    fixed_idx = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, np.int64).reshape(-1)
    if ((fixed_idx < 0) | (fixed_idx >= n)).any():
        bad = fixed_idx[(fixed_idx < 0) | (fixed_idx >= n)][0]
        raise ValueError(f"build: `fixed` index {int(bad)} is out of range (there are {n} particles)")
    is_fixed = np.zeros(n, bool)
    is_fixed[fixed_idx] = True

    m_arr = np.asarray(concrete(masses) if concrete(masses) is not None else masses)
    if np.ndim(m_arr) == 0:
        m_arr = np.full(n, float(m_arr))
    _check_shape("build", "masses", m_arr, (n,))
    if m_arr.dtype.kind not in "biuf":
        raise TypeError(f"build: `masses` must be real numbers, got dtype {m_arr.dtype}")
    bad = ~is_fixed & ~(np.isfinite(m_arr) & (m_arr > 0))
    if bad.any():
        p = int(np.argmax(bad))
        raise ValueError(f"build: `masses` must be finite and > 0 for particles that are not in `fixed`; "
                         f"particle {p} has mass {m_arr[p]}")
    inv_mass = np.where(is_fixed, 0.0, 1.0 / np.where(is_fixed, 1.0, m_arr))

    rod_pairs = _pairs("rods", rods, n)
    rope_pairs = _pairs("ropes", ropes, n)
    pairs = np.concatenate([rod_pairs, rope_pairs], 0)
    is_rope = np.concatenate([np.zeros(len(rod_pairs), bool), np.ones(len(rope_pairs), bool)])
    m = len(pairs)
    if m == 0:
        raise ValueError("build: the model needs at least one constraint (`rods` or `ropes`)")
    i, j = pairs[:, 0], pairs[:, 1]

    if rest_lengths is None:
        xn = np.asarray(x, np.float64)
        rest = np.linalg.norm(xn[j] - xn[i], axis=-1)
    else:
        rest = rest_lengths
        _check_shape("build", "rest_lengths", rest, (m,))
        _check_values("build", "rest_lengths", rest, nonneg=True)
    rest = jnp.asarray(rest, dtype)

    if velocities is None:
        v = jnp.zeros_like(x)
    else:
        v = jnp.asarray(velocities, dtype)
        _check_shape("build", "velocities", v, (n, dim))
        _check_values("build", "velocities", v)

    if gravity is None:
        g = jnp.zeros(dim, dtype).at[-1].set(-9.81)
    elif np.ndim(gravity) == 0:
        _check_values("build", "gravity", gravity)
        g = jnp.zeros(dim, dtype).at[-1].set(-jnp.asarray(gravity, dtype))
    else:
        _check_shape("build", "gravity", gravity, (dim,))
        _check_values("build", "gravity", gravity)
        g = jnp.asarray(gravity, dtype)

    if colouring is None:
        colour = greedy_colouring(i, j, n)
    else:
        colour = np.asarray(colouring)
        _check_shape("build", "colouring", colour, (m,))
        if colour.dtype.kind not in "iu" or (colour < 0).any():
            raise ValueError("build: `colouring` must hold non-negative integers")
        check_colouring(i, j, colour, n)
    if grid_shape is None:
        view = (n,)
    else:
        view = tuple(int(s) for s in grid_shape)
        if int(np.prod(view)) != n or any(s < 1 for s in view):
            raise ValueError(f"build: `grid_shape` {view} must multiply to the number of particles {n}")

    topo = Topology(n, dim, i, j, is_rope, colour, view)
    model = Model(jnp.asarray(inv_mass, dtype), rest, g, topo)
    state = State(x, v, jnp.zeros(m, dtype))
    return model, state
