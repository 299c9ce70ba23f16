"""Independent references: planar pendulum chains in reduced (angle) coordinates.

Conventions match `jc.scenes`: the pivot is at the origin, angles are absolute, measured from the downward
vertical, counter-clockwise positive; bob k = bob k-1 + L_k (sin a_k, -cos a_k); gravity g along -y.

Integrated with scipy DOP853 (rtol = atol = 1e-12) when scipy is installed, otherwise with classical RK4 in
float64 NumPy (step `rk4_step`, 1e-4 s by default), so the benchmarks need no scipy.
"""
from __future__ import annotations

import importlib.util

import numpy as np


def _chain_rhs(lengths, masses, g):
    L = np.asarray(lengths, np.float64)
    m = np.asarray(masses, np.float64)
    nl = len(L)
    # tail[a, b] = total mass of the bobs at or beyond link max(a, b)
    tail_from = np.cumsum(m[::-1])[::-1]
    tail = tail_from[np.maximum.outer(np.arange(nl), np.arange(nl))]
    LL = np.outer(L, L)

    def rhs(_, y):
        th, om = y[:nl], y[nl:]
        diff = th[:, None] - th[None, :]
        M = tail * LL * np.cos(diff)
        f = -(tail * LL * np.sin(diff)) @ (om * om) - g * L * tail_from * np.sin(th)
        return np.concatenate([om, np.linalg.solve(M, f)])

    return rhs


def have_scipy() -> bool:
    return importlib.util.find_spec("scipy") is not None


def _rk4(rhs, y0, t, h):
    out, y, now = [], np.array(y0, np.float64), 0.0
    for target in t:
        n = int(np.ceil((target - now) / h - 1e-9))
        if n > 0:
            hh = (target - now) / n
            for _ in range(n):
                k1 = rhs(now, y); k2 = rhs(now, y + hh / 2 * k1)
                k3 = rhs(now, y + hh / 2 * k2); k4 = rhs(now, y + hh * k3)
                y = y + hh / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                now += hh
        out.append(y.copy())
    return np.stack(out, 1)


def chain_angles(angles, lengths, masses, t, g=9.81, omegas=None, rtol=1e-12, atol=1e-12, method=None,
                 rk4_step=1e-4):
    """Angles and angular velocities [2 n_links, len(t)] of the reduced-coordinate chain (see module doc).
    method: None (scipy DOP853 if installed, else RK4), 'scipy' or 'rk4'."""
    th0 = np.asarray(angles, np.float64)
    om0 = np.zeros_like(th0) if omegas is None else np.asarray(omegas, np.float64)
    t = np.atleast_1d(np.asarray(t, np.float64))
    rhs = _chain_rhs(lengths, masses, g)
    y0 = np.concatenate([th0, om0])
    if method is None:
        method = "scipy" if have_scipy() else "rk4"
    if method == "rk4":
        return _rk4(rhs, y0, t, rk4_step)
    from scipy.integrate import solve_ivp
    sol = solve_ivp(rhs, (0.0, float(t.max())), y0, method="DOP853", t_eval=t, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    return sol.y


def chain_positions(angles, lengths, masses, t, g=9.81, omegas=None, rtol=1e-12, atol=1e-12, method=None):
    """Bob positions [len(t), n_links, 2] of a planar chain of massless rigid links with point masses at the
    link ends (Lagrange's equations in absolute angles)."""
    y = chain_angles(angles, lengths, masses, t, g, omegas, rtol, atol, method)
    th = y[: len(np.atleast_1d(angles))].T  # [T, n_links]
    L = np.asarray(lengths, np.float64)
    steps = np.stack([L * np.sin(th), -L * np.cos(th)], -1)  # [T, n_links, 2]
    return np.cumsum(steps, axis=1)


def double_pendulum_positions(angles, lengths, masses, t, g=9.81, method=None):
    """Bob positions [len(t), 2, 2] of the double pendulum released from rest at `angles`."""
    return chain_positions(angles, lengths, masses, t, g, method=method)


def describe(method=None) -> str:
    if method is None:
        method = "scipy" if have_scipy() else "rk4"
    return ("reduced (angle) coordinates, scipy DOP853, rtol = atol = 1e-12, float64" if method == "scipy"
            else "reduced (angle) coordinates, classical RK4, h = 1e-4 s, float64 NumPy")


#: The recording docs/fitting.md fits: a planar double pendulum started mid-swing at angular velocities the fit does not
#: know, recorded at 30 Hz for 3 s with 2 mm of Gaussian noise on every coordinate (seed 23).
RECORDING = dict(masses=(1.0, 0.7), lengths=(0.9, 0.6), angles=(1.0, -0.5), omegas=(1.5, -2.0), rate=30.0,
                 duration=3.0, noise=2e-3, seed=23, g=9.81)


def double_pendulum_recording(seed=None, noise=None, method=None, **changes):
    """A recording made without jaxcon: the double pendulum of `RECORDING` (any of its entries may be changed by
    keyword) integrated in angle coordinates (`chain_positions`, DOP853 at 1e-12), sampled at `rate` Hz from
    t = 0 to `duration` s inclusive, the bobs' positions perturbed by `noise` m of Gaussian noise
    (np.random.default_rng(seed)).

    Returns (t [S], observed [S, 2, 2] noisy bob positions, truth [S, 2, 2] exact positions, spec dict)."""
    spec = dict(RECORDING, **changes)
    spec["seed"] = spec["seed"] if seed is None else seed
    spec["noise"] = spec["noise"] if noise is None else noise
    t = np.arange(int(round(spec["duration"] * spec["rate"])) + 1) / spec["rate"]
    truth = chain_positions(spec["angles"], spec["lengths"], spec["masses"], t, spec["g"], spec["omegas"],
                            method=method)
    rng = np.random.default_rng(spec["seed"])
    return t, truth + spec["noise"] * rng.standard_normal(truth.shape), truth, spec


def driven_pendulum(t, length, angle, omega=0.0, pivot=None, force=None, mass=1.0, g=9.81, rtol=1e-12,
                    atol=1e-12, method=None):
    """A planar pendulum (point mass `mass` on a massless rod of `length`) whose pivot follows a prescribed path
    and whose bob is pushed by a prescribed force, in its angle coordinate (conventions of the module doc).

    pivot(t) -> (p, p', p'') three [2] arrays (m, m/s, m/s^2), default at rest at the origin; force(t) -> [2]
    (N) on the bob, default none. With e = (sin a, -cos a) and e_a = (cos a, sin a) the bob is at p + L e and
    m L a'' = (F - m p'') . e_a - m g sin a. Starts at `angle` with angular velocity `omega` (rad/s; the bob then
    moves at p'(0) + L omega e_a).

    Returns (bob [len(t), 2], pivot [len(t), 2]) positions at the times t (DOP853 at rtol = atol = 1e-12, or
    RK4 without scipy, as `chain_angles`)."""
    L, m = float(length), float(mass)
    pivot = pivot or (lambda _: (np.zeros(2), np.zeros(2), np.zeros(2)))
    force = force or (lambda _: np.zeros(2))

    def rhs(s, y):
        a, w = y
        ea = np.array([np.cos(a), np.sin(a)])
        acc = (np.dot(np.asarray(force(s), np.float64) / m - pivot(s)[2], ea) - g * np.sin(a)) / L
        return np.array([w, acc])

    t = np.atleast_1d(np.asarray(t, np.float64))
    y0 = np.array([float(angle), float(omega)])
    if method is None:
        method = "scipy" if have_scipy() else "rk4"
    if method == "rk4":
        a = _rk4(rhs, y0, t, 1e-4)[0]
    else:
        from scipy.integrate import solve_ivp
        sol = solve_ivp(rhs, (0.0, float(t.max())), y0, method="DOP853", t_eval=t, rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError(sol.message)
        a = sol.y[0]
    p = np.stack([np.asarray(pivot(s)[0], np.float64) for s in t])
    return p + L * np.stack([np.sin(a), -np.cos(a)], -1), p
