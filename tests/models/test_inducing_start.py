"""``InducingTransition.from_linear`` / ``model_from_linear`` start exactly at the linear model
(the textbook Kalman likelihood of ``tests/reference.py``), and the fits report their initial
log-likelihood at the start parameters (an independent filter run there)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchfilt
from tests.reference import kalman_filter
from torchfilt.exceptions import InputTypeError
from torchfilt.models import (
    CholeskyCovariance,
    InducingTransition,
    LinearGaussianModel,
    LinearModel,
    StateSpaceModel,
)
from torchfilt.training import fit_em, fit_measurement_only

D = torch.float64
A = torch.tensor([[0.9, 0.2], [-0.3, 0.7]], dtype=D)
H = torch.tensor([[1.0, 0.0], [0.4, 1.0]], dtype=D)
Q = torch.tensor([[0.05, 0.02], [0.02, 0.08]], dtype=D)  # full, not diagonal
R = torch.tensor([[0.04, 0.01], [0.01, 0.09]], dtype=D)
X0, P0 = torch.zeros(2, dtype=D), torch.eye(2, dtype=D)


def _data(T: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    LQ, LR = torch.linalg.cholesky(Q), torch.linalg.cholesky(R)
    x, ys = torch.zeros(2, dtype=D), []
    for _ in range(T):
        x = A @ x + LQ @ torch.randn(2, generator=g, dtype=D)
        ys.append(H @ x + LR @ torch.randn(2, generator=g, dtype=D))
    return torch.stack(ys)


def _reference_ll(y: torch.Tensor) -> float:
    n = lambda t: t.numpy()  # noqa: E731
    return float(kalman_filter(n(A), n(H), n(Q), n(R), n(y), n(X0), n(P0))[-1])


def test_model_from_linear_starts_at_the_linear_likelihood() -> None:
    y = _data()
    lin = LinearGaussianModel(A, H, Q, R)
    with torch.no_grad():
        sm = torchfilt.filters.rts_smooth(torchfilt.CKF(lin).filter(y, x0=X0, P0=P0))
    # inducing points on the smoothed states, and far from every state (no extra variance there)
    model = InducingTransition.model_from_linear(lin, inducing=6, states=sm.mean)
    far = InducingTransition.model_from_linear(lin, inducing=6, states=sm.mean + 50.0)
    ref = _reference_ll(y)
    for m in (model, far):
        with torch.no_grad():
            ll = float(torchfilt.CKF(m).filter(y, x0=X0, P0=P0).log_likelihood)
        assert abs(ll - ref) <= 1e-8 * abs(ref), (ll, ref)
    # the full Q is carried (not its diagonal), and R with the measurement side
    assert torch.allclose(model.transition.noise_cov(), Q, rtol=1e-12)
    assert torch.allclose(model.measurement.noise_cov(), R, rtol=1e-12)
    # the old default (outputscale 0.1) is visibly off the linear likelihood: the test can fail
    loose = InducingTransition.model_from_linear(lin, inducing=6, states=sm.mean, outputscale=0.1)
    with torch.no_grad():
        ll_loose = float(torchfilt.CKF(loose).filter(y, x0=X0, P0=P0).log_likelihood)
    assert abs(ll_loose - ref) > 1e-3 * abs(ref)
    with pytest.raises(InputTypeError, match="linear"):
        InducingTransition.model_from_linear(model)  # type: ignore[arg-type]


def test_bounded_hyperparameters_keep_the_prediction_finite() -> None:
    f = InducingTransition(2, 5, lengthscale=1.0, outputscale=0.1)
    f.init_inducing(torch.randn(30, 2, generator=torch.Generator().manual_seed(1), dtype=D))
    x = torch.randn(1, 8, 2, generator=torch.Generator().manual_seed(2), dtype=D)
    with torch.no_grad():
        for ls, sc in ((500.0, 0.0), (-500.0, 0.0), (0.0, 500.0), (0.0, -500.0)):
            f.log_lengthscale.fill_(ls)
            f.log_outputscale.fill_(sc)
            p = f.predict(x)
            assert bool(torch.isfinite(p.mean).all()) and bool(torch.isfinite(p.var).all())


def _learnable() -> StateSpaceModel:
    f = InducingTransition(2, 0, linear=0.5 * A)
    h = LinearModel(H, CholeskyCovariance(2 * R), name="measurement")
    return StateSpaceModel(f, h, Q=CholeskyCovariance(2 * Q))


@pytest.mark.parametrize("method", ["em", "likelihood"])
def test_initial_log_likelihood_is_the_value_at_the_start(method: str) -> None:
    y = _data(120, seed=1)
    model = _learnable()
    with torch.no_grad():
        start = float(torchfilt.CKF(model).filter(y, x0=X0, P0=P0).log_likelihood)
    fit = fit_measurement_only(
        model, y, x0=X0, P0=P0, known_channels=[0, 1], method=method, iterations=3
    )
    assert fit.initial_log_likelihood == pytest.approx(start, rel=1e-10)
    assert fit.detail.initial_log_likelihood == pytest.approx(start, rel=1e-10)
    assert fit.log_likelihood > start


def test_em_initial_log_likelihood_of_a_linear_model() -> None:
    y = _data(120, seed=2)
    lin = LinearGaussianModel(0.5 * A, H, 2 * Q, 2 * R)
    ref = float(kalman_filter(*(t.numpy() for t in (0.5 * A, H, 2 * Q, 2 * R, y, X0, P0)))[-1])
    fit = fit_em(lin, y, x0=X0, P0=P0, known_channels=[0, 1], iterations=2)
    assert fit.initial_log_likelihood == pytest.approx(ref, rel=1e-10)
    assert np.isfinite(fit.log_likelihood) and fit.log_likelihood > ref


def test_fitting_the_gp_model_leaves_the_linear_model_alone() -> None:
    """The GP model's measurement side is a copy: EM on it (which learns R) must not move the
    learnable linear model it started from."""
    y = _data()
    lin = LinearGaussianModel(A, H, Q, R).learnable()
    before = {k: v.detach().clone() for k, v in lin.state_dict().items()}
    with torch.no_grad():
        sm = torchfilt.filters.rts_smooth(torchfilt.CKF(lin).filter(y, x0=X0, P0=P0))
    model = InducingTransition.model_from_linear(lin, inducing=4, states=sm.mean)
    fit = fit_em(model, y, x0=X0, P0=P0, known_channels=[0], iterations=2)
    assert fit.log_likelihood > fit.initial_log_likelihood  # the fit moved its own model
    assert not torch.allclose(model.measurement.noise_cov(), R)
    for k, v in lin.state_dict().items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
