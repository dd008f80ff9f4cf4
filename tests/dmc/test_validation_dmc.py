"""OpenLoopPredictor input validation (issue 12): the missing-data rule shared with the CKF, NaN
gains and states refused, an empty recording refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfilt.dmc import FOPDT, IPDT, OpenLoopPredictor, StepResponseModel
from torchfilt.exceptions import InputError, ShapeError

D = torch.float64
#: two evaluations of the same linear recursion in float64 (different op order)
EXACT_TOL = 1e-10


def _model() -> StepResponseModel:
    Gu = [[FOPDT(2.0, 4.0, 1.5)], [IPDT(0.2, 2.0, 1.0)]]
    return StepResponseModel.from_transfer_functions(Gu, dt=1.0, horizon=10)


def _reference(pred: OpenLoopPredictor, y: np.ndarray, du: np.ndarray) -> np.ndarray:
    """The recursion in numpy, skipping the correction of every non-finite component."""
    r = pred.realization
    A, B, H, K = (t.numpy() for t in (r.A, r.B, r.H, pred.gain))
    x = pred.initial_state().numpy()
    out = []
    for k in range(y.shape[0]):
        xp = A @ x + B @ du[k]
        eps = y[k] - H @ xp
        ok = np.isfinite(y[k])
        x = xp + K[:, ok] @ eps[ok]
        out.append(x)
    return np.stack(out)


@pytest.mark.parametrize("bad", [float("inf"), float("-inf"), float("nan")])
def test_non_finite_measurement_is_missing(bad):
    """Before: one +inf made every later prediction non-finite."""
    model = _model()
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0)
    g = torch.Generator().manual_seed(3)
    y = torch.randn(12, model.ny, generator=g, dtype=D)
    du = torch.randn(12, model.nu, generator=g, dtype=D)
    y[4, 0] = bad
    y[7, 1] = bad
    run = pred.run(y, du)
    assert torch.isfinite(run.states).all() and torch.isfinite(run.predictions).all()
    ref = _reference(pred, y.numpy(), du.numpy())
    np.testing.assert_allclose(run.states.numpy(), ref, atol=EXACT_TOL, rtol=0)
    assert torch.isnan(run.innovations[4, 0]) and torch.isnan(run.innovations[7, 1])
    assert int(torch.isnan(run.innovations).sum()) == 2
    # the online path follows the same rule
    pred.reset()
    for k in range(12):
        pred.update(y[k], du[k])
    np.testing.assert_allclose(pred.state.numpy(), ref[-1], atol=EXACT_TOL, rtol=0)


def test_nan_gain_is_refused():
    model = _model()
    n = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0).state_dim
    K = torch.zeros(n, model.ny, dtype=D)
    K[0, 0] = float("nan")
    with pytest.raises(InputError, match="gain contains non-finite"):
        OpenLoopPredictor(model, gain=K)
    with pytest.raises(InputError, match="h contains non-finite"):
        OpenLoopPredictor.classical(model, h=float("nan"))


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_x0_and_state_are_refused(value):
    model = _model()
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0)
    x0 = pred.initial_state()
    x0[2] = value
    y = torch.zeros(5, model.ny, dtype=D)
    with pytest.raises(InputError, match="x0 contains non-finite"):
        pred.run(y, x0=x0)
    with pytest.raises(InputError, match="state contains non-finite"):
        pred.step(x0, y[0])
    with pytest.raises(InputError, match="state contains non-finite"):
        pred.reset(x0)
    with pytest.raises(InputError, match="level contains non-finite"):
        pred.initial_state(value)


def test_empty_recording_is_refused():
    model = _model()
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0)
    with pytest.raises(ShapeError, match="y: the time dimension T must be at least 1"):
        pred.run(torch.zeros(0, model.ny, dtype=D))


def test_batch_shapes_that_do_not_broadcast():
    model = _model()
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0)
    y = torch.zeros(3, 5, model.ny, dtype=D)
    with pytest.raises(ShapeError, match="x0: batch shape"):
        pred.run(y, x0=torch.zeros(4, pred.state_dim, dtype=D))
    with pytest.raises(ShapeError, match="batch shapes do not broadcast"):
        pred.run(y, torch.zeros(2, 5, model.nu, dtype=D))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.complex64])
def test_measurement_dtype_rule(dtype):
    model = _model()
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=1.0)
    with pytest.raises(InputError, match="y: "):
        pred.run(torch.zeros(5, model.ny, dtype=dtype))


def test_model_must_be_a_step_response_model():
    with pytest.raises(InputError, match="model must be a StepResponseModel"):
        OpenLoopPredictor(object(), Q_Y=0.3, Q_y=1.0)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="model must be a StepResponseModel"):
        OpenLoopPredictor.classical("model")  # type: ignore[arg-type]
