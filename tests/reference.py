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
