"""Linear stability of Gauss-Seidel around a hub (docs/solvers.md, "Hubs"): the spectral radius of the
constraint-error recurrence of XPBD (one sweep per substep, v = (p - x) / h) and of warm-started PGS with
Baumgarte stabilisation, for a star of N spokes solved one constraint at a time and as one exact block.

Linearised about a star at rest length (unit spokes, every particle of unit mass), in constraint space:

* XPBD: a sweep leaves the residual R e of the prediction e, R = I - A (D + L)^-1 (A = J M^-1 J^T, D + L its
  lower triangle in sweep order, or its block lower triangle for block Gauss-Seidel). The velocity from
  positions carries the unconverged part into the next prediction: e_next = R (2 e - e_prev).
* PGS(k sweeps, beta): lam = G^k lam_prev + H_k b with b = -(s + beta e), G = I - M^-1 A the sweep's error
  operator, H_k = sum_{i<k} G^i M^-1; then s' = s + A lam (s: h times the relative velocity), e' = e + s'.

Above 1 rounding error grows without bound. Run: `python benchmarks/hub_stability.py` (NumPy only, seconds).
"""
import numpy as np


def star(n_spokes, dim):
    """Jacobian [N, (N + 1) dim] of a hub (particle 0) joined to N rim particles at unit distance."""
    if dim == 2:
        a = 2 * np.pi * np.arange(n_spokes) / n_spokes
        rim = np.stack([np.cos(a), np.sin(a)], -1)
    else:
        v = np.random.default_rng(0).normal(size=(n_spokes, 3))
        rim = v / np.linalg.norm(v, axis=1, keepdims=True)
    J = np.zeros((n_spokes, (n_spokes + 1) * dim))
    for k in range(n_spokes):
        J[k, :dim], J[k, (k + 1) * dim:(k + 2) * dim] = -rim[k], rim[k]
    return J


def sweep_inverse(A, blocks):
    """M^-1 of one (block) Gauss-Seidel sweep over `blocks` (lists of rows, in order)."""
    order = [k for b in blocks for k in b]
    P = np.eye(len(A))[order]
    Ap, DL, s = P @ A @ P.T, np.zeros_like(A), 0
    for b in blocks:
        e = s + len(b)
        DL[s:e, :e] = Ap[s:e, :e]
        s = e
    return P.T @ np.linalg.inv(DL) @ P


def rho(M):
    return float(max(abs(np.linalg.eigvals(M))))


def xpbd(A, Minv):
    m = len(A)
    R = np.eye(m) - A @ Minv
    return rho(np.block([[2 * R, -R], [np.eye(m), np.zeros((m, m))]]))


def pgs(A, Minv, sweeps=10, beta=0.2):
    m = len(A)
    I, Z = np.eye(m), np.zeros((m, m))
    G = I - Minv @ A
    Gk = np.linalg.matrix_power(G, sweeps)
    Hk = sum(np.linalg.matrix_power(G, i) for i in range(sweeps)) @ Minv
    lam = np.hstack([-beta * Hk, -Hk, Gk])
    s_new = np.hstack([Z, I, Z]) + A @ lam
    return rho(np.vstack([np.hstack([I, Z, Z]) + s_new, s_new, lam]))


if __name__ == "__main__":
    print("| spokes | dim | XPBD, one row at a time | PGS(10), one row at a time | XPBD, star | PGS(10), star |")
    print("|---|---|---|---|---|---|")
    for n in (8, 9, 16, 64):
        for dim in (2, 3):
            J = star(n, dim)
            A = J @ J.T
            rows, block = sweep_inverse(A, [[k] for k in range(n)]), sweep_inverse(A, [list(range(n))])
            print(f"| {n} | {dim} | {xpbd(A, rows):.2f} | {pgs(A, rows):.2f} | {xpbd(A, block):.2f} | "
                  f"{pgs(A, block):.2f} |")
