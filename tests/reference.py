"""Independent references: reduced-coordinate (angle) equations of motion solved by SciPy at tight tolerance."""
import numpy as np
from scipy.integrate import solve_ivp


def double_pendulum_rhs(t, s, l1, l2, m1, m2, g):
    a1, a2, w1, w2 = s
    d = a1 - a2
    den = 2 * m1 + m2 - m2 * np.cos(2 * d)
    dw1 = (-g * (2 * m1 + m2) * np.sin(a1) - m2 * g * np.sin(a1 - 2 * a2)
           - 2 * np.sin(d) * m2 * (w2 ** 2 * l2 + w1 ** 2 * l1 * np.cos(d))) / (l1 * den)
    dw2 = (2 * np.sin(d) * (w1 ** 2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(a1)
                            + w2 ** 2 * l2 * m2 * np.cos(d))) / (l2 * den)
    return [w1, w2, dw1, dw2]


def double_pendulum_positions(angles, lengths, masses, t, g=9.81):
    """Bob positions [len(t), 2, 2] of a double pendulum released at rest from absolute `angles` (from the
    downward vertical, counter-clockwise), pivot at the origin. DOP853 with rtol = atol = 1e-12."""
    (l1, l2), (m1, m2) = lengths, masses
    t = np.atleast_1d(np.asarray(t, np.float64))
    sol = solve_ivp(double_pendulum_rhs, (0.0, float(t.max())), [angles[0], angles[1], 0.0, 0.0],
                    method="DOP853", t_eval=t, rtol=1e-12, atol=1e-12, args=(l1, l2, m1, m2, g))
    a1, a2 = sol.y[0], sol.y[1]
    p1 = np.stack([l1 * np.sin(a1), -l1 * np.cos(a1)], -1)
    p2 = p1 + np.stack([l2 * np.sin(a2), -l2 * np.cos(a2)], -1)
    return np.stack([p1, p2], 1)
