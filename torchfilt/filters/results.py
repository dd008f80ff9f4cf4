"""Result containers of the filters and smoothers (NamedTuples of tensors)."""

from __future__ import annotations

import warnings
from collections.abc import Collection, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import DivergenceWarning, ExecutionError
from torchfilt.settings import NumericsPath

__all__ = [
    "FilterResult",
    "KalmanFilterResult",
    "ParallelFilterResult",
    "RecordSink",
    "SmootherResult",
    "StepRecord",
    "concat_records",
    "stack_records",
    "warn_nonfinite",
]


class FilterResult(NamedTuple):
    """Output of a Gaussian filter over ``T`` steps.

    Input convention (:mod:`torchfilt.filters`): step ``t`` predicts ``x_t`` from ``x_{t-1}``
    with the input row ``u[..., t, :]`` and updates with ``y[..., t, :]``, passing the same row
    to the measurement; the prior ``N(x0, P0)`` is the belief about ``x_{-1}``.

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
        numerics: which numerics path the run took, as
            :func:`torchfilt.filters.plan.plan` decided it (:class:`torchfilt.settings.NumericsPath`:
            eager, compiled or graphed, or the exact runner; small-matrix kernels; jitter or NaN on
            a failed factorisation; why a first choice was left), or ``None`` for a result built
            by hand.
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
    numerics: NumericsPath | None = None

    @property
    def path(self) -> str:
        """Which computation produced the result: ``"cubature"`` (sigma points), ``"kalman"``
        (the closed-form recursion of a linear model) or ``"parallel"`` (its associative scan)."""
        return "cubature"


class StepRecord(NamedTuple):
    """What one filter step contributes to a :class:`FilterResult` (shapes without ``T``).

    Attributes:
        mean: ``(..., n)``. cov: ``(..., n, n)``. predicted_mean: ``(..., n)``.
        predicted_cov: ``(..., n, n)``. measurement_mean: ``(..., m)``. innovation: ``(..., m)``.
        innovation_cov: ``(..., m, m)``. log_likelihood: ``(...)``. cross_cov: ``(..., n, n)``.
    """

    mean: Tensor
    cov: Tensor
    predicted_mean: Tensor
    predicted_cov: Tensor
    measurement_mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    cross_cov: Tensor


#: Where each :class:`StepRecord` field is stacked over time: vectors at -2, matrices at -3.
_TIME_DIM = {
    "mean": -2,
    "cov": -3,
    "predicted_mean": -2,
    "predicted_cov": -3,
    "measurement_mean": -2,
    "innovation": -2,
    "innovation_cov": -3,
    "cross_cov": -3,
}


def stack_records(
    records: Sequence[StepRecord], observed: Tensor, numerics: NumericsPath | None = None
) -> FilterResult:
    """Stack per-step records into a :class:`FilterResult`, field by field (no host sync).

    Args:
        records: one :class:`StepRecord` per step, ``T`` of them.
        observed: bool ``(..., T, m)``, expanded to the run's batch shape.
        numerics: the run's numerics path.
    """
    fields = {
        name: torch.stack([getattr(r, name) for r in records], dim=dim)
        for name, dim in _TIME_DIM.items()
    }
    loglik = torch.stack([r.log_likelihood for r in records], dim=-1).sum(-1)
    return FilterResult(**fields, observed=observed, log_likelihood=loglik, numerics=numerics)


class RecordSink:
    """Collects a filter's per-step records into a :class:`FilterResult`.

    Without autograd recording, the fields are written step by step into tensors allocated once
    (at the first step, ``(..., T, n)`` and ``(..., T, n, n)``), so the peak memory of a run is
    the result plus one step's temporaries, not twice the result as with stacking a list at the
    end; time fields not in ``keep`` are never stored. When the first record carries a graph,
    it keeps the records and stacks them (:func:`stack_records`) so gradients flow. Both give
    the same numbers bit for bit.

    Args:
        steps: the number of steps ``T``.
        keep: the time fields to store (default all); the others become empty tensors.
    """

    def __init__(self, steps: int, keep: Collection[str] | None = None) -> None:
        self.steps = int(steps)
        self.keep = frozenset(_TIME_DIM) if keep is None else frozenset(keep) & set(_TIME_DIM)
        self.records: list[StepRecord] = []
        self.buffers: dict[str, Tensor] = {}
        self.loglik: Tensor | None = None
        self.graph: bool | None = None
        self.count = 0

    def append(self, rec: StepRecord) -> None:
        """Store the record of the next step."""
        t = self.count
        if self.graph is None:
            self.graph = torch.is_grad_enabled() and any(
                isinstance(v, Tensor) and v.requires_grad for v in rec
            )
        if self.graph:
            self.records.append(rec)
        else:
            if t == 0:
                for name, dim in _TIME_DIM.items():
                    v = getattr(rec, name)
                    if name in self.keep:
                        shape = list(v.shape)
                        shape.insert(v.dim() + 1 + dim, self.steps)
                        self.buffers[name] = v.new_empty(shape)
                ll = rec.log_likelihood
                self.loglik = ll.new_empty(*ll.shape, self.steps)
            for name, buf in self.buffers.items():
                buf.select(_TIME_DIM[name], t).copy_(getattr(rec, name))
            assert self.loglik is not None
            self.loglik[..., t] = rec.log_likelihood
        self.count += 1

    def result(self, observed: Tensor, numerics: NumericsPath | None = None) -> FilterResult:
        """The :class:`FilterResult` of all ``T`` steps (fields not kept are empty)."""
        if self.count != self.steps:
            raise ExecutionError(f"RecordSink: {self.count} of {self.steps} steps recorded")
        if self.graph:
            res = stack_records(self.records, observed, numerics)
            empty = res.mean.new_empty(0)
            return res._replace(**{k: empty for k in _TIME_DIM if k not in self.keep})  # type: ignore[arg-type]
        assert self.loglik is not None
        empty = self.loglik.new_empty(0)
        fields = {k: self.buffers.get(k, empty) for k in _TIME_DIM}
        return FilterResult(
            **fields, observed=observed, log_likelihood=self.loglik.sum(-1), numerics=numerics
        )


def concat_records(
    chunks: Sequence[StepRecord], observed: Tensor, numerics: NumericsPath | None = None
) -> FilterResult:
    """Join records of consecutive chunks of steps (fields with a time dimension, the
    log-likelihood ``(..., K)``) into a :class:`FilterResult`, field by field."""
    fields = {
        name: torch.cat([getattr(c, name) for c in chunks], dim=dim)
        for name, dim in _TIME_DIM.items()
    }
    loglik = torch.cat([c.log_likelihood for c in chunks], dim=-1).sum(-1)
    return FilterResult(**fields, observed=observed, log_likelihood=loglik, numerics=numerics)


def warn_nonfinite(res: FilterResult, *, stacklevel: int) -> None:
    """Emit a :class:`DivergenceWarning` if some sequences of ``res`` are non-finite.

    ``stacklevel`` counts from this function (as in :func:`warnings.warn`)."""
    finite = torch.isfinite(res.mean).all(-1).all(-1)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        warnings.warn(
            f"{bad} of {finite.numel()} sequences produced non-finite estimates "
            "(covariance lost definiteness or the model returned non-finite values)",
            DivergenceWarning,
            stacklevel=stacklevel,
        )


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
