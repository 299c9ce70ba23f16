"""Independent references: planar pendulum chains in reduced (angle) coordinates, solved with scipy DOP853.

Conventions match `jc.scenes`: the pivot is at the origin, angles are absolute, measured from the downward
vertical, counter-clockwise positive; bob k = bob k-1 + L_k (sin a_k, -cos a_k); gravity g along -y.
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


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


def chain_positions(angles, lengths, masses, t, g=9.81, omegas=None, rtol=1e-12, atol=1e-12):
    """Bob positions [len(t), n_links, 2] of a planar chain of massless rigid links with point masses at the
    link ends (Lagrange's equations in absolute angles), integrated with scipy DOP853."""
    th0 = np.asarray(angles, np.float64)
    om0 = np.zeros_like(th0) if omegas is None else np.asarray(omegas, np.float64)
    t = np.atleast_1d(np.asarray(t, np.float64))
    sol = solve_ivp(_chain_rhs(lengths, masses, g), (0.0, float(t.max())), np.concatenate([th0, om0]),
                    method="DOP853", t_eval=t, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    th = sol.y[: len(th0)].T  # [T, n_links]
    L = np.asarray(lengths, np.float64)
    steps = np.stack([L * np.sin(th), -L * np.cos(th)], -1)  # [T, n_links, 2]
    return np.cumsum(steps, axis=1)


def double_pendulum_positions(angles, lengths, masses, t, g=9.81):
    """Bob positions [len(t), 2, 2] of the double pendulum released from rest at `angles` (DOP853,
    rtol = atol = 1e-12)."""
    return chain_positions(angles, lengths, masses, t, g)
