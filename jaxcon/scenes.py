"""Ready-made scenes. Each returns (model, state).

Pendulum-like scenes are 2-D; particle 0 is the fixed pivot at the origin, particles 1..n the bobs in order,
constraint k joins particle k to particle k+1. Angles are from the downward vertical, counter-clockwise
positive: bob = previous + L (sin a, -cos a).
"""
from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp
import numpy as np

from jaxcon.core import constraints
from jaxcon.core.checks import check_real, check_values, resolve_dtype
from jaxcon.core.model import build
from jaxcon.core.pytree import concrete

# Every physical value of a scene (lengths, masses, angles, size) may be a traced JAX value: scenes build their
# arrays with jax.numpy, so `jax.grad` of a rollout with respect to an initial angle or a length goes through
# the scene. Values known now are checked; traced ones cannot be. Counts (n_links, nx, ny) are static.


def _value(owner, name, value, shape, *, positive=False):
    """A scalar or an array of `shape`, real and finite (and > 0 if `positive`) where known now."""
    check_real(owner, name, value)
    if np.shape(value) != tuple(shape):
        want = "a scalar" if shape == () else f"shape {tuple(shape)}"
        raise ValueError(f"{owner}: `{name}` must be {want}, got shape {np.shape(value)}")
    check_values(owner, name, value, positive=positive)
    return value


def _dtype(owner, dtype, *values):
    return resolve_dtype(owner, dtype, *values)


def _planar_chain(lengths, angles):
    """[n + 1, 2] positions: the pivot at the origin, then each bob at the previous + L (sin a, -cos a)."""
    steps = jnp.stack([lengths * jnp.sin(angles), -lengths * jnp.cos(angles)], -1)
    return jnp.concatenate([jnp.zeros((1, 2), steps.dtype), jnp.cumsum(steps, 0)], 0)


def _link_chain(owner, lengths, masses, angles, kind, dtype, gravity):
    if kind not in ("rod", "rope"):
        raise ValueError(f"{owner}: `kind` must be 'rod' or 'rope', got {kind!r}")
    cast = lambda a: jnp.asarray(a).astype(dtype)  # noqa: E731
    x = _planar_chain(cast(lengths), cast(angles))
    pairs = [(k, k + 1) for k in range(len(x) - 1)]
    return build(
        x, jnp.concatenate([jnp.ones(1, dtype), cast(masses)]), rods=pairs if kind == "rod" else None,
        ropes=pairs if kind == "rope" else None, fixed=[0], gravity=gravity,
    )


def pendulum(length: float = 1.0, mass: float = 1.0, angle: float = 0.3, *, kind: str = "rod",
             dtype=None, gravity=None):
    """A single 2-D pendulum: fixed pivot at the origin and one bob of `mass` kg on a rod (or rope) of `length`
    m, at `angle` rad from the downward vertical. dtype: None for JAX's default float dtype (float64 under
    x64), unless a float array is passed as a value."""
    _value("pendulum", "length", length, (), positive=True)
    _value("pendulum", "mass", mass, (), positive=True)
    _value("pendulum", "angle", angle, ())
    dtype = _dtype("pendulum", dtype, length, mass, angle)
    return _link_chain("pendulum", jnp.reshape(jnp.asarray(length), (1,)), jnp.reshape(jnp.asarray(mass), (1,)),
                       jnp.reshape(jnp.asarray(angle), (1,)), kind, dtype, gravity)


def double_pendulum(lengths: Sequence[float] = (1.0, 1.0), masses: Sequence[float] = (1.0, 1.0),
                    angles: Sequence[float] = (1.5708, 1.5708), *, dtype=None, gravity=None):
    """A 2-D double pendulum of two rods; `angles` are absolute angles of each rod from the downward vertical."""
    _value("double_pendulum", "lengths", lengths, (2,), positive=True)
    _value("double_pendulum", "masses", masses, (2,), positive=True)
    _value("double_pendulum", "angles", angles, (2,))
    dtype = _dtype("double_pendulum", dtype, lengths, masses, angles)
    return _link_chain("double_pendulum", lengths, masses, angles, "rod", dtype, gravity)


def chain(n_links: int = 50, length: float = 5.0, mass: float = 0.5, end_mass: float | None = None,
          angle: float = 1.5708, kind: str = "rod", *, dtype=None, gravity=None):
    """A straight chain of `n_links` equal links (total `length` m) hanging from a fixed pivot, released at
    `angle` from the downward vertical. `mass` is the total mass spread over the bobs; the last bob weighs
    `end_mass` instead when given. `kind`: 'rod' (bilateral) or 'rope' (unilateral)."""
    if isinstance(n_links, bool) or not isinstance(n_links, (int, np.integer)) or n_links < 1:
        raise ValueError(f"chain: `n_links` must be an int >= 1, got {n_links!r}")
    _value("chain", "length", length, (), positive=True)
    _value("chain", "mass", mass, (), positive=True)
    _value("chain", "angle", angle, ())
    if end_mass is not None:
        _value("chain", "end_mass", end_mass, (), positive=True)
    dtype = _dtype("chain", dtype, length, mass, angle, *([] if end_mass is None else [end_mass]))
    masses = jnp.full(n_links, jnp.asarray(mass).astype(dtype) / n_links)
    if end_mass is not None:
        masses = masses.at[-1].set(jnp.asarray(end_mass).astype(dtype))
    lengths = jnp.full(n_links, jnp.asarray(length).astype(dtype) / n_links)
    return _link_chain("chain", lengths, masses, jnp.full(n_links, jnp.asarray(angle).astype(dtype)), kind,
                       dtype, gravity)


def cloth_edges(nx: int, ny: int):
    """Structural and shear edges of an nx-by-ny grid (row-major particle index r * nx + c) and a colouring
    with 8 colours whose every colour is a strided box of the grid: horizontal edges split by column parity,
    vertical edges by row parity, and each diagonal direction by column parity when nx is even (by row
    parity when it is odd). With nx even, the model stores each row as its even columns then its odd ones
    (see jaxcon.core.topology), and every colour, diagonals included, is then one box of unit-step row runs."""
    idx = np.arange(nx * ny).reshape(ny, nx)
    groups = []
    for c0 in (0, 1):
        groups.append((idx[:, c0:-1:2], idx[:, c0 + 1::2]))
    for r0 in (0, 1):
        groups.append((idx[r0:-1:2, :], idx[r0 + 1::2, :]))
    if nx % 2 == 0:
        for c0 in (0, 1):
            groups.append((idx[:-1, c0:-1:2], idx[1:, c0 + 1::2]))
        for c0 in (0, 1):
            groups.append((idx[:-1, c0 + 1::2], idx[1:, c0:-1:2]))
    else:
        for r0 in (0, 1):
            groups.append((idx[r0:-1:2, :-1], idx[r0 + 1::2, 1:]))
        for r0 in (0, 1):
            groups.append((idx[r0:-1:2, 1:], idx[r0 + 1::2, :-1]))
    pairs, colour = [], []
    for c, (a, b) in enumerate(groups):
        if a.size:
            pairs.append(np.stack([a.ravel(), b.ravel()], -1))
            colour.append(np.full(a.size, c))
    return np.concatenate(pairs), np.concatenate(colour)


def cloth_hinges(nx: int, ny: int) -> np.ndarray:
    """The interior edges of an nx-by-ny grid triangulated along the diagonals (r, c)-(r+1, c+1), each with its
    two wings: [h, 4] particle indices (edge i, j, then the wings on either side), for `jc.constraints.bending`.
    Every edge shared by two triangles: the diagonals, the horizontal edges of interior rows and the vertical
    edges of interior columns."""
    idx = np.arange(nx * ny).reshape(ny, nx)
    diag = np.stack([idx[:-1, :-1], idx[1:, 1:], idx[:-1, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    horiz = np.stack([idx[1:-1, :-1], idx[1:-1, 1:], idx[:-2, :-1], idx[2:, 1:]], -1).reshape(-1, 4)
    vert = np.stack([idx[:-1, 1:-1], idx[1:, 1:-1], idx[1:, 2:], idx[:-1, :-2]], -1).reshape(-1, 4)
    return np.concatenate([diag, horiz, vert])


def cloth(nx: int = 32, ny: int = 32, size: float = 1.0, mass: float = 1.0, *, dtype=None, gravity=None,
          layout: str = "auto", bending=None):
    """A 3-D square cloth of nx-by-ny particles, side `size` m and total `mass` kg, lying horizontally in the
    z = 0 plane (gravity along -z), held by its two corners of the edge y = 0. Rods on structural and shear
    edges. `layout`: see `jc.build`. `bending`: None, or a compliance alpha >= 0 (rad per N m; 0 is rigid) of
    `jc.constraints.bending` on every interior edge of the grid triangulated along its (r, c)-(r+1, c+1)
    diagonals (`cloth_hinges`), rest angle 0 (flat), the set named "bending"."""
    for name, v in (("nx", nx), ("ny", ny)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
            raise ValueError(f"cloth: `{name}` must be an int >= 2, got {v!r}")
    _value("cloth", "size", size, (), positive=True)
    _value("cloth", "mass", mass, (), positive=True)
    dtype = _dtype("cloth", dtype, size, mass)
    s = jnp.asarray(size).astype(dtype)
    u = jnp.linspace(0, 1, nx, dtype=dtype)[None, :] * jnp.ones((ny, 1), dtype)
    w = jnp.linspace(0, 1, ny, dtype=dtype)[:, None] * jnp.ones((1, nx), dtype)
    x = jnp.stack([s * u.ravel(), s * w.ravel(), jnp.zeros(nx * ny, dtype)], -1)
    pairs, colour = cloth_edges(nx, ny)
    masses = jnp.full(nx * ny, jnp.asarray(mass).astype(dtype) / (nx * ny))
    sets = None
    if bending is not None:
        if nx < 3 and ny < 3:
            raise ValueError(f"cloth: `bending` needs interior edges, a grid of at least 2 by 3; got {nx} by {ny}")
        hinges = cloth_hinges(nx, ny)
        sets = [constraints.bending(hinges, rest=np.zeros(len(hinges)), compliance=bending, name="bending")]
    return build(x, masses, rods=pairs, fixed=[0, nx - 1], gravity=gravity, colouring=colour,
                 grid_shape=(ny, nx), layout=layout, constraints=sets)


# ---- contact scenes ---------------------------------------------------------------------------------------------
#: Regulation pool: ball diameter 57.15 mm and mass 170 g; a 9-foot table's playing surface, 2.54 m by 1.27 m.
BALL_RADIUS = 0.028575
BALL_MASS = 0.17
TABLE = (2.54, 1.27)


def _count(owner, name, value, minimum):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{owner}: `{name}` must be an int >= {minimum}, got {value!r}")


def billiards(speed: float = 10.0, rows: int = 5, *, angle: float = 0.0, restitution: float = 0.95,
              friction: float = 0.05, gap: float = 1e-4, dtype=None, collide=True, max_neighbours=None):
    """A 2-D break, seen from above: a triangle of `rows` rows of balls (15 for 5 rows) racked with its apex on
    the foot spot, and the cue ball (particle 0) on the head spot moving at `speed` m/s towards the apex,
    `angle` rad off the long axis. Regulation radius and mass; the four cushions are planes; no gravity in the
    table's plane and no rolling resistance (a table without friction: momentum is conserved until a cushion
    is hit). Racked balls are `gap` m (>= 0) apart. `restitution` and `friction` (ball-ball and ball-cushion) are
    the model's leaves. Particles 1.. are the rack, row by row from the apex.

    The rack must fit on the table: between the foot spot and the foot cushion there is room for 13 rows at the
    default gap (`billiards_max_rows`); more are refused (they would start outside the cushions, pushed into
    each other).
    `collide` and `max_neighbours` are passed to `jc.build`: True (all pairs up to 256 balls) or "grid" (the
    neighbour grid, whose capacity per ball is `max_neighbours`; all pairs need no capacity and ignore it)."""
    _count("billiards", "rows", rows, 1)
    for name, v in (("speed", speed), ("angle", angle)):
        _value("billiards", name, v, ())
    _value("billiards", "gap", gap, ())
    g = concrete(gap)
    if g is None:
        raise TypeError("billiards: `gap` sets the rack's layout and must be a concrete number, not a traced value")
    g = float(g)
    if g < 0:
        raise ValueError(f"billiards: `gap` must be >= 0 (racked balls would overlap), got {g}")
    if rows > billiards_max_rows(g):
        raise ValueError(f"billiards: a rack of {rows} rows does not fit on the table {TABLE} m: from the foot spot "
                         f"to the foot cushion there is room for at most {billiards_max_rows(g)} rows with gap {g:g} m "
                         "(more would start outside the cushions, pushed into each other)")
    dtype = _dtype("billiards", dtype, speed, angle)
    L_, W = TABLE
    d = 2 * BALL_RADIUS + g
    rack = [(L_ * 0.75 + r * d * np.sqrt(3) / 2, W / 2 + (k - r / 2) * d) for r in range(rows) for k in range(r + 1)]
    x = jnp.asarray(np.array([(L_ * 0.25, W / 2)] + rack), dtype)
    a = jnp.asarray(angle).astype(dtype)
    v0 = jnp.asarray(speed).astype(dtype) * jnp.stack([jnp.cos(a), jnp.sin(a)])
    v = jnp.zeros_like(x).at[0].set(v0)
    planes = [((1.0, 0.0), 0.0), ((-1.0, 0.0), -L_), ((0.0, 1.0), 0.0), ((0.0, -1.0), -W)]
    return build(x, BALL_MASS, velocities=v, gravity=jnp.zeros(2, dtype), radius=BALL_RADIUS, collide=collide,
                 max_neighbours=max_neighbours, planes=planes, restitution=restitution, friction=friction,
                 restitution_threshold=0.05, dtype=dtype)


def billiards_max_rows(gap: float = 1e-4) -> int:
    """The most rows of racked balls `gap` m apart that fit on the `billiards` table: the last row's balls inside
    the foot cushion (the apex sits on the foot spot, a quarter of the table from it) and inside the side
    cushions."""
    L_, W = TABLE
    d = 2 * BALL_RADIUS + gap
    deep = int(np.floor((0.25 * L_ - BALL_RADIUS) / (d * np.sqrt(3) / 2) + 1e-9)) + 1
    wide = int(np.floor((W - 2 * BALL_RADIUS) / d + 1e-9)) + 1
    return min(deep, wide)


def drape(n: int = 16, size: float = 1.0, mass: float = 0.5, *, height: float = 1.0, sphere_radius: float = 0.3,
          friction: float = 0.3, dtype=None):
    """A free n-by-n cloth (structural and shear rods, `size` m square, `mass` kg) held flat `height` m above
    the ground plane z = 0 and centred over a static sphere resting on the ground, released from rest.
    Particle radius: a quarter of the grid spacing."""
    _count("drape", "n", n, 2)
    for name, v in (("size", size), ("mass", mass), ("height", height), ("sphere_radius", sphere_radius)):
        _value("drape", name, v, (), positive=True)
    dtype = _dtype("drape", dtype, size, mass, height, sphere_radius)
    s = jnp.asarray(size).astype(dtype)
    u = jnp.linspace(-0.5, 0.5, n, dtype=dtype)
    gx, gy = jnp.meshgrid(u, u)
    x = jnp.stack([s * gx.ravel(), s * gy.ravel(), jnp.full(n * n, jnp.asarray(height).astype(dtype))], -1)
    pairs, colour = cloth_edges(n, n)
    R = jnp.asarray(sphere_radius).astype(dtype)
    return build(x, jnp.asarray(mass).astype(dtype) / (n * n), rods=pairs, colouring=colour, grid_shape=(n, n),
                 radius=0.25 * s / (n - 1), planes=[((0.0, 0.0, 1.0), 0.0)],
                 spheres=[(jnp.stack([0 * R, 0 * R, R]), R)], friction=friction, dtype=dtype)


def cloth_drop(n: int = 24, size: float = 1.0, mass: float = 0.5, *, tilt: float = 0.1, height: float = 0.02,
               radius: float = 0.45, friction: float = 0.3, collide=True, max_neighbours=None, dtype=None):
    """A free n-by-n cloth that falls onto the floor z = 0 and folds onto itself: the self-collision scene of docs/contacts.md.

    The cloth (structural and shear rods, `size` m square, `mass` kg) hangs almost upright: its rows rise along
    z, leaning `tilt` rad (0 < tilt < pi / 2) from the vertical towards +y, its lowest row `height` m above the
    floor, released from rest. Its bottom lands first and the rest folds down over it in layers (at the default
    tilt of 0.1 rad, three to five layers within 2 s; at 0.3 it mostly falls flat, with one small fold). Particle radius:
    `radius` grid spacings (default 0.45: two layers stay 0.9 spacings apart, and a particle, wider than 0.354
    spacings, cannot slip through a cell of the other layer). `collide` (True or "grid", passed to `jc.build`):
    every pair of its particles may collide except those a rod joins or that start within contact distance;
    True lists all pairs up to 256 particles and uses the neighbour grid above, "grid" always uses it. The
    grid's capacity per particle is `max_neighbours` (default 32: a fold brings more candidates per particle
    than a pile of balls). Particle r * n + c sits in row r (height) and column c (x). Unlike the other scenes,
    its values must be concrete: which pairs start within contact distance is decided at build (`jc.build`)."""
    _count("cloth_drop", "n", n, 2)
    if collide is None or (isinstance(collide, (bool, np.bool_)) and not collide):
        raise ValueError("cloth_drop: `collide` must be True or 'grid' (the scene is about self-collision); build "
                         "the cloth with `jc.build` for one without")
    for name, v in (("size", size), ("mass", mass), ("radius", radius)):
        _value("cloth_drop", name, v, (), positive=True)
    for name, v in (("tilt", tilt), ("height", height), ("friction", friction)):
        _value("cloth_drop", name, v, ())
    t, h, rad = concrete(tilt), concrete(height), concrete(radius)
    if t is not None and not 0 < float(t) < np.pi / 2:
        raise ValueError(f"cloth_drop: `tilt` must lie in (0, pi / 2) rad (0 stands upright and does not fold), "
                         f"got {t}")
    if h is not None and float(h) < 0:
        raise ValueError(f"cloth_drop: `height` must be >= 0 (the cloth starts above the floor), got {h}")
    if rad is not None and float(rad) >= 1:
        raise ValueError(f"cloth_drop: `radius` (in grid spacings) must be < 1, so that neighbours a rod joins do not "
                         f"overlap, got {rad}")
    dtype = _dtype("cloth_drop", dtype, size, mass, tilt, height)
    s = jnp.asarray(size).astype(dtype)
    r = jnp.asarray(radius).astype(dtype) * s / (n - 1)
    u = jnp.linspace(0, 1, n, dtype=dtype)
    gx, gh = jnp.meshgrid(u, u)
    a = jnp.asarray(tilt).astype(dtype)
    up = s * gh.ravel()
    x = jnp.stack([s * gx.ravel(), up * jnp.sin(a), jnp.asarray(height).astype(dtype) + r + up * jnp.cos(a)], -1)
    pairs, colour = cloth_edges(n, n)
    k = 32 if max_neighbours is None and (collide == "grid" or n * n > 256) else max_neighbours
    return build(x, jnp.asarray(mass).astype(dtype) / (n * n), rods=pairs, colouring=colour, grid_shape=(n, n),
                 radius=r, collide=collide, max_neighbours=k, planes=[((0.0, 0.0, 1.0), 0.0)], friction=friction,
                 dtype=dtype)


def falling_chain(n_links: int = 20, length: float = 1.0, mass: float = 0.5, *, height: float = 0.5,
                  angle: float = 0.3, friction: float = 0.5, restitution: float = 0.0, dtype=None):
    """A free 2-D chain of `n_links` rods (n_links + 1 particles, `length` m, `mass` kg in all) held straight
    at `angle` rad above the horizontal with its lowest end `height` m above the floor y = 0, released from rest.
    Particle radius: a quarter of a link."""
    _count("falling_chain", "n_links", n_links, 1)
    for name, v in (("length", length), ("mass", mass), ("height", height)):
        _value("falling_chain", name, v, (), positive=True)
    _value("falling_chain", "angle", angle, ())
    dtype = _dtype("falling_chain", dtype, length, mass, height, angle)
    a = jnp.asarray(angle).astype(dtype)
    s = jnp.linspace(0, 1, n_links + 1, dtype=dtype) * jnp.asarray(length).astype(dtype)
    x = jnp.stack([s * jnp.cos(a), jnp.asarray(height).astype(dtype) + s * jnp.sin(a)], -1)
    pairs = np.stack([np.arange(n_links), np.arange(1, n_links + 1)], -1)
    return build(x, jnp.asarray(mass).astype(dtype) / (n_links + 1), rods=pairs,
                 radius=0.25 * jnp.asarray(length).astype(dtype) / n_links, planes=[((0.0, 1.0), 0.0)],
                 friction=friction, restitution=restitution, dtype=dtype)


def disc_box_layout(n: int, radius: float = 0.5, *, columns=None, drop: float = 1.0, spacing: float = 1.1):
    """Where `disc_box` puts its discs: (positions [n, 2] as NumPy, box width W). Rows of `columns` discs
    (default ceil(sqrt(n))) `2 spacing radius` apart, every other row shifted by half that, rows `sqrt(3)
    spacing radius` apart, the lowest `drop` m above the floor y = 0; the box spans 0 <= x <= W with W the
    width of `columns + 1/2` discs at that spacing plus a gap of `radius` at each side. Peers (Box2D, pymunk)
    build the same box from it."""
    _count("disc_box", "n", n, 1)
    c = int(np.ceil(np.sqrt(n))) if columns is None else columns
    _count("disc_box", "columns", c, 1)
    r, s = float(radius), 2 * float(spacing) * float(radius)
    k = np.arange(n)
    row, col = k // c, k % c
    x = 2 * r + (col + 0.5 * (row % 2)) * s
    y = r + float(drop) + row * s * np.sqrt(3) / 2
    width = 3 * r + (c - 0.5) * s + 2 * r
    return np.stack([x, y], -1), width


def disc_box(n: int = 1024, radius: float = 0.5, mass: float = 1.0, *, friction: float = 0.5,
             restitution: float = 0.0, columns=None, drop: float = 1.0, collide="grid", max_neighbours=None,
             dtype=None):
    """A 2-D pile: n discs of `radius` m and `mass` kg in staggered rows (`disc_box_layout`) dropped from rest
    into a box (a floor y = 0 and walls x = 0 and x = W), under gravity, `friction` and `restitution` on every
    contact (docs/contacts.md's disc box: R = 0.5 m, 1 kg, mu 0.5, e 0). `collide` and `max_neighbours` go to `jc.build`
    ("grid": the neighbour grid at any size)."""
    for name, v in (("radius", radius), ("mass", mass), ("drop", drop)):
        _value("disc_box", name, v, (), positive=True)
    x, width = disc_box_layout(n, radius, columns=columns, drop=drop)
    dtype = _dtype("disc_box", dtype, radius, mass)
    planes = [((0.0, 1.0), 0.0), ((1.0, 0.0), 0.0), ((-1.0, 0.0), -width)]
    return build(jnp.asarray(x, dtype), jnp.asarray(mass).astype(dtype), radius=radius, collide=collide,
                 max_neighbours=max_neighbours, planes=planes, friction=friction, restitution=restitution,
                 dtype=dtype)
