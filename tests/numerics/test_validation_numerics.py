"""Bad input to the numerics fails with a clear TorchfiltError (issue 12): bounded least squares,
the DARE."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize as so
import torch

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics import Box, SolverStatus, bounded_least_squares, solve_dare

D = torch.float64
#: our solution vs scipy.optimize.least_squares (both stop near 1e-8 in the J^T J metric)
NL_ATOL = 1e-6

#: an exponential fit y = a exp(b t): the start point is far from the optimum
T_DATA = np.linspace(0.0, 1.0, 8)
Y_DATA = 2.0 * np.exp(-1.3 * T_DATA) + 0.05 * np.sin(7.0 * T_DATA)
X0 = np.array([1.0, 0.0])


def _res(x: torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(T_DATA, dtype=x.dtype)
    y = torch.as_tensor(Y_DATA, dtype=x.dtype)
    return x[..., :1] * torch.exp(x[..., 1:] * t) - y


def _jac(x: torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(T_DATA, dtype=x.dtype)
    e = torch.exp(x[..., 1:] * t)
    return torch.stack([e, x[..., :1] * t * e], dim=-1)


def _scipy_optimum() -> tuple[np.ndarray, float]:
    sol = so.least_squares(
        lambda x: x[0] * np.exp(x[1] * T_DATA) - Y_DATA, X0, xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    return sol.x, float(sol.cost)


@pytest.mark.parametrize(
    "residual",
    [
        lambda x: _res(x).detach(),
        lambda x: _res(x.detach()),
        lambda x: torch.as_tensor(Y_DATA, dtype=x.dtype).expand(*x.shape[:-1], len(Y_DATA)),
    ],
    ids=["detach-out", "detach-in", "constant"],
)
def test_non_differentiable_residual_is_refused(residual):
    """Before: CONVERGED at the start point with cost 0.5 against an optimum of 0.002."""
    with pytest.raises(InputError, match=r"does not depend differentiably on x.*jacobian="):
        bounded_least_squares(residual, torch.tensor(X0, dtype=D))


def test_detached_residual_with_its_jacobian_matches_scipy():
    x_ref, cost_ref = _scipy_optimum()
    sol = bounded_least_squares(
        lambda x: _res(x).detach(), torch.tensor(X0, dtype=D), jacobian=_jac
    )
    assert int(sol.status) == int(SolverStatus.CONVERGED)
    np.testing.assert_allclose(sol.x.numpy(), x_ref, atol=NL_ATOL)
    np.testing.assert_allclose(float(sol.cost), cost_ref, rtol=NL_ATOL)
    # and the differentiable residual reaches the same optimum through autograd
    sol2 = bounded_least_squares(_res, torch.tensor(X0, dtype=D))
    np.testing.assert_allclose(sol2.x.numpy(), x_ref, atol=NL_ATOL)


def test_residual_returning_numpy_is_refused():
    with pytest.raises(InputError, match="residual returned ndarray"):
        bounded_least_squares(lambda x: _res(x).detach().numpy(), torch.tensor(X0, dtype=D))


@pytest.mark.parametrize(
    "residual", [lambda x: 0.5 * (_res(x) ** 2).sum(-1), lambda x: float(_res(x).detach().sum())]
)
def test_scalar_residual_is_refused(residual):
    with pytest.raises((ShapeError, InputError), match="residual returned"):
        bounded_least_squares(residual, torch.tensor(X0, dtype=D))


def test_integer_residual_is_refused():
    with pytest.raises(InputError, match=r"residual returned dtype torch\.int64"):
        bounded_least_squares(lambda x: x.long(), torch.zeros(2, dtype=D))


def test_bounds_batch_shape_must_broadcast_with_x0():
    box = Box(torch.zeros(3, 2, dtype=D), torch.ones(3, 2, dtype=D))
    with pytest.raises(ShapeError, match=r"bounds: batch shape \(3,\) does not broadcast.*\(4,\)"):
        bounded_least_squares(lambda x: x - 2.0, torch.zeros(4, 2, dtype=D), box)
    # a broadcasting batch is fine: every problem is clipped at its own upper bound 1
    sol = bounded_least_squares(lambda x: x - 2.0, torch.zeros(2, dtype=D), box)
    assert sol.x.shape == (3, 2) and torch.equal(sol.x, torch.ones(3, 2, dtype=D))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_start_is_refused(dtype):
    with pytest.raises(InputError, match=rf"x0: {dtype} is not supported"):
        bounded_least_squares(lambda x: x - 1.0, torch.zeros(2, dtype=dtype))


def test_bounds_must_be_a_box():
    with pytest.raises(InputError, match="bounds must be a Box"):
        bounded_least_squares(lambda x: x, torch.zeros(2, dtype=D), (0.0, 1.0))  # type: ignore[arg-type]


def test_dare_batch_shapes_that_do_not_broadcast():
    A = torch.eye(2, dtype=D).expand(3, 2, 2) * 0.5
    C = torch.ones(4, 1, 2, dtype=D)
    with pytest.raises(ShapeError, match="batch shapes do not broadcast"):
        solve_dare(A, C, torch.eye(2, dtype=D), torch.eye(1, dtype=D))


def test_dare_half_precision_is_refused():
    with pytest.raises(InputError, match=r"A: torch\.float16 is not supported"):
        solve_dare(torch.eye(2, dtype=torch.float16), torch.ones(1, 2), torch.eye(2), torch.eye(1))
