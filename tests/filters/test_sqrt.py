"""The square-root CKF stays positive definite where the plain form in float32 does not."""

import warnings

import torch

import torchfilt
from torchfilt import CKF, LinearGaussianModel


def stiff_problem(dtype):
    A = torch.tensor([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0, 0.0]], dtype=dtype)
    Q = torch.diag(torch.tensor([1e-8, 1e-8, 1e-6], dtype=dtype))
    R = torch.tensor([[1e-8]], dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    t = torch.arange(200, dtype=dtype)[:, None]
    y = 0.5 * t**2 + 1e-4 * torch.randn(200, 1, generator=gen, dtype=dtype)
    P0 = torch.diag(torch.tensor([1e4, 1e4, 1e4], dtype=dtype))
    return LinearGaussianModel(A, H, Q, R), y, torch.zeros(3, dtype=dtype), P0


def test_plain_float32_loses_definiteness_sqrt_does_not():
    model, y, x0, P0 = stiff_problem(torch.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
        plain = CKF(model).filter(y, x0=x0, P0=P0, path="cubature")
    sq = CKF(model, sqrt=True).filter(y, x0=x0, P0=P0, path="cubature")
    plain_cov = plain.cov.double()
    finite = torch.isfinite(plain_cov).all(-1).all(-1)
    lost = (~finite).any() or (torch.linalg.eigvalsh(plain_cov[finite])[:, 0] < 0).any()
    assert lost, "the stress case no longer stresses the plain form"
    assert torch.isfinite(sq.mean).all() and torch.isfinite(sq.cov).all()
    ev = torch.linalg.eigvalsh(sq.cov.double())
    # PSD up to the float32 rounding of forming S S^T
    assert (ev[:, 0] >= -1e-6 * ev[:, -1]).all()
    # and it stays close to the float64 answer
    model64, y64, x064, P064 = stiff_problem(torch.float64)
    ref = CKF(model64, sqrt=True).filter(y64, x0=x064, P0=P064, path="cubature")
    assert torch.allclose(sq.mean.double(), ref.mean, rtol=1e-3, atol=1e-2)


def test_sqrt_rejects_negative_weights():
    model, *_ = stiff_problem(torch.float64)
    try:
        CKF(model, rule=torchfilt.cubature.UnscentedRule(kappa=-2.0), sqrt=True)
    except ValueError as e:
        assert "non-negative" in str(e)
    else:
        raise AssertionError("expected ValueError")
