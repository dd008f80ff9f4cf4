"""The input convention (stated once in torchfilt.filters and docs/guide/filtering.md): step ``t``
predicts ``x_t`` from ``x_{t-1}`` with the row ``u[..., t, :]`` and maps ``y_t`` with the same row.

An input that is nonzero at one step only shows which row each path uses: the exact Kalman
filter, its parallel scan, the cubature filter, the online predict/update, prediction ahead, the
simulator, and the pairs GP models are trained on. Any path that used the row before or after
would move the impulse by one step and fail.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.filters import free_run, iterated_smoother, k_step_ahead
from torchfilt.models.gp.data import measurement_pairs, transition_pairs
from torchfilt.systems import simulate

D = torch.float64
T, J = 8, 3  # the input is 1 at step J only
A = torch.tensor([[0.9, 0.2], [0.0, 0.8]], dtype=D)
B = torch.tensor([[1.0], [2.0]], dtype=D)
H = torch.tensor([[1.0, 0.0]], dtype=D)
DD = torch.tensor([[5.0]], dtype=D)


def _impulse() -> torch.Tensor:
    u = torch.zeros(T, 1, dtype=D)
    u[J] = 1.0
    return u


def _expected() -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted means with all measurements missing from x0 = 0, and predicted outputs: zero
    before step J, ``A^(t-J) B`` from it; the output adds ``D`` at step J."""
    mean = torch.zeros(T, 2, dtype=D)
    for t in range(J, T):
        mean[t] = torch.linalg.matrix_power(A, t - J) @ B[:, 0]
    out = mean @ H.mT
    out[J] += DD[0]
    return mean, out


def _linear() -> LinearGaussianModel:
    return LinearGaussianModel(
        A=A, H=H, Q=0.1 * torch.eye(2, dtype=D), R=torch.eye(1, dtype=D), B=B, D=DD
    )


def _nonlinear() -> StateSpaceModel:
    """The same maps as callables (the cubature path, no linear structure to find)."""
    return StateSpaceModel(
        lambda x, u: x @ A.mT + u @ B.mT,
        lambda x, u: x @ H.mT + u @ DD.mT,
        Q=0.1 * torch.eye(2, dtype=D),
        R=torch.eye(1, dtype=D),
    )


PRIOR = {"x0": torch.zeros(2, dtype=D), "P0": torch.eye(2, dtype=D)}


@pytest.mark.parametrize(
    ("model", "kw"),
    [
        ("linear", {"path": "kalman"}),
        ("linear", {"path": "kalman", "parallel": True}),
        ("linear", {"path": "cubature"}),
        ("nonlinear", {}),
    ],
)
def test_filter_uses_row_t_for_step_t(model: str, kw: dict) -> None:
    mdl = _linear() if model == "linear" else _nonlinear()
    y = torch.full((T, 1), math.nan, dtype=D)
    res = CKF(mdl).filter(y, _impulse(), **PRIOR, **kw)
    mean, out = _expected()
    torch.testing.assert_close(res.predicted_mean, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.measurement_mean, out, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("parallel", [False, True])
def test_smoothers_use_row_t_for_step_t(parallel: bool) -> None:
    """With nothing measured the smoothed means are the predicted ones: the impulse at step J."""
    y = torch.full((T, 1), math.nan, dtype=D)
    mean, _ = _expected()
    sm = CKF(_nonlinear()).smooth(y, _impulse(), **PRIOR)
    torch.testing.assert_close(sm.mean, mean, rtol=1e-10, atol=1e-10)
    it = iterated_smoother(_nonlinear(), y, _impulse(), **PRIOR, parallel=parallel)
    torch.testing.assert_close(it.mean, mean, rtol=1e-10, atol=1e-10)


def test_online_steps_use_the_row_of_the_step() -> None:
    ckf = CKF(_nonlinear())
    u = _impulse()
    mean, out = _expected()
    state = ckf.init(**PRIOR)
    for t in range(T):
        state = ckf.predict(state, u[t])
        torch.testing.assert_close(state.mean, mean[t], rtol=1e-12, atol=1e-12)
        state, stats = ckf.update(state, torch.full((1,), math.nan, dtype=D), u[t])
        torch.testing.assert_close(stats.measurement_mean, out[t], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("model", ["linear", "nonlinear"])
def test_prediction_ahead_uses_row_t_for_step_t(model: str) -> None:
    mdl = _linear() if model == "linear" else _nonlinear()
    y = torch.randn(T, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    mean, out = _expected()
    sim = free_run(mdl, y, _impulse(), **PRIOR, burn_in=0)
    torch.testing.assert_close(sim.mean, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(sim.output_mean, out, rtol=1e-12, atol=1e-12)
    ahead = k_step_ahead(mdl, y.fill_(math.nan), _impulse(), **PRIOR, horizon=2)
    torch.testing.assert_close(ahead.mean, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ahead.output_mean, out, rtol=1e-12, atol=1e-12)


def _noise_free() -> LinearGaussianModel:
    zero = torch.zeros(2, 2, dtype=D)
    return LinearGaussianModel(A=A, H=H, Q=zero, R=torch.zeros(1, 1, dtype=D), B=B, D=DD)


def test_simulator_and_gp_training_pairs_pair_the_filters_rows() -> None:
    """simulate() and the GP training pairs use the filter's rows: a filter started at the
    simulation's initial state reproduces its states, and every transition pair's target is
    ``f`` of its state and input (what a GP fitted to the pairs learns)."""
    model = _noise_free()
    g = torch.Generator().manual_seed(1)
    u = torch.randn(T, 1, dtype=D, generator=g)
    x_init = torch.tensor([0.5, -1.0], dtype=D)
    sim = simulate(model, T, x_init, u=u, generator=g)
    # the filter, from the simulation's initial state with nothing measured, reproduces it
    res = CKF(model).filter(
        torch.full((T, 1), math.nan, dtype=D), u, x0=x_init, P0=1e-12 * torch.eye(2, dtype=D)
    )
    torch.testing.assert_close(res.predicted_mean, sim.states, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(res.measurement_mean, sim.measurements, rtol=1e-10, atol=1e-10)
    # a recording of states x[0..T] (row 0 the initial state) with the T inputs that drove it
    recording = torch.cat([sim.initial.unsqueeze(0), sim.states])
    pairs = transition_pairs(recording, u)
    assert pairs.inputs is not None
    target = pairs.states @ A.mT + pairs.inputs @ B.mT
    torch.testing.assert_close(pairs.targets, target, rtol=1e-12, atol=1e-12)
    # the (T + 1)-row input column of a log (last row unused) pairs the same rows
    logged = torch.cat([u, torch.full((1, 1), 7.0, dtype=D)])
    torch.testing.assert_close(transition_pairs(recording, logged).inputs, pairs.inputs)
    # measurement pairs: y_t with x_t and the same row u_t
    mp = measurement_pairs(sim.states, sim.measurements, u)
    assert mp.inputs is not None
    torch.testing.assert_close(
        mp.targets, mp.states @ H.mT + mp.inputs @ DD.mT, rtol=1e-12, atol=1e-12
    )
