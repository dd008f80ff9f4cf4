"""Textbook Kalman filter and RTS smoother in NumPy float64: the independent reference for tests.

Written from the closed-form equations (Särkkä & Svensson 2023, thms 4.2 and 12.2), with explicit
row selection for missing components. Deliberately simple: no batching, no tricks.
"""

from __future__ import annotations

import numpy as np


def kalman_filter(A, H, Q, R, y, m0, P0, B=None, u=None, obs=None):
    """Returns means, covs, predicted means, predicted covs, log-likelihood. Q may be (T, n, n)."""
    T = y.shape[0]
    m, P = m0.copy(), P0.copy()
    ms, Ps, mps, Pps = [], [], [], []
    ll = 0.0
    for t in range(T):
        m = A @ m + (B @ u[t] if B is not None else 0.0)
        P = A @ P @ A.T + (Q[t] if Q.ndim == 3 else Q)
        mps.append(m.copy())
        Pps.append(P.copy())
        o = np.isfinite(y[t]) if obs is None else (obs[t] & np.isfinite(y[t]))
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ P @ Ho.T + Ro
            K = P @ Ho.T @ np.linalg.inv(S)
            e = y[t][o] - Ho @ m
            m = m + K @ e
            P = P - K @ S @ K.T
            k = int(o.sum())
            ll += -0.5 * (
                e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] + k * np.log(2 * np.pi)
            )
        ms.append(m.copy())
        Ps.append(P.copy())
    return np.array(ms), np.array(Ps), np.array(mps), np.array(Pps), ll


def rts_smoother(A, ms, Ps, mps, Pps):
    T = ms.shape[0]
    msm, Psm = ms.copy(), Ps.copy()
    for t in range(T - 2, -1, -1):
        G = Ps[t] @ A.T @ np.linalg.inv(Pps[t + 1])
        msm[t] = ms[t] + G @ (msm[t + 1] - mps[t + 1])
        Psm[t] = Ps[t] + G @ (Psm[t + 1] - Pps[t + 1]) @ G.T
    return msm, Psm


# --------------------------------------------------------------------------- constrained CKF
def constrained_points_ref(m, P, lo, hi, theta="paper"):
    """Spec cckf.md s.2 written out point by point: returns points (2n, n) and weights (2n,)."""
    from scipy.stats import norm

    n = len(m)
    S = np.linalg.cholesky(P)
    dirs = np.concatenate([np.sqrt(n) * S.T, -np.sqrt(n) * S.T])  # row i = column i of sqrt(n) S
    pts, ths = [], []
    for d in dirs:
        th = np.inf
        for j in range(n):
            if d[j] > 0 and np.isfinite(hi[j]):
                th = min(th, (hi[j] - m[j]) / d[j])
            elif d[j] < 0 and np.isfinite(lo[j]):
                th = min(th, (lo[j] - m[j]) / d[j])
        ths.append(th)
        pts.append(m + min(1.0, th) * d)
    ths = np.array(ths) * (np.sqrt(n) if theta == "std" else 1.0)
    F = norm.cdf(ths) - 0.5
    w = np.empty(2 * n)
    for i in range(n):
        tot = F[i] + F[i + n]
        w[i], w[i + n] = (0.5, 0.5) if tot <= 0 else (F[i] / tot, F[i + n] / tot)
    return np.array(pts), w / n


def nddr_box_qp(Xi, P, H, R, z, lo, hi):
    """argmin_{lo<=x<=hi} (x-Xi)^T P^-1 (x-Xi) + (z-Hx)^T R^-1 (z-Hx), by scipy's BVLS."""
    from scipy.optimize import lsq_linear

    Wp = np.linalg.inv(np.linalg.cholesky(P))
    Wr = np.linalg.inv(np.linalg.cholesky(R))
    A = np.vstack([Wp, Wr @ H])
    b = np.concatenate([Wp @ Xi, Wr @ z])
    return lsq_linear(A, b, bounds=(lo, hi), method="bvls", tol=1e-15).x


def cckf_linear_ref(A, H, Q, R, y, m0, P0, lo, hi, covariance="paper", theta="paper", R_point=None):
    """Linear-model CCKF, one point and one box-QP at a time (NumPy/SciPy, float64).

    ``R_point(X)``, if given, is the per-point measurement variance added to R in each point's
    reconciliation (and averaged into P_yy).
    """
    m, P = m0.copy(), P0.copy()
    ms, Ps = [], []
    for t in range(y.shape[0]):
        X, w = constrained_points_ref(m, P, lo, hi, theta)
        Xs = X @ A.T
        m = w @ Xs
        D = Xs - m
        P = (D * w[:, None]).T @ D + Q
        m = np.clip(m, lo, hi)
        X, w = constrained_points_ref(m, P, lo, hi, theta)
        Y = X @ H.T
        Rs = [R + (0 if R_point is None else R_point(x)) for x in X]
        ym = w @ Y
        E = Y - ym
        Rbar = sum(wi * Ri for wi, Ri in zip(w, Rs, strict=True))
        Pyy = (E * w[:, None]).T @ E + Rbar
        Pxy = ((X - w @ X) * w[:, None]).T @ E
        Xk = np.array([nddr_box_qp(x, P, H, Ri, y[t], lo, hi) for x, Ri in zip(X, Rs, strict=True)])
        m = w @ Xk
        Dk = Xk - m
        P = (Dk * w[:, None]).T @ Dk
        if covariance == "corrected":
            K = Pxy @ np.linalg.inv(Pyy)
            P = P + K @ Rbar @ K.T
        ms.append(m.copy())
        Ps.append(P.copy())
    return np.array(ms), np.array(Ps)
