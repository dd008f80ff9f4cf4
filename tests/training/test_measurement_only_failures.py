"""A measurement-only fit that cannot go on says so with a ``FitError`` naming the fit and the
step, never a raw torch error or a silent NaN result; and from a deliberately bad start (huge or
tiny log-lengthscales, a huge log-outputscale, coincident inducing inputs) it stays in the finite
region and ends no worse than its start. Reference values: the filter log-likelihood of the
start, computed by an independent CKF run."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import torchfilt
from torchfilt.exceptions import FitError, TorchfiltError
from torchfilt.models import CholeskyCovariance, InducingTransition, LinearModel, StateSpaceModel
from torchfilt.models.base import Prediction
from torchfilt.optim import GuardedStep
from torchfilt.training import fit_measurement_only

D = torch.float64
A = torch.tensor([[0.9, 0.2], [-0.3, 0.7]], dtype=D)
H = torch.tensor([[1.0, 0.0], [0.4, 1.0]], dtype=D)
Q = torch.tensor([[0.05, 0.02], [0.02, 0.08]], dtype=D)
R = torch.tensor([[0.04, 0.01], [0.01, 0.09]], dtype=D)
X0, P0 = torch.zeros(2, dtype=D), torch.eye(2, dtype=D)
NAMES = {"em": "fit_em", "likelihood": r'fit_measurement_only\(method="likelihood"\)'}


def _data(T: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    LQ, LR = torch.linalg.cholesky(Q), torch.linalg.cholesky(R)
    x, xs, ys = torch.zeros(2, dtype=D), [], []
    for _ in range(T):
        x = A @ x + LQ @ torch.randn(2, generator=g, dtype=D)
        xs.append(x)
        ys.append(H @ x + LR @ torch.randn(2, generator=g, dtype=D))
    return torch.stack(ys), torch.stack(xs)


class PlainCholesky(InducingTransition):
    """An inducing transition as a user might write it: a plain ``torch.linalg.cholesky`` of the
    inducing-point kernel, no jitter (a raw ``LinAlgError`` where it is singular)."""

    def predict(self, x: torch.Tensor, u: torch.Tensor | None = None) -> Prediction:
        ls = self.log_lengthscale.exp()
        Zs, zs = self.inducing_inputs / ls, x / ls
        Kxz = torch.exp(-0.5 * (zs.unsqueeze(-2) - Zs).pow(2).sum(-1))
        Kzz = torch.exp(-0.5 * (Zs.unsqueeze(-2) - Zs).pow(2).sum(-1))
        L = torch.linalg.cholesky(Kzz)
        W = torch.cholesky_solve(Kxz.reshape(-1, Kzz.shape[-1]).mT, L).mT.reshape(Kxz.shape)
        mean = x @ self.linear.mT + W @ self.inducing_outputs.mT
        var = self.log_outputscale.exp() * (1 - (W * Kxz).sum(-1, keepdim=True)).clamp(0, 1)
        return Prediction(mean, var)


def _model(f: InducingTransition) -> StateSpaceModel:
    h = LinearModel(H, CholeskyCovariance(2 * R), name="measurement")
    return StateSpaceModel(f, h, Q=CholeskyCovariance(2 * Q))


def _fit(model: StateSpaceModel, y: torch.Tensor, method: str, **kw):  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_measurement_only(
            model, y, x0=X0, P0=P0, known_channels=[0, 1], method=method,  # type: ignore[arg-type]
            m_step_iterations=2, **kw,
        )  # fmt: skip


@pytest.mark.parametrize("method", ["em", "likelihood"])
def test_a_failed_factorisation_is_a_fit_error_naming_the_fit_and_the_step(method: str) -> None:
    y, _ = _data()
    f = PlainCholesky(2, 3, linear=0.5 * A)
    with torch.no_grad():
        f.inducing_inputs.zero_()  # coincident inducing inputs: K_ZZ is singular
    with pytest.raises(FitError, match=NAMES[method]) as err:
        _fit(_model(f), y, method, iterations=2)
    assert isinstance(err.value, TorchfiltError)
    step = "the initial E-step" if method == "em" else "the start"
    assert step in str(err.value)
    assert err.value.fit and err.value.step


@pytest.mark.parametrize("method", ["em", "likelihood"])
def test_a_non_finite_start_is_a_fit_error(method: str) -> None:
    y, X = _data()
    f = InducingTransition(2, 3, linear=0.5 * A)
    f.init_inducing(X)
    with torch.no_grad():
        f.inducing_outputs.fill_(1e200)  # the predicted covariance overflows
    with pytest.raises(FitError, match=NAMES[method]) as err:
        _fit(_model(f), y, method, iterations=2)
    assert "before iteration 1" in str(err.value)


@pytest.mark.parametrize("method", ["em", "likelihood"])
def test_a_model_that_fails_after_a_step_names_the_iteration(method: str) -> None:
    """The model fails everywhere once iteration 1 is done (its callback breaks it): the fit
    cannot evaluate anything at iteration 2 and says so, naming it (EM: its M-step)."""
    y, X = _data()
    f = PlainCholesky(2, 3, linear=0.5 * A)
    f.init_inducing(X)
    done: list[int] = []

    def callback(state) -> None:  # type: ignore[no-untyped-def]
        done.append(state.iteration)
        with torch.no_grad():
            f.inducing_inputs.zero_()

    step = "iteration 2, M-step" if method == "em" else "iteration 2"
    with pytest.raises(FitError, match=NAMES[method] + ": " + step):
        # the likelihood method retries a failed L-BFGS iteration (once, then with a learning
        # rate shortened SHRINKS times) within the budget
        _fit(_model(f), y, method, iterations=GuardedStep.SHRINKS + 3, callback=callback)
    assert done == [1]


@pytest.mark.parametrize("method", ["em", "likelihood"])
@pytest.mark.parametrize("bad", ["lengthscale huge", "lengthscale tiny", "outputscale huge"])
def test_a_bad_start_ends_finite_and_no_worse(method: str, bad: str) -> None:
    y, X = _data()
    f = InducingTransition(2, 3, linear=0.5 * A, outputscale=0.1)
    f.init_inducing(X)
    with torch.no_grad():
        if bad == "lengthscale huge":
            f.log_lengthscale.fill_(1e3)
        elif bad == "lengthscale tiny":
            f.log_lengthscale.fill_(-1e3)
        else:
            f.log_outputscale.fill_(1e3)
    model = _model(f)
    with torch.no_grad():
        start = float(torchfilt.CKF(model).filter(y, x0=X0, P0=P0).log_likelihood)
    assert math.isfinite(start)
    fit = _fit(model, y, method, iterations=2)
    assert fit.initial_log_likelihood == pytest.approx(start, rel=1e-6)  # an extreme start
    assert math.isfinite(fit.log_likelihood) and fit.log_likelihood >= start
    assert all(bool(torch.isfinite(p).all()) for p in fit.model.parameters())
