"""Fits that stop by themselves and say what they cost (issue 27 §1), and parameters held fixed
in every fit (``fixed=``): the windowed convergence rule is on by default, early stopping that
cannot act warns, the progress line carries the stage's estimated time, and fixed parameters end
bit-identical while the free ones reach the reference optimum."""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
import pytest
import torch
from torch import nn

import torchfilt
from torchfilt.exceptions import ConvergenceWarning, InputError
from torchfilt.io.progress import ProgressBar
from torchfilt.models import LinearGaussianModel
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import FitLoop, OptimizerOptions, Outcome, StoppingOptions, WindowOptions
from torchfilt.training import Sequences, calibrate, fit_em, fit_likelihood

DT = torch.float64
X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)


def simulate(a: float, q: float, r: float, T: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x, ys = torch.zeros(1, dtype=DT), []
    for _ in range(T):
        x = a * x + math.sqrt(q) * torch.randn(1, generator=g, dtype=DT)
        ys.append(x + math.sqrt(r) * torch.randn(1, generator=g, dtype=DT))
    return torch.stack(ys)


class Gain(nn.Module):
    """``x -> A x`` with a learnable ``A``."""

    def __init__(self, a: float) -> None:
        super().__init__()
        self.A = nn.Parameter(torch.tensor([[a]], dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x @ self.A.mT


def ar1(a: float = 0.9) -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(
        Gain(a),
        lambda x, u: x,
        Q=ScalarCovariance(1.0, 1, dtype=DT),
        R=ScalarCovariance(1.0, 1, dtype=DT),
    )


# ----------------------------------------------------------------------------- stopping
def test_stopping_options_document_the_windowed_default():
    s = StoppingOptions()
    assert s.rtol == 1e-6 and s.rtol_window == 20
    with pytest.raises(InputError, match="rtol"):
        StoppingOptions(rtol=-1.0)


def test_loop_stops_when_the_loss_stopped_moving():
    """A loss that settles: the loop stops with "converged" at the first iteration where
    ``|L_k - L_{k-w}| <= rtol * max(1, |L_k|)``, not at its budget."""
    losses = [1.0 + 2.0**-k for k in range(200)]
    loop = FitLoop(iterations=200, rtol=1e-6, rtol_window=5)
    stopped = loop.run(lambda it: Outcome({"iteration": it, "loss": losses[it - 1]}))
    k = len(loop.history)
    assert stopped == "converged" and k < 200
    L = [r["loss"] for r in loop.history]
    assert abs(L[-1] - L[-6]) <= 1e-6 * max(1, abs(L[-1]))
    assert abs(L[-2] - L[-7]) > 1e-6 * max(1, abs(L[-2]))  # not one iteration earlier
    off = FitLoop(iterations=200)  # the loop itself: off unless asked
    assert off.run(lambda it: Outcome({"iteration": it, "loss": 1.0})) == "iterations"


def test_fit_likelihood_stops_by_default_where_the_loss_is_flat():
    y = simulate(0.9, 0.3, 0.5, 150, seed=3)
    model = ar1()
    fit = fit_likelihood(
        model, y, x0=X0, P0=P0, iterations=2000, optimizer=OptimizerOptions(lr=0.05)
    )
    assert fit.stopped == "converged" and fit.iterations < 2000
    again = fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=30, stopping=StoppingOptions(rtol=0))
    assert again.stopped == "iterations" and again.iterations == 30


def test_em_stops_by_the_window_rule_too():
    y = simulate(1.0, 0.1, 0.5, 120, seed=5)
    lg = LinearGaussianModel(torch.eye(1, dtype=DT), torch.eye(1, dtype=DT), P0, P0)
    fit = fit_em(
        lg,
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=500,
        stopping=StoppingOptions(tol=0, rtol=1e-6),
    )
    assert fit.stopped == "converged" and fit.iterations < 500
    assert all("loss" in r for r in fit.history)


def test_patience_without_validation_warns():
    y = simulate(0.9, 0.3, 0.5, 60, seed=1)
    with pytest.warns(ConvergenceWarning, match="patience=5 was given but there is no held-out"):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=2, stopping=StoppingOptions(patience=5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=2)  # the default: no warning


def test_patience_given_to_em_warns_that_em_has_no_early_stopping():
    """EM has no held-out early stopping: a patience given to it (directly, or through
    fit_measurement_only's EM) warns instead of being dropped in silence; the default does not."""
    y = simulate(0.9, 0.3, 0.5, 60, seed=1)
    lg = LinearGaussianModel(0.5 * torch.eye(1, dtype=DT), torch.eye(1, dtype=DT), P0, P0)
    kw = dict(x0=X0, P0=P0, known_channels=[0], iterations=2)
    with pytest.warns(ConvergenceWarning, match="patience=3 was given, but fit_em has no early"):
        fit = fit_em(lg, y, **kw, stopping=StoppingOptions(patience=3))
    assert fit.iterations == 2
    with pytest.warns(ConvergenceWarning, match="fit_em has no early stopping"):
        torchfilt.fit_measurement_only(
            lg, y, **kw, stopping=StoppingOptions(patience=3), noise_scale="none", method="em"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_em(lg, y, **kw, stopping=StoppingOptions(tol=1e-12))  # no patience: no warning


class _Seen:
    def __init__(self) -> None:
        self.info: list[str] = []

    def update(self, done: int, info: str = "") -> None:
        self.info.append(info)


def test_progress_shows_the_estimated_time_after_a_few_iterations():
    seen = _Seen()
    loop = FitLoop(iterations=6, progress=seen)
    loop.run(lambda it: Outcome({"iteration": it, "loss": float(it)}, info=f"loss {it}"))
    assert all("eta" not in s for s in seen.info[: FitLoop.ETA_AFTER - 1])
    assert all("stage ~" in s and "eta " in s for s in seen.info[FitLoop.ETA_AFTER - 1 :])
    stream = io.StringIO()
    bar = ProgressBar("fit", 6, stream=stream)
    FitLoop(iterations=6, progress=bar).run(lambda it: Outcome({"loss": float(it)}, info="x"))
    assert "eta" in stream.getvalue()


# ----------------------------------------------------------------------------- fixed
def test_unknown_fixed_name_is_an_input_error():
    y = simulate(0.9, 0.3, 0.5, 40, seed=1)
    with pytest.raises(InputError, match=r"fixed: 'transition\.B' is no parameter"):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=2, fixed=["transition.B"])
    lg = LinearGaussianModel(torch.eye(1, dtype=DT), torch.eye(1, dtype=DT), P0, P0)
    with pytest.raises(InputError, match="fixed: 'C' is no block"):
        fit_em(lg, y, x0=X0, P0=P0, known_channels=[0], iterations=2, fixed=["C"])


def _sm_q_r(y: torch.Tensor, a: float) -> tuple[float, float]:
    """statsmodels' MLE of ``q, r`` of the AR(1) plus noise with ``a`` known (the prior as
    torchfilt's: the state before the first step is N(0, 1))."""
    from statsmodels.tsa.statespace import mlemodel

    class M(mlemodel.MLEModel):
        def __init__(self, endog):
            super().__init__(endog, k_states=1, k_posdef=1)
            self["design"] = np.eye(1)
            self["transition"] = np.array([[a]])
            self["selection"] = np.eye(1)

        def update(self, params, **kwargs):
            params = super().update(params, **kwargs)
            q, r = np.exp(params)
            self["state_cov"] = np.array([[q]])
            self["obs_cov"] = np.array([[r]])
            self.ssm.initialize_known(np.zeros(1), np.array([[a * a + q]]))

    res = M(y.numpy()).fit(
        start_params=np.zeros(2), method="lbfgs", maxiter=5000, pgtol=1e-11, factr=10.0,
        disp=False, cov_type="none",
    )  # fmt: skip
    q, r = np.exp(res.params)
    return float(q), float(r)


def test_fixed_A_is_bit_identical_and_Q_R_reach_the_reference_optimum():
    y = simulate(0.8, 0.3, 0.5, 200, seed=7)
    model = ar1(0.8)
    A_before = model.transition._fn.A.detach().clone()
    fit = fit_likelihood(
        model,
        y,
        x0=X0,
        P0=P0,
        optimizer="lbfgs",
        iterations=60,
        fixed=["transition._fn.A"],
        stopping=StoppingOptions(tol=1e-13, rtol=0),
    )
    assert fit.stopped in ("converged", "iterations")
    assert torch.equal(model.transition._fn.A.detach(), A_before)
    q_ref, r_ref = _sm_q_r(y, 0.8)
    with torch.no_grad():
        q = float(model.transition.noise_cov().reshape(-1)[0])
        r = float(model.measurement.noise_cov().reshape(-1)[0])
    assert q == pytest.approx(q_ref, rel=1e-4) and r == pytest.approx(r_ref, rel=1e-4)


def test_em_with_A_fixed_keeps_it_and_re_estimates_Q_and_R():
    y = simulate(1.0, 0.1, 0.5, 150, seed=11)
    A = torch.tensor([[0.97]], dtype=DT)
    lg = LinearGaussianModel(A.clone(), torch.eye(1, dtype=DT), 0.5 * P0, 2.0 * P0)
    fit = fit_em(
        lg,
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=200,
        fixed=["A"],
        stopping=StoppingOptions(tol=1e-12, rtol=0, atol=0),
    )
    m = fit.model
    assert isinstance(m, LinearGaussianModel)
    assert torch.equal(m.A, A)
    assert float(m.transition.noise_cov().reshape(-1)[0]) != 0.5
    assert float(m.measurement.noise_cov().reshape(-1)[0]) != 2.0
    # EM with A fixed reaches the likelihood optimum over (q, r) at that A
    q_ref, r_ref = _sm_q_r(y, 0.97)
    q = float(m.transition.noise_cov().reshape(-1)[0])
    r = float(m.measurement.noise_cov().reshape(-1)[0])
    assert q == pytest.approx(q_ref, rel=2e-3) and r == pytest.approx(r_ref, rel=2e-3)


def test_calibrate_holds_fixed_parameters():
    """``calibrate(fixed=...)``: names of the calibrated model; the named scale stays exactly at
    its start while the others are fitted."""
    base = torchfilt.StateSpaceModel(
        lambda x, u: 0.9 * x, lambda x, u: x, Q=0.3 * P0.clone(), R=0.5 * P0.clone()
    )
    y = simulate(0.9, 0.6, 0.5, 120, seed=2).unsqueeze(0)
    free = calibrate(
        base,
        Sequences(y),
        x0=X0,
        P0=P0,
        iterations=5,
        windows=WindowOptions(window=None, burn_in=20),
    )
    names = dict(free.model.named_parameters())
    held = next(n for n in names if n.startswith("transition") and "scale" in n)
    cal = calibrate(
        base,
        Sequences(y),
        x0=X0,
        P0=P0,
        iterations=5,
        fixed=[held],
        windows=WindowOptions(window=None, burn_in=20),
    )
    longer = calibrate(
        base,
        Sequences(y),
        x0=X0,
        P0=P0,
        iterations=9,
        fixed=[held],
        windows=WindowOptions(window=None, burn_in=20),
    )
    after, later = dict(cal.model.named_parameters()), dict(longer.model.named_parameters())
    assert torch.equal(after[held], later[held])  # both still the start, bit for bit
    assert not torch.equal(after[held], names[held])  # the free fit moves it
    assert cal.fit.log_likelihood > cal.fit.initial_log_likelihood  # the free ones are fitted
    with pytest.raises(InputError, match="fixed: 'nope' is no parameter"):
        calibrate(base, Sequences(y), x0=X0, P0=P0, iterations=2,
                            fixed=["nope"])  # fmt: skip
