"""Ready-made scenes. Each returns (model, state).

Pendulum-like scenes are 2-D; particle 0 is the fixed pivot at the origin, particles 1..n the bobs in order,
constraint k joins particle k to particle k+1. Angles are from the downward vertical, counter-clockwise
positive: bob = previous + L (sin a, -cos a).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ._model import build


def _positive(owner, name, value):
    a = np.asarray(value, np.float64)
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"{owner}: `{name}` must be finite and > 0, got {value!r}")
    return a


def _finite(owner, name, value):
    a = np.asarray(value, np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{owner}: `{name}` must be finite, got {value!r}")
    return a


def _planar_chain(lengths, angles):
    pts = [np.zeros(2)]
    for L, a in zip(lengths, angles):
        pts.append(pts[-1] + L * np.array([np.sin(a), -np.cos(a)]))
    return np.stack(pts)


def _link_chain(owner, lengths, masses, angles, kind, dtype, gravity):
    if kind not in ("rod", "rope"):
        raise ValueError(f"{owner}: `kind` must be 'rod' or 'rope', got {kind!r}")
    x = _planar_chain(lengths, angles).astype(dtype)
    pairs = [(k, k + 1) for k in range(len(lengths))]
    return build(
        x, np.concatenate([[1.0], masses]), rods=pairs if kind == "rod" else None,
        ropes=pairs if kind == "rope" else None, fixed=[0], gravity=gravity,
    )


def pendulum(length: float = 1.0, mass: float = 1.0, angle: float = 0.3, *, kind: str = "rod",
             dtype=None, gravity=None):
    """A single 2-D pendulum: fixed pivot at the origin and one bob on a rod (or rope) of `length` m."""
    L = _positive("pendulum", "length", length)
    m = _positive("pendulum", "mass", mass)
    a = _finite("pendulum", "angle", angle)
    return _link_chain("pendulum", [L], [m], [a], kind, dtype or np.float32, gravity)


def double_pendulum(lengths: Sequence[float] = (1.0, 1.0), masses: Sequence[float] = (1.0, 1.0),
                    angles: Sequence[float] = (1.5708, 1.5708), *, dtype=None, gravity=None):
    """A 2-D double pendulum of two rods; `angles` are absolute angles of each rod from the downward vertical."""
    L = _positive("double_pendulum", "lengths", lengths)
    m = _positive("double_pendulum", "masses", masses)
    a = _finite("double_pendulum", "angles", angles)
    for name, v in (("lengths", L), ("masses", m), ("angles", a)):
        if v.shape != (2,):
            raise ValueError(f"double_pendulum: `{name}` must hold 2 values, got shape {v.shape}")
    return _link_chain("double_pendulum", L, m, a, "rod", dtype or np.float32, gravity)


def chain(n_links: int = 50, length: float = 5.0, mass: float = 0.5, end_mass: float | None = None,
          angle: float = 1.5708, kind: str = "rod", *, dtype=None, gravity=None):
    """A straight chain of `n_links` equal links (total `length` m) hanging from a fixed pivot, released at
    `angle` from the downward vertical. `mass` is the total mass spread over the bobs; the last bob weighs
    `end_mass` instead when given. `kind`: 'rod' (bilateral) or 'rope' (unilateral)."""
    if isinstance(n_links, bool) or not isinstance(n_links, (int, np.integer)) or n_links < 1:
        raise ValueError(f"chain: `n_links` must be an int >= 1, got {n_links!r}")
    total = float(_positive("chain", "length", length))
    mtot = float(_positive("chain", "mass", mass))
    a = float(_finite("chain", "angle", angle))
    masses = np.full(n_links, mtot / n_links)
    if end_mass is not None:
        masses[-1] = float(_positive("chain", "end_mass", end_mass))
    return _link_chain("chain", np.full(n_links, total / n_links), masses, np.full(n_links, a), kind,
                       dtype or np.float32, gravity)


def cloth_edges(nx: int, ny: int):
    """Structural and shear edges of an nx-by-ny grid (row-major particle index r * nx + c) and a colouring
    with 8 colours whose every colour is a strided box of the grid: horizontal edges split by column parity,
    vertical edges by row parity, and each diagonal direction by column parity when nx is even (by row
    parity when it is odd). With nx even, the model stores each row as its even columns then its odd ones
    (see jaxcon._topology), and every colour, diagonals included, is then one box of unit-step row runs."""
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


def cloth(nx: int = 32, ny: int = 32, size: float = 1.0, mass: float = 1.0, *, dtype=None, gravity=None):
    """A 3-D square cloth of nx-by-ny particles, side `size` m and total `mass` kg, lying horizontally in the
    z = 0 plane (gravity along -z), held by its two corners of the edge y = 0. Rods on structural and shear
    edges."""
    for name, v in (("nx", nx), ("ny", ny)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
            raise ValueError(f"cloth: `{name}` must be an int >= 2, got {v!r}")
    s = float(_positive("cloth", "size", size))
    mtot = float(_positive("cloth", "mass", mass))
    gx, gy = np.meshgrid(np.linspace(0, s, nx), np.linspace(0, s, ny))
    x = np.stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)], -1).astype(dtype or np.float32)
    pairs, colour = cloth_edges(nx, ny)
    return build(x, np.full(nx * ny, mtot / (nx * ny)), rods=pairs, fixed=[0, nx - 1], gravity=gravity,
                 colouring=colour, grid_shape=(ny, nx))
