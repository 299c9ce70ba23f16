"""Model (static topology + differentiable physical parameters), State and Trajectory, and `build`."""
from __future__ import annotations

from typing import Any, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core import layout as _layout
from jaxcon.core.checks import (
    check_real,
    check_scalar,
    check_shape,
    check_simulation_dtype,
    check_values,
    resolve_dtype,
)
from jaxcon.core.constraints import Constraint, flatten_sets
from jaxcon.core.contact import ContactTopology, check_max_neighbours, contact_pairs, joined_at_rest, uses_grid
from jaxcon.core.pytree import concrete, pytree_dataclass, static_field
from jaxcon.core.topology import SetInfo, Topology, check_colouring, parse_pairs as _pairs, star_colouring

Array = Any


@pytree_dataclass
class Model:
    """A constrained particle system.

    Leaves (differentiable, batchable):
      inv_mass:    [n] 1/kg; 0 marks a fixed particle.
      rest_length: [m] metres, one per constraint in the order given to `build` (rods first, then ropes).
      gravity:     [dim] m/s^2.
    Contact leaves (None unless the model has contacts; see `build` and docs/contacts.md):
      radius: [n] m; friction: Coulomb mu (scalar); restitution: e in [0, 1] (scalar);
      restitution_threshold: approach speed (m/s) below which impacts are inelastic;
      plane_normal [P, dim] (unit), plane_offset [P]: particle i stays in n . x >= offset + r_i;
      sphere_centre [S, dim], sphere_radius [S]: static spheres particles stay outside of.
    Constraint sets: `constraints`, a tuple of `jc.Constraint` (their params and compliance are leaves), in the
      order given to `build`; their impulses follow the rods' and ropes' in lam.
    Static: `topology` (index pairs, kinds, colouring, layout) and `contact` (a ContactTopology, or None).
    """

    inv_mass: Array
    rest_length: Array
    gravity: Array
    topology: Topology = static_field()
    radius: Array = None
    friction: Array = None
    restitution: Array = None
    restitution_threshold: Array = None
    plane_normal: Array = None
    plane_offset: Array = None
    sphere_centre: Array = None
    sphere_radius: Array = None
    contact: Optional[ContactTopology] = static_field(default=None)
    constraints: tuple = ()

    def __post_init__(self):
        check_model("Model", self)

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
        kinds = ", ".join([plural(k, kind) for k, kind in ((t.m_pairs - ropes, "rod"), (ropes, "rope")) if k]
                          + [f"{info.m} {info.name}" for info in t.sets])
        dtype = jnp.result_type(self.inv_mass)
        c = self.contact
        contacts = "" if c is None else ", contacts: " + ", ".join(
            [plural(k, word) for k, word in ((c.n_planes, "plane"), (c.n_spheres, "sphere"), (c.n_pairs, "pair"))
             if k] + ([f"a neighbour grid of {c.grid_k} per particle"] if c.grid_k else []))
        return (f"Model({plural(t.n, 'particle')}{fixed}, {plural(t.m, 'constraint')}"
                f"{f' ({kinds})' if kinds else ''}, {plural(t.n_colours, 'colour')}{contacts}, dim={t.dim}, "
                f"dtype={dtype})")


_CONTACT_LEAVES = ("radius", "friction", "restitution", "restitution_threshold", "plane_normal", "plane_offset",
                   "sphere_centre", "sphere_radius")


def check_model(owner: str, model, prefix: str = "") -> None:
    """What `build` refuses, refused on a model's leaves wherever they are known now: shapes, finite values,
    signs, plane normals, radii. `Model.__post_init__` (so `model.replace`) runs it with owner "Model"; the
    rollouts run it again at their entry (owner the call, prefix "model.") for models rebuilt from leaves, which
    bypasses `__post_init__`. Traced leaves are not checked."""
    t = model.topology
    if not isinstance(t, Topology):
        raise TypeError(f"{owner}: `{prefix}topology` must be a Topology, got {type(t).__name__}")
    for name, shape, sign in (("inv_mass", (t.n,), True), ("rest_length", (t.m_pairs,), True),
                              ("gravity", (t.dim,), False)):
        check_shape(owner, prefix + name, getattr(model, name), shape)
        check_values(owner, prefix + name, getattr(model, name), nonneg=sign)
    w = concrete(model.inv_mass)
    if w is not None and t.fixed.any() and (np.asarray(w)[t.fixed] != 0).any():
        p = int(np.flatnonzero(t.fixed & (np.asarray(w) != 0))[0])
        raise ValueError(f"{owner}: `{prefix}inv_mass[{p}]` is {float(np.asarray(w)[p])}, but particle {p} was fixed "
                         "when the model was built, and its colouring lets constraints that share a fixed particle "
                         "be solved together; build the model again with that particle free")
    _check_contact_leaves(owner, model, prefix)
    _check_sets(owner, model, prefix)


def _check_sets(owner, model, prefix) -> None:
    """The model's constraint sets are those its topology was built with: same count, sizes and kinds."""
    t, cons = model.topology, model.constraints
    if not isinstance(cons, tuple) or len(cons) != len(t.sets) or not all(isinstance(c, Constraint) for c in cons):
        raise ValueError(f"{owner}: `{prefix}constraints` must be the {len(t.sets)} jc.Constraint sets the model was "
                         f"built with, got {type(cons).__name__} of {len(cons) if isinstance(cons, tuple) else '?'}")
    for b, (c, info) in enumerate(zip(cons, t.sets)):
        try:
            check_values(owner, f"{prefix}constraints[{b}].compliance", c.compliance, nonneg=True)
            for key, value in c.params.items():
                check_values(owner, f"{prefix}constraints[{b}].params[{key!r}]", value)
        except ValueError as e:
            raise ValueError(f"{e} (constraint set {info.name!r})") from None
        if c.m != info.m or c.arity != info.k or c.unilateral != info.unilateral or not np.array_equal(
                c.particles.array, info.particles):
            raise ValueError(f"{owner}: `{prefix}constraints` set {info.name!r} differs from the one the model was "
                             "built with (particles or kind); build the model again to change them")
        if c.name != info.name:
            raise ValueError(f"{owner}: `{prefix}constraints` set {info.name!r} is named {c.name!r}; a model's sets keep "
                             "the names they were built with (repr, errors and `jc.fit` use them)")
        if info.fn is not None and c.fn is not info.fn:
            raise ValueError(f"{owner}: `{prefix}constraints` set {info.name!r} has another `fn` "
                             f"({getattr(c.fn, '__name__', c.fn)!r}, built with "
                             f"{getattr(info.fn, '__name__', info.fn)!r}); build the model again to change a kind")


def _check_contact_leaves(owner, model, prefix) -> None:
    c, t = model.contact, model.topology
    if c is None:
        given = [k for k in _CONTACT_LEAVES if getattr(model, k) is not None]
        if given:
            raise ValueError(f"{owner}: `{prefix}{given[0]}` is set but the model has no contacts (build it with "
                             "`planes`, `spheres` or `collide`)")
        return
    if not isinstance(c, ContactTopology):
        raise TypeError(f"{owner}: `{prefix}contact` must be a ContactTopology or None, got {type(c).__name__}")
    shapes = {"radius": (t.n,), "friction": (), "restitution": (), "restitution_threshold": (),
              "plane_normal": (c.n_planes, t.dim), "plane_offset": (c.n_planes,),
              "sphere_centre": (c.n_spheres, t.dim), "sphere_radius": (c.n_spheres,)}
    for k, shape in shapes.items():
        check_shape(owner, prefix + k, getattr(model, k), shape)
        check_values(owner, prefix + k, getattr(model, k), positive=k == "sphere_radius",
                     nonneg=k in ("radius", "friction", "restitution", "restitution_threshold"))
    e = concrete(model.restitution)
    if e is not None and float(e) > 1:
        raise ValueError(f"{owner}: `{prefix}restitution` must be in [0, 1], got {float(e)} (above 1 every bounce "
                         "gains energy)")
    nc = concrete(model.plane_normal)
    if nc is not None and len(nc):
        zero = np.linalg.norm(np.asarray(nc, np.float64), axis=-1) == 0
        if zero.any():
            raise ValueError(f"{owner}: `{prefix}plane_normal[{int(np.argmax(zero))}]` is zero: a plane needs a "
                             "nonzero normal (particles stay in normal . x >= offset + radius)")
    check_contact_radii(owner, prefix + "radius", concrete(model.radius), c.pairs.array, c.has_grid)


def check_contact_radii(owner, name, radius, pairs, grid) -> None:
    """Particles that may collide need a size: each candidate pair a positive sum of radii, and with a neighbour
    grid (where every pair may collide) at most one particle of radius 0. `radius` [n] known now, or None."""
    if radius is None:
        return
    rc = np.asarray(radius)
    if len(pairs):
        both = rc[pairs[:, 0]] + rc[pairs[:, 1]]
        if (both <= 0).any():
            k = int(np.argmax(both <= 0))
            raise ValueError(f"{owner}: particles {tuple(pairs[k].tolist())} may collide (`collide`) but both have "
                             f"`{name}` 0; give them a radius > 0")
    if grid and np.sum(rc <= 0) > 1:
        raise ValueError(f"{owner}: with the neighbour grid every pair of particles may collide, so at most one "
                         f"particle may have `{name}` 0, got {int(np.sum(rc <= 0))}; give them a radius > 0")


@pytree_dataclass
class State:
    """What changes in time.

      x:   [n, dim] positions (m).
      v:   [n, dim] velocities (m/s).
      lam: [m] constraint impulse of the last step (N s; > 0 pulls the two particles together), the
           warm start of the next step.
      contact_n: [k] normal contact impulses of the last step (N s, >= 0, pushing apart), or None for a model
           without contacts (also accepted, as zeros, for one with them). Order: `ContactTopology`.
      contact_t: [k, dim] friction impulses of the last step (N s, world frame, in the contact's tangent plane,
           |contact_t| <= mu contact_n), acting on the contact's second particle (the particle, for obstacles).
      contact_partners: [n, K] int, for a model with a neighbour grid only (else None): the partner j of each
           grid slot of the last step (-1: empty), whose impulse is contact_n[Q n + i K + s] (docs/contacts.md).
           None on a grid model's state: no partners known, the grid contacts are not warm-started.
    """

    x: Array
    v: Array
    lam: Array
    contact_n: Array = None
    contact_t: Array = None
    contact_partners: Array = None

    def __post_init__(self):
        """What a state can say about itself: its grid partners (if any) are -1 or particle indices, where known
        now. Everything against a model is checked where the state is used (`check_state`)."""
        if self.contact_partners is not None:
            check_partners("State", "contact_partners", self.contact_partners)

    def __repr__(self):
        extra = "" if self.contact_n is None else f", contact_n={jnp.shape(self.contact_n)}"
        return (f"State(x={jnp.shape(self.x)}, v={jnp.shape(self.v)}, lam={jnp.shape(self.lam)}{extra}, "
                f"dtype={jnp.result_type(self.x)})")


@pytree_dataclass
class Trajectory:
    """Per-step record of a rollout (after each step): x, v [steps, n, dim]; lam [steps, m]; for models with
    contacts also contact_n [steps, k] and contact_t [steps, k, dim] (see `State`); for models with a neighbour
    grid also contact_partners [steps, n, K] (see `State`) and contact_overflow [steps] int: the candidate pairs
    the grid had no room for, summed over the steps since the previous record (every step's with save_every 1;
    > 0: contacts may have been missed; raise `max_neighbours`)."""

    x: Array
    v: Array
    lam: Array
    contact_n: Array = None
    contact_t: Array = None
    contact_partners: Array = None
    contact_overflow: Array = None


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
    check_simulation_dtype(owner, "state.x", jnp.result_type(state.x))
    check_shape(owner, "state.x", state.x, (t.n, t.dim))
    check_shape(owner, "state.v", state.v, (t.n, t.dim))
    check_shape(owner, "state.lam", state.lam, (t.m,))
    names = ["x", "v", "lam"]
    c = model.contact
    other = " (is it a state of another model? this model has {})".format(
        "no contacts" if c is None else f"{c.k} contact slots: {c!r}")
    for name, shape in (("contact_n", None if c is None else (c.k,)),
                        ("contact_t", None if c is None else (c.k, t.dim))):
        a = getattr(state, name)
        if a is None:
            continue
        if shape is None:
            raise ValueError(f"{owner}: `state.{name}` is set but the model has no contacts (is it a state of "
                             "another model?)")
        if not hasattr(a, "dtype") or not jnp.issubdtype(jnp.result_type(a), jnp.floating):
            raise TypeError(f"{owner}: `state.{name}` must be a floating-point array")
        check_shape(owner, f"state.{name}", a, shape, hint=other)
        names.append(name)
    for name in names:
        check_values(owner, f"state.{name}", getattr(state, name))
    p = state.contact_partners
    if p is not None:
        if c is None or not c.has_grid:
            raise ValueError(f"{owner}: `state.contact_partners` is set but the model has no neighbour grid (is it "
                             "a state of another model?)")
        check_shape(owner, "state.contact_partners", p, (t.n, c.grid_k), hint=other)
        check_partners(owner, "state.contact_partners", p)


def check_partners(owner: str, name: str, partners) -> None:
    """A neighbour grid's partners [..., n, K]: integers, each -1 (an empty slot) or another particle's index
    (0 <= j < n, j != the row's particle), where known now."""
    if not hasattr(partners, "dtype") or not jnp.issubdtype(jnp.result_type(partners), jnp.integer):
        raise TypeError(f"{owner}: `{name}` must be an integer array (-1 or a particle index per slot), got "
                        f"{getattr(partners, 'dtype', type(partners).__name__)}")
    p = concrete(partners)
    if p is None or np.ndim(p) < 2:
        return
    n = p.shape[-2]
    rows = np.arange(n).reshape((n, 1))
    bad = (p < -1) | (p >= n) | (p == rows)
    if bad.any():
        idx = tuple(np.argwhere(bad)[0].tolist())
        raise ValueError(f"{owner}: `{name}` must hold -1 (an empty slot) or the index of another particle "
                         f"(0 to {n - 1}); entry {list(idx)} is {int(p[idx])}")


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
    layout: str = "auto",
    dtype=None,
    radius=None,
    collide=False,
    max_neighbours: Optional[int] = None,
    planes: Optional[Sequence] = None,
    spheres: Optional[Sequence] = None,
    friction=None,
    restitution=None,
    restitution_threshold=None,
    constraints=None,
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
      layout: 'compact' (every colour in one table whose rows a sweep visits in a loop: gradients compile 3
        to 4x faster, and run slower), 'unrolled' (one block per colour, each compiled separately: the fastest
        run time), or 'auto' (default): compact with at least 4 colours and at most 256 constraints in any
        colour, or with more than 12 colours (compile time grows with the colours); constraint sets likewise
        (docs/constraints.md). Static. Results agree to rounding (docs/performance.md). A
        particle with 9 or more constraints is a hub, whose constraints are solved together (docs/solvers.md,
        "Hubs"); constraints that share only a fixed particle may share a colour.
      dtype: float dtype of the model and state. None: the dtype of `positions` when it is a floating-point
        array, else JAX's default float dtype (float64 under `jax_enable_x64`, float32 otherwise).

    Contacts (docs/contacts.md; values are differentiable leaves, counts static; then rods are optional):
      radius: particle radius (m), a scalar or [n]; default 0 (points). Particles in `collide` pairs need > 0.
      collide: True (every pair except two of one rod, rope or small constraint row or two of one connected
        piece within contact distance here, which needs concrete `positions` and `radius`: self-collision), "grid"
        (the same pairs, always on the neighbour grid; True uses it above 256 particles), or a list of (i, j)
        pairs, exactly those (docs/contacts.md). Every contact solver steps a grid model, with substeps.
      max_neighbours: the grid's capacity, partners kept per particle (static int >= 1, capped at the number of
        particles; default 8 in 2-D, 16 in 3-D). Candidates beyond it are counted in `Trajectory.contact_overflow` and `jc.diagnose`.
      planes: [(normal, offset), ...]: particles stay in normal . x >= offset + radius (normal normalised).
      spheres: [(centre, R), ...]: static spheres of radius R > 0 every particle stays outside of.
      friction, restitution: Coulomb mu >= 0 and e in [0, 1] of every contact (default 0 and 0).
      restitution_threshold: approach speed (m/s, default 0.5) below which an impact is inelastic, so that
        resting contacts (approach speed g dt per step) do not bounce.
      constraints: `jc.Constraint` sets of any kind (docs/constraints.md; built-ins in `jc.constraints`), after
        the rods and ropes in lam; checked here (particles in range and not all fixed, fn scalar, unique names).

    Returns:
      (model, state).
    """
    x, dtype = _positions(positions, dtype)
    n, dim = x.shape
    is_fixed = _fixed_mask(fixed, n)
    inv_mass = _inverse_masses(masses, is_fixed, dtype)
    pairs, is_rope = _constraint_pairs(rods, ropes, n)
    sets = _constraint_sets(constraints, x, is_fixed, dtype)
    m = len(pairs) + sum(c.m for c in sets)
    contact_pairs_, grid_k, skipped = _collisions(collide, max_neighbours, n, dim, pairs, sets, x, radius, is_fixed)
    has_contacts = bool(planes) or bool(spheres) or len(contact_pairs_) > 0 or grid_k > 0
    if m == 0 and not has_contacts:
        raise ValueError("build: the model needs at least one constraint (`rods`, `ropes` or `constraints`) or "
                         "contact (`planes`, `spheres` or `collide`)")
    i, j = pairs[:, 0], pairs[:, 1]
    rest = _rest_lengths(rest_lengths, positions, x, i, j, dtype)
    v = _velocities(velocities, x)
    g = _gravity("build", gravity, dim, dtype)
    topo = _topology(n, dim, i, j, is_rope, colouring, grid_shape, layout, is_fixed,
                     tuple(SetInfo(c.particles.array, c.unilateral, c.name, c.fn) for c in sets))
    model = Model(inv_mass, rest, g, topo, constraints=tuple(sets))
    return _with_contacts(model, State(x, v, jnp.zeros(m, dtype)), contact_pairs_, has_contacts, grid=(grid_k, skipped),
                          radius=radius, planes=planes, spheres=spheres, friction=friction, restitution=restitution,
                          threshold=restitution_threshold)


def _positions(positions, dtype):
    """`build`'s positions, checked, as an [n, dim] array in the model's dtype, and that dtype."""
    check_real("build", "positions", positions)
    dtype = resolve_dtype("build", dtype, positions, names="`positions`")
    x = jnp.asarray(positions).astype(dtype)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"build: `positions` must have shape [n, 2] or [n, 3], got {tuple(x.shape)}")
    if x.shape[0] < 1:
        raise ValueError("build: `positions` must hold at least one particle")
    check_values("build", "positions", x)
    return x, dtype


def _constraint_pairs(rods, ropes, n):
    """`build`'s rods then ropes as one [m, 2] pair array, and which of them are ropes."""
    rod_pairs, rope_pairs = _pairs("rods", rods, n), _pairs("ropes", ropes, n)
    is_rope = np.concatenate([np.zeros(len(rod_pairs), bool), np.ones(len(rope_pairs), bool)])
    return np.concatenate([rod_pairs, rope_pairs], 0), is_rope


def _skipped(collide, pairs, sets, x, radius, n, fixed):
    """The pairs `collide=True` (or "grid") skips (`contact.joined_at_rest`): those of one rod, rope or small
    constraint row, and those of one connected piece within contact distance at build, which needs the positions and the
    radius known now. An explicit list of pairs skips nothing; `collide=False` has nothing to skip."""
    if not ((isinstance(collide, (bool, np.bool_)) and collide) or isinstance(collide, str)):
        return pairs                            # False, None or an explicit list
    groups = [pairs] + [c.particles.array for c in sets]
    if not any(len(g) and np.shape(g)[-1] >= 2 for g in groups):
        return pairs
    r = None
    if radius is not None and np.ndim(radius) in (0, 1) and np.size(radius) in (1, n):
        xc, rc = concrete(x), concrete(radius)
        if xc is None or rc is None:
            raise TypeError("build: with collide=True and particles joined by rods, ropes or constraints, the pairs "
                            "already within contact distance at build are skipped, which needs `positions` and "
                            "`radius` known now, not traced; build the model outside the transformation (then "
                            "change its leaves), or pass `collide` as a list of (i, j) pairs")
        r = np.broadcast_to(np.asarray(rc, np.float64), (n,))
        x = xc
        if not (np.isfinite(r).all() and np.isfinite(np.asarray(x, np.float64)).all()):
            r = None                            # refused with a clear error further on (`_contact_leaves`)
    return joined_at_rest(n, groups, x, r, fixed)


def _collisions(collide, max_neighbours, n, dim, rods, sets, x, radius, fixed):
    """`build`'s particle-particle contacts: (static candidate pairs [k, 2], neighbour-grid capacity or 0, the
    pairs that never collide [m, 2] (`_skipped`))."""
    joined = _skipped(collide, rods, sets, x, radius, n, fixed)
    pairs = contact_pairs(collide, n, joined)
    # a particle has at most n - 1 partners: a larger capacity only costs memory and compile time (K = 1e4 with 20
    # particles took 70 s to compile), so it is capped at n
    grid_k = min(check_max_neighbours(max_neighbours, collide, dim), n) if uses_grid(collide, n) else 0
    if max_neighbours is not None and not grid_k:
        check_max_neighbours(max_neighbours, collide, dim)
    return pairs, grid_k, joined


def _velocities(velocities, x):
    """`build`'s initial velocities, checked, in the dtype of the positions x [n, dim] (zero when None)."""
    if velocities is None:
        return jnp.zeros_like(x)
    check_real("build", "velocities", velocities)
    check_shape("build", "velocities", velocities, x.shape)
    check_values("build", "velocities", velocities)
    return jnp.asarray(velocities).astype(x.dtype)


def _with_contacts(model, state, pairs, has_contacts, radius, planes, spheres, friction, restitution, threshold,
                   grid=(0, None)):
    """`build`'s (model, state) with its contact leaves and topology, and zero contact impulses."""
    if not has_contacts:
        given = [k for k, val in (("radius", radius), ("friction", friction), ("restitution", restitution),
                                  ("restitution_threshold", threshold)) if val is not None]
        if given:
            raise ValueError(f"build: `{given[0]}` is given but the model has no contacts; pass `planes`, "
                             "`spheres` or `collide`")
        return model, state
    t, dtype = model.topology, state.x.dtype
    grid_k, joined = grid
    leaves = _contact_leaves(t.n, t.dim, dtype, radius, planes, spheres, friction, restitution, threshold, pairs,
                             grid_k > 0)
    ct = ContactTopology(t.n, len(leaves["plane_offset"]), len(leaves["sphere_radius"]), pairs, t.pos, grid_k,
                         joined)
    model = model.replace(contact=ct, **leaves)
    state = state.replace(contact_n=jnp.zeros(ct.k, dtype), contact_t=jnp.zeros((ct.k, t.dim), dtype))
    if grid_k:
        state = state.replace(contact_partners=jnp.full((t.n, grid_k), -1, jnp.int32))
    return model, state


def _contact_leaves(n, dim, dtype, radius, planes, spheres, friction, restitution, threshold, pairs,
                    grid=False) -> dict:
    """The contact leaves of `build`, checked where known and cast to `dtype`."""
    def scalar(name, value, default, hi=None):
        if value is None:
            return jnp.asarray(default, dtype)
        check_scalar("build", name, value, 0.0, hi)
        return jnp.asarray(value).astype(dtype)

    if radius is None:
        r = jnp.zeros(n, dtype)
    else:
        check_real("build", "radius", radius)
        if np.ndim(radius) not in (0, 1):
            raise ValueError(f"build: `radius` must be a scalar or have shape ({n},), got {np.shape(radius)}")
        if np.ndim(radius) == 1:
            check_shape("build", "radius", radius, (n,))
        check_values("build", "radius", radius, nonneg=True)
        r = jnp.broadcast_to(jnp.asarray(radius).astype(dtype), (n,))
    check_contact_radii("build", "radius", concrete(r), pairs, grid)
    normals, offsets = _obstacles("planes", planes, dim, dtype, "(normal, offset)")
    centres, radii = _obstacles("spheres", spheres, dim, dtype, "(centre, R)")
    check_values("build", "spheres' R", radii, positive=True)
    nc = concrete(normals)
    if nc is not None and len(nc):
        norm = np.linalg.norm(np.asarray(nc, np.float64), axis=-1)
        if (norm == 0).any():
            raise ValueError(f"build: `planes[{int(np.argmax(norm == 0))}]` has a zero normal")
        normals = jnp.asarray(np.asarray(nc, np.float64) / norm[:, None], dtype)
    elif len(normals):
        normals = _layout.safe_norm(normals, axis=-1)[1]
    return dict(radius=r, friction=scalar("friction", friction, 0.0),
                restitution=scalar("restitution", restitution, 0.0, 1.0),
                restitution_threshold=scalar("restitution_threshold", threshold, 0.5),
                plane_normal=normals, plane_offset=offsets, sphere_centre=centres, sphere_radius=radii)


def _obstacles(name, items, dim, dtype, form):
    """[(vector [dim], scalar), ...] -> ([k, dim], [k]) arrays in `dtype`."""
    if items is None:
        items = []
    try:
        items = list(items)
    except TypeError:
        raise TypeError(f"build: `{name}` must be a list of {form} tuples, got {type(items).__name__}") from None
    vecs, scalars = [], []
    for q, item in enumerate(items):
        try:
            a, b = item
        except (TypeError, ValueError):
            raise ValueError(f"build: `{name}[{q}]` must be a {form} tuple, got {item!r}") from None
        check_real("build", f"{name}[{q}]", a)
        check_real("build", f"{name}[{q}]", b)
        check_shape("build", f"{name}[{q}][0]", a, (dim,))
        check_shape("build", f"{name}[{q}][1]", b, ())
        check_values("build", f"{name}[{q}]", a)
        check_values("build", f"{name}[{q}]", b)
        vecs.append(jnp.asarray(a).astype(dtype))
        scalars.append(jnp.asarray(b).astype(dtype))
    if not vecs:
        return jnp.zeros((0, dim), dtype), jnp.zeros((0,), dtype)
    return jnp.stack(vecs), jnp.stack(scalars)


def _rest_lengths(rest_lengths, positions, x, i, j, dtype):
    """[m] rest lengths: as given (checked), or the initial distances (in float64 when known now)."""
    if rest_lengths is None:
        xc = concrete(positions)
        if xc is not None:      # known now: the distances in float64, rounded once
            xc = np.asarray(xc, np.float64)
            return jnp.asarray(np.linalg.norm(xc[j] - xc[i], axis=-1), dtype)
        return _layout.safe_norm(x[j] - x[i], axis=-1)[0]
    check_real("build", "rest_lengths", rest_lengths)
    check_shape("build", "rest_lengths", rest_lengths, (len(i),))
    check_values("build", "rest_lengths", rest_lengths, nonneg=True)
    return jnp.asarray(rest_lengths).astype(dtype)


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


def _topology(n, dim, i, j, is_rope, colouring, grid_shape, layout, fixed, sets=()) -> Topology:
    """`build`'s static topology: the colouring (checked, or the default with hub stars; constraints of one
    colour may share a fixed particle), the constraint sets' and the layout."""
    colour, star = _colouring(colouring, i, j, n, fixed)
    return Topology(n, dim, i, j, is_rope, colour, _view(grid_shape, n), layout, star=star, fixed=fixed, sets=sets)


def _constraint_sets(constraints, x, fixed, dtype) -> list:
    """`build`'s constraint sets, checked against the model (n particles, `fixed`, dim) and with their floating
    leaves in the model's dtype; names made unique."""
    n, dim = x.shape
    out, sets = [], flatten_sets(constraints)
    names = _unique_names([c.name for c in sets])
    for c, name in zip(sets, names):
        p = c.particles.array
        bad = (p < 0) | (p >= n)
        if bad.any():
            r = int(np.argwhere(bad)[0][0])
            raise ValueError(f"build: constraint set {c.name!r}: `particles[{r}]` = {p[r].tolist()} has an index out "
                             f"of range (there are {n} particles)")
        frozen = fixed[p].all(axis=1)
        if frozen.any():
            r = int(np.argmax(frozen))
            raise ValueError(f"build: constraint set {c.name!r}: `particles[{r}]` = {p[r].tolist()} are all fixed, so "
                             "the constraint can move nothing")
        one = {k: jax.ShapeDtypeStruct(np.shape(v)[1:], jnp.result_type(v)) for k, v in c.params.items()}
        try:
            out_shape = jax.eval_shape(c.fn, jax.ShapeDtypeStruct((c.arity, dim), dtype), one)
        except Exception as e:           # noqa: BLE001 - the user's function failed on the right shapes
            raise ValueError(f"build: constraint set {c.name!r}: `fn` failed on x [{c.arity}, {dim}] and one "
                             f"constraint's params: {type(e).__name__}: {e}") from None
        if not (hasattr(out_shape, "shape") and out_shape.shape == ()):
            raise ValueError(f"build: constraint set {c.name!r}: `fn` must return a scalar for x [{c.arity}, {dim}], "
                             f"got {getattr(out_shape, 'shape', out_shape)}")
        if c.grad is not None:
            _check_grad(c, dim, dtype, one)
        cast = {k: jnp.asarray(v).astype(dtype) if jnp.issubdtype(jnp.result_type(v), jnp.floating) else v
                for k, v in c.params.items()}
        _check_finite_rows(c, name, x, cast)
        out.append(c.replace(params=cast, compliance=jnp.asarray(c.compliance).astype(dtype), name=name))
    return out


def _check_finite_rows(c, name, x, params) -> None:
    """Refuse a set with a row whose C is not finite at the positions it is built at (where those and its
    params are known now): such a row would be inactive from the first step, silently."""
    if concrete(x) is None or any(concrete(v) is None for v in params.values()):
        return
    C = np.asarray(jax.vmap(lambda idx, p: c.fn(x[idx], p))(jnp.asarray(c.particles.array), params))
    bad = ~np.isfinite(C)
    if bad.any():
        r = int(np.argmax(bad))
        raise ValueError(f"build: constraint set {name!r}: `fn` is {C[r]} at `positions` for `particles[{r}]` = "
                         f"{c.particles.array[r].tolist()} ({int(bad.sum())} of {c.m} rows not finite); a row whose "
                         "C is not finite is inactive, so this constraint would never act")


def _unique_names(names) -> list:
    """Each set's name, unique: a name's first set keeps it, a repeat becomes "<name>_<k>" with the smallest
    k >= 1 that no set is named (so "d", "d", "d_1" give "d", "d_2", "d_1")."""
    given, taken, out = set(names), set(), []
    for name in names:
        new, k = name, 1
        while new in taken:
            new = f"{name}_{k}"
            while new in given or new in taken:
                k += 1
                new = f"{name}_{k}"
        taken.add(new)
        out.append(new)
    return out


def _check_grad(c, dim, dtype, one):
    """A set's hand-written gradient must run on x [k, dim] and one constraint's params and return [k, dim]."""
    try:
        g = jax.eval_shape(c.grad, jax.ShapeDtypeStruct((c.arity, dim), dtype), one)
    except Exception as e:           # noqa: BLE001 - the user's function failed on the right shapes
        raise ValueError(f"build: constraint set {c.name!r}: `grad` failed on x [{c.arity}, {dim}] and one "
                         f"constraint's params: {type(e).__name__}: {e}") from None
    if getattr(g, "shape", None) != (c.arity, dim):
        raise ValueError(f"build: constraint set {c.name!r}: `grad` must return the gradient of `fn`, "
                         f"[{c.arity}, {dim}], got {getattr(g, 'shape', g)}")


def _colouring(colouring, i, j, n, fixed):
    """(colour [m], star [m]): the default colouring with stars around hubs (`star_colouring`), or the user's
    (checked; no stars)."""
    if colouring is None:
        star, colour = star_colouring(i, j, n, fixed)
        return colour, star
    colour = np.asarray(colouring)
    check_shape("build", "colouring", colour, (len(i),))
    if colour.dtype.kind not in "iu" or (colour < 0).any():
        raise ValueError("build: `colouring` must hold non-negative integers")
    check_colouring(i, j, colour, n, fixed)
    return colour, None


def _view(grid_shape, n):
    if grid_shape is None:
        return (n,)
    view = tuple(int(s) for s in grid_shape)
    if int(np.prod(view)) != n or any(s < 1 for s in view):
        raise ValueError(f"build: `grid_shape` {view} must multiply to the number of particles {n}")
    return view
