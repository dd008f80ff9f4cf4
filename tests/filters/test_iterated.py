"""The iterated posterior-linearisation smoother: exact on linear models, and its parallel form
converges to the sequential one on the book's pendulum."""

import json
from pathlib import Path

import pytest
import torch
from linear_support import make_problem, t64
from test_kalman import assert_same

import torchfilt
from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import ConvergenceWarning, InputError
from torchfilt.filters import iterated_smoother
from torchfilt.systems import pendulum

DATA = Path(__file__).resolve().parents[2] / "data" / "reference" / "pendulum" / "pendulum.json"
#: statistical linearisation of a linear map is exact up to rounding
LINEAR_TOL = 1e-9
#: both smoothers iterate to tol = 1e-11; their fixed points then agree to this
FIXED_POINT_TOL = 1e-8
ITER_TOL = 1e-11
D = torch.float64


@pytest.fixture(scope="module")
def pendulum_data():
    d = json.loads(DATA.read_text())
    return torch.tensor(d["X"], dtype=D).T, torch.tensor(d["Y"], dtype=D)[:, None]


@pytest.mark.parametrize("parallel", [False, True], ids=["sequential", "parallel"])
def test_linear_model_gives_the_rts_smoother(parallel):
    p = make_problem(0)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    args, kw = (t64(p["y"]), t64(p["u"])), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    want = CKF(model).smooth(*args, **kw)
    got = iterated_smoother(model, *args, **kw, parallel=parallel, tol=ITER_TOL)
    assert_same(got.mean, want.mean, "smoothed mean", LINEAR_TOL)
    assert_same(got.cov, want.cov, "smoothed cov", LINEAR_TOL)
    assert_same(got.filtered.log_likelihood, want.filtered.log_likelihood, "ll", LINEAR_TOL)


def test_pendulum_parallel_equals_sequential(pendulum_data):
    _, Y = pendulum_data
    Y = Y[:120]
    kw = dict(x0=torch.zeros(2, dtype=D), P0=torch.eye(2, dtype=D), tol=ITER_TOL, max_iter=40)
    seq = iterated_smoother(pendulum.model(), Y, **kw)
    par = iterated_smoother(pendulum.model(), Y, **kw, parallel=True)
    assert seq.path == "kalman" and par.path == "parallel"
    assert_same(par.mean, seq.mean, "smoothed mean", FIXED_POINT_TOL)
    assert_same(par.cov, seq.cov, "smoothed cov", FIXED_POINT_TOL)
    # and it is a fixed point: linearising once more around it changes nothing
    again = iterated_smoother(pendulum.model(), Y, **kw, parallel=True, init=par)
    assert_same(again.mean, par.mean, "one more iteration", FIXED_POINT_TOL)


@pytest.mark.slow
def test_pendulum_full_run_beats_the_cubature_smoother(pendulum_data):
    X, Y = pendulum_data
    kw = dict(x0=torch.zeros(2, dtype=D), P0=torch.eye(2, dtype=D))
    ckf = CKF(pendulum.model()).smooth(Y, **kw)
    seq = iterated_smoother(pendulum.model(), Y, **kw, tol=ITER_TOL, max_iter=40)
    par = iterated_smoother(pendulum.model(), Y, **kw, tol=ITER_TOL, max_iter=40, parallel=True)
    assert_same(par.mean, seq.mean, "smoothed mean", FIXED_POINT_TOL)
    assert_same(par.cov, seq.cov, "smoothed cov", FIXED_POINT_TOL)
    rmse = lambda sm: float(torchfilt.rmse(X[:, 0], sm.mean[:, 0], dim=0))  # noqa: E731
    assert rmse(par) < rmse(ckf)


def test_missing_components_controls_and_batch():
    def f(x, u):
        return torch.stack(
            [x[..., 0] + 0.1 * x[..., 1], x[..., 1] - 0.1 * torch.sin(x[..., 0]) + 0.1 * u[..., 0]],
            -1,
        )

    def h(x, u):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1] + 0.5 * u[..., 0]], -1)

    Q = torch.tensor([[0.02, 0.005], [0.005, 0.03]], dtype=D)
    model = StateSpaceModel(f, h, Q=Q, R=0.1 * torch.eye(2, dtype=D))
    gen = torch.Generator().manual_seed(0)
    y = torch.randn(3, 40, 2, dtype=D, generator=gen)
    y[torch.rand(3, 40, 2, generator=gen) < 0.2] = float("nan")
    y[:, 5] = float("nan")
    u = torch.randn(40, 1, dtype=D, generator=gen)
    # this problem contracts slowly (about 0.6 per iteration): allow enough iterations
    kw = dict(x0=torch.zeros(2, dtype=D), P0=torch.eye(2, dtype=D), tol=ITER_TOL, max_iter=100)
    seq = iterated_smoother(model, y, u, **kw)
    par = iterated_smoother(model, y, u, **kw, parallel=True)
    assert par.mean.shape == (3, 40, 2)
    assert_same(par.mean, seq.mean, "smoothed mean", FIXED_POINT_TOL)
    assert_same(par.cov, seq.cov, "smoothed cov", FIXED_POINT_TOL)
    one = iterated_smoother(model, y[1], u, **kw, parallel=True)
    assert_same(par.mean[1], one.mean, "batch element 1", FIXED_POINT_TOL)


def test_errors_and_convergence_warning(pendulum_data):
    _, Y = pendulum_data
    kw = dict(x0=torch.zeros(2, dtype=D), P0=torch.eye(2, dtype=D))
    with pytest.raises(InputError, match="max_iter must be at least 1"):
        iterated_smoother(pendulum.model(), Y[:10], **kw, max_iter=0)
    with pytest.warns(ConvergenceWarning, match="moved by more than tol"):
        iterated_smoother(pendulum.model(), Y[:50], **kw, max_iter=1, tol=1e-14)
