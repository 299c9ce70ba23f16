"""MuJoCo reference curves for `bench --speed-vs-error` (optional: used only when `mujoco` is installed).

The scenes are jaxcon's planar pendulums and chains written as MuJoCo hinge chains: body k hangs from body k-1
by a hinge about the out-of-plane axis, and carries its bob as a point mass (an inertial frame at the link's
end with a negligible rotational inertia); the links themselves are massless. jaxcon's 2-D (x, y) with gravity
along -y maps to MuJoCo's (x, z). Joint angles are relative (link k against link k-1); jaxcon's scene angles
are absolute from the downward vertical.

Cost: `mujoco.rollout.rollout` steps the model in C (recording the state every step, like `jc.rollout`), so
no Python loop is timed. Median of `repeats` runs.
"""
from __future__ import annotations

import time
from typing import Sequence

import numpy as np


def available() -> bool:
    try:
        import mujoco  # noqa: F401
        from mujoco import rollout  # noqa: F401
    except ImportError:
        return False
    return True


def _xml(lengths, masses, dt, integrator, gravity=9.81):
    body = ""
    for L, m in zip(reversed(lengths), reversed(masses)):
        body = (f'<body pos="0 0 {{prev}}"><joint type="hinge" axis="0 -1 0" damping="0"/>'
                f'<inertial pos="0 0 {-L!r}" mass="{m!r}" diaginertia="1e-9 1e-9 1e-9"/>'
                + body.replace("{prev}", repr(-L)) + "</body>")
    body = body.replace("{prev}", "0", 1)
    return (f'<mujoco><option timestep="{dt!r}" gravity="0 0 {-gravity!r}" integrator="{integrator}">'
            f'<flag contact="disable"/></option><worldbody>{body}</worldbody></mujoco>')


def planar_chain(lengths: Sequence[float], masses: Sequence[float], dt: float, integrator: str = "Euler"):
    """An MjModel of a planar chain of massless links with point bobs (joint k: angle of link k relative to
    link k-1)."""
    import mujoco
    return mujoco.MjModel.from_xml_string(_xml([float(v) for v in lengths], [float(v) for v in masses], dt,
                                               integrator))


def bob_positions(model, qpos) -> np.ndarray:
    """[n, 2] bob positions (jaxcon's x, y) for joint angles qpos."""
    import mujoco
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    p = np.asarray(data.xipos[1:])
    return np.stack([p[:, 0], p[:, 2]], axis=-1)


def run(lengths, masses, angles, dt: float, T: float, integrator: str = "Euler", repeats: int = 3):
    """Release the chain at rest from absolute `angles`; returns (bob positions [n, 2] at t = T (NaN if the
    run blew up), median wall s of the T / dt steps, whether the final state is finite). Link lengths are exact
    by construction (hinges)."""
    import mujoco
    from mujoco import rollout

    model = planar_chain(lengths, masses, dt, integrator)
    data = mujoco.MjData(model)
    a = np.asarray(angles, np.float64)
    data.qpos[:] = np.diff(a, prepend=0.0)
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state0 = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state0, spec)
    steps = int(round(T / dt))
    out = np.empty((1, steps, state0.size))
    walls = []
    for _ in range(max(1, repeats) + 1):     # the first run warms up
        t0 = time.perf_counter()
        rollout.rollout(model, data, state0[None], nstep=steps, state=out)
        walls.append(time.perf_counter() - t0)
    final = out[0, -1]
    nq = model.nq
    qpos = final[1:1 + nq]                      # FULLPHYSICS: time, qpos, qvel, ...
    finite = bool(np.all(np.isfinite(final)))
    pos = bob_positions(model, qpos) if finite else np.full((len(a), 2), np.nan)
    return pos, float(np.median(walls[1:])), finite
