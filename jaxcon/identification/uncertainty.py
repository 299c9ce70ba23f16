"""What a fit can say about its own result: which parameters ran to a bound of their transform, the 1-sigma
uncertainty of every fitted value (Gauss-Newton covariance at the optimum, scaled by the residual variance), and
the directions the data do not determine (a warning naming the parameters).

All of it runs on the host in float64 NumPy, once, after the fit."""
from __future__ import annotations

import warnings
from typing import NamedTuple, Optional

import jax
import numpy as np

from jaxcon.identification.params import STATE_PARAMS, derivative

#: A log-parameterised value "ran to a bound" when it reached 0 or inf in its dtype, or left its initial value by
#: more than this factor (either way): a collapsed mass ratio (1e-34 or 1e34), not a physical fit.
LOG_BOUND_FACTOR = 1e8
#: A logit-parameterised value ran to a bound when it lies within this fraction of its range of lo or hi.
LOGIT_BOUND_MARGIN = 1e-4
#: The fitted result is a misfit (not converged) when its position errors have a lag-1 correlation from frame to
#: frame above this: what is left is mostly the model missing the motion, not measurement noise. Below it, a
#: correlation above MISFIT_SIGMAS / sqrt(pairs of frames) (beyond chance for white noise) gets a MisfitWarning.
MISFIT_CORRELATION = 0.5
MISFIT_SIGMAS = 4.0
#: A direction of the (Jacobi-scaled) Gauss-Newton matrix J^T J with an eigenvalue below this fraction of the
#: largest is one the data do not determine (a singular value ratio of 1e-5).
NULL_RTOL = 1e-10


class IdentifiabilityWarning(UserWarning):
    """`jc.fit`: some combination of the fitted parameters is not determined by the data."""


class MisfitWarning(UserWarning):
    """`jc.fit`: the errors left are correlated from frame to frame beyond chance: part of them is the model
    missing the motion, not noise, so `std` (which assumes noise) understates the uncertainty."""


def at_bounds(pset, u, u0) -> list:
    """Messages for every fitted leaf that ran to a bound of its transform (see LOG_BOUND_FACTOR,
    LOGIT_BOUND_MARGIN); identity leaves have none."""
    out = []
    leaves, start = pset.treedef.flatten_up_to(u), pset.treedef.flatten_up_to(u0)
    for lab, a, a0, p in zip(pset.labels, leaves, start, pset.specs):
        a, a0 = np.asarray(a, np.float64), np.asarray(a0, np.float64)
        mask = np.broadcast_to(np.asarray(p.mask), a.shape)
        if p.kind == "log":
            value = np.exp(a)
            dtype = np.asarray(p.fixed).dtype
            info = np.finfo(dtype if np.issubdtype(dtype, np.floating) else np.float64)
            bad = mask & ((value <= info.tiny) | (value >= info.max) | ~np.isfinite(a)
                          | (np.abs(a - a0) > np.log(LOG_BOUND_FACTOR)))
            why = f"log transform: 0, inf or a factor over {LOG_BOUND_FACTOR:g} from its start"
        elif p.kind == "logit":
            s = 1 / (1 + np.exp(-a))
            value = p.lo + (p.hi - p.lo) * s
            bad = mask & ((s < LOGIT_BOUND_MARGIN) | (s > 1 - LOGIT_BOUND_MARGIN))
            why = f"logit transform: within {LOGIT_BOUND_MARGIN:g} of its range from ({p.lo:g}, {p.hi:g})"
        else:
            continue
        for idx in zip(*np.nonzero(bad)) if a.ndim else ([()] if bad else []):
            name = lab + (f"[{', '.join(map(str, idx))}]" if idx else "")
            start_value = np.exp(a0[idx]) if p.kind == "log" else p.lo + (p.hi - p.lo) / (1 + np.exp(-a0[idx]))
            out.append(f"{name} = {value[idx]:.3g} (started at {start_value:.3g}; {why})")
    return out


class Uncertainty(NamedTuple):
    std_u: np.ndarray          # [p] 1-sigma of every raveled unconstrained entry (0: not fitted, inf: undetermined)
    unidentified: tuple        # descriptions of the directions the data do not determine
    gauge: int                 # how many null directions are x0 / v0 components every constraint step removes


def gauss_newton(J, ssr, active, gauge=None, labels=None) -> Optional[Uncertainty]:
    """The Gauss-Newton covariance of the unconstrained parameters at the optimum.

    J [N, p] the Jacobian of the whole-record residuals r [N], ssr = sum(r^2) (both may carry a common scale:
    the covariance is ssr / (N - q) (J^T J)^-1 over the q `active` entries, which is invariant to it). The matrix is
    Jacobi-scaled (unit diagonal) before its eigen-decomposition; eigenvalues below NULL_RTOL of the largest are
    null directions. A null direction inside `gauge` (columns [p, g]: directions that change nothing any solver
    step keeps, such as a velocity along a rod) is dropped (its variance counts as 0); any other null direction
    makes the std of the entries it involves inf and is described in `unidentified`.
    Returns None when J or r is not finite or there are no more residuals than parameters."""
    J, ssr = np.asarray(J, np.float64), float(ssr)
    active = np.asarray(active, bool)
    q, N = int(active.sum()), J.shape[0]
    if not (np.all(np.isfinite(J)) and np.isfinite(ssr)) or N <= q or q == 0:
        return None
    Ja = J[:, active]
    A = Ja.T @ Ja
    s = np.sqrt(np.diag(A))
    s = np.where(s > 0, s, 1.0)
    lam, V = np.linalg.eigh(A / np.outer(s, s))
    null = lam <= NULL_RTOL * max(lam.max(), np.finfo(np.float64).tiny)
    keep = ~null
    sigma2 = ssr / (N - q)
    cov_y = (V[:, keep] / lam[keep]) @ V[:, keep].T * sigma2
    std = np.sqrt(np.maximum(np.diag(cov_y), 0)) / s
    W = _non_gauge(V[:, null], None if gauge is None else np.asarray(gauge, np.float64)[active] * s[:, None])
    if W.shape[1]:
        involved = np.any(np.abs(W) > 0.01, axis=1)
        std = np.where(involved, np.inf, std)
    out = np.zeros(active.shape)
    out[active] = std
    names = None if labels is None else [lab for lab, a in zip(labels, active) if a]
    # described in the unconstrained coordinates themselves (y = s z): the common log-scale of all masses
    # reads as equal weights
    return Uncertainty(out, tuple(_describe(w / s, names) for w in W.T), int(null.sum()) - W.shape[1])


def _non_gauge(V0, G):
    """The part of the null space V0 [q, k] (orthonormal columns) outside span(G) [q, g]: orthonormal columns."""
    if V0.shape[1] == 0:
        return V0
    R = V0
    if G is not None and G.size:
        U, sv, _ = np.linalg.svd(G, full_matrices=False)
        Q = U[:, sv > 1e-9 * max(sv.max(), 1e-300)]
        R = V0 - Q @ (Q.T @ V0)
    U, sv, _ = np.linalg.svd(R, full_matrices=False)
    return U[:, sv > 0.1]


def _describe(w, names) -> str:
    w = w / np.abs(w).max() * (1 if w[np.argmax(np.abs(w))] > 0 else -1)
    order = [i for i in np.argsort(-np.round(np.abs(w), 2), kind="stable") if abs(w[i]) >= 0.2][:6]
    label = (lambda i: f"entry {i}") if names is None else (lambda i: names[i])  # noqa: E731
    return " ".join(f"{w[i]:+.2g} {label(i)}" for i in order)


def warn_unidentified(unidentified, pset, stacklevel=2):
    if not unidentified:
        return
    warnings.warn(
        f"fit: the data do not determine {len(unidentified)} direction(s) of the fitted parameters (in the "
        "coordinates the fit moves: log or logit of transformed values): "
        + "; ".join(f"[{d}]" for d in unidentified)
        + ". Moving along such a direction leaves every fitted position unchanged, so these values are arbitrary "
        "and their std is inf. For example, the common scale of all masses when only positions are observed and "
        "nothing else sets a force scale: fix one mass (fit a mass ratio with setup=), or observe what sets the "
        "scale.", IdentifiabilityWarning, stacklevel=stacklevel)


def std_like(pset, u, std_u):
    """The 1-sigma of every fitted value (delta method through each leaf's transform), shaped like the fitted
    parameters; 0 for entries that are not fitted."""
    leaves = pset.treedef.flatten_up_to(u)
    out, k = [], 0
    for a, p in zip(leaves, pset.specs):
        n = int(np.size(a))
        su = np.asarray(std_u[k:k + n]).reshape(np.shape(a))
        d, fitted = derivative(a, p), np.broadcast_to(np.asarray(p.mask), np.shape(a))
        with np.errstate(invalid="ignore"):                    # inf * 0 (a logit at its bound): inf below
            value = np.where(np.isinf(su), np.inf, su * d)
        out.append(np.where(fitted, value, 0.0).astype(np.asarray(a).dtype))
        k += n
    return pset.treedef.unflatten(out)


def state_gauge(pset, model, state_b, batched, frame0_observed):
    """[p, g] directions of the raveled parameters that every constraint step removes: for "v0", a velocity
    M^-1 G^T c along the rods at x0 (the solver's first step takes it out with the rods' impulses); for "x0" the
    same displacement when the initial frame is not observed (the first projection takes it out). None when
    neither is fitted."""
    names = [lab for lab in pset.labels if lab in STATE_PARAMS and (lab == "v0" or not frame0_observed)]
    t = model.topology
    if not pset.named or not names or t.m == 0:
        return None
    rods = np.nonzero(~np.asarray(t.is_rope))[0]
    w = np.asarray(model.inv_mass, np.float64)
    x = np.asarray(state_b.x, np.float64)                                            # [B, n, dim]
    i, j = np.asarray(t.i)[rods], np.asarray(t.j)[rods]
    sizes = [int(np.size(a)) for a in jax.tree.leaves(pset.u0)]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    cols = []
    for lab_index, lab in enumerate(pset.labels):
        if lab not in names:
            continue
        for b in range(x.shape[0]):
            d = x[b, j] - x[b, i]
            n = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
            for c in range(len(rods)):
                g = np.zeros(x.shape)
                g[b, i[c]] -= w[i[c]] * n[c]
                g[b, j[c]] += w[j[c]] * n[c]
                col = np.zeros(offsets[-1])
                col[offsets[lab_index]:offsets[lab_index + 1]] = (g if batched else g[0]).ravel()
                cols.append(col)
    return np.stack(cols, 1) if cols else None


#: The frame-to-frame pairs (over all recordings) the lag-1 correlation needs to tell noise from a misfit: those
#: of one recording of 8 frames.
MIN_LAG_PAIRS = 7


def _exact(err, obs) -> bool:
    """The errors are 0 or below 1e-5 of the observed motion (the RMS of obs about its mean over the frames):
    exact data fitted to rounding."""
    motion = np.sqrt(np.mean((obs - obs.mean(axis=1, keepdims=True)) ** 2))
    ss = float(np.sum(err ** 2))
    return np.isfinite(ss) and (ss <= 0 or np.sqrt(ss / err.size) < 1e-5 * motion)


def lag_pairs(err) -> int:
    """The frame-to-frame pairs of err [B, S, k, dim], over all recordings: B (S - 1)."""
    return int(err.shape[0] * max(err.shape[1] - 1, 0))


def residual_correlation(err, obs):
    """The lag-1 correlation of the position errors err [B, S, k, dim] from frame to frame, pooled: sum e_s e_s+1
    / sum e_s^2. None with fewer than MIN_LAG_PAIRS (7) frame-to-frame pairs over the recordings, or for exact
    data fitted to rounding (`_exact`)."""
    ss = float(np.sum(err ** 2))
    if lag_pairs(err) < MIN_LAG_PAIRS or not np.isfinite(ss) or _exact(err, obs):
        return None
    return float(np.sum(err[:, 1:] * err[:, :-1]) / ss)


def too_few_frames(err, obs) -> bool:
    """The misfit cannot be checked: fewer than MIN_LAG_PAIRS frame-to-frame pairs, and errors above the
    exact-data level (with so few frames the lag-1 correlation does not tell noise from a misfit, and there is no
    noise level to compare the RMS with)."""
    return lag_pairs(err) < MIN_LAG_PAIRS and not _exact(err, obs)


def warn_misfit(corr, err, stacklevel=2):
    """A MisfitWarning when the errors' lag-1 correlation `corr` is beyond chance for white noise (above
    MISFIT_SIGMAS / sqrt(pairs)) but not a misfit (<= MISFIT_CORRELATION, which fails the fit instead)."""
    pairs = err.size // err.shape[1] * (err.shape[1] - 1)
    if corr is None or corr > MISFIT_CORRELATION or corr <= MISFIT_SIGMAS / np.sqrt(pairs):
        return
    warnings.warn(
        f"fit: the position errors left (RMS {1e3 * np.sqrt(np.mean(err ** 2)):.3g} mm) are correlated from frame to "
        f"frame ({corr:.2f}, beyond chance for noise: {MISFIT_SIGMAS:g} / sqrt({pairs}) = "
        f"{MISFIT_SIGMAS / np.sqrt(pairs):.2f}): part of them is the model missing the motion, so the fitted "
        "values may be off by more than their std. A solver with a smaller forward error at this dt (a smaller "
        "dt, RATTLE; docs/fitting.md) or a missing parameter would remove it.", MisfitWarning, stacklevel=stacklevel)
