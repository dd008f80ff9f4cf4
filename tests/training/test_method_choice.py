"""fit_measurement_only(method="both"): both methods from the same start, the better kept by
the held-out innovation likelihood, scored here by the textbook Kalman filter of
tests/reference.py (the model is linear-Gaussian: a GP transition without inducing points);
method="auto" (the default): the likelihood method only after an EM that stalls or fails
(a small re-entry radar case, where EM stalls). Float64, seeded."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference import kalman_filter

from torchfilt.exceptions import FitError
from torchfilt.models import (
    CholeskyCovariance,
    InducingTransition,
    LinearGaussianModel,
    LinearModel,
    StateSpaceModel,
)
from torchfilt.optim import CheckpointOptions
from torchfilt.training import EMState, Sequences, fit_measurement_only
from torchfilt.training.noise_scale import INFLATE_SCALES, held_out_noise_scale

DT = torch.float64
X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)
#: 2 recordings of 80 steps: held-out tails of 16 steps each, 32 in all (at least 30)
RUNS, STEPS, HEAD = 2, 80, 64
KW = dict(x0=X0, P0=P0, known_channels=[0], iterations=4, m_step_iterations=3)


def _data(seed: int = 3) -> torch.Tensor:
    """``(2, 80, 1)`` of ``x' = 0.9 x + w``, ``w ~ N(0, 0.2)``, ``y = x + v``, ``v ~ N(0, 0.1)``."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(RUNS, 1, dtype=DT)
    ys = []
    for _ in range(STEPS):
        x = 0.9 * x + math.sqrt(0.2) * torch.randn(RUNS, 1, generator=g, dtype=DT)
        ys.append(x + math.sqrt(0.1) * torch.randn(RUNS, 1, generator=g, dtype=DT))
    return torch.stack(ys, dim=1)


def _start() -> StateSpaceModel:
    """A learnable linear model: the linear part of a GP transition (no inducing point), its Q
    and the sensor's R learnable, the sensor's map known (the gauge)."""
    f = InducingTransition(1, 0, linear=torch.tensor([[0.3]], dtype=DT))
    f.bias.requires_grad_(False)
    h = LinearModel(torch.eye(1, dtype=DT), CholeskyCovariance(torch.eye(1, dtype=DT)))
    return StateSpaceModel(f, h, Q=CholeskyCovariance(torch.eye(1, dtype=DT)))


def _reference_score(model: StateSpaceModel, y: torch.Tensor, start: int) -> float:
    """The textbook Kalman filter's log-likelihood of steps ``start:`` of every recording (the
    filter runs from the prior through the head)."""
    base = model.transition.base  # type: ignore[union-attr]
    a = base.linear.detach().numpy()
    q = model.transition.noise_cov().detach().numpy()
    r = model.measurement.noise_cov().detach().numpy()
    h = np.eye(1)
    total = 0.0
    for rec in y.numpy():
        whole = kalman_filter(a, h, q, r, rec, X0.numpy(), P0.numpy())[-1]
        head = kalman_filter(a, h, q, r, rec[:start], X0.numpy(), P0.numpy())[-1]
        total += whole - (head if start else 0.0)
    return float(total)


def test_auto_keeps_the_method_with_the_better_held_out_likelihood():
    y = _data()
    start = _start()
    before = {k: v.clone() for k, v in start.state_dict().items()}
    fit = fit_measurement_only(start, y, **KW, method="both")  # type: ignore[arg-type]
    # the given model is left as given
    assert all(torch.equal(v, before[k]) for k, v in start.state_dict().items())
    assert [r["method"] for r in fit.compared] == ["em", "likelihood"]
    assert all(r["basis"] == "held-out" for r in fit.compared)
    scores, fits = {}, {}
    for method in ("em", "likelihood"):
        # each method alone on the heads, from the same start
        alone = fit_measurement_only(_start(), y[:, :HEAD], **KW, method=method, noise_scale="none")  # type: ignore[arg-type]
        fits[method] = alone
        scores[method] = _reference_score(alone.model, y, HEAD)
        record = next(r for r in fit.compared if r["method"] == method)
        assert record["score"] == pytest.approx(scores[method], rel=1e-9)
        assert record["log_likelihood"] == pytest.approx(alone.log_likelihood, rel=1e-12)
    assert abs(scores["em"] - scores["likelihood"]) > 1e-3  # the choice is a real one
    best = max(scores, key=scores.__getitem__)
    assert fit.method == best
    assert [r["kept"] for r in fit.compared] == [m == best for m in ("em", "likelihood")]
    assert fit.log_likelihood == pytest.approx(fits[best].log_likelihood, rel=1e-12)
    # then the kept fit's process noise is scaled on the same held-out tails
    data = Sequences(y, None, X0, P0)
    want = held_out_noise_scale(
        fits[best].model, data, [HEAD] * RUNS, dtype=DT, scales=INFLATE_SCALES
    )
    assert fit.noise_scale is not None and fit.noise_scale.scale == want.scale


def test_auto_without_held_out_data_compares_the_training_likelihood():
    y = _data()
    fit = fit_measurement_only(_start(), y, **KW, method="both", noise_scale="none")  # type: ignore[arg-type]
    assert fit.noise_scale is None and {r["basis"] for r in fit.compared} == {"training"}
    for record in fit.compared:
        alone = fit_measurement_only(_start(), y, **KW, method=record["method"], noise_scale="none")  # type: ignore[arg-type]
        assert record["score"] == pytest.approx(_reference_score(alone.model, y, 0), rel=1e-9)
    assert fit.method == max(fit.compared, key=lambda r: r["score"])["method"]


class _Broken(FitError):
    pass


def test_a_method_that_fails_is_recorded_and_the_other_kept():
    y = _data()

    def em_breaks(state):  # type: ignore[no-untyped-def]
        if isinstance(state, EMState):
            raise _Broken("the E-step broke", fit="fit_em", step="iteration 1")

    fit = fit_measurement_only(_start(), y, **KW, callback=em_breaks)  # type: ignore[arg-type]
    assert fit.method == "likelihood"
    em = fit.compared[0]
    assert em["method"] == "em" and "the E-step broke" in em["error"] and not em["kept"]
    assert em["score"] == -math.inf

    def both_break(state):  # type: ignore[no-untyped-def]
        raise _Broken(f"{type(state).__name__} broke", fit="fit", step="iteration 1")

    with pytest.raises(FitError, match='method="auto"\\): no method fitted') as err:
        fit_measurement_only(_start(), y, **KW, callback=both_break)  # type: ignore[arg-type]
    assert "em: EMState broke" in str(err.value)
    assert "likelihood: LikelihoodState broke" in str(err.value)


def test_a_linear_model_of_plain_tensors_is_ems_alone():
    y = _data()
    lg = LinearGaussianModel(
        torch.tensor([[0.3]], dtype=DT), torch.eye(1, dtype=DT), torch.eye(1, dtype=DT),
        torch.eye(1, dtype=DT),
    )  # fmt: skip
    fit = fit_measurement_only(lg, y, **KW)  # type: ignore[arg-type]
    assert fit.method == "em"
    assert "nothing to fit" in fit.compared[1]["skipped"]
    em = fit_measurement_only(lg, y, **KW, method="em")  # type: ignore[arg-type]
    assert fit.log_likelihood == em.log_likelihood
    torch.testing.assert_close(
        fit.model.transition.noise_cov(), em.model.transition.noise_cov(), rtol=0, atol=0
    )


class _Killed(Exception):
    pass


def test_each_method_checkpoints_to_its_own_file_and_a_killed_run_resumes(tmp_path):
    y = _data()
    whole = fit_measurement_only(_start(), y, **KW, method="both")  # type: ignore[arg-type]
    path = tmp_path / "run.pt"

    def killed(state):  # type: ignore[no-untyped-def]
        if not isinstance(state, EMState) and state.iteration == 2:
            raise _Killed  # killed in the likelihood fit, after EM finished

    with pytest.raises(_Killed):
        fit_measurement_only(_start(), y, **KW, method="both", checkpoint=path, callback=killed)  # type: ignore[arg-type]
    assert (tmp_path / "run.em.pt").exists() and (tmp_path / "run.likelihood.pt").exists()
    assert not path.exists()
    resumed = fit_measurement_only(
        _start(), y, **KW, method="both", checkpoint=CheckpointOptions(path, resume=True)
    )  # type: ignore[arg-type]
    assert resumed.method == whole.method
    assert [r["score"] for r in resumed.compared] == [r["score"] for r in whole.compared]
    for a, b in zip(resumed.model.parameters(), whole.model.parameters(), strict=True):
        assert torch.equal(a, b)


def test_validation_recordings_decide_and_both_fit_all_the_data():
    y, val = _data(), _data(seed=4)
    fit = fit_measurement_only(_start(), y, **KW, method="both", validation=val, noise_scale="none")  # type: ignore[arg-type]
    assert {r["basis"] for r in fit.compared} == {"validation"} and fit.noise_scale is None
    for record in fit.compared:
        alone = fit_measurement_only(
            _start(), y, **KW, method=record["method"], validation=val, noise_scale="none"
        )  # type: ignore[arg-type]
        assert record["score"] == pytest.approx(_reference_score(alone.model, val, 0), rel=1e-9)
        assert record["log_likelihood"] == pytest.approx(alone.log_likelihood, rel=1e-12)
    assert fit.method == max(fit.compared, key=lambda r: r["score"])["method"]


def test_auto_keeps_an_em_that_did_not_stall_as_em_alone():
    y = _data()
    auto = fit_measurement_only(_start(), y, **KW)  # type: ignore[arg-type]
    em = fit_measurement_only(_start(), y, **KW, method="em")  # type: ignore[arg-type]
    assert auto.method == "em" and auto.stopped == "iterations"
    assert "EM ended 'iterations', not stalled" in auto.compared[1]["skipped"]
    assert auto.log_likelihood == em.log_likelihood and auto.noise_scale == em.noise_scale
    for a, b in zip(auto.model.parameters(), em.model.parameters(), strict=True):
        assert torch.equal(a, b)


def _radar() -> StateSpaceModel:
    """Re-entry from radar range (torchfilt.systems.reentry): the drag law's log air-density
    decay learned from 3e-5 (true 5e-5), the radar's gain and offset from 1.005 and 500 ft."""
    from torch import nn

    from torchfilt.models import AffineSensor, DiagonalCovariance, FunctionModel, ScalarCovariance
    from torchfilt.systems import reentry

    class Drag(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.log_gamma = nn.Parameter(torch.tensor(math.log(3e-5), dtype=DT))

        def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
            return reentry.transition(x, gamma=self.log_gamma.exp())

    q = DiagonalCovariance(torch.tensor([1e2, 1e2, 1e-10], dtype=DT))
    h = AffineSensor(reentry.measurement, out_dim=1, scale=1.005, bias=500.0)
    return StateSpaceModel(
        FunctionModel(Drag(), q, name="transition"),
        h,
        R=ScalarCovariance(torch.tensor(4e4, dtype=DT), 1),
    )


def test_auto_fits_the_likelihood_method_after_an_em_that_stalls():
    from torchfilt.systems import reentry

    y = reentry.simulate_truth(2, steps=60, seed=11).measurements
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT), reentry.prior_cov()
    kw = dict(x0=x0, P0=P0, known_channels=[0], iterations=2, noise_scale="none")
    auto = fit_measurement_only(_radar(), y, **kw)  # type: ignore[arg-type]
    em, lik = auto.compared
    assert em["stopped"] == "no improvement" and "skipped" not in lik
    both = fit_measurement_only(_radar(), y, **kw, method="both")  # type: ignore[arg-type]
    assert [c["score"] for c in auto.compared] == [c["score"] for c in both.compared]
    assert auto.method == both.method == max(auto.compared, key=lambda c: c["score"])["method"]
