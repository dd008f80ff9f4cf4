"""Issue 24 item 5: half precision is refused at every entry point (an InputTypeError naming the
argument, never a silent upcast next to a float64 prior), and inputs ``u`` that the model would
drop (it takes no inputs) are refused with an InputError naming ``u`` and the model's width."""

from __future__ import annotations

import pytest
import torch

from torchfilt import CKF, LinearGaussianModel, fit_em, fit_likelihood
from torchfilt.exceptions import InputError, InputTypeError, ShapeError
from torchfilt.filters import kalman_filter, kalman_smoother
from torchfilt.filters.inputs import model_input_width
from torchfilt.models import InducingTransition

D = torch.float64
T = 6


def _model(nu: int = 0) -> LinearGaussianModel:
    B = torch.ones(2, nu, dtype=D) if nu else None
    return LinearGaussianModel(
        torch.eye(2, dtype=D) * 0.9,
        torch.ones(1, 2, dtype=D),
        torch.eye(2, dtype=D) * 0.1,
        torch.eye(1, dtype=D),
        B=B,
    )


X0, P0 = torch.zeros(2, dtype=D), torch.eye(2, dtype=D)


def _y(dtype: torch.dtype = D) -> torch.Tensor:
    return torch.randn(T, 1, generator=torch.Generator().manual_seed(0), dtype=D).to(dtype)


def _online_update(model, y, u=None, *, x0=X0, P0=P0):
    f = CKF(model)
    u0 = None if u is None else u[0]
    return f.update(f.predict(f.init(x0, P0), u0), y[0], u0)


def _online_predict(model, y, u=None, *, x0=X0, P0=P0):
    f = CKF(model)
    return f.predict(f.init(x0, P0), None if u is None else u[0])


def _fit(fn, **options):
    def run(model, y, u=None, *, x0=X0, P0=P0):
        u = None if u is None else u.unsqueeze(0)
        return fn(model, y.unsqueeze(0), u, x0=x0, P0=P0, iterations=1, **options)

    return run


ENTRY_POINTS = {
    "kalman_filter": kalman_filter,
    "kalman_smoother": kalman_smoother,
    "CKF.filter": lambda m, y, u=None, **kw: CKF(m).filter(y, u, **kw),
    "CKF.filter cubature": lambda m, y, u=None, **kw: CKF(m).filter(y, u, path="cubature", **kw),
    "CKF.smooth": lambda m, y, u=None, **kw: CKF(m).smooth(y, u, **kw),
    "online update": _online_update,
    "fit_likelihood": _fit(fit_likelihood),
    "fit_em": _fit(fit_em, known_channels=[0]),
}


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_half_precision_measurements_are_refused_beside_a_float64_prior(entry, half) -> None:
    """``y`` in half precision with a float64 prior used to be upcast to float64 silently."""
    with pytest.raises(InputTypeError, match=r"^y: torch\.(float16|bfloat16) is not supported"):
        ENTRY_POINTS[entry](_model(), _y(half), x0=X0, P0=P0)


@pytest.mark.parametrize("entry", ["kalman_filter", "CKF.filter", "online update"])
def test_half_precision_prior_is_refused(entry) -> None:
    with pytest.raises(InputTypeError, match=r"^P0: torch\.float16"):
        ENTRY_POINTS[entry](_model(), _y(), x0=X0, P0=P0.half())


@pytest.mark.parametrize("entry", sorted({*ENTRY_POINTS, "online predict"}))
@pytest.mark.parametrize("nu", [1, 3])
def test_inputs_for_a_model_without_inputs_are_refused(entry, nu) -> None:
    """A model without B and D used to drop ``u`` (of any width) silently."""
    u = torch.ones(T, nu, dtype=D)
    run = _online_predict if entry == "online predict" else ENTRY_POINTS[entry]
    with pytest.raises(InputError, match=r"^u: the model takes no inputs \(.*width.* 0"):
        run(_model(), _y(), u, x0=X0, P0=P0)


@pytest.mark.parametrize("entry", ["CKF.filter cubature", "online update", "fit_likelihood"])
def test_inputs_of_the_wrong_width_are_refused(entry) -> None:
    """The exact path refused this already (B's width); the other paths now do too."""
    u = torch.ones(T, 3, dtype=D)
    with pytest.raises(ShapeError, match=r"^u: expected shape \(\.\.\., nu\) with nu = 2"):
        ENTRY_POINTS[entry](_model(nu=2), _y(), u, x0=X0, P0=P0)


def test_inputs_of_the_right_width_still_run() -> None:
    u = torch.ones(T, 2, dtype=D)
    res = CKF(_model(nu=2)).filter(_y(), u, x0=X0, P0=P0)
    ref = CKF(_model(nu=2)).filter(_y(), u, x0=X0, P0=P0, path="cubature")
    torch.testing.assert_close(res.mean, ref.mean)


def test_model_input_width() -> None:
    assert model_input_width(_model()) == 0
    assert model_input_width(_model(nu=2)) == 2
    ind = InducingTransition(2, 4, input_dim=0, dtype=D)
    assert ind.input_dim == 0


def test_calibrate_refuses_inputs_for_a_model_without_inputs() -> None:
    """The calibrated wrapper hides the model's width: checked on the model given."""
    from torchfilt import calibrate
    from torchfilt.optim import WindowOptions
    from torchfilt.training.likelihood import Sequences

    y, u = _y().unsqueeze(0), torch.ones(1, T, 2, dtype=D)
    with pytest.raises(InputError, match=r"^u: the model takes no inputs"):
        calibrate(
            _model(), Sequences(y, u), x0=X0, P0=P0, iterations=1,
            windows=WindowOptions(burn_in=0),
        )  # fmt: skip
