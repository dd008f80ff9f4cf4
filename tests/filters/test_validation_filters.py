"""Filter-side validation of issue 12, written against the current filter core (torchfilt/filters/*).

These fail today; they belong to the filter-core refactor. Each is ``xfail(strict=True)``: once the
core change lands and a test passes, the strict xfail fails, and the marker comes off. The dtype
rule is :mod:`torchfilt.numerics.dtypes` (``check_real_tensor``), the missing-data rule
:mod:`torchfilt.numerics.missing`.
"""

from __future__ import annotations

import pytest
import torch

from torchfilt import CKF, StateSpaceModel
from torchfilt.exceptions import InputError, ShapeError, TorchfiltError
from torchfilt.filters import ConstrainedCKF, rts_smooth
from torchfilt.filters.metrics import coverage, rmse

D = torch.float64


def _model(dtype: torch.dtype = D) -> StateSpaceModel:
    """A linear model written as callables, so the filter takes its cubature path (the one these
    checks are about; a LinearGaussianModel would take the exact Kalman path)."""
    H = torch.ones(1, 2, dtype=D)
    return StateSpaceModel(
        lambda x, u: x,
        lambda x, u: x @ H.to(x.dtype).mT,
        Q=0.1 * torch.eye(2, dtype=D),
        R=torch.eye(1, dtype=D),
    ).to(dtype)


def _kw(dtype: torch.dtype = D) -> dict[str, torch.Tensor]:
    return dict(x0=torch.zeros(2, dtype=dtype), P0=torch.eye(2, dtype=dtype))


def test_mask_cannot_stretch_y():
    """Today: y (1, 1) with a mask (3, 7, 5) runs 7 steps on 5 components."""
    with pytest.raises(ShapeError, match="mask"):
        CKF(_model()).filter(
            torch.zeros(1, 1, dtype=D), mask=torch.ones(3, 7, 5, dtype=torch.bool), **_kw()
        )


def test_mask_with_more_steps_than_y():
    with pytest.raises(ShapeError, match="mask"):
        CKF(_model()).filter(
            torch.zeros(1, 1, dtype=D), mask=torch.ones(4, 1, dtype=torch.bool), **_kw()
        )


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_refused_by_the_dtype_rule(dtype):
    """Today: NotImplementedError "linalg_eigh_cpu" not implemented for 'Half' from torch."""
    y = torch.zeros(5, 1, dtype=dtype)
    with pytest.raises(InputError, match=rf"{dtype} is not supported"):
        CKF(_model(torch.float32)).filter(y, **_kw(dtype))


@pytest.mark.parametrize(
    "y",
    [
        torch.zeros(5, 1, dtype=torch.int64),
        torch.zeros(5, 1, dtype=torch.complex128),
        torch.zeros(5, 1, dtype=D).numpy(),
    ],
    ids=["int64", "complex", "numpy"],
)
def test_bad_measurement_types_are_input_errors(y):
    """Today: TypeError (not a TorchfiltError), so the CLI would show a traceback."""
    with pytest.raises(InputError, match="y"):
        CKF(_model()).filter(y, **_kw())


def test_non_bool_mask_is_an_input_error():
    with pytest.raises(InputError, match="mask"):
        CKF(_model()).filter(torch.zeros(5, 1, dtype=D), mask=torch.ones(5, 1), **_kw())


@pytest.mark.parametrize(
    "P0",
    [torch.zeros(2, 2, dtype=D), torch.full((2, 2), float("nan"), dtype=D)],
    ids=["zero", "nan"],
)
def test_bad_prior_covariance_is_an_input_error(P0):
    """Today: a bare ValueError."""
    with pytest.raises(InputError, match="P0"):
        CKF(_model()).filter(torch.zeros(5, 1, dtype=D), x0=torch.zeros(2, dtype=D), P0=P0)


def test_rmse_shape_mismatch_is_a_shape_error():
    """Today: RuntimeError from torch's broadcasting."""
    with pytest.raises(ShapeError):
        rmse(torch.zeros(3, 2, dtype=D), torch.zeros(4, 3, dtype=D))


def test_coverage_errors_are_torchfilt_errors():
    x = torch.zeros(3, 2, dtype=D)
    with pytest.raises(ShapeError):
        coverage(x, torch.zeros(4, 2, dtype=D), torch.zeros(4, 2, 2, dtype=D))
    with pytest.raises(InputError, match="level"):
        coverage(x, x, torch.eye(2, dtype=D).expand(3, 2, 2), 1.5)


def test_rts_smooth_needs_a_filter_result():
    with pytest.raises(InputError, match="FilterResult"):
        rts_smooth(None)  # type: ignore[arg-type]


def test_constrained_ckf_graphed_is_refused_or_constrained():
    """Today: graphed() builds a GraphedFilter around the plain CKF step (the constrained step
    lives in a closure it never sees). On the CPU the capture is unavailable, so the refusal must
    name the constrained filter rather than the device."""
    filt = ConstrainedCKF(_model(), lower=[0.0, 0.0], upper=[10.0, 10.0])
    with pytest.raises(TorchfiltError, match="ConstrainedCKF"):
        filt.graphed(
            torch.zeros(5, 1, dtype=D), x0=torch.ones(2, dtype=D), P0=torch.eye(2, dtype=D)
        )
