"""Calibration of learned models by the filter likelihood: honest NEES on autocorrelated noise,
the pipeline stage, resume, and the building blocks (windows, parametrisations, fit loop)."""

from __future__ import annotations

import math

import pytest
import torch

import torchfilt
from torchfilt.exceptions import InputError, RecipeError, RunError
from torchfilt.models.gp import GPTransition
from torchfilt.models.params import (
    Bounded,
    CholeskyCovariance,
    DiagonalCovariance,
    Positive,
    ScalarCovariance,
)
from torchfilt.optim import CheckpointOptions, OptimizerOptions, StoppingOptions, WindowOptions
from torchfilt.training.likelihood import Sequences, fit_likelihood, window_data

DT = torch.float64
N = 2
#: the consistency band of the acceptance table: mean NEES in [0.5 n, 2 n]
NEES_BAND = (0.5 * N, 2.0 * N)
#: the AR(1) coefficient of the process noise: what a one-step GP cannot see
RHO = 0.8
SIG_E, R_SD, EVERY = 0.05, 0.3, 5


def simulate_drift(recs: int, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Two random walks driven by AR(1) (autocorrelated) increments, both measured every
    ``EVERY`` steps with noise ``R_SD``. Returns states ``(R, T+1, 2)`` and measurements
    ``(R, T, 2)`` (NaN between measurements)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(recs, N, dtype=DT)
    w = torch.zeros(recs, N, dtype=DT)
    xs, ys = [x], []
    for t in range(steps):
        w = RHO * w + SIG_E * torch.randn(recs, N, generator=g, dtype=DT)
        x = x + w
        y = x + R_SD * torch.randn(recs, N, generator=g, dtype=DT)
        if (t + 1) % EVERY:
            y = torch.full_like(y, math.nan)
        xs.append(x)
        ys.append(y)
    return torch.stack(xs, 1), torch.stack(ys, 1)


@pytest.fixture(scope="module")
def drift_model():
    X, Y = simulate_drift(3, 150, seed=0)
    g = torch.Generator().manual_seed(0)
    idx = torch.randperm(3 * 150, generator=g)[:150]
    xk, xn = X[:, :-1].reshape(-1, N)[idx], X[:, 1:].reshape(-1, N)[idx]
    f = GPTransition.fit(xk, None, xn, increment=True, iterations=30, progress=False, seed=0)
    model = torchfilt.StateSpaceModel(f, lambda x, u: x, R=R_SD**2 * torch.eye(N, dtype=DT))
    return model, Y


def _test_nees(model: torchfilt.StateSpaceModel) -> float:
    X, Y = simulate_drift(6, 150, seed=1)
    with torch.no_grad():
        res = torchfilt.CKF(model).filter(
            Y, x0=torch.zeros(N, dtype=DT), P0=0.1 * torch.eye(N, dtype=DT)
        )
    return float(torchfilt.nees(X[:, 1:], res.mean, res.cov)[:, 20:].mean())


def test_calibration_moves_nees_into_the_band(drift_model):
    """The GP's one-step noise is far too small for AR(1) increments; the filter likelihood sees
    the multi-step drift between measurements and scales it up. The uncalibrated control fails the
    same assertion."""
    model, Y = drift_model
    uncal = _test_nees(model)
    cal = torchfilt.calibrate(
        model,
        Sequences(Y),
        x0=torch.zeros(N, dtype=DT),
        P0=0.1 * torch.eye(N, dtype=DT),
        sides=("transition",),
        iterations=40,
        windows=WindowOptions(window=50, burn_in=10),
        optimizer=OptimizerOptions(lr=0.15),
    )
    calibrated = _test_nees(cal.model)
    assert not NEES_BAND[0] <= uncal <= NEES_BAND[1], uncal
    assert NEES_BAND[0] <= calibrated <= NEES_BAND[1], (uncal, calibrated, cal.parameters)
    assert min(cal.parameters["transition"]["scale"]) > 2.0
    assert cal.fit.log_likelihood > cal.fit.initial_log_likelihood
    # the base model is shared, not modified
    assert cal.model.transition.base is model.transition


# ------------------------------------------------------------------------------ building blocks
def test_windows_count_every_step_once():
    y = torch.randn(2, 23, 1, dtype=DT)
    y[1, 17:] = math.nan  # a shorter second recording (padded)
    w = window_data(y, None, [23, 17], window=8, burn_in=3)
    counted = torch.zeros(2, 23, dtype=torch.int64)
    for j in range(w.y.shape[0]):
        r, s = int(w.rec[j]), int(w.start[j])
        for k in range(8):
            if bool(w.counted[j, k]):
                counted[r, s + k] += 1
                assert torch.equal(w.y[j, k], y[r, s + k])
    # every step after the first burn-in is counted exactly once
    assert bool((counted[0, 3:] == 1).all()) and bool((counted[0, :3] == 0).all())
    assert bool((counted[1, 3:17] == 1).all()) and bool((counted[1, 17:] == 0).all())
    with pytest.raises(InputError, match="burn_in"):
        window_data(y, None, [23, 17], window=8, burn_in=8)


@pytest.mark.parametrize("seed", range(5))
def test_parametrisations_stay_valid_under_random_updates(seed):
    g = torch.Generator().manual_seed(seed)
    params = [
        CholeskyCovariance(torch.eye(3, dtype=DT)),
        DiagonalCovariance(torch.ones(4, dtype=DT)),
        ScalarCovariance(2.0, 3, dtype=DT),
    ]
    pos, box = Positive(1.0, low=0.5, dtype=DT), Bounded(0.3, -1.0, 2.0, dtype=DT)
    for _ in range(20):
        with torch.no_grad():
            for m in [*params, pos, box]:
                for p in m.parameters():
                    p.add_(0.7 * torch.randn(p.shape, generator=g, dtype=DT))
        with torch.no_grad():
            for c in params:
                P = c()
                assert torch.allclose(P, P.mT)
                assert bool((torch.linalg.eigvalsh(P) > 0).all())
            assert float(pos()) > 0.5
            assert -1.0 < float(box()) < 2.0


def test_parametrisations_round_trip_their_initial_values():
    P = torch.tensor([[2.0, 0.3, 0.1], [0.3, 1.0, -0.2], [0.1, -0.2, 0.5]], dtype=DT)
    with torch.no_grad():
        assert torch.allclose(CholeskyCovariance(P)(), P, rtol=1e-12, atol=1e-14)
        assert torch.allclose(DiagonalCovariance(torch.diag(P))().diagonal(), torch.diag(P))
        assert math.isclose(float(Positive(0.7, dtype=DT)()), 0.7, rel_tol=1e-12)
        assert math.isclose(float(Bounded(0.25, 0.0, 1.0, dtype=DT)()), 0.25, rel_tol=1e-12)
    with pytest.raises(InputError, match="positive definite"):
        CholeskyCovariance(-P)
    with pytest.raises(InputError, match="inside"):
        Bounded(2.0, 0.0, 1.0)


def _linear_problem(seed: int = 0, T: int = 60):
    g = torch.Generator().manual_seed(seed)
    A = torch.tensor([[0.9]], dtype=DT)
    x = torch.zeros(3, 1, dtype=DT)
    ys = []
    for _ in range(T):
        x = x @ A.mT + 0.5 * torch.randn(3, 1, generator=g, dtype=DT)
        ys.append(x + 0.3 * torch.randn(3, 1, generator=g, dtype=DT))
    y = torch.stack(ys, 1)
    Q, R = ScalarCovariance(1.0, 1, dtype=DT), ScalarCovariance(1.0, 1, dtype=DT)
    model = torchfilt.StateSpaceModel(lambda x, u: x @ A.mT, lambda x, u: x, Q=Q, R=R)
    return model, y, (Q, R)


def test_resume_equals_uninterrupted(tmp_path):
    kw = dict(x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), iterations=12)
    kw.update(
        windows=WindowOptions(window=20, burn_in=5, refresh_every=4),
        optimizer=OptimizerOptions(lr=0.1),
    )
    model, y, (Q, R) = _linear_problem()
    full = fit_likelihood(model, y, **kw)
    with torch.no_grad():
        want = (Q().clone(), R().clone())

    class Killed(Exception):
        pass

    def kill(state):
        if state.iteration == 8:  # after the checkpoint at 6: iterations 7 and 8 are lost
            raise Killed

    model2, y2, _ = _linear_problem()
    ck = tmp_path / "fit.ckpt"
    with pytest.raises(Killed):
        fit_likelihood(model2, y2, checkpoint=CheckpointOptions(ck, every=3), callback=kill, **kw)
    model3, y3, (Q3, R3) = _linear_problem()
    resumed = fit_likelihood(
        model3, y3, **kw, checkpoint=CheckpointOptions(ck, every=3, resume=True)
    )
    with torch.no_grad():
        assert torch.equal(Q3(), want[0]) and torch.equal(R3(), want[1])
    assert [h["loss"] for h in resumed.history] == [h["loss"] for h in full.history]
    # a checkpoint of another fit is refused
    model4, y4, _ = _linear_problem(seed=1)
    with pytest.raises(RunError, match="another fit"):
        fit_likelihood(model4, y4, **kw, checkpoint=CheckpointOptions(ck, every=3, resume=True))


def test_early_stopping_and_callback():
    model, y, _ = _linear_problem()
    x0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)
    seen = []
    fit = fit_likelihood(
        model,
        y[:2],
        x0=x0,
        P0=P0,
        iterations=300,
        validation=Sequences(y[2:]),
        optimizer=OptimizerOptions(lr=0.2),
        stopping=StoppingOptions(patience=3),
    )
    assert fit.stopped == "early stopping" and fit.iterations < 300
    assert fit.validation is not None
    assert fit.validation == max(h["validation"] for h in fit.history)
    model, y, _ = _linear_problem()
    fit = fit_likelihood(
        model,
        y,
        x0=x0,
        P0=P0,
        iterations=50,
        callback=lambda s: seen.append(s.iteration) or s.iteration == 4,
    )
    assert fit.stopped == "callback" and seen == [1, 2, 3, 4]


def test_fit_likelihood_input_errors():
    model, y, _ = _linear_problem()
    x0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)
    with pytest.raises(InputError, match="optimizer"):
        fit_likelihood(model, y, x0=x0, P0=P0, optimizer="sgd")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="lr"):
        fit_likelihood(model, y, x0=x0, P0=P0, optimizer=OptimizerOptions(lr=math.nan))
    with pytest.raises(torchfilt.exceptions.ShapeError, match="x0"):
        fit_likelihood(model, y, x0=torch.zeros(2, dtype=DT), P0=P0)
    with pytest.raises(InputError, match="nothing to fit"):
        fit_likelihood(model, y, x0=x0, P0=P0, parameters=[])
    with pytest.raises(InputError, match="no measurement"):
        fit_likelihood(model, torch.full_like(y, math.nan), x0=x0, P0=P0)


def test_recipe_calibrate_section(tmp_path):
    from torchfilt.pipeline import load_recipe

    base = '[dataset]\npath = "d"\n[transition]\nmodel = "system:reaction"\n[measurement]\nmodel = "system:reaction"\n'
    p = tmp_path / "r.toml"
    p.write_text(base)
    assert load_recipe(p).calibrate["enabled"] is True
    p.write_text(base + "[calibrate]\nenabled = false\n")
    assert load_recipe(p).calibrate["enabled"] is False
    for bad, msg in [
        ("windw = 3", "unknown key"),
        ("burn_in = 200", "burn_in"),
        ('sides = ["bogus"]', "sides"),
        ("lr = -1", "lr"),
    ]:
        p.write_text(base + f"[calibrate]\n{bad}\n")
        with pytest.raises(RecipeError, match=msg):
            load_recipe(p)


# ------------------------------------------------------------------------------ sensor drift
def test_sensor_drift_states_equal_the_hand_written_augmented_model():
    from torchfilt.models.drift import with_sensor_drift

    q, r1, r2, tau, sd = 0.01, 0.04, 0.09, 20.0, 0.3
    base = torchfilt.StateSpaceModel(
        lambda x, u: x,
        lambda x, u: torch.cat([x, x], -1),
        Q=torch.tensor([[q]], dtype=DT),
        R=torch.diag(torch.tensor([r1, r2], dtype=DT)),
    )
    drift = with_sensor_drift(base, [1], time_constant=tau, sd=sd)
    a = math.exp(-1.0 / tau)
    A = torch.diag(torch.tensor([1.0, a], dtype=DT))
    H = torch.tensor([[1.0, 0.0], [1.0, 1.0]], dtype=DT)
    manual = torchfilt.StateSpaceModel(
        lambda x, u: x @ A.mT,
        lambda x, u: x @ H.mT,
        Q=torch.diag(torch.tensor([q, sd**2 * (1 - a * a)], dtype=DT)),
        R=torch.diag(torch.tensor([r1, r2], dtype=DT)),
    )
    g = torch.Generator().manual_seed(5)
    y = torch.randn(3, 40, 2, generator=g, dtype=DT)
    y[:, ::3, 0] = math.nan
    x0, P0 = drift.prior(torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT))
    assert x0.shape == (2,) and torch.allclose(P0, torch.diag(torch.tensor([1.0, sd**2], dtype=DT)))
    with torch.no_grad():
        a_res = torchfilt.CKF(drift).filter(y, x0=x0, P0=P0)
        b_res = torchfilt.CKF(manual).filter(y, x0=x0, P0=P0)
    torch.testing.assert_close(a_res.mean, b_res.mean, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(a_res.cov, b_res.cov, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(a_res.log_likelihood, b_res.log_likelihood, rtol=1e-10, atol=0)
    # the drift parameters are fitted with the calibration (and reported)
    cal = torchfilt.calibrate(
        drift,
        Sequences(y),
        x0=x0,
        P0=P0,
        iterations=3,
        windows=WindowOptions(window=None, burn_in=20),
    )
    assert set(cal.parameters) == {"transition", "measurement", "drift"}
    assert cal.parameters["drift"]["channels"] == [1]
    assert cal.parameters["drift"]["time_constant"][0] != tau  # moved
    assert float(drift.time_constant.detach()) == pytest.approx(tau)  # the given model is kept
