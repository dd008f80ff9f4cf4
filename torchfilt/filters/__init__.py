"""Filters and smoothers: the batched cubature Gaussian filter, RTS smoothing and metrics."""

from torchfilt.filters.constrained import ConstrainedCKF, ConstrainedInfo
from torchfilt.filters.gaussian import CKF, GaussianFilter
from torchfilt.filters.graphed import GraphedFilter
from torchfilt.filters.metrics import coverage, nees, nis, rmse
from torchfilt.filters.results import FilterResult, SmootherResult
from torchfilt.filters.smoother import rts_smooth

__all__ = [
    "CKF",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "FilterResult",
    "GaussianFilter",
    "GraphedFilter",
    "SmootherResult",
    "coverage",
    "nees",
    "nis",
    "rmse",
    "rts_smooth",
]
