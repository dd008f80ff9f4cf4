"""Filters and smoothers: the batched cubature Gaussian filter, the exact and parallel-in-time
Kalman filter for linear models, RTS and iterated smoothing, and metrics.

The filter is a scan of two pure steps, :func:`predict` and :func:`update` (and, for the
constrained CKF, :func:`constrained_predict` and :func:`constrained_update`), over a
:class:`Belief`; :class:`GaussianFilter` binds a model and options to them. How a run executes
(exact Kalman or cubature; eager, compiled or graphed; which exact runner) is decided in one place,
:func:`torchfilt.filters.plan.plan`, and carried out by the engines of
:mod:`torchfilt.filters.engine`, which run any step of its ``Step`` protocol.
:func:`free_run` and :func:`k_step_ahead` predict ahead (a :class:`Forecast` of the state and the
output).

Input convention (every filter, smoother, fit and prediction of torchfilt follows it, and every
docstring that mentions input rows refers here): step ``t`` predicts ``x_t`` from ``x_{t-1}``
with the input row ``u[..., t, :]`` and updates with ``y[..., t, :]``, passing the same row to
the measurement::

    x_t = f(x_{t-1}, u_t) + w_t,   y_t = h(x_t, u_t) + v_t,   u_t = u[..., t, :]

The prior ``N(x0, P0)`` is the belief about ``x_{-1}``, the state before the first step. In a log
whose row 0 is the prior's time (states ``x[0..T]``), input row ``k`` drives the step from row
``k`` to row ``k + 1``: filter it with ``y = measurements[1:]`` and ``u = inputs[:-1]``; the GP
transition pairs ``(x[k], u[k]) -> x[k+1]`` of :func:`torchfilt.models.gp.data.transition_pairs`
are that pairing.

Every name exported here is for users. The engines' own types (``Step``, ``OnlineStep``, the
engines, ``ExecutionPlan``, ``TraceFailure``, ``CubatureStep``) stay in
:mod:`torchfilt.filters.engine`, :mod:`torchfilt.filters.plan` and
:mod:`torchfilt.filters.cubature_step`, with the records only their ``Step`` protocol passes
(:class:`torchfilt.filters.results.StepRecord`, :class:`torchfilt.filters.inputs.FilterInputs`):
a user who writes a step of their own imports them from there.
"""

import importlib
import warnings
from typing import Any

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


#: Engine records once exported here (deprecated here; remove in the next release): their
#: modules.
_ENGINE_RECORDS = {
    "FilterInputs": "torchfilt.filters.inputs",
    "StepRecord": "torchfilt.filters.results",
}


def __getattr__(name: str) -> Any:
    """The deprecated names of :data:`_ENGINE_RECORDS`, with a ``DeprecationWarning``."""
    if name in _ENGINE_RECORDS:
        module = _ENGINE_RECORDS[name]
        warnings.warn(
            f"torchfilt.filters.{name} is deprecated (a record of the engines' Step protocol); "
            f"use {module}.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(module), name)
    raise AttributeError(f"module 'torchfilt.filters' has no attribute {name!r}")
