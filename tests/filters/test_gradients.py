"""The filter and smoother are differentiable end to end (gradcheck in float64)."""

import pytest
import torch

from torchfilt import CKF, StateSpaceModel
from torchfilt.cubature import UnscentedRule


def make(qscale, sqrt, rule=None):
    def f(x, u):
        return torch.stack(
            [x[..., 0] + 0.1 * x[..., 1], x[..., 1] - 0.1 * torch.sin(x[..., 0]) + 0.1 * u[..., 0]],
            -1,
        )

    def h(x, u):
        return torch.sin(x[..., :1]) + 0.5 * x[..., 1:]

    Q = qscale * torch.tensor([[0.02, 0.005], [0.005, 0.03]], dtype=torch.float64)
    m = StateSpaceModel(f, h, Q=Q, R=torch.tensor([[0.1]], dtype=torch.float64))
    return CKF(m, rule=rule, sqrt=sqrt)


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
@pytest.mark.parametrize("rule", [None, UnscentedRule(kappa=1.0)], ids=["ckf", "ukf"])
def test_gradcheck_filter_and_smoother(sqrt, rule):
    gen = torch.Generator().manual_seed(0)
    y = torch.randn(4, 1, dtype=torch.float64, generator=gen)
    y[2, 0] = float("nan")  # a missing step on the gradient path
    u = torch.randn(4, 1, dtype=torch.float64, generator=gen)
    x0 = torch.tensor([0.3, -0.2], dtype=torch.float64, requires_grad=True)
    L0 = torch.tensor([[1.0, 0.0], [0.3, 0.8]], dtype=torch.float64, requires_grad=True)
    q = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    yy = torch.nan_to_num(y).requires_grad_(True)
    missing = torch.isnan(y)

    def fn(x0, L0, q, yy):
        filt = make(q, sqrt, rule)
        yv = torch.where(missing, torch.full_like(yy, float("nan")), yy)
        sm = filt.smooth(yv, u, x0=x0, P0=L0 @ L0.mT)
        return sm.filtered.log_likelihood, sm.mean, sm.cov

    assert torch.autograd.gradcheck(fn, (x0, L0, q, yy), eps=1e-6, atol=1e-6)
