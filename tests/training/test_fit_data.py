"""One name for the data of every fit (issue 23): ``fit_likelihood``, ``fit_em``,
``fit_measurement_only`` and ``calibrate`` take ``(model, y, u=None)`` where ``y`` is a tensor,
a list of tensors, a ``Sequences`` or a list of ``Recording`` (log layout), and give the same
result, bit for bit, for the same data in each of these forms; ``validation=`` takes the same
kinds; ``calibrate(recordings=...)`` warns and gives the same result.

The reference of the log layout is written here from the simulated arrays (a recording's row 0
is the prior's time: its measurement is not used, and its last input row drives no step), not
derived from the conversion under test."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
import pytest
import torch
from torch import nn

import torchfilt
from torchfilt.exceptions import InputError
from torchfilt.io import Recording
from torchfilt.io.manifest import Channel
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import OptimizerOptions, WindowOptions
from torchfilt.training import (
    Sequences,
    calibrate,
    fit_em,
    fit_likelihood,
    fit_measurement_only,
)
from torchfilt.training.data import as_sequences

DT = torch.float64
X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)
CHANNELS = (Channel("x", "state"), Channel("u", "input"), Channel("y", "measurement"))


def simulate(lengths: tuple[int, ...], seed: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """``x_t = 0.8 x_{t-1} + 0.5 u_t + w``, ``y_t = x_t + v``: measurements ``(T_i, 1)`` (some
    missing) and inputs ``(T_i, 1)`` of recordings of different lengths, filter convention."""
    g = torch.Generator().manual_seed(seed)
    ys, us = [], []
    for T in lengths:
        u = torch.randn(T, 1, generator=g, dtype=DT)
        x, y = torch.zeros(1, dtype=DT), []
        for t in range(T):
            x = 0.8 * x + 0.5 * u[t] + math.sqrt(0.2) * torch.randn(1, generator=g, dtype=DT)
            y.append(x + math.sqrt(0.3) * torch.randn(1, generator=g, dtype=DT))
        yt = torch.stack(y)
        yt[3::7] = math.nan  # missing measurements
        ys.append(yt)
        us.append(u)
    return ys, us


def as_recordings(ys: list[torch.Tensor], us: list[torch.Tensor]) -> list[Recording]:
    """The same data in the log layout: row 0 the prior's time (no measurement), the input of row
    ``k`` drives the step to row ``k + 1`` (the last row's input drives none)."""
    recs = []
    for y, u in zip(ys, us, strict=True):
        T = y.shape[0]
        nan = torch.full((1,), math.nan, dtype=DT)
        cols = {
            "x": np.full(T + 1, math.nan),
            "u": torch.cat([u[:, 0], torch.tensor([123.0], dtype=DT)]),  # last row: unused
            "y": torch.cat([nan, y[:, 0]]),
        }
        recs.append(Recording.from_arrays(np.arange(T + 1.0), CHANNELS, cols))
    return recs


class GainInput(nn.Module):
    """``x -> a x + b u`` with learnable ``a`` and ``b``."""

    def __init__(self) -> None:
        super().__init__()
        self.a = nn.Parameter(torch.tensor([[0.5]], dtype=DT))
        self.b = nn.Parameter(torch.tensor([[0.1]], dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        assert u is not None
        return x @ self.a.mT + u @ self.b.mT


def learnable() -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(
        GainInput(),
        lambda x, u: x,
        Q=ScalarCovariance(1.0, 1, dtype=DT),
        R=ScalarCovariance(1.0, 1, dtype=DT),
    )


def linear() -> torchfilt.LinearGaussianModel:
    e = torch.eye(1, dtype=DT)
    return torchfilt.LinearGaussianModel(0.5 * e, e, e, e, B=0.1 * e)


def fixed_map() -> torchfilt.StateSpaceModel:
    """A model of callables with constant noise: what ``calibrate`` scales."""
    return torchfilt.StateSpaceModel(
        lambda x, u: 0.8 * x + 0.5 * u, lambda x, u: x, Q=0.1 * P0.clone(), R=0.2 * P0.clone()
    )


@pytest.fixture(scope="module")
def data() -> dict[str, Any]:
    ys, us = simulate((30, 24, 18), seed=0)
    vy, vu = simulate((20, 16), seed=1)
    return {
        "ys": ys,
        "us": us,
        "recs": as_recordings(ys, us),
        "vy": vy,
        "vu": vu,
        "vrecs": as_recordings(vy, vu),
    }


def forms(d: dict[str, Any]) -> list[tuple[tuple[Any, ...], Any]]:
    """The training data as ``(y, u)`` positional arguments and the held-out data, in the three
    forms: tensor lists, a Sequences, a list of recordings."""
    return [
        ((d["ys"], d["us"]), Sequences(d["vy"], d["vu"])),
        ((Sequences(d["ys"], d["us"]),), Sequences(d["vy"], d["vu"])),
        ((d["recs"],), d["vrecs"]),
    ]


def values(model: nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def matrices(model: Any) -> list[torch.Tensor]:
    """``A, B, Q, R`` of a linear-Gaussian model."""
    return [model.A, model.B, model.transition.noise_cov(), model.measurement.noise_cov()]


def assert_same(a: list[torch.Tensor], b: list[torch.Tensor]) -> None:
    assert len(a) == len(b)
    for p, q in zip(a, b, strict=True):
        torch.testing.assert_close(p, q, rtol=0.0, atol=0.0, equal_nan=True)  # bit for bit


def test_layout_reference_matches_the_conversion(data):
    """The recordings hold the reference tensors in the log layout (checks the fixture itself)."""
    seqs = Sequences.from_recordings(data["recs"])
    assert_same(list(seqs.y), data["ys"])
    assert seqs.u is not None
    assert_same(list(seqs.u), data["us"])
    assert seqs.x0 is None and seqs.P0 is None


def test_fit_likelihood_gives_the_same_fit_for_each_form(data):
    outs = []
    for args, val in forms(data):
        model = learnable()
        fit = fit_likelihood(
            model, *args, x0=X0, P0=P0, iterations=4, validation=val, optimizer="adam"
        )
        outs.append((fit, values(model)))
    ref_fit, ref_params = outs[0]
    assert ref_fit.log_likelihood > ref_fit.initial_log_likelihood  # it fitted something
    assert ref_fit.validation is not None
    for fit, params in outs[1:]:
        assert fit.log_likelihood == ref_fit.log_likelihood
        assert fit.validation == ref_fit.validation
        assert [h["loss"] for h in fit.history] == [h["loss"] for h in ref_fit.history]
        assert_same(params, ref_params)


def test_fit_em_gives_the_same_fit_for_each_form(data):
    outs = []
    for args, _ in forms(data):
        fit = fit_em(linear(), *args, x0=X0, P0=P0, known_channels=[0], iterations=3)
        outs.append(fit)
    ref = outs[0]
    assert ref.log_likelihood > ref.initial_log_likelihood
    for fit in outs[1:]:
        assert fit.log_likelihood == ref.log_likelihood
        assert fit.measurements == ref.measurements
        assert_same(matrices(fit.model), matrices(ref.model))


@pytest.mark.parametrize("method", ["em", "likelihood"])
def test_fit_measurement_only_gives_the_same_fit_for_each_form(data, method):
    outs = []
    for args, val in forms(data):
        model = learnable() if method == "likelihood" else linear()
        fit = fit_measurement_only(
            model, *args, x0=X0, P0=P0, known_channels=[0], method=method, iterations=3,
            optimizer="adam" if method == "likelihood" else None,
            validation=val if method == "likelihood" else None,
        )  # fmt: skip
        outs.append(fit)
    ref = outs[0]
    for fit in outs[1:]:
        assert fit.log_likelihood == ref.log_likelihood
        assert fit.initial_log_likelihood == ref.initial_log_likelihood
        if method == "likelihood":
            assert fit.detail.validation == ref.detail.validation  # type: ignore[union-attr]
            assert_same(values(fit.model), values(ref.model))
        else:
            assert_same(matrices(fit.model), matrices(ref.model))


def _calibrate(*args: Any, **kw: Any) -> Any:
    kw.setdefault("validation", None)
    return calibrate(
        fixed_map(), *args, x0=X0, P0=P0, iterations=4,
        windows=WindowOptions(window=None, burn_in=2), optimizer=OptimizerOptions(lr=0.1), **kw,
    )  # fmt: skip


def test_calibrate_gives_the_same_calibration_for_each_form(data):
    outs = [_calibrate(*args, validation=val) for args, val in forms(data)]
    ref = outs[0]
    assert ref.fit.log_likelihood > ref.fit.initial_log_likelihood
    for res in outs[1:]:
        assert res.fit.log_likelihood == ref.fit.log_likelihood
        assert res.fit.validation == ref.fit.validation
        assert res.parameters == ref.parameters
        assert_same(values(res.model), values(ref.model))


def test_calibrate_recordings_keyword_warns_and_gives_the_same_result(data):
    plain = _calibrate(data["recs"])
    with pytest.warns(DeprecationWarning, match=r"recordings= is deprecated; pass y="):
        old = _calibrate(recordings=data["recs"])
    assert old.fit.log_likelihood == plain.fit.log_likelihood
    assert old.fit.history[-1]["loss"] == plain.fit.history[-1]["loss"]
    assert_same(values(old.model), values(plain.model))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        by_name = _calibrate(y=data["recs"])  # the new keyword does not warn
    assert_same(values(by_name.model), values(plain.model))


def test_recordings_with_inputs_u_is_an_input_error_naming_u(data):
    recs, us = data["recs"], data["us"]
    with pytest.raises(InputError, match=r"^u: must be None when y is recordings"):
        fit_likelihood(learnable(), recs, us, x0=X0, P0=P0, iterations=1)
    with pytest.raises(InputError, match=r"^u: must be None when y is recordings"):
        fit_em(linear(), recs, us, x0=X0, P0=P0, known_channels=[0], iterations=1)
    with pytest.raises(InputError, match=r"^u: must be None when y is recordings"):
        fit_measurement_only(linear(), recs, us, x0=X0, P0=P0, known_channels=[0], iterations=1)
    with pytest.raises(InputError, match=r"^u: must be None when y is recordings"):
        calibrate(fixed_map(), recs, us, x0=X0, P0=P0, iterations=1)
    with pytest.raises(InputError, match=r"^u: must be None when y is a Sequences"):
        fit_likelihood(learnable(), Sequences(data["ys"], us), us, x0=X0, P0=P0, iterations=1)


def test_a_sequences_prior_is_used_before_the_keyword_prior(data):
    """A Sequences that carries its own prior (as calibrate always did) fits as that prior given
    by keyword."""
    x0 = torch.tensor([0.7], dtype=DT)
    m1, m2 = learnable(), learnable()
    a = fit_likelihood(
        m1, Sequences(data["ys"], data["us"], x0, 2 * P0), x0=X0, P0=P0, iterations=2
    )
    b = fit_likelihood(m2, data["ys"], data["us"], x0=x0, P0=2 * P0, iterations=2)
    assert a.log_likelihood == b.log_likelihood
    assert_same(values(m1), values(m2))


def test_from_recordings_refuses_what_is_not_a_list_of_recordings(data):
    with pytest.raises(InputError, match=r"y: no recordings given"):
        Sequences.from_recordings([])
    with pytest.raises(InputError, match=r"validation\[1\]: expected a Recording"):
        Sequences.from_recordings([data["recs"][0], data["ys"][0]], name="validation")
    one_row = Recording.from_arrays(
        np.arange(1.0), CHANNELS, {"x": np.zeros(1), "u": np.zeros(1), "y": np.zeros(1)}
    )
    with pytest.raises(InputError, match=r"y\[1\]: .*at least 2 rows"):
        Sequences.from_recordings([data["recs"][0], one_row])
    no_inputs = Recording.from_arrays(
        np.arange(3.0), CHANNELS[::2], {"x": np.zeros(3), "y": np.zeros(3)}
    )
    with pytest.raises(InputError, match=r"y\[1\]: .*has no inputs"):
        Sequences.from_recordings([data["recs"][0], no_inputs])
    # a list of recordings whose second item is a tensor: the message names the item
    with pytest.raises(InputError, match=r"y\[1\]: expected a Recording"):
        fit_likelihood(learnable(), [data["recs"][0], data["ys"][0]], x0=X0, P0=P0)


def test_as_sequences_keeps_tensors_as_given(data):
    y = torch.stack([t[:18] for t in data["ys"]])
    seqs = as_sequences(y, None, x0=X0, P0=P0)
    assert seqs.y is y and seqs.u is None and seqs.x0 is X0 and seqs.P0 is P0


def test_recordings_keyword_is_calibrates_alone() -> None:
    """``recordings=`` is the old name of ``calibrate``'s data only: the other fits never took it,
    so there it is an unknown keyword (an ``InputError`` naming it), not a deprecated one."""
    model = torchfilt.LinearGaussianModel(
        torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64),
        torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64),
    )  # fmt: skip
    y = torch.zeros(1, 5, 1, dtype=torch.float64)
    x0, P0 = torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64)
    with pytest.raises(InputError, match="recordings"):
        torchfilt.fit_likelihood(model, recordings=y, x0=x0, P0=P0)  # type: ignore[call-arg]
