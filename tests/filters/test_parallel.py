"""Parallel-in-time Kalman filter and smoother = the sequential ones (values and gradients)."""

import numpy as np
import pytest
import torch
from linear_support import make_problem, t64
from test_kalman import assert_results_equal, assert_same

from torchfilt import CKF, LinearGaussianModel
from torchfilt.models import TimeVarying

#: the scan reassociates the recursion; in float64 the two agree to this
PARALLEL_TOL = 1e-9


def model_of(p, Q=None, R=None):
    Q = t64(p["Q"]) if Q is None else Q
    R = t64(p["R"]) if R is None else R
    return LinearGaussianModel(t64(p["A"]), t64(p["H"]), Q, R, B=t64(p["B"]))


@pytest.mark.parametrize("T", [1, 2, 15, 40])
@pytest.mark.parametrize("seed", [0, 1])
def test_parallel_equals_sequential(seed, T):
    """Missing components (and a wholly missing step), controls; every field of both passes."""
    p = make_problem(seed, T=max(T, 4))
    y, u = t64(p["y"][:T]), t64(p["u"][:T])
    filt = CKF(model_of(p))
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    seq = filt.smooth(y, u, **kw)
    par = filt.smooth(y, u, **kw, parallel=True)
    assert par.path == "parallel" and seq.path == "kalman"
    assert_results_equal(par.filtered, seq.filtered, PARALLEL_TOL)
    assert_same(par.mean, seq.mean, "smoothed mean", PARALLEL_TOL)
    assert_same(par.cov, seq.cov, "smoothed cov", PARALLEL_TOL)
    assert_same(par.gain, seq.gain, "gain", PARALLEL_TOL)
    fpar = filt.filter(y, u, **kw, parallel=True)
    assert_results_equal(fpar, seq.filtered, PARALLEL_TOL)


def test_parallel_batched_mask_and_time_varying_noise():
    p = make_problem(2, T=30, missing=0.0)
    T, m = p["y"].shape
    rng = np.random.default_rng(4)
    Qt = np.linspace(0.5, 2.0, T)[:, None, None] * p["Q"]
    model = model_of(p, Q=TimeVarying(t64(Qt)))
    gen = torch.Generator().manual_seed(1)
    y = t64(p["y"]) + torch.randn(3, 2, T, m, generator=gen, dtype=torch.float64)
    mask = torch.tensor(rng.random((3, 2, T, m)) > 0.25)
    x0 = torch.randn(3, 2, 3, generator=gen, dtype=torch.float64)
    kw = dict(x0=x0, P0=t64(p["P0"]), mask=mask)
    seq = CKF(model).smooth(y, t64(p["u"]), **kw)
    par = CKF(model).smooth(y, t64(p["u"]), **kw, parallel=True)
    assert par.mean.shape == (3, 2, T, 3)
    assert_results_equal(par.filtered, seq.filtered, PARALLEL_TOL)
    assert_same(par.mean, seq.mean, "smoothed mean", PARALLEL_TOL)
    assert_same(par.cov, seq.cov, "smoothed cov", PARALLEL_TOL)


def test_parallel_gradients_equal_sequential():
    p = make_problem(3, T=20)

    def grads(parallel):
        A = t64(p["A"]).requires_grad_(True)
        Lq = torch.linalg.cholesky(t64(p["Q"])).requires_grad_(True)
        R = t64(p["R"]).requires_grad_(True)
        model = LinearGaussianModel(A, t64(p["H"]), Lq @ Lq.mT, R, B=t64(p["B"]))
        sm = CKF(model).smooth(
            t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), parallel=parallel
        )
        loss = sm.filtered.log_likelihood + sm.mean.sum() + sm.cov.diagonal(0, -2, -1).sum()
        return torch.autograd.grad(loss, (A, Lq, R))

    for name, a, b in zip("A Lq R".split(), grads(True), grads(False), strict=True):
        assert_same(a, b, f"d loss / d {name}", PARALLEL_TOL)
