"""Constraints of any kind: `Constraint` (a user's C(x) = 0 or C(x) >= 0 with J = dC/dx from autodiff) and the
built-in kinds written through it (`bending`, `angle`, `angle_limits`, `area`, `volume`, `distance`).

A `Constraint` declares m constraints of one kind. `fn(x, p) -> scalar` is C for one of them: `x` is [k, dim],
the positions of its k particles in the order given, `p` a dict holding that constraint's entry of each
parameter. The force it applies is J^T lam with J = dC/dx; a unilateral constraint keeps C >= 0 with lam >= 0.
`compliance` alpha (m/N for a length, 1/(N m) for an angle: the inverse stiffness of C) gives the constraint the
potential energy C^2 / (2 alpha); 0 is a hard constraint.

Sign convention inside the solvers. Rods and ropes keep the library's tension convention (lam > 0 pulls their
particles together), which is a distance kind with C = L - |x_j - x_i|: the same lam. The solvers work with
-C (`C_lib`, the stretch of a rod) and -J v, and apply w_p J_p lam: written so, a rod's update is the same
arithmetic whichever path computes it (docs/constraints.md).
"""
from __future__ import annotations

from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core.checks import check_real, check_values
from jaxcon.core.pytree import StaticArray, concrete

Array = Any


class Constraint:
    """m constraints of one kind: `fn(x [k, dim], p) -> C`, on `particles` [m, k] (particle indices), with
    parameters `params` {name: [m, ...]} and `compliance` (a scalar or [m], >= 0). A pytree: the parameters and
    the compliance are leaves (differentiable, batchable, fitted by `jc.fit` as "<name>.<param>" and
    "<name>.compliance"); `fn`, the particles, `unilateral` and `name` are static.

    Args:
      fn: C for one constraint, a JAX-traceable function of x [k, dim] and a dict p of that constraint's
        parameters (each param's entry, shape [...] for a param of shape [m, ...]). Returns a scalar. Its
        gradient is taken with `jax.grad`; where it is not finite (a degenerate configuration) the constraint
        is inactive for that step.
      particles: [m, k] particle indices (k >= 1), the order `fn` sees them in.
      params: {name: [m, ...] array}, or None.
      unilateral: False for C = 0 (pushes and pulls), True for C >= 0 (lam >= 0: it only pushes C up).
      compliance: alpha >= 0, a scalar or [m]: the constraint's potential energy is C^2 / (2 alpha).
      name: the set's name (for `jc.fit` and error messages); default fn.__name__, made unique by `jc.build`.
      grad: optionally, `grad(x, p) -> [k, dim]`, the gradient of `fn` written by hand (a tuned kernel: the
        built-in `bending` has one). The solvers use it in place of `jax.grad(fn)`; derivatives through a rollout
        differentiate it in turn. `jc.build` checks its shape; tests/test_constraints_layout.py checks the
        built-in one against `jax.grad`.
    """

    def __init__(self, fn: Callable, particles, params: Optional[dict] = None, *, unilateral: bool = False,
                 compliance=0.0, name: Optional[str] = None, grad: Optional[Callable] = None):
        if not callable(fn):
            raise TypeError(f"Constraint: `fn` must be a function (x [k, dim], p) -> scalar, got {type(fn).__name__}")
        if grad is not None and not callable(grad):
            raise TypeError(f"Constraint: `grad` must be None or a function (x [k, dim], p) -> [k, dim], got "
                            f"{type(grad).__name__}")
        idx = _particles(particles)
        m = idx.shape[0]
        if not isinstance(unilateral, (bool, np.bool_)):
            raise TypeError(f"Constraint: `unilateral` must be a bool, got {unilateral!r}")
        if name is not None and (not isinstance(name, str) or not name or "." in name):
            raise ValueError(f"Constraint: `name` must be a non-empty string without '.', got {name!r}")
        self.fn, self.grad = fn, grad
        self.particles = StaticArray(idx)
        self.unilateral = bool(unilateral)
        self.name = name if name is not None else getattr(fn, "__name__", "constraint")
        self.params = _params(params or {}, m, self.name)
        self.compliance = _compliance(compliance, m, self.name)

    @property
    def m(self) -> int:
        return int(self.particles.array.shape[0])

    @property
    def arity(self) -> int:
        return int(self.particles.array.shape[1])

    def replace(self, **changes) -> "Constraint":
        """A copy with `params`, `compliance` or `name` replaced (checked as by the constructor)."""
        bad = set(changes) - {"params", "compliance", "name"}
        if bad:
            raise ValueError(f"Constraint.replace: cannot replace {sorted(bad)}; build a new Constraint")
        return Constraint(self.fn, self.particles.array, changes.get("params", self.params),
                          unilateral=self.unilateral, compliance=changes.get("compliance", self.compliance),
                          name=changes.get("name", self.name), grad=self.grad)

    def __repr__(self):
        kind = "C >= 0" if self.unilateral else "C = 0"
        return (f"Constraint({self.name!r}, {self.m} x {self.arity} particles, {kind}, params "
                f"{sorted(self.params)})")


def _flatten(c):
    keys = sorted(c.params)
    children = [(jax.tree_util.DictKey(k), c.params[k]) for k in keys] + \
        [(jax.tree_util.GetAttrKey("compliance"), c.compliance)]
    return children, (c.fn, c.particles, c.unilateral, c.name, tuple(keys), c.grad)


def _unflatten(aux, children):
    c = object.__new__(Constraint)
    c.fn, c.particles, c.unilateral, c.name, keys, c.grad = aux
    c.params = dict(zip(keys, children[:-1]))
    c.compliance = children[-1]
    return c


jax.tree_util.register_pytree_with_keys(Constraint, _flatten, _unflatten,
                                        lambda c: ([c.params[k] for k in sorted(c.params)] + [c.compliance],
                                                   _flatten(c)[1]))


def _particles(particles) -> np.ndarray:
    try:
        a = np.asarray(particles)
    except ValueError:
        raise ValueError("Constraint: `particles` must be an [m, k] array of particle indices; the rows are of "
                         "different lengths (ragged)") from None
    if a.dtype == object:
        raise ValueError("Constraint: `particles` must be an [m, k] array of particle indices; the rows are of "
                         "different lengths (ragged)")
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"Constraint: `particles` must be an [m, k] array of particle indices (m, k >= 1), got "
                         f"shape {a.shape}")
    if a.dtype.kind not in "iu":
        if a.dtype.kind == "f" and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
            a = a.astype(np.int64)
        else:
            raise ValueError(f"Constraint: `particles` must hold integer particle indices, got dtype {a.dtype}")
    a = a.astype(np.int64)
    for r, row in enumerate(a):
        if len(set(row.tolist())) != len(row):
            raise ValueError(f"Constraint: `particles[{r}]` = {row.tolist()} names a particle twice")
    return a


def _params(params: dict, m: int, name: str) -> dict:
    if not isinstance(params, dict):
        raise TypeError(f"Constraint {name!r}: `params` must be a dict {{name: [m, ...] array}}, got "
                        f"{type(params).__name__}")
    out = {}
    for key, value in params.items():
        if not isinstance(key, str) or not key or "." in key:
            raise ValueError(f"Constraint {name!r}: parameter names must be non-empty strings without '.', got "
                             f"{key!r}")
        check_real(f"Constraint {name!r}", f"params[{key!r}]", value)
        shape = np.shape(value)
        if len(shape) < 1 or shape[0] != m:
            raise ValueError(f"Constraint {name!r}: `params[{key!r}]` must have a leading axis of {m} (one entry "
                             f"per constraint), got shape {shape}")
        check_values(f"Constraint {name!r}", f"params[{key!r}]", value)
        out[key] = value if hasattr(value, "dtype") else np.asarray(value, np.float64)
    return out


def _compliance(value, m: int, name: str):
    check_real(f"Constraint {name!r}", "compliance", value)
    if np.ndim(value) not in (0, 1) or (np.ndim(value) == 1 and np.shape(value)[0] != m):
        raise ValueError(f"Constraint {name!r}: `compliance` must be a scalar or have shape ({m},), got shape "
                         f"{np.shape(value)}")
    check_values(f"Constraint {name!r}", "compliance", value, nonneg=True)
    if np.ndim(value) == 0:
        c = concrete(value)
        return np.full(m, float(c)) if c is not None else jnp.broadcast_to(value, (m,))
    return value


# ---- built-in kinds ------------------------------------------------------------------------------------------
def _rest(name, rest, fn, positions, particles, key="rest"):
    """A kind's rest values [m]: as given, or fn at `positions` (the configuration it was built in)."""
    if rest is not None:
        return {key: rest if np.ndim(rest) else np.full(len(particles), float(rest))}
    if positions is None:
        raise ValueError(f"{name}: pass `rest` or the `positions` to take it from")
    x = jnp.asarray(positions)
    n = x.shape[0] if x.ndim == 2 else None
    if n is None:
        raise ValueError(f"{name}: `positions` must be [n, dim], got shape {tuple(x.shape)}")
    bad = (particles < 0) | (particles >= n)
    if bad.any():       # JAX indexing would clamp (or wrap) these silently
        r = int(np.argwhere(bad)[0][0])
        raise ValueError(f"{name}: `particles[{r}]` = {particles[r].tolist()} is out of range for the {n} particles "
                         f"in `positions` (indices must be in [0, {n - 1}])")
    return {key: jax.vmap(lambda idx: fn(x[idx], {key: jnp.zeros((), x.dtype)}))(jnp.asarray(particles))}


def _cross(a, b):
    """Cross product of 3-vectors along the last axis, or the scalar z-component of 2-vectors."""
    if a.shape[-1] == 2:
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return jnp.cross(a, b)


def dihedral(x, p):
    """Bending across the edge (x0, x1) shared by triangles (x0, x1, x2) and (x0, x1, x3): the dihedral angle
    (rad, 0 for a flat pair, signed) minus p["rest"]. 3-D."""
    e = x[1] - x[0]
    n1 = jnp.cross(e, x[2] - x[0])
    n2 = jnp.cross(x[3] - x[0], e)
    e_unit = e / jnp.sqrt(jnp.sum(e * e))
    theta = jnp.arctan2(jnp.sum(jnp.cross(n1, n2) * e_unit), jnp.sum(n1 * n2))
    return theta - p["rest"]


def dihedral_grad(x, p):
    """The gradient of `dihedral` ([4, 3]), written out (Bridson, Marino and Fedkiw 2003): a wing moves the angle
    at the rate 1 / (its height over the edge) along its triangle's normal, and the edge's ends take what keeps
    the sum zero, weighted by where each wing's foot lies along the edge. Autodiff of `dihedral` evaluated
    about 2.5x slower on CPU (its atan2 and three normalisations)."""
    e = x[1] - x[0]
    n1 = jnp.cross(e, x[2] - x[0])
    n2 = jnp.cross(x[3] - x[0], e)
    length = jnp.sqrt(jnp.sum(e * e))
    e_unit = e / length
    a1 = n1 / jnp.sum(n1 * n1)
    a2 = n2 / jnp.sum(n2 * n2)
    g0 = jnp.sum((x[2] - x[1]) * e_unit) * a1 + jnp.sum((x[3] - x[1]) * e_unit) * a2
    g1 = -jnp.sum((x[2] - x[0]) * e_unit) * a1 - jnp.sum((x[3] - x[0]) * e_unit) * a2
    return -jnp.stack([g0, g1, length * a1, length * a2])


def bending(particles, *, rest=None, compliance=0.0, positions=None, name="bending"):
    """Dihedral bending constraints (`dihedral`) on [m, 4] particles (edge i, j; wings k, l), 3-D. `rest`:
    [m] rest angles (rad), or taken from `positions`; `compliance` in 1/(N m) (0: rigid hinges)."""
    particles = _particles(particles)
    if particles.shape[1] != 4:
        raise ValueError(f"{name}: `particles` must be [m, 4] (edge i, j, then the two wings), got {particles.shape}")
    return Constraint(dihedral, particles, _rest(name, rest, dihedral, positions, particles),
                      compliance=compliance, name=name, grad=dihedral_grad)


def corner_angle(x, p):
    """The angle (rad) at x1 between x0 - x1 and x2 - x1, minus p["rest"]: signed in 2-D (counter-clockwise
    from x0 - x1), in [0, pi] in 3-D (not differentiable at 0 and pi there)."""
    u, v = x[0] - x[1], x[2] - x[1]
    c = _cross(u, v)
    s = c if x.shape[-1] == 2 else jnp.sqrt(jnp.sum(c * c))
    return jnp.arctan2(s, jnp.sum(u * v)) - p["rest"]


def _wrap(a):
    """An angle (rad) wrapped into (-pi, pi]."""
    return a - 2 * jnp.pi * jnp.ceil((a - jnp.pi) / (2 * jnp.pi))


def bend_angle(x, p):
    """`corner_angle`, with the difference from p["rest"] wrapped into (-pi, pi] in 2-D: C is continuous at the
    rest angle wherever it lies (a straight arm's rest angle pi is on atan2's branch cut), and the constraint
    pulls the short way round. In 3-D the angle lies in [0, pi] and nothing is wrapped."""
    d = corner_angle(x, p)
    return _wrap(d) if x.shape[-1] == 2 else d


def angle(particles, *, rest=None, compliance=0.0, positions=None, name="angle"):
    """Angle constraints (`bend_angle`) at the middle of [m, 3] particles, 2-D or 3-D; `rest` [m] (rad) or
    taken from `positions` (in 2-D in (-pi, pi]: a straight arm's rest is pi, held from either side)."""
    particles = _particles(particles)
    if particles.shape[1] != 3:
        raise ValueError(f"{name}: `particles` must be [m, 3] (the angle is at the middle one), got {particles.shape}")
    r = _rest(name, rest, corner_angle, positions, particles)
    if rest is None:
        r = {"rest": _wrap(r["rest"])}       # atan2(-0.0, -1) = -pi: the same angle as pi
    return Constraint(bend_angle, particles, r, compliance=compliance, name=name)


def angle_limits(particles, lo, hi, *, name="angle_limit"):
    """A joint limit: the angle at the middle of [m, 3] particles kept within [lo, hi] (rad), as a unilateral
    pair (`corner_angle` - lo >= 0 and hi - `corner_angle` >= 0). Returns a list of two Constraints."""
    particles = _particles(particles)
    m = len(particles)
    lo_, hi_ = np.broadcast_to(np.asarray(lo, np.float64), (m,)), np.broadcast_to(np.asarray(hi, np.float64), (m,))
    if np.any(lo_ > hi_):
        raise ValueError(f"{name}: `lo` must be <= `hi`")

    def upper(x, p):
        return -corner_angle(x, p)
    return [Constraint(corner_angle, particles, {"rest": lo_}, unilateral=True, name=f"{name}_lo"),
            Constraint(upper, particles, {"rest": hi_}, unilateral=True, name=f"{name}_hi")]


def polygon_area(x, p):
    """The area of the polygon x[0], ..., x[k-1], minus p["rest"]. In 2-D the signed area (counter-clockwise
    positive); in 3-D the magnitude of the vector area sum(x_i x x_{i+1}) / 2 (the area of a planar polygon in any
    orientation; not differentiable at area 0, where the row is inactive)."""
    y = jnp.roll(x, -1, axis=0)
    if x.shape[-1] == 2:
        return 0.5 * jnp.sum(x[:, 0] * y[:, 1] - y[:, 0] * x[:, 1]) - p["rest"]
    a = 0.5 * jnp.sum(jnp.cross(x, y), axis=0)
    return jnp.sqrt(jnp.sum(a * a)) - p["rest"]


def area(particles, *, rest=None, compliance=0.0, positions=None, name="area"):
    """Area constraints (`polygon_area`) on [m, k] particles, each a polygon in order: signed in 2-D, the
    vector area's magnitude in 3-D; `rest` or taken from `positions`."""
    particles = _particles(particles)
    if particles.shape[1] < 3:
        raise ValueError(f"{name}: a polygon needs at least 3 particles, got {particles.shape[1]}")
    return Constraint(polygon_area, particles, _rest(name, rest, polygon_area, positions, particles),
                      compliance=compliance, name=name)


def tetra_volume(x, p):
    """The signed volume of the tetrahedron x0..x3 (positive when x1 - x0, x2 - x0, x3 - x0 are right-handed),
    minus p["rest"]. 3-D."""
    return jnp.dot(x[1] - x[0], jnp.cross(x[2] - x[0], x[3] - x[0])) / 6 - p["rest"]


def volume(particles, *, faces=None, rest=None, compliance=0.0, positions=None, name="volume"):
    """Volume constraints, 3-D: tetrahedra ([m, 4] particles, `tetra_volume`), or with `faces` one closed
    triangle mesh ([1, k] particles: its vertices; `faces` [F, 3] indices into them, oriented outwards), whose
    enclosed volume sum(x_a . (x_b x x_c)) / 6 is kept. `rest` or taken from `positions`."""
    particles = _particles(particles)
    if faces is None:
        if particles.shape[1] != 4:
            raise ValueError(f"{name}: tetrahedra need [m, 4] particles (or pass `faces` for a closed mesh), got "
                             f"{particles.shape}")
        return Constraint(tetra_volume, particles, _rest(name, rest, tetra_volume, positions, particles),
                          compliance=compliance, name=name)
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu" or f.min() < 0 or f.max() >= particles.shape[1]:
        raise ValueError(f"{name}: `faces` must be [F, 3] indices into the {particles.shape[1]} mesh vertices")
    fa, fb, fc = (np.asarray(f[:, c]) for c in range(3))

    def mesh_volume(x, p):
        return jnp.sum(jnp.sum(x[fa] * jnp.cross(x[fb], x[fc]), -1)) / 6 - p["rest"]
    mesh_volume.__name__ = name
    return Constraint(mesh_volume, particles, _rest(name, rest, mesh_volume, positions, particles),
                      compliance=compliance, name=name)


def length(x, p):
    """|x1 - x0| - p["rest"]: a distance written as a user constraint (the built-in rods do the same faster)."""
    d = x[1] - x[0]
    return jnp.sqrt(jnp.sum(d * d)) - p["rest"]


def distance(particles, *, rest=None, compliance=0.0, positions=None, unilateral=False, name="distance"):
    """Distance constraints (`length`) on [m, 2] particles; `rest` or taken from `positions`. With
    `unilateral`, C = |d| - L >= 0 keeps them at least L apart (a strut that only pushes)."""
    particles = _particles(particles)
    if particles.shape[1] != 2:
        raise ValueError(f"{name}: `particles` must be [m, 2] (pairs), got {particles.shape}")
    if rest is not None:
        check_real(name, "rest", rest)
        check_values(name, "rest", rest, nonneg=True)     # |d| = negative L has no solution
    return Constraint(length, particles, _rest(name, rest, length, positions, particles), unilateral=unilateral,
                      compliance=compliance, name=name)


def is_constraint(c) -> bool:
    return isinstance(c, Constraint)


def flatten_sets(constraints) -> list:
    """`build`'s `constraints`: a Constraint or a (nested) list of them, flattened in order."""
    if constraints is None:
        return []
    if isinstance(constraints, Constraint):
        return [constraints]
    out = []
    try:
        items = list(constraints)
    except TypeError:
        raise TypeError(f"build: `constraints` must be a list of jc.Constraint, got {type(constraints).__name__}") from None
    for c in items:
        if isinstance(c, (list, tuple)):
            out += flatten_sets(c)
        elif isinstance(c, Constraint):
            out.append(c)
        else:
            raise TypeError(f"build: `constraints` must hold jc.Constraint objects, got {type(c).__name__}")
    return out


__all__ = ["Constraint", "bending", "angle", "angle_limits", "area", "volume", "distance", "dihedral",
           "corner_angle", "bend_angle", "polygon_area", "tetra_volume", "length"]
