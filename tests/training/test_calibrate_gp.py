"""Calibration that also refits GP hyperparameters (``calibrate(..., gp=...)``) through the frozen
predictor's differentiable twin: the twin equals the frozen predictor, its gradients equal finite
differences, the fit recovers a corrupted noise and lengthscale that variance scales alone cannot
repair, and a killed fit resumes equal to an uninterrupted one."""

from __future__ import annotations

import math

import pytest
import torch

import torchfilt
from torchfilt.exceptions import InputError
from torchfilt.models.gp import GPTransition
from torchfilt.optim import CheckpointOptions, OptimizerOptions
from torchfilt.training.likelihood import Sequences

DT = torch.float64
#: x_{k+1} = A x_k + w, w ~ N(0, Q); y = x + v, v ~ N(0, RV)
A, Q, RV = 0.95, 0.01, 0.01
X0 = torch.zeros(1, dtype=DT)
P0 = torch.eye(1, dtype=DT)


def simulate(recs: int, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """States ``(R, T+1, 1)`` and measurements ``(R, T, 1)`` of the AR(1) system."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(recs, 1, generator=g, dtype=DT)
    xs, ys = [x], []
    for _ in range(steps):
        x = A * x + math.sqrt(Q) * torch.randn(recs, 1, generator=g, dtype=DT)
        xs.append(x)
        ys.append(x + math.sqrt(RV) * torch.randn(recs, 1, generator=g, dtype=DT))
    return torch.stack(xs, 1), torch.stack(ys, 1)


def _gp(states: torch.Tensor, variance: str = "exact", pairs: int = 80) -> GPTransition:
    """A GP transition on ``pairs`` random one-step pairs of true states."""
    xk, xn = states[:, :-1].reshape(-1, 1), states[:, 1:].reshape(-1, 1)
    idx = torch.randperm(xk.shape[0], generator=torch.Generator().manual_seed(0))[:pairs]
    xk, xn = xk[idx], xn[idx]
    return GPTransition.fit(xk, None, xn, iterations=50, progress=False, seed=0, variance=variance)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def data():
    X, Y = simulate(4, 100, seed=0)
    return X, Y, _gp(X)


def _corrupted(f: GPTransition, noise: float = 1.0, lengthscale: float = 1.0) -> GPTransition:
    """A copy of ``f`` with its noise and lengthscale multiplied, frozen again."""
    f = GPTransition.from_state(f.to_state())  # type: ignore[assignment]
    grp = f.groups[0]
    with torch.no_grad():
        grp.likelihood.noise = grp.likelihood.noise * noise
        k = grp.gp.covar_module.base_kernel
        k.lengthscale = k.lengthscale * lengthscale
    f.freeze(**f.freeze_options)
    return f


def _model(f: GPTransition) -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(f, lambda x, u: x, R=RV * torch.eye(1, dtype=DT))


def test_twin_equals_the_frozen_predictor(data):
    X, _, f = data
    pts = torch.linspace(-1.5, 1.5, 23, dtype=DT).unsqueeze(-1)
    want = f.predict(pts)
    frozen = f.predictor
    try:
        f.predictor = f.twin()
        got = f.predict(pts)
    finally:
        f.predictor = frozen
    assert torch.allclose(got.mean, want.mean, rtol=0, atol=1e-12)
    assert torch.allclose(got.var, want.var, rtol=1e-10, atol=0)
    assert got.mean.requires_grad and not want.mean.requires_grad
    # a low-rank frozen form is within its tolerance of the (exact) twin
    lr = _gp(X)
    lr.freeze("lowrank", rank=8)
    approx = lr.predict(pts)
    lr.predictor = lr.twin()
    exact = lr.predict(pts)
    assert torch.allclose(approx.mean, exact.mean.detach(), atol=1e-6)
    assert bool((approx.var >= exact.var.detach() * (1 - 1e-9)).all())


def test_twin_gradients_equal_finite_differences():
    """The gradient of a loss of the twin's predictions (means and variances) in the raw
    hyperparameters equals central finite differences (float64)."""
    X, _ = simulate(1, 30, seed=3)
    f = _gp(X)
    params = f.hyperparameter_tensors("all")
    assert len(params) == 3  # noise, outputscale, lengthscale
    pts = torch.linspace(-1.0, 1.0, 5, dtype=DT).unsqueeze(-1)
    w = torch.linspace(0.5, 1.5, 5, dtype=DT).unsqueeze(-1)

    def loss() -> torch.Tensor:
        f.predictor = f.twin()
        out = f.predict(pts)
        return (w * out.mean).sum() + (w * out.var.log()).sum()

    grads = torch.autograd.grad(loss(), params)
    eps = 1e-6
    checked = 0
    for p, g in zip(params, grads, strict=True):
        flat, gflat = p.data.view(-1), g.reshape(-1)
        for i in range(flat.numel()):
            keep = float(flat[i])
            with torch.no_grad():
                flat[i] = keep + eps
                up = float(loss())
                flat[i] = keep - eps
                down = float(loss())
                flat[i] = keep
            fd = (up - down) / (2 * eps)
            assert abs(fd - float(gflat[i])) <= 1e-6 * (1 + abs(fd)), (p.shape, i, fd, gflat[i])
            checked += 1
    assert checked == 3
    assert all(float(g.abs().sum()) > 0 for g in grads)


def test_gp_noise_refit_repairs_what_scales_cannot(data):
    """The GP's noise is 30x the true Q: the filter is under-confident, and variance scales kept
    at or above 1 cannot shrink it. Refitting the noise by the filter likelihood recovers Q."""
    _, Y, f = data
    bad = _corrupted(f, noise=30.0)
    before = bad.noise_variance.clone()
    kw = dict(x0=X0, P0=P0, sides=("transition",), iterations=60)
    control = torchfilt.calibrate(_model(bad), Sequences(Y), **kw)
    fitted = torchfilt.calibrate(_model(bad), Sequences(Y), gp="noise", **kw)
    mid = torch.zeros(1, 1, dtype=DT)

    def total_var(m: torchfilt.StateSpaceModel) -> float:
        with torch.no_grad():
            return float(m.transition.predict(mid).var.reshape(()))

    assert total_var(control.model) > 10 * Q  # the control fails the assertion below
    assert 0.5 * Q < total_var(fitted.model) < 2 * Q
    assert fitted.fit.log_likelihood > control.fit.log_likelihood + 100
    # the input model is untouched, the result is frozen again with the same options and equals
    # its twin
    assert torch.equal(bad.noise_variance, before)
    g = fitted.refit["transition"]
    assert g is not bad and g.frozen and g.freeze_options == bad.freeze_options
    assert set(fitted.refit) == {"transition"} and not control.refit
    pts = torch.linspace(-1, 1, 7, dtype=DT).unsqueeze(-1)
    want = g.predict(pts)
    g.predictor = g.twin()
    got = g.predict(pts)
    g.freeze(**g.freeze_options)
    assert torch.allclose(got.var.detach(), want.var, rtol=1e-9)


def test_gp_all_refits_a_wrong_lengthscale(data):
    """A lengthscale 50x too short makes the GP mean revert to its constant between training
    inputs; refitting the kernel hyperparameters (``gp="all"``) repairs the predictions of held-out
    states, the noise refit alone does not."""
    _, Y, f = data
    bad = _corrupted(f, lengthscale=0.02)
    kw = dict(
        x0=X0, P0=P0, sides=("transition",), iterations=60, optimizer=OptimizerOptions(lr=0.2)
    )
    noise_only = torchfilt.calibrate(_model(bad), Sequences(Y), gp="noise", **kw)
    every = torchfilt.calibrate(_model(bad), Sequences(Y), gp="all", **kw)
    Xt, _ = simulate(4, 100, seed=5)
    xk, xn = Xt[:, :-1].reshape(-1, 1), Xt[:, 1:].reshape(-1, 1)

    def rmse(g: GPTransition) -> float:
        with torch.no_grad():
            return float((g.predict_mean(xk) - xn).pow(2).mean().sqrt())

    assert rmse(every.refit["transition"]) < 0.7 * rmse(noise_only.refit["transition"])
    assert rmse(every.refit["transition"]) < 1.15 * rmse(f)  # the GP before corruption
    assert every.fit.log_likelihood > noise_only.fit.log_likelihood


def test_gp_refit_resumes_equal_to_uninterrupted(data, tmp_path):
    _, Y, f = data
    bad = _corrupted(f, noise=30.0)
    kw = dict(x0=X0, P0=P0, sides=("transition",), iterations=8, gp="all")
    full = torchfilt.calibrate(_model(bad), Sequences(Y), **kw)

    class Killed(Exception):
        pass

    def kill(state):
        if state.iteration == 5:
            raise Killed

    ck = tmp_path / "cal.ckpt"
    with pytest.raises(Killed):
        torchfilt.calibrate(
            _model(bad),
            Sequences(Y),
            checkpoint=CheckpointOptions(ck, every=3),
            callback=kill,
            **kw,
        )
    # the killed fit left the input model as it was
    assert torch.equal(bad.noise_variance, _corrupted(f, noise=30.0).noise_variance)
    resumed = torchfilt.calibrate(
        _model(bad), Sequences(Y), **kw, checkpoint=CheckpointOptions(ck, every=3, resume=True)
    )
    assert [h["loss"] for h in resumed.fit.history] == [h["loss"] for h in full.fit.history]
    a, b = full.refit["transition"], resumed.refit["transition"]
    for (k, v), (_, w) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(v, w), k


def test_gp_refit_errors(data):
    X, Y, f = data
    with pytest.raises(InputError, match="gp: expected"):
        torchfilt.calibrate(_model(f), Sequences(Y), x0=X0, P0=P0, gp="kernel")  # type: ignore[arg-type]
    # no GP among the calibrated sides
    with pytest.raises(InputError, match="no side"):
        torchfilt.calibrate(
            _model(f), Sequences(Y), x0=X0, P0=P0, sides=("measurement",), gp="noise"
        )
    mt = GPTransition.fit(
        X[:, :-1].reshape(-1, 1),
        None,
        X[:, 1:].reshape(-1, 1),
        structure="multitask",
        iterations=5,
        progress=False,
    )
    with pytest.raises(InputError, match="structure 'multitask'"):
        torchfilt.calibrate(_model(mt), Sequences(Y), x0=X0, P0=P0, gp="noise")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="twin"):
        mt.twin()
    with pytest.raises(InputError, match="which"):
        f.hyperparameter_tensors("kernel")  # type: ignore[arg-type]
