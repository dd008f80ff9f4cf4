"""GP models inside the CKF: law of total variance, composition, and the Kalman filter reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gp_support import DT, one_thread
from reference import kalman_filter

from torchfilt import CKF, StateSpaceModel
from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.optim import OptimizerOptions

pytestmark = pytest.mark.usefixtures("one_thread")
__all__ = ["one_thread"]

#: Same quantity computed by the filter and by hand (float64, same operations up to order).
HAND_RTOL = 1e-10
#: GP-CKF vs Kalman filter (GP fitted on 400 pairs): mean error in posterior standard deviations,
#: and the ratio of posterior variances. 400 pairs leave a standard error of ~0.03 on each entry of
#: the learned dynamics, which moves the unobserved x2 by up to ~0.35 posterior sd.
KF_MEAN_SD = 0.5
KF_VAR_RATIO = (0.7, 1.45)

#: Autograd vs central differences (step 1e-5) of the filter's log-likelihood.
FD_RTOL = 1e-5
FD_ATOL = 1e-6

A = np.array([[0.9, 0.2], [0.0, 0.8]])
Q = np.diag([0.05, 0.02])
H = np.array([[1.0, 0.0]])
R = np.array([[0.1]])


def _stationary_cov() -> np.ndarray:
    P = np.eye(2)
    for _ in range(300):
        P = A @ P @ A.T + Q
    return P


def _linear_data(steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A stationary run of the linear system: states ``(steps + 1, 2)``, measurements ``(steps + 1, 1)``."""
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(np.zeros(2), _stationary_cov())
    xs, ys = [x], [H @ x + rng.normal(0, R[0, 0] ** 0.5, 1)]
    for _ in range(steps):
        x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        xs.append(x)
        ys.append(H @ x + rng.normal(0, R[0, 0] ** 0.5, 1))
    return torch.tensor(np.array(xs), dtype=DT), torch.tensor(np.array(ys), dtype=DT)


@pytest.fixture(scope="module")
def linear_gps():
    torch.set_num_threads(1)
    states, meas = _linear_data(400, seed=0)
    fit = dict(iterations=60, optimizer=OptimizerOptions("adam", lr=0.1), progress=False)
    f = GPTransition.fit(states, **fit)
    h = GPMeasurement.fit(states, meas, inputs=[0], **fit)
    return f, h


def test_learned_noise_matches_the_system(linear_gps):
    f, h = linear_gps
    torch.testing.assert_close(
        f.noise_variance, torch.tensor(np.diag(Q), dtype=DT), rtol=0.35, atol=0
    )
    torch.testing.assert_close(
        h.noise_variance, torch.tensor([R[0, 0]], dtype=DT), rtol=0.35, atol=0
    )


@pytest.mark.parametrize("measurement", ["known", "gp"])
def test_gp_ckf_is_close_to_the_kalman_filter(linear_gps, measurement):
    f, h = linear_gps
    _, y = _linear_data(40, seed=11)
    y = y[1:]
    Rt = torch.tensor(R, dtype=DT)
    model = (
        StateSpaceModel(f, lambda x, u: x[..., :1], R=Rt)  # learned f, known h
        if measurement == "known"
        else StateSpaceModel(f, h)
    )
    m0, P0 = np.zeros(2), _stationary_cov()  # the prior the GP's training data cover
    res = CKF(model).filter(y, x0=torch.zeros(2, dtype=DT), P0=torch.tensor(P0, dtype=DT))
    ms, Ps, *_ = kalman_filter(A, H, Q, R, y.numpy(), m0, P0)
    sd = np.sqrt(np.diagonal(Ps, axis1=-2, axis2=-1))
    err = np.abs(res.mean.numpy() - ms) / sd
    assert err.max() < KF_MEAN_SD, err.max()
    ratio = np.diagonal(res.cov.numpy(), axis1=-2, axis2=-1) / np.diagonal(Ps, axis1=-2, axis2=-1)
    assert KF_VAR_RATIO[0] < ratio.min() and ratio.max() < KF_VAR_RATIO[1], ratio


def _one_step_by_hand(f, h, Rv, x0, P0, y, point_variance):
    """Predicted covariance and innovation covariance of one CKF step, written out."""
    n = 2
    S = torch.linalg.cholesky(P0)
    xi = np.sqrt(n) * torch.cat([torch.eye(n, dtype=DT), -torch.eye(n, dtype=DT)])
    w = torch.full((2 * n,), 1.0 / (2 * n), dtype=DT)
    X = x0 + xi @ S.T
    pf = f.predict(X)
    m = w @ pf.mean
    D = pf.mean - m
    Vf = (
        torch.diag(w @ pf.var)
        if point_variance == "total"
        else torch.diag(f.predict(x0[None]).var[0])
    )
    P_pred = D.T @ (w[:, None] * D) + Vf
    Xu = m + xi @ torch.linalg.cholesky(P_pred).T
    ph = h.predict(Xu)
    ym = w @ ph.mean
    E = ph.mean - ym
    Vh = (
        torch.diag(w @ ph.var)
        if point_variance == "total"
        else torch.diag(h.predict(m[None]).var[0])
    )
    P_yy = E.T @ (w[:, None] * E) + Vh + Rv
    return P_pred, P_yy


@pytest.mark.parametrize("point_variance", ["total", "mean"])
@pytest.mark.parametrize("sqrt", [False, True])
def test_filter_computes_the_law_of_total_variance(linear_gps, point_variance, sqrt):
    f, h = linear_gps
    Rv = torch.tensor([[0.03]], dtype=DT)  # extra measurement noise on top of the GP's own
    model = StateSpaceModel(f, h, R=Rv)
    x0 = torch.tensor([0.3, -0.2], dtype=DT)
    P0 = torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=DT)
    y = torch.tensor([[0.4]], dtype=DT)
    res = CKF(model, sqrt=sqrt, point_variance=point_variance).filter(y, x0=x0, P0=P0)
    with torch.no_grad():
        P_pred, P_yy = _one_step_by_hand(f, h, Rv, x0, P0, y, point_variance)
    torch.testing.assert_close(res.predicted_cov[0], P_pred, rtol=HAND_RTOL, atol=1e-13)
    torch.testing.assert_close(res.innovation_cov[0], P_yy, rtol=HAND_RTOL, atol=1e-13)
    # the GP variance is a real part of Q and R here (not negligible against the spread)
    assert float(f.noise_variance.min()) > 0.01 * float(P_pred.diagonal().min())


def test_multitask_gp_in_the_filter(linear_gps):
    states, _ = _linear_data(150, seed=3)
    f = GPTransition.fit(
        states, structure="multitask", iterations=40, optimizer=OptimizerOptions("adam", lr=0.1),
        progress=False,
    )  # fmt: skip
    _, h = linear_gps
    _, y = _linear_data(20, seed=12)
    res = CKF(StateSpaceModel(f, h)).filter(
        y[1:], x0=torch.zeros(2, dtype=DT), P0=torch.eye(2, dtype=DT)
    )
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.log_likelihood).all()
    pred = f.predict(torch.zeros(6, 2, dtype=DT))
    assert pred.var is None and pred.cov is not None  # the filter adds cov, never var + cov


def test_gradients_flow_through_the_filter(linear_gps):
    f, h = linear_gps
    _, y = _linear_data(10, seed=13)
    x0 = torch.zeros(2, dtype=DT, requires_grad=True)
    ckf = CKF(StateSpaceModel(f, h))

    def ll(x):
        return ckf.filter(y[1:], x0=x, P0=torch.eye(2, dtype=DT)).log_likelihood

    ll(x0).backward()
    grad = x0.grad
    assert grad is not None
    eps = 1e-5
    for i in range(2):
        e = torch.zeros(2, dtype=DT)
        e[i] = eps
        with torch.no_grad():
            fd = (ll(x0 + e) - ll(x0 - e)) / (2 * eps)
        torch.testing.assert_close(grad[i], fd, rtol=FD_RTOL, atol=FD_ATOL)
