"""Filters and smoothers: the batched cubature Gaussian filter, the exact and parallel-in-time
Kalman filter for linear models, RTS and iterated smoothing, and metrics.

The filter is a scan of two pure steps, :func:`predict` and :func:`update` (and, for the
constrained CKF, :func:`constrained_predict` and :func:`constrained_update`), over a
:class:`Belief`; :class:`GaussianFilter` binds a model and options to them. How a run executes
(exact Kalman or cubature; eager, compiled or graphed; which exact runner) is decided in one place,
:func:`torchfilt.filters.plan.plan`, and carried out by the engines of
:mod:`torchfilt.filters.engine`, which run any step of its ``Step`` protocol.
"""

from torchfilt.filters.constrained import (
    ConstrainedCKF,
    ConstrainedInfo,
    SolverInfo,
    constrained_predict,
    constrained_update,
)
from torchfilt.filters.forecast import Forecast, free_run, k_step_ahead
from torchfilt.filters.gaussian import CKF, FilterState, GaussianFilter
from torchfilt.filters.graphed import GraphedFilter
from torchfilt.filters.inputs import FilterInputs
from torchfilt.filters.iterated import iterated_smoother
from torchfilt.filters.kalman import kalman_filter, kalman_smoother
from torchfilt.filters.metrics import coverage, nees, nis, rmse
from torchfilt.filters.results import (
    FilterResult,
    KalmanFilterResult,
    ParallelFilterResult,
    SmootherResult,
    StepRecord,
)
from torchfilt.filters.smoother import rts_smooth
from torchfilt.filters.steps import (
    Belief,
    Noise,
    PredictCache,
    UnitPoints,
    UpdateStats,
    predict,
    update,
)

__all__ = [
    "CKF",
    "Belief",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "FilterInputs",
    "FilterResult",
    "FilterState",
    "Forecast",
    "GaussianFilter",
    "GraphedFilter",
    "KalmanFilterResult",
    "Noise",
    "ParallelFilterResult",
    "PredictCache",
    "SmootherResult",
    "SolverInfo",
    "StepRecord",
    "UnitPoints",
    "UpdateStats",
    "constrained_predict",
    "constrained_update",
    "coverage",
    "free_run",
    "iterated_smoother",
    "k_step_ahead",
    "kalman_filter",
    "kalman_smoother",
    "nees",
    "nis",
    "predict",
    "rmse",
    "rts_smooth",
    "update",
]
