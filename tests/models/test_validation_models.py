"""Model outputs are checked against the declared dimensions and the dtype rule (issue 12)."""

from __future__ import annotations

import pytest
import torch

from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import InputError, ModelError, ShapeError, TorchfiltError
from torchfilt.models import FunctionModel, Prediction, check_output, check_prediction
from torchfilt.numerics import check_compute_dtype, check_real_tensor

D = torch.float64
N, M = 3, 2


def _kw(n: int = N) -> dict[str, torch.Tensor]:
    return dict(x0=torch.zeros(n, dtype=D), P0=torch.eye(n, dtype=D))


def _model(f, h, n: int = N, m: int = M) -> StateSpaceModel:
    return StateSpaceModel(f, h, Q=0.01 * torch.eye(n, dtype=D), R=torch.eye(m, dtype=D))


def _h(x: torch.Tensor) -> torch.Tensor:
    return x[..., :M]


@pytest.mark.parametrize(
    ("f", "shape"),
    [
        (lambda x: 0.9 * x[..., :1], r"\(6, 1\)"),  # (..., 1) for n = 3: three copies of state 1
        (lambda x: 0.9 * x[:1], r"\(1, 3\)"),  # (1, n): every point mapped like the first
        (lambda x: x[0], r"\(3,\)"),  # (n,): the batch dimension dropped
        (lambda x: x.sum(), r"\(\)"),  # a scalar
    ],
)
def test_transition_output_too_small_is_refused(f, shape):
    model = _model(f, _h)
    with pytest.raises(ModelError, match=rf"transition returned shape {shape}.*d = 3"):
        CKF(model).filter(torch.zeros(4, M, dtype=D), **_kw())


def test_measurement_with_one_column_for_two_is_refused():
    model = _model(lambda x: x, lambda x: x[..., :1])
    with pytest.raises(ModelError, match=r"measurement returned shape \(6, 1\).*d = 2"):
        CKF(model).filter(torch.zeros(4, M, dtype=D), **_kw())


def test_measurement_returning_int64_is_refused():
    model = _model(lambda x: x, lambda x: x[..., :M].long())
    with pytest.raises(ModelError, match=r"measurement returned dtype torch\.int64"):
        CKF(model).filter(torch.zeros(4, M, dtype=D), **_kw())


def test_model_returning_non_tensor_is_a_model_error():
    model = _model(lambda x: x.numpy(), _h)
    with pytest.raises(ModelError, match="transition returned ndarray"):
        CKF(model).filter(torch.zeros(4, M, dtype=D), **_kw())


def test_floating_output_of_other_dtype_is_cast_to_the_points():
    scale = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    f = FunctionModel(lambda x: x * scale, torch.eye(N), name="transition")
    x = torch.ones(4, N, dtype=torch.float32)
    out = f.predict(x).mean
    assert out.dtype == torch.float32
    assert torch.equal(out, 0.5 * x)


def test_larger_leading_shape_is_allowed():
    """A model with batched parameters may return more leading dimensions than its points."""
    w = torch.arange(1.0, 6.0, dtype=D).reshape(5, 1, 1)
    f = FunctionModel(lambda x: w * x, torch.eye(N, dtype=D), name="transition")
    x = torch.ones(4, N, dtype=D)
    out = f.predict(x).mean
    assert out.shape == (5, 4, N)
    assert torch.equal(out[2], 3.0 * x)


def test_correct_output_unchanged_and_check_output_direct():
    x = torch.randn(2, 5, N, dtype=D)
    out = 2.0 * x
    assert check_output(out, x, N, "f") is out
    with pytest.raises(ModelError, match=r"f returned shape \(2, 1, 3\)"):
        check_output(out[:, :1], x, N, "f")


def test_linear_model_input_with_wrong_width():
    model = LinearGaussianModel(
        torch.eye(2, dtype=D),
        torch.ones(1, 2, dtype=D),
        torch.eye(2, dtype=D),
        torch.eye(1, dtype=D),
        B=torch.ones(2, 1, dtype=D),
    )
    with pytest.raises(ShapeError, match=r"u: expected shape \(\.\.\., nu\) with nu = 1"):
        CKF(model).filter(
            torch.zeros(5, 1, dtype=D),
            torch.zeros(5, 3, dtype=D),
            x0=torch.zeros(2, dtype=D),
            P0=torch.eye(2, dtype=D),
        )


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_matrices_are_refused(dtype):
    with pytest.raises(InputError, match=rf"A: {dtype} is not supported"):
        LinearGaussianModel(torch.eye(2, dtype=dtype), torch.ones(1, 2), torch.eye(2), torch.eye(1))
    with pytest.raises(InputError, match=rf"Q: {dtype} is not supported"):
        StateSpaceModel(lambda x: x, _h, Q=torch.eye(2, dtype=dtype), R=torch.eye(M))


def test_non_finite_matrix_is_refused():
    A = torch.eye(2, dtype=D)
    A[0, 1] = float("nan")
    with pytest.raises(InputError, match="A contains non-finite"):
        LinearGaussianModel(A, torch.ones(1, 2), torch.eye(2), torch.eye(1))


@pytest.mark.parametrize(
    ("dtype", "ok"),
    [
        (torch.float32, True),
        (torch.float64, True),
        (torch.float16, False),
        (torch.bfloat16, False),
        (torch.int64, False),
        (torch.complex64, False),
        ("float64", False),
    ],
)
def test_compute_dtype_rule(dtype, ok):
    if ok:
        assert check_compute_dtype(dtype) is dtype
    else:
        with pytest.raises(InputError, match="dtype"):
            check_compute_dtype(dtype)


@pytest.mark.parametrize(
    ("dtype", "integers", "ok"),
    [
        (torch.float32, False, True),
        (torch.float64, False, True),
        (torch.int64, True, True),
        (torch.int64, False, False),
        (torch.float16, True, False),
        (torch.bfloat16, False, False),
        (torch.complex128, True, False),
        (torch.bool, True, False),
    ],
)
def test_real_tensor_rule(dtype, integers, ok):
    t = torch.zeros(2, dtype=dtype)
    if ok:
        assert check_real_tensor(t, "v", integers=integers) is t
    else:
        with pytest.raises(TorchfiltError, match="v: "):
            check_real_tensor(t, "v", integers=integers)


def test_check_prediction_covers_variance_and_covariance():
    x = torch.randn(5, N, dtype=D)
    mean = torch.zeros(5, 2, dtype=D)
    ok = check_prediction(
        Prediction(mean, torch.ones(5, 2), torch.eye(2).expand(5, 2, 2)), x, 2, "gp"
    )
    assert ok.var.dtype == D and ok.cov.dtype == D
    with pytest.raises(ModelError, match=r"gp \(variance\) returned shape \(5, 1\)"):
        check_prediction(Prediction(mean, torch.ones(5, 1, dtype=D)), x, 2, "gp")
    with pytest.raises(ModelError, match=r"gp \(covariance\): shape \(5, 2\)"):
        check_prediction(Prediction(mean, None, torch.ones(5, 2, dtype=D)), x, 2, "gp")
    with pytest.raises(ModelError, match=r"gp\.predict returned tuple"):
        check_prediction((mean,), x, 2, "gp")
