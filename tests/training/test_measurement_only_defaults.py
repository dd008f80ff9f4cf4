"""No crash from the defaults on a case like the ones users bring: one recording of a Van der
Pol oscillator (200 steps), its non-linear sensor known, a rough linear model (the oscillator
linearised at the origin, which misses the cubic damping) as the nominal transition under an
``InducingTransition``, ``fit_measurement_only`` with its default options for both methods and a
small iteration budget. The default ``noise_scale="auto"`` holds out the last 40 steps, so the
fit sees the first 160. The fit must end with finite parameters, a finite log-likelihood no
worse than its start (the value of an independent CKF run there on those 160 steps) and a
held-out noise scale, or raise a ``FitError`` naming the fit and the step."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import torchfilt
from torchfilt.exceptions import FitError
from torchfilt.models import CholeskyCovariance, InducingTransition, StateSpaceModel
from torchfilt.training import fit_measurement_only

D = torch.float64
DT, MU, T = 0.1, 1.0, 200


def _vdp(x: torch.Tensor) -> torch.Tensor:
    """One Euler step of the Van der Pol oscillator, ``(..., 2) -> (..., 2)``."""
    x1, x2 = x[..., 0], x[..., 1]
    return torch.stack([x1 + DT * x2, x2 + DT * (MU * (1 - x1**2) * x2 - x1)], -1)


def _nominal(x: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor:
    """The oscillator linearised at the origin (no cubic damping): a rough model."""
    x1, x2 = x[..., 0], x[..., 1]
    return torch.stack([x1 + DT * x2, x2 + DT * (MU * x2 - x1)], -1)


def _sensor(x: torch.Tensor) -> torch.Tensor:
    """The known non-linear sensor: a position through a soft saturation, and a product."""
    return torch.stack([2.0 * torch.tanh(0.5 * x[..., 0]), x[..., 0] * x[..., 1]], -1)


R = torch.diag(torch.tensor([0.01, 0.02], dtype=D))


def _data() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    x, xs, ys = torch.tensor([1.5, 0.0], dtype=D), [], []
    for _ in range(T):
        x = _vdp(x) + 0.02 * torch.randn(2, generator=g, dtype=D)
        xs.append(x)
        ys.append(_sensor(x) + R.sqrt() @ torch.randn(2, generator=g, dtype=D))
    return torch.stack(ys), torch.stack(xs)


# the likelihood method's L-BFGS takes about a minute here on 2 shared cores: slow
@pytest.mark.parametrize("method", ["em", pytest.param("likelihood", marks=pytest.mark.slow)])
def test_defaults_do_not_crash_on_a_nonlinear_oscillator(method: str) -> None:
    y, _ = _data()
    x0, P0 = torch.tensor([1.0, 0.0], dtype=D), torch.eye(2, dtype=D)
    q0 = 1e-3 * torch.eye(2, dtype=D)
    pilot = StateSpaceModel(InducingTransition(2, 0, nominal=_nominal), _sensor, Q=q0, R=R)
    with torch.no_grad():
        X = torchfilt.CKF(pilot).filter(y, x0=x0, P0=P0).mean
    f = InducingTransition(2, 8, nominal=_nominal, lengthscale=X.std(0), outputscale=1e-3)
    f.init_inducing(X)
    model = StateSpaceModel(f, _sensor, Q=CholeskyCovariance(q0), R=R)
    heads = y[: T - math.floor(0.2 * T)]
    with torch.no_grad():
        start = float(torchfilt.CKF(model).filter(heads, x0=x0, P0=P0).log_likelihood)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = fit_measurement_only(
                model, y, x0=x0, P0=P0, known_channels=[0, 1], method=method,  # type: ignore[arg-type]
                iterations=3,
            )  # fmt: skip
    except FitError as e:  # allowed, if it names the fit and the step
        assert e.fit and e.step and e.fit in str(e) and e.step in str(e)
        return
    assert fit.initial_log_likelihood == pytest.approx(start, rel=1e-8)
    assert math.isfinite(fit.log_likelihood) and fit.log_likelihood >= start
    assert all(bool(torch.isfinite(p).all()) for p in fit.model.parameters())
    assert fit.noise_scale is not None and fit.noise_scale.held_out == 2 * 40
