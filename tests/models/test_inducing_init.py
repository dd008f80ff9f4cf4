"""``InducingTransition.fit_residual``: the DTC posterior mean of the residual at the inducing
inputs, against the regularised least-squares problem it solves (numpy ``lstsq`` on the stacked
system), and what it buys: the one-step prediction of logged transitions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models import InducingTransition

D = torch.float64


def _pairs(N: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(N, 2, generator=gen, dtype=D)
    u = torch.randn(N, 1, generator=gen, dtype=D)
    xn = torch.stack([torch.sin(x[:, 0]) + 0.5 * u[:, 0], 0.8 * x[:, 1] - 0.3 * x[:, 0] ** 2], -1)
    return x, u, xn + 0.05 * torch.randn(N, 2, generator=gen, dtype=D)


def test_fit_residual_solves_the_regularised_least_squares_problem() -> None:
    x, u, xn = _pairs(60, 0)
    f = InducingTransition(2, 7, input_dim=1, lengthscale=1.3, outputscale=[0.5, 0.2])
    f.init_inducing(x, u)
    noise = torch.tensor([0.01, 0.03], dtype=D)
    f.fit_residual(x, xn, u, noise=noise)
    # reference: min_U |r - A U|^2 / noise + U^T (s C)^-1 U, A = C_XZ C_ZZ^-1, by lstsq
    Z = f.inducing_inputs.detach().numpy()
    zx = np.concatenate([x.numpy(), u.numpy()], -1)
    ls = 1.3

    def corr(a, b):
        return np.exp(-0.5 * (((a[:, None, :] - b[None]) / ls) ** 2).sum(-1))

    C = corr(Z, Z) + f.jitter * np.eye(7)
    A = corr(zx, Z) @ np.linalg.inv(C)
    r = xn.numpy() - zx @ np.concatenate([np.eye(2), np.zeros((2, 1))], -1).T  # random walk W
    L = np.linalg.cholesky(C)
    for j, s in enumerate([0.5, 0.2]):
        lhs = np.vstack([A / np.sqrt(noise[j].item()), np.linalg.inv(L) / np.sqrt(s)])
        rhs = np.concatenate([r[:, j] / np.sqrt(noise[j].item()), np.zeros(7)])
        ref = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
        np.testing.assert_allclose(f.inducing_outputs[j].detach().numpy(), ref, rtol=1e-6)


def test_fit_residual_predicts_held_out_transitions() -> None:
    x, u, xn = _pairs(200, 1)
    xt, ut, xnt = _pairs(200, 2)
    f = InducingTransition(2, 20, input_dim=1, lengthscale=1.0, outputscale=1.0)
    f.init_inducing(x, u)
    with torch.no_grad():
        before = (f.predict(xt, ut).mean - xnt).pow(2).mean().sqrt()
    f.fit_residual(x, xn, u, noise=0.01)
    with torch.no_grad():
        after = (f.predict(xt, ut).mean - xnt).pow(2).mean().sqrt()
    # the inducing inputs lie along the cloud's first principal direction (init_inducing), so
    # the residual is learned there only: a clear gain, not a perfect fit
    assert after < 0.7 * before, (float(before), float(after))


def test_fit_residual_refusals() -> None:
    x, u, xn = _pairs(10, 3)
    f = InducingTransition(2, 3, input_dim=1)
    f.init_inducing(x, u)
    with pytest.raises(ShapeError, match="inputs"):
        f.fit_residual(x, xn)
    with pytest.raises(ShapeError, match="next_states"):
        f.fit_residual(x, xn[:5], u)
    bad = xn.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(InputError, match="finite"):
        f.fit_residual(x, bad, u)
    with pytest.raises(InputError, match="noise"):
        f.fit_residual(x, xn, u, noise=0.0)
