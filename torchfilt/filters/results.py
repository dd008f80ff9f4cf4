"""Result containers of the filters and smoothers (NamedTuples of tensors)."""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

__all__ = ["FilterResult", "KalmanFilterResult", "ParallelFilterResult", "SmootherResult"]


class FilterResult(NamedTuple):
    """Output of a Gaussian filter over ``T`` steps.

    The filter starts from the prior ``N(x0, P0)`` at time 0; step ``t`` (0-based) predicts with
    ``u[..., t, :]`` and updates with ``y[..., t, :]``.

    Attributes:
        mean: filtered means ``E[x_t | y_{1:t}]``, shape ``(..., T, n)``.
        cov: filtered covariances, shape ``(..., T, n, n)``.
        predicted_mean: one-step predicted means ``E[x_t | y_{1:t-1}]``, shape ``(..., T, n)``.
        predicted_cov: predicted covariances, shape ``(..., T, n, n)``.
        measurement_mean: predicted measurements, shape ``(..., T, m)``.
        innovation: ``y_t`` minus the predicted measurement, NaN where not observed,
            shape ``(..., T, m)``.
        innovation_cov: innovation covariances ``P_yy`` (all components, noise included),
            shape ``(..., T, m, m)``.
        observed: which measurement components were used, shape ``(..., T, m)``.
        log_likelihood: ``sum_t log N(y_t; y^-_t, P_yy)`` over observed components, shape ``(...)``.
        cross_cov: ``Cov(x_{t-1}, x_t | y_{1:t-1})`` from the prediction (``x_{-1}`` is the prior),
            which the RTS smoother needs, shape ``(..., T, n, n)``.
    """

    mean: Tensor
    cov: Tensor
    predicted_mean: Tensor
    predicted_cov: Tensor
    measurement_mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    observed: Tensor
    log_likelihood: Tensor
    cross_cov: Tensor

    @property
    def path(self) -> str:
        """Which computation produced the result: ``"cubature"`` (sigma points), ``"kalman"``
        (the closed-form recursion of a linear model) or ``"parallel"`` (its associative scan)."""
        return "cubature"


class KalmanFilterResult(FilterResult):
    """A :class:`FilterResult` computed by the closed-form Kalman recursion (``path ==
    "kalman"``). Same fields; a field left out with ``outputs=`` is an empty tensor."""

    __slots__ = ()

    @property
    def path(self) -> str:
        return "kalman"


class ParallelFilterResult(FilterResult):
    """A :class:`FilterResult` computed by the parallel-in-time (associative scan) Kalman filter
    (``path == "parallel"``)."""

    __slots__ = ()

    @property
    def path(self) -> str:
        return "parallel"


class SmootherResult(NamedTuple):
    """Output of a Rauch-Tung-Striebel smoother.

    Attributes:
        mean: smoothed means ``E[x_t | y_{1:T}]``, shape ``(..., T, n)``.
        cov: smoothed covariances, shape ``(..., T, n, n)``.
        gain: smoother gains ``G_t``, ``t = 0..T-2``, shape ``(..., T-1, n, n)``.
        filtered: the forward pass.
    """

    mean: Tensor
    cov: Tensor
    gain: Tensor
    filtered: FilterResult

    @property
    def path(self) -> str:
        """The path of the forward pass (see :attr:`FilterResult.path`)."""
        return self.filtered.path
