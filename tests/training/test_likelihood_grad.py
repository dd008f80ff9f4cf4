"""Gradients of the filter's log-likelihood against float64 finite differences.

Covered: the plain and the square-root CKF, learnable Q and R (log-diagonal and Cholesky
parametrisations), a drag-like model constant, missing measurement components, time-varying
noise, and a frozen GP predictor wrapped in a :class:`~torchfilt.models.CalibratedModel`.
"""

from __future__ import annotations

import pytest
import torch
from torch.func import functional_call

import torchfilt
from torchfilt.models import CalibratedModel, TimeVarying
from torchfilt.models.gp import GPMeasurement
from torchfilt.models.params import Bounded, CholeskyCovariance, DiagonalCovariance, Positive

DT = torch.float64
#: finite-difference step and tolerances of torch.autograd.gradcheck (float64)
FD_EPS = 1e-6
FD_ATOL = 1e-5
FD_RTOL = 1e-4
T, N = 12, 2


def _data(seed: int, missing: bool) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(3, T, 2, generator=g, dtype=DT)
    if missing:
        drop = torch.rand(3, T, 2, generator=g, dtype=DT) < 0.3
        y = torch.where(drop, torch.full_like(y, float("nan")), y)
    return y


def _loglik(model: torchfilt.StateSpaceModel, y: torch.Tensor, sqrt: bool) -> torch.Tensor:
    x0 = torch.tensor([0.1, -0.2], dtype=DT)
    res = torchfilt.CKF(model, sqrt=sqrt).filter(y, x0=x0, P0=0.5 * torch.eye(N, dtype=DT))
    return res.log_likelihood.sum()


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
@pytest.mark.parametrize("missing", [False, True], ids=["full", "missing"])
def test_gradcheck_noise_and_constants(sqrt: bool, missing: bool) -> None:
    y = _data(0, missing)
    drag = Positive(0.3, dtype=DT)
    gain = Bounded(0.8, 0.0, 2.0, dtype=DT)
    Q = CholeskyCovariance(torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=DT))
    R = DiagonalCovariance(torch.tensor([0.3, 0.4], dtype=DT))

    def f(x, u):
        return torch.stack(
            [x[..., 0] + 0.1 * x[..., 1], x[..., 1] - 0.1 * drag() * x[..., 1] ** 2], -1
        )

    def h(x, u):
        return torch.stack([gain() * x[..., 0], torch.sin(x[..., 1])], -1)

    model = torchfilt.StateSpaceModel(f, h, Q=Q, R=R)
    holder = torch.nn.ModuleDict({"drag": drag, "gain": gain, "model": model})
    names = [
        "drag.raw",
        "gain.raw",
        "model.transition.noise_param.raw_diag",
        "model.transition.noise_param.raw_lower",
        "model.measurement.noise_param.raw",
    ]
    params = dict(holder.named_parameters())
    assert sorted(params) == sorted(names)

    def fn(*values):
        # the closures f and h call drag() and gain(): functional_call swaps their parameters too
        return _swap(holder, names, values, lambda: _loglik(model, y, sqrt))

    inputs = [params[n].detach().clone().requires_grad_(True) for n in names]
    assert torch.autograd.gradcheck(fn, inputs, eps=FD_EPS, atol=FD_ATOL, rtol=FD_RTOL)


def _swap(holder, names, values, body):
    """Evaluate ``body()`` with the parameters ``names`` of ``holder`` replaced by ``values``."""

    class _Body(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.holder = holder

        def forward(self):
            return body()

    return functional_call(
        _Body(), {f"holder.{n}": v for n, v in zip(names, values, strict=True)}, ()
    )


def test_gradcheck_time_varying_noise() -> None:
    y = _data(1, True)
    g = torch.Generator().manual_seed(2)
    base = torch.rand(T, 2, generator=g, dtype=DT) + 0.2
    A = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=DT)

    def fn(log_r, log_q):
        Rk = TimeVarying(torch.diag_embed(base * log_r.exp()))
        Q = torch.diag(log_q.exp())
        model = torchfilt.StateSpaceModel(lambda x, u: x @ A.mT, lambda x, u: x, Q=Q, R=Rk)
        return _loglik(model, y, sqrt=False)

    inputs = [
        torch.tensor([0.1, -0.3], dtype=DT, requires_grad=True),
        torch.tensor([-1.0, -0.5], dtype=DT, requires_grad=True),
    ]
    assert torch.autograd.gradcheck(fn, inputs, eps=FD_EPS, atol=FD_ATOL, rtol=FD_RTOL)


def test_gradcheck_gp_predictor_calibrated() -> None:
    """Through the frozen GP predictor: the variance scales, the floor and the prior mean."""
    g = torch.Generator().manual_seed(3)
    xs = torch.rand(40, 2, generator=g, dtype=DT) * 2 - 1
    ys = torch.stack([torch.sin(2 * xs[:, 0]), xs[:, 0] * xs[:, 1]], -1)
    ys = ys + 0.05 * torch.randn(40, 2, generator=g, dtype=DT)
    h = GPMeasurement.fit(xs, ys, iterations=20, progress=False, seed=0)
    y = _data(4, True) * 0.3
    A = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=DT)
    hc = CalibratedModel(h, scale=[1.5, 0.7], floor=[1e-3, 2e-3])

    model = torchfilt.StateSpaceModel(lambda x, u: x @ A.mT, hc, Q=0.05 * torch.eye(2, dtype=DT))
    holder = torch.nn.ModuleDict({"h": hc})

    def fn(log_scale, log_floor, x0):
        def body():
            res = torchfilt.CKF(model).filter(y, x0=x0, P0=0.2 * torch.eye(2, dtype=DT))
            return res.log_likelihood.sum()

        return _swap(holder, ["h.log_scale", "h.log_floor"], [log_scale, log_floor], body)

    inputs = [
        hc.log_scale.detach().clone().requires_grad_(True),
        hc.log_floor.detach().clone().requires_grad_(True),
        torch.tensor([0.1, -0.1], dtype=DT, requires_grad=True),
    ]
    assert torch.autograd.gradcheck(fn, inputs, eps=FD_EPS, atol=FD_ATOL, rtol=FD_RTOL)
