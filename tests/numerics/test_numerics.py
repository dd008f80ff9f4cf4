import warnings

import numpy as np
import pytest
import scipy.stats
import torch
from conftest import TIGHT, random_spd

from torchfilt.exceptions import CholeskyJitterWarning
from torchfilt.numerics import (
    chi2_quantile,
    cholesky_ok,
    gaussian_log_prob,
    psd_solve,
    safe_cholesky,
    symmetrize,
    tria,
)


def test_symmetrize():
    A = torch.randn(3, 4, 4, dtype=torch.float64)
    S = symmetrize(A)
    assert torch.equal(S, S.mT)
    assert torch.allclose(S, 0.5 * (A + A.mT))


def test_safe_cholesky_matches_exact_for_spd():
    rng = np.random.default_rng(1)
    A = torch.tensor(np.stack([random_spd(rng, 5) for _ in range(3)]))
    L = safe_cholesky(A)
    assert torch.allclose(L, torch.linalg.cholesky(A), rtol=TIGHT, atol=0)


def test_safe_cholesky_jitters_singular_and_warns():
    v = torch.tensor([[1.0], [2.0], [3.0]], dtype=torch.float64)
    A = torch.stack([v @ v.mT, torch.eye(3, dtype=torch.float64)])  # first is rank one
    with pytest.warns(CholeskyJitterWarning, match="jitter"):
        L = safe_cholesky(A, name="A")
    assert torch.isfinite(L).all()
    # the good element is untouched, the bad one is close to the original
    assert torch.equal(L[1], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(L[0] @ L[0].mT, A[0], atol=1e-8)


def test_safe_cholesky_indefinite_gives_nan_or_raises():
    A = torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CholeskyJitterWarning)
        L = safe_cholesky(torch.stack([A, torch.eye(2, dtype=torch.float64)]))
        assert torch.isnan(L[0]).all() and torch.isfinite(L[1]).all()
        with pytest.raises(ValueError, match="covariance X is not positive definite"):
            safe_cholesky(A, on_failure="raise", name="covariance X")


def test_cholesky_ok():
    A = torch.stack([torch.eye(2), -torch.eye(2)]).double()
    assert cholesky_ok(A).tolist() == [True, False]


def test_psd_solve_matches_numpy():
    rng = np.random.default_rng(2)
    A = random_spd(rng, 6, cond=1e4)
    B = rng.standard_normal((6, 3))
    X = psd_solve(torch.tensor(A), torch.tensor(B)).numpy()
    np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-9)


@pytest.mark.parametrize("k", [2, 5, 9])
def test_tria_equals_cholesky_of_product(k):
    A = torch.randn(4, 5, k, dtype=torch.float64)
    S = tria(A)
    assert torch.allclose(S, S.tril())
    assert (S.diagonal(dim1=-2, dim2=-1) >= 0).all()
    assert torch.allclose(S @ S.mT, A @ A.mT, rtol=TIGHT, atol=1e-12)
    if k >= 5:
        assert torch.allclose(S, torch.linalg.cholesky(A @ A.mT), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("dof", [1, 2, 3, 7.5, 40])
def test_chi2_quantile_matches_scipy(dof):
    for p in (0.025, 0.5, 0.975):
        q = float(chi2_quantile(p, dof))
        assert q == pytest.approx(scipy.stats.chi2.ppf(p, dof), rel=1e-10)


def test_chi2_quantile_rejects_bad_input():
    with pytest.raises(ValueError, match="p must lie"):
        chi2_quantile(1.0, 2)
    with pytest.raises(ValueError, match="dof"):
        chi2_quantile(0.5, 0)


def test_gaussian_log_prob_matches_scipy():
    rng = np.random.default_rng(3)
    S = random_spd(rng, 3)
    e = rng.standard_normal(3)
    L = torch.linalg.cholesky(torch.tensor(S))
    got = float(gaussian_log_prob(torch.tensor(e), L))
    want = scipy.stats.multivariate_normal(np.zeros(3), S).logpdf(e)
    assert got == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
def test_unrolled_small_kernels_match_lapack(n):
    from torchfilt.numerics import small

    gen = torch.Generator().manual_seed(n)
    X = torch.randn(small.SMALL_BATCH, n, n + 2, generator=gen, dtype=torch.float64)
    A = X @ X.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    B = torch.randn(small.SMALL_BATCH, n, 3, generator=gen, dtype=torch.float64)
    assert small.use_unrolled(A)
    L, info = small.cholesky_ex(A)
    assert (info == 0).all()
    assert torch.allclose(L, torch.linalg.cholesky(A), rtol=TIGHT, atol=1e-12)
    want = torch.linalg.solve_triangular(L, B, upper=False)
    assert torch.allclose(small.solve_tril(L, B), want, rtol=TIGHT, atol=1e-12)
    assert torch.allclose(
        small.cholesky_solve(B, L), torch.linalg.solve(A, B), rtol=1e-8, atol=1e-10
    )


def test_unrolled_cholesky_reports_failures_like_lapack():
    from torchfilt.numerics import small

    A = torch.eye(3, dtype=torch.float64).repeat(small.SMALL_BATCH, 1, 1)
    A[5, 1, 1] = -1.0
    A[9, 2, 2] = float("nan")
    _, info = small.cholesky_ex(A)
    _, info_ref = torch.linalg.cholesky_ex(A[:8])
    assert info[5] == 2 and info[9] == 3 and info_ref[5] == 2
    assert (info[[i for i in range(small.SMALL_BATCH) if i not in (5, 9)]] == 0).all()


def test_safe_cholesky_jitter_on_a_tensor_with_grad_warns_only_about_the_jitter():
    """The jitter report read a tensor that carries a gradient into a float, which raised
    torch's "Converting a tensor with requires_grad=True" UserWarning inside likelihood fits."""
    A = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=torch.float64, requires_grad=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        L = safe_cholesky(A, name="A")
    assert {type(w.message) for w in caught} == {CholeskyJitterWarning}
    L.sum().backward()
    assert A.grad is not None and bool(torch.isfinite(A.grad).all())
