"""The closed-form noise block of fit_em's gradient M-step (``torchfilt.training.em_noise``):
the exact weighted residual covariance (numpy), a stationary point of the expected
complete-data log-likelihood (its gradient in the raw parameters vanishes), and left to L-BFGS
wherever the closed form does not apply."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfilt.models import (
    CholeskyCovariance,
    DiagonalCovariance,
    FunctionModel,
    Prediction,
    ScalarCovariance,
)
from torchfilt.numerics import gaussian_log_prob, safe_cholesky
from torchfilt.training.em_noise import closed_form_noise

f64 = torch.float64
K, P, N = 40, 6, 3


def _map(x: torch.Tensor) -> torch.Tensor:
    return torch.stack(
        [torch.sin(x[..., 0]) + x[..., 1], 0.5 * x[..., 1] * x[..., 2], x[..., 2]], -1
    )


def _case(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(K, P, N, generator=g, dtype=f64)
    target = _map(pts) + torch.randn(K, P, N, generator=g, dtype=f64) @ torch.tensor(
        [[0.3, 0.0, 0.0], [0.1, 0.2, 0.0], [0.0, -0.05, 0.4]], dtype=f64
    )
    w = torch.full((P,), 1.0 / P, dtype=f64)
    return pts, target, w


def _numpy_s(pts, target, w) -> np.ndarray:
    e = (target - _map(pts)).numpy()
    S = np.zeros((N, N))
    for k in range(K):
        for p in range(P):
            S += w[p].item() * np.outer(e[k, p], e[k, p])
    return S / K


def _one_process(*v):
    return [t.to(f64) for t in v]


@pytest.mark.parametrize(
    ("noise", "family"),
    [
        (CholeskyCovariance(torch.eye(N, dtype=f64)), lambda S: S),
        (DiagonalCovariance(torch.ones(N, dtype=f64)), lambda S: np.diag(np.diag(S))),
        (ScalarCovariance(1.0, N, dtype=f64), lambda S: np.trace(S) / N * np.eye(N)),
    ],
)
def test_the_noise_is_the_weighted_residual_covariance_of_its_family(noise, family):
    pts, target, w = _case()
    side = FunctionModel(_map, noise, name="transition")
    free = {id(p) for p in side.parameters()}
    got = closed_form_noise(side, pts, None, target, w, free, _one_process)
    assert {id(p) for p in got} == free
    np.testing.assert_allclose(
        side.noise_cov().detach().numpy(), family(_numpy_s(pts, target, w)), rtol=1e-12, atol=1e-14
    )
    # a maximiser: the gradient of the expected complete-data log-likelihood vanishes there
    q = (gaussian_log_prob(target - _map(pts), safe_cholesky(side.noise_cov())) * w).sum()
    grads = torch.autograd.grad(q, list(side.parameters()))
    assert max(float(g.abs().max()) for g in grads) < 1e-9


def test_a_data_parallel_fit_sums_before_dividing():
    """Two processes with halves of the steps end with the covariance of all steps."""
    pts, target, w = _case(1)
    want = FunctionModel(_map, CholeskyCovariance(torch.eye(N, dtype=f64)), name="transition")
    closed_form_noise(want, pts, None, target, w, {id(p) for p in want.parameters()}, _one_process)
    halves = []
    for part in (slice(0, K // 2), slice(K // 2, K)):
        side = FunctionModel(_map, CholeskyCovariance(torch.eye(N, dtype=f64)), name="transition")
        e = target[part] - _map(pts[part])
        halves.append((side, torch.einsum("kpi,kpj,p->ij", e, e, w), float(e.shape[0])))
    total_S = halves[0][1] + halves[1][1]
    total_n = halves[0][2] + halves[1][2]
    for (side, _, _), part in zip(halves, (slice(0, K // 2), slice(K // 2, K)), strict=True):
        summed = lambda S, n: [total_S, torch.tensor(total_n)]  # noqa: E731  (the collective)
        closed_form_noise(
            side, pts[part], None, target[part], w, {id(p) for p in side.parameters()}, summed
        )
        torch.testing.assert_close(side.noise_cov(), want.noise_cov(), rtol=1e-12, atol=1e-14)


def test_left_to_lbfgs_where_there_is_no_closed_form():
    pts, target, w = _case(2)
    start = torch.eye(N, dtype=f64)

    class WithVariance(FunctionModel):  # a GP-like side: the variance couples map and noise
        def predict(self, x, u=None):
            return Prediction(_map(x), var=torch.full_like(x, 0.1))

    cases = [
        FunctionModel(_map, start, name="transition"),  # a constant noise: nothing to learn
        WithVariance(_map, CholeskyCovariance(start), name="transition"),
        FunctionModel(_map, CholeskyCovariance(start.expand(2, N, N)), name="transition"),
    ]
    for side in cases:
        free = {id(p) for p in side.parameters()}
        assert closed_form_noise(side, pts, None, target, w, free, _one_process) == []
    fixed = FunctionModel(_map, CholeskyCovariance(start), name="transition")
    assert closed_form_noise(fixed, pts, None, target, w, set(), _one_process) == []
    negative = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, -1.5], dtype=f64)  # a rule's weights
    assert (
        closed_form_noise(
            fixed, pts, None, target, negative, {id(p) for p in fixed.parameters()}, _one_process
        )
        == []
    )
    for side in [*cases, fixed]:  # nothing moved
        torch.testing.assert_close(side.noise_cov().detach().reshape(-1, N, N)[0], start)
