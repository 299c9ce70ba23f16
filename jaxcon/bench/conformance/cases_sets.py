"""Hard constraint sets under contact: a hard (compliance 0) `area` or `volume` keeps its value within 1% while
contacts press on it, in every solver that accepts the scene."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import CONTACT_SOLVERS, Outcome, SOLVERS, case


def _icosphere():
    """A level-1 icosphere on the unit sphere: vertices [42, 3], outward faces [80, 3], edges [120, 2]."""
    t = (1 + 5 ** 0.5) / 2
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
             (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    mids = {}

    def mid(i, j):
        key = (min(i, j), max(i, j))
        if key not in mids:
            m = verts[i] + verts[j]
            verts.append(m / np.linalg.norm(m))
            mids[key] = len(verts) - 1
        return mids[key]

    fine = []
    for a, b, c in faces:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        fine += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    edges = sorted({(min(a, b), max(a, b)) for f in fine for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))})
    return np.array(verts), np.array(fine), np.array(edges)


def _mesh_volume(x, faces):
    """Signed volume of a closed triangle mesh (NumPy, any leading axes)."""
    a, b, c = (x[..., faces[:, k], :] for k in range(3))
    return np.einsum("...fi,...fi->...f", a, np.cross(b, c)).sum(-1) / 6


@case("hard volume squeezed",
      """A level-1 icosphere (42 vertices of 0.01 kg, radius 0.2 m, its 120 edges a compliant `distance` set of
      alpha = 1e-3 m/N, one hard `volume` constraint over its 80 faces) on the floor z = 0 and pressed by contacts.
      Full size: a frictionless ceiling plane lowered from z = 0.41 m to 0.28 m (70% of the diameter) over 1 s,
      then held 0.5 s, dt 1/480 (the mesh must end squeezed, height <= 0.29 m). Reduced: pressed onto the floor
      by its own weight at 10 g (98.1 m/s^2, the edges sag by about 10%), 0.3 s at dt 1/480. The number: the
      largest |V / V0 - 1| over the run. Bound: 1%.""",
      "the start volume", solvers=CONTACT_SOLVERS)
def hard_volume_squeezed(solver_name: str, full: bool) -> Outcome:
    verts, faces, edges = _icosphere()
    pos = 0.2 * verts
    pos[:, 2] -= pos[:, 2].min()
    vol0 = _mesh_volume(pos, faces)
    top, bottom, dt = 0.41, 0.28, 1 / 480
    planes = [((0.0, 0.0, 1.0), 0.0)] + ([((0.0, 0.0, -1.0), -top)] if full else [])
    model, state = jc.build(pos, np.full(len(pos), 0.01),
                            constraints=[jc.constraints.distance(edges, positions=pos, compliance=1e-3),
                                         jc.constraints.volume([list(range(len(pos)))], faces=faces, positions=pos)],
                            planes=planes, friction=0.0, gravity=None if full else 10 * 9.81)
    solver = SOLVERS[solver_name]()
    if not full:
        _, traj = jc.rollout(model, state, solver, dt, 144)
        err = float(np.max(np.abs(_mesh_volume(np.asarray(traj.x), faces) / vol0 - 1)))
        return Outcome(err, err <= 0.01, "max |V / V0 - 1| <= 0.01")
    chunk, worst, height = 8, 0.0, np.inf
    run = jax.jit(lambda m, s: jc.rollout(m, s, solver, dt, chunk))
    jc.rollout(model, state, solver, dt, 1)              # the checks before tracing (a refusal raises here)
    for c in range(int(round(1.5 / (dt * chunk)))):
        ceiling = top + (bottom - top) * min((c + 1) * chunk * dt / 1.0, 1.0)
        model = model.replace(plane_offset=jnp.asarray([0.0, -ceiling], model.plane_offset.dtype))
        state, traj = run(model, state)
        x = np.asarray(traj.x)
        worst = max(worst, float(np.max(np.abs(_mesh_volume(x, faces) / vol0 - 1))))
        height = float(np.ptp(x[-1, :, 2]))
    ok = worst <= 0.01 and height <= 0.29
    return Outcome(worst, ok, f"max |V / V0 - 1| <= 0.01 (end height {height:.3f} m <= 0.29)")


@case("hard area dropped",
      """A ring of N particles of 0.01 kg on a circle of radius 0.3 m, neighbours joined by rods, one hard `area`
      constraint, dropped onto the floor y = 0 (friction 0.5): full size N = 32 from 0.5 m, 2 s at dt 1/240;
      reduced N = 24 from 0.3 m, 1 s. The number: the largest |A / A0 - 1| over the run. Bound: 1%.""",
      "the start area", solvers=CONTACT_SOLVERS)
def hard_area_dropped(solver_name: str, full: bool) -> Outcome:
    n, drop, steps = (32, 0.5, 480) if full else (24, 0.3, 240)
    radius = 0.3
    a = 2 * np.pi * np.arange(n) / n
    pos = np.stack([radius * np.cos(a), radius * np.sin(a) + radius + drop], 1)
    model, state = jc.build(pos, np.full(n, 0.01), rods=[(i, (i + 1) % n) for i in range(n)],
                            constraints=[jc.constraints.area([list(range(n))], positions=pos)],
                            planes=[((0.0, 1.0), 0.0)], friction=0.5)
    _, traj = jc.rollout(model, state, SOLVERS[solver_name](), 1 / 240, steps)
    x = np.asarray(traj.x)
    y = np.roll(x, -1, axis=-2)
    area = 0.5 * np.sum(x[..., 0] * y[..., 1] - y[..., 0] * x[..., 1], -1)
    a0 = 0.5 * n * radius ** 2 * np.sin(2 * np.pi / n)
    err = float(np.max(np.abs(area / a0 - 1)))
    landed = float(x[:, :, 1].min()) < 0.01
    return Outcome(err, err <= 0.01 and landed, "max |A / A0 - 1| <= 0.01 (and the ring reached the floor)")
