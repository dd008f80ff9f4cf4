"""Every input of the fits is checked before the first filter pass (issue 24 item 4): a wrong
input raises a TorchfiltError naming the argument at once, never a crash deep in a reshape or
a Cholesky after minutes of work."""

from __future__ import annotations

import time

import pytest
import torch

import torchfilt
from torchfilt.exceptions import InputError, InputTypeError
from torchfilt.models import InducingTransition
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import CheckpointOptions
from torchfilt.training import fit_em, fit_likelihood

DT = torch.float64


def model() -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(
        lambda x, u: x,
        lambda x, u: x,
        Q=ScalarCovariance(1.0, 1, dtype=DT),
        R=ScalarCovariance(1.0, 1, dtype=DT),
    )


def data(T: int = 40) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.randn(T, 1, generator=g, dtype=DT).cumsum(0)


X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)


@pytest.mark.parametrize("y", [torch.zeros(0, 1, dtype=DT), [data(), torch.zeros(0, 1, dtype=DT)]])
def test_zero_length_recording_is_an_input_error(y):
    with pytest.raises(InputError, match=r"y(\[1\])?: .*no steps"):
        fit_likelihood(model(), y, x0=X0, P0=P0, iterations=2)


def test_indefinite_P0_is_refused_before_any_filter_pass(monkeypatch):
    calls = []
    real = torchfilt.filters.CKF.filter

    def spy(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)

    monkeypatch.setattr(torchfilt.filters.CKF, "filter", spy)
    t0 = time.perf_counter()
    with pytest.raises(InputError, match="P0: must be positive definite"):
        fit_likelihood(model(), data(), x0=X0, P0=-P0, iterations=2)
    assert not calls and time.perf_counter() - t0 < 5
    with pytest.raises(InputError, match="P0"):
        fit_em(model(), data(), x0=X0, P0=-P0, known_channels=[0], iterations=2)


def test_non_finite_prior_is_refused():
    with pytest.raises(InputError, match="x0: contains non-finite"):
        fit_likelihood(model(), data(), x0=torch.tensor([float("nan")], dtype=DT), P0=P0)


def test_zero_iterations_is_an_input_error():
    with pytest.raises(InputError, match="iterations must be at least 1"):
        fit_likelihood(model(), data(), x0=X0, P0=P0, iterations=0)
    with pytest.raises(InputError, match="iterations must be at least 1"):
        fit_em(model(), data(), x0=X0, P0=P0, known_channels=[0], iterations=0)


def test_resume_without_checkpoint_is_an_input_error():
    with pytest.raises(InputError, match="resume=True needs checkpoint="):
        fit_likelihood(
            model(), data(), x0=X0, P0=P0, iterations=2, checkpoint=CheckpointOptions(resume=True)
        )
    with pytest.raises(InputError, match="resume=True needs checkpoint="):
        fit_em(
            model(),
            data(),
            x0=X0,
            P0=P0,
            known_channels=[0],
            iterations=2,
            checkpoint=CheckpointOptions(resume=True),
        )


@pytest.mark.parametrize("name", ["y", "list", "x0", "P0"])
def test_integer_inputs_are_type_errors(name):
    y: object = data()
    x0, P0i = X0, P0
    if name == "y":
        y = torch.ones(30, 1, dtype=torch.int64)
    elif name == "list":
        y = [data(), torch.ones(30, 1, dtype=torch.int64)]
    elif name == "x0":
        x0 = torch.zeros(1, dtype=torch.int64)
    else:
        P0i = torch.eye(1, dtype=torch.int64)
    with pytest.raises(InputTypeError, match=r"(y|y\[1\]|x0|P0): expected a floating-point"):
        fit_likelihood(model(), y, x0=x0, P0=P0i, iterations=2)  # type: ignore[arg-type]


def test_inducing_cholesky_failure_is_no_raw_linalg_error():
    """Coincident inducing inputs with no jitter make K_ZZ singular: the prediction is NaN
    (jitter first, with a warning), so a fit steps back, never a raw torch LinAlgError."""
    tr = InducingTransition(1, torch.zeros(3, 1, dtype=DT), jitter=0.0, dtype=DT)
    x = torch.zeros(4, 1, dtype=DT)
    with pytest.warns(torchfilt.exceptions.CholeskyJitterWarning):
        pred = tr.predict(x)
    assert pred.mean.shape == (4, 1)
