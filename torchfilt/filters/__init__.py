"""Filters and smoothers: the batched cubature Gaussian filter, the exact and parallel-in-time
Kalman filter for linear models, RTS and iterated smoothing, and metrics."""

from torchfilt.filters.constrained import ConstrainedCKF, ConstrainedInfo
from torchfilt.filters.gaussian import CKF, GaussianFilter
from torchfilt.filters.graphed import GraphedFilter
from torchfilt.filters.iterated import iterated_smoother
from torchfilt.filters.kalman import kalman_filter, kalman_smoother
from torchfilt.filters.metrics import coverage, nees, nis, rmse
from torchfilt.filters.results import (
    FilterResult,
    KalmanFilterResult,
    ParallelFilterResult,
    SmootherResult,
)
from torchfilt.filters.smoother import rts_smooth

__all__ = [
    "CKF",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "FilterResult",
    "GaussianFilter",
    "GraphedFilter",
    "KalmanFilterResult",
    "ParallelFilterResult",
    "SmootherResult",
    "coverage",
    "iterated_smoother",
    "kalman_filter",
    "kalman_smoother",
    "nees",
    "nis",
    "rmse",
    "rts_smooth",
]
