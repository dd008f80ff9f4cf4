import numpy as np
import pytest
import scipy.stats
import torch

from torchfilt import CKF, LinearGaussianModel, nees, nis, rmse, simulate


def test_nis_matches_numpy_with_missing():
    gen = torch.Generator().manual_seed(1)
    A = torch.eye(2, dtype=torch.float64)
    H = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    m = LinearGaussianModel(
        A, H, 0.1 * torch.eye(2, dtype=torch.float64), torch.eye(3, dtype=torch.float64)
    )
    y = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    y[2, 1] = float("nan")
    y[5] = float("nan")
    res = CKF(m).filter(
        y, x0=torch.zeros(2, dtype=torch.float64), P0=torch.eye(2, dtype=torch.float64)
    )
    got, dof = nis(res)
    for t in range(10):
        o = res.observed[t].numpy()
        e = res.innovation[t].numpy()[o]
        S = res.innovation_cov[t].numpy()[np.ix_(o, o)]
        want = e @ np.linalg.solve(S, e) if o.any() else 0.0
        assert float(got[t]) == pytest.approx(want, rel=1e-10, abs=1e-14)
        assert int(dof[t]) == o.sum()


def test_nees_and_rmse_match_numpy():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    m = torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    B = torch.randn(5, 7, 3, 3, generator=gen, dtype=torch.float64)
    P = B @ B.mT + torch.eye(3)
    got = nees(x, m, P)
    d = (x - m).numpy()
    want = np.einsum("...i,...ij,...j->...", d, np.linalg.inv(P.numpy()), d)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10)
    np.testing.assert_allclose(rmse(x, m).numpy(), np.sqrt((d**2).mean(-2)), rtol=1e-12)


def test_consistent_filter_has_chi2_nees_and_nis():
    """Seeded Monte Carlo: on its own model the KF's mean NEES is n and mean NIS is m."""
    dtype = torch.float64
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0]], dtype=dtype)
    model = LinearGaussianModel(
        A, H, 0.01 * torch.eye(2, dtype=dtype), 0.5 * torch.eye(1, dtype=dtype)
    )
    P0 = torch.eye(2, dtype=dtype)
    sim = simulate(
        model,
        30,
        torch.zeros(2, dtype=dtype),
        P0=P0,
        batch_shape=(2000,),
        generator=torch.Generator().manual_seed(3),
    )
    res = CKF(model).filter(sim.measurements, x0=torch.zeros(2, dtype=dtype), P0=P0)
    runs = 2000 * 30
    # 99.9% two-sided chi-square bounds on the mean of `runs` chi2(k) variables
    for value, k in ((nees(sim.states, res.mean, res.cov).mean(), 2), (nis(res)[0].mean(), 1)):
        lo = scipy.stats.chi2.ppf(0.0005, k * runs) / runs
        hi = scipy.stats.chi2.ppf(0.9995, k * runs) / runs
        assert lo < float(value) < hi


def test_coverage_counts_errors_inside_interval():
    from torchfilt import coverage

    mean = torch.zeros(4, 2, dtype=torch.float64)
    cov = torch.diag_embed(torch.tensor([[1.0, 4.0]] * 4, dtype=torch.float64))
    x = torch.tensor([[0.0, 0.0], [1.9, 3.0], [2.0, 4.0], [-2.6, -5.2]], dtype=torch.float64)
    # 95%: |e| <= 1.960 sd -> state 1 (sd 1): 0, 1.9 in, 2.0, 2.6 out; state 2 (sd 2): 0, 3 in, 4, 5.2 out
    # 99%: |e| <= 2.576 sd -> only 2.6 (state 1) and 5.2 (state 2) are out
    assert coverage(x, mean, cov).tolist() == [0.5, 0.5]
    assert coverage(x, mean, cov, level=0.99).tolist() == [0.75, 0.75]
    with pytest.raises(ValueError, match="level"):
        coverage(x, mean, cov, level=1.0)
