"""Maximum likelihood through the filter against statsmodels' state-space MLE (float64).

On a linear-Gaussian model the CKF is the Kalman filter, so its innovation likelihood is the exact
likelihood and its maximiser must equal that of an independent implementation: statsmodels'
``MLEModel`` (its own Kalman filter and optimiser).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from statsmodels.tsa.statespace import mlemodel as sm_mlemodel

import torchfilt
from torchfilt.models.params import CholeskyCovariance, DiagonalCovariance, ScalarCovariance
from torchfilt.optim import StoppingOptions
from torchfilt.training.likelihood import fit_likelihood

DT = torch.float64
#: relative agreement of the two maximisers (the issue's acceptance figure)
MLE_RTOL = 1e-4
#: statsmodels' optimiser tolerance
SM_GTOL = 1e-11


def simulate(A, H, Q, R, T, seed):
    g = torch.Generator().manual_seed(seed)
    n, m = A.shape[0], H.shape[0]
    LQ, LR = torch.linalg.cholesky(Q), torch.linalg.cholesky(R)
    x = torch.zeros(n, dtype=DT)
    ys = []
    for _ in range(T):
        x = A @ x + LQ @ torch.randn(n, generator=g, dtype=DT)
        ys.append(H @ x + LR @ torch.randn(m, generator=g, dtype=DT))
    return torch.stack(ys)


class _LinearMLE(sm_mlemodel.MLEModel):
    """statsmodels model with known A, H, prior; Q and R from Cholesky factors with log diagonals
    (or log variances when ``diagonal``)."""

    def __init__(self, y, A, H, x0, P0, q_full: bool, r_full: bool):
        n, m = A.shape[0], H.shape[0]
        super().__init__(y, k_states=n, k_posdef=n)
        self["design"] = H
        self["transition"] = A
        self["selection"] = np.eye(n)
        self.A, self.x0, self.P0 = A, x0, P0
        self.n, self.m, self.q_full, self.r_full = n, m, q_full, r_full

    def _unpack(self, p, d, full):
        if not full:
            k = d if d > 1 else 1
            return np.diag(np.exp(p[:k])), p[k:]
        L = np.zeros((d, d), dtype=p.dtype)
        k = d * (d + 1) // 2
        L[np.tril_indices(d)] = p[:k]
        L[np.diag_indices(d)] = np.exp(np.diag(L))
        return L @ L.T, p[k:]

    def matrices(self, params):
        Q, rest = self._unpack(np.asarray(params), self.n, self.q_full)
        R, _ = self._unpack(rest, self.m, self.r_full)
        return Q, R

    def update(self, params, **kwargs):
        params = super().update(params, **kwargs)
        Q, R = self.matrices(params)
        self["state_cov"] = Q
        self["obs_cov"] = R
        # torchfilt's prior is the state before the first step: a1 = A x0, P1 = A P0 A' + Q
        self.ssm.initialize_known(self.A @ self.x0, self.A @ self.P0 @ self.A.T + Q)


def _n_params(d: int, full: bool) -> int:
    return d * (d + 1) // 2 if full else d


def _sm_fit(y, A, H, x0, P0, q_full, r_full, start):
    mod = _LinearMLE(y.numpy(), A.numpy(), H.numpy(), x0.numpy(), P0.numpy(), q_full, r_full)
    res = mod.fit(
        start_params=start,
        method="lbfgs",
        maxiter=5000,
        pgtol=SM_GTOL,
        factr=10.0,
        disp=False,
        cov_type="none",
    )
    Q, R = mod.matrices(res.params)
    return Q, R, float(res.llf)


@pytest.mark.parametrize(
    ("case", "n", "m", "q_full", "r_full"),
    [("scalar", 1, 1, False, False), ("matrix", 2, 2, True, False)],
)
def test_mle_equals_statsmodels(case, n, m, q_full, r_full):
    if n == 1:
        A = torch.tensor([[0.9]], dtype=DT)
        H = torch.tensor([[1.0]], dtype=DT)
        Qt, Rt = torch.tensor([[0.3]], dtype=DT), torch.tensor([[0.5]], dtype=DT)
    else:
        A = torch.tensor([[0.95, 0.1], [-0.1, 0.9]], dtype=DT)
        H = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=DT)
        Qt = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=DT)
        Rt = torch.diag(torch.tensor([0.3, 0.2], dtype=DT))
    y = simulate(A, H, Qt, Rt, T=150, seed=3 if n == 1 else 4)
    x0, P0 = torch.zeros(n, dtype=DT), torch.eye(n, dtype=DT)
    Q = (
        CholeskyCovariance(torch.eye(n, dtype=DT))
        if q_full
        else (
            ScalarCovariance(1.0, 1, dtype=DT)
            if n == 1
            else DiagonalCovariance(torch.ones(n, dtype=DT))
        )
    )
    R = (
        DiagonalCovariance(torch.ones(m, dtype=DT))
        if not r_full
        else CholeskyCovariance(torch.eye(m, dtype=DT))
    )
    model = torchfilt.StateSpaceModel(lambda x, u: x @ A.mT, lambda x, u: x @ H.mT, Q=Q, R=R)
    fit = fit_likelihood(
        model,
        y,
        x0=x0,
        P0=P0,
        optimizer="lbfgs",
        iterations=60,
        stopping=StoppingOptions(tol=1e-13),
    )
    assert fit.stopped in ("converged", "iterations")
    # statsmodels from the same start (identity Q, R: zero raw parameters)
    start = np.zeros(_n_params(n, q_full) + _n_params(m, r_full))
    Qs, Rs, llf = _sm_fit(y, A, H, x0, P0, q_full, r_full, start)
    with torch.no_grad():
        Qh, Rh = Q().numpy(), R().numpy()
    np.testing.assert_allclose(fit.log_likelihood, llf, rtol=1e-9)
    np.testing.assert_allclose(Qh, Qs, rtol=MLE_RTOL, atol=MLE_RTOL * np.abs(Qs).max())
    np.testing.assert_allclose(Rh, Rs, rtol=MLE_RTOL, atol=MLE_RTOL * np.abs(Rs).max())
    # and the fit moved: the identity start is far from the optimum
    assert fit.log_likelihood > fit.initial_log_likelihood + 1.0
