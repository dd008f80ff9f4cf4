"""The machinery of :mod:`torchfilt.filters.forecast`: the prediction step and output map of a
filter laid out with time leading, and the free-run and k-step-ahead recursions over a filter.

The façade methods :meth:`GaussianFilter.free_run <torchfilt.filters.GaussianFilter.free_run>`
and :meth:`GaussianFilter.k_step_ahead <torchfilt.filters.GaussianFilter.k_step_ahead>` call
:func:`free_run_with` and :func:`k_step_ahead_with` with themselves; the model-level functions of
:mod:`torchfilt.filters.forecast` with a filter they build.
"""

from __future__ import annotations

import operator
from collections.abc import Collection
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor

from torchfilt.cubature import CubatureRule
from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.filters import kalman_steps, steps
from torchfilt.filters.cubature_step import CubatureStep
from torchfilt.filters.inputs import FilterInputs, check_inputs
from torchfilt.filters.kalman import noise_steps
from torchfilt.filters.plan import Path, exact_path
from torchfilt.filters.results import FilterResult
from torchfilt.filters.steps import Belief, Noise, PointVariance, UnitPoints
from torchfilt.models import LinearSystem, StateSpaceModel, linear_system
from torchfilt.numerics import symmetrize

__all__ = ["Forecast", "ForecastFilter", "free_run_with", "k_step_ahead_with"]


class Forecast(NamedTuple):
    """Predictive means and covariances of the state and the output over ``T`` steps.

    Which measurements each step is conditioned on is said by the function that returned it
    (:func:`~torchfilt.filters.free_run`, :func:`~torchfilt.filters.k_step_ahead`).

    Attributes:
        mean: predicted state means ``(..., T, n)``.
        cov: predicted state covariances ``(..., T, n, n)``.
        output_mean: predicted output means ``(..., T, m)``.
        output_cov: predicted output covariances ``(..., T, m, m)``, the measurement noise ``R``
            included: the spread of a new measurement ``y_t`` (what a 95% band of the data uses).
        output_cov_noise_free: the same without the additive measurement noise ``R``
            ``(..., T, m, m)``: the spread of the noise-free output (a model's per-point
            measurement variance, e.g. a GP's, stays in).
    """

    mean: Tensor
    cov: Tensor
    output_mean: Tensor
    output_cov: Tensor
    output_cov_noise_free: Tensor


class ForecastFilter(Protocol):
    """What the recursions read of a filter (a :class:`~torchfilt.filters.GaussianFilter`
    satisfies it).

    Attributes:
        model: the state-space model.
        rule: the cubature rule.
        point_variance: ``"total"`` or ``"mean"``.
        redraw: whether the update re-draws its points (the exact path needs it).
    """

    model: StateSpaceModel
    rule: CubatureRule
    point_variance: Any
    redraw: bool

    def filter(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
        path: Path = "auto",
        parallel: bool = False,
        outputs: Collection[str] | None = None,
    ) -> FilterResult:
        """Filter measurements ``y (..., T, m)`` with inputs ``u (..., T, nu)`` from the prior
        ``x0 (..., n)``, ``P0 (..., n, n)`` (``mask (..., T, m)``)."""
        ...


def _mv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` for ``M (..., a, b)``, ``v (..., b)``, batch dimensions broadcast."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _time_leading(x: Tensor, event: int, batch: int) -> Tensor:
    """``x (*b, T, *event)`` as ``(T, 1.., *b, *event)`` with ``batch`` batch dimensions."""
    x = x.movedim(-event - 1, 0)
    missing = batch - (x.dim() - 1 - event)
    return x.reshape(x.shape[0], *[1] * missing, *x.shape[1:])


class _Propagator:
    """The prediction step and the output map of one filter, in a time-leading layout.

    Beliefs are ``(T', *batch, n)``: the leading axis is time (or the forecast origin), so that a
    model's own batch dimensions broadcast as in an ordinary step. ``u``, ``Q`` and ``R`` are laid
    out likewise, ``(T, *b, d)`` and ``(T, *b, d, d)``.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        rule: CubatureRule,
        point_variance: PointVariance,
        exact: bool,
        inputs: FilterInputs,
    ) -> None:
        self.model = model
        self.rule = rule
        self.point_variance = point_variance
        like = inputs.x0
        T = inputs.y.shape[-2]
        n, m = model.state_dim, model.obs_dim
        b = len(inputs.batch)
        self.Q = _time_leading(noise_steps(model.transition, "Q", T, n, like), 2, b)
        self.R = _time_leading(noise_steps(model.measurement, "R", T, m, like), 2, b)
        self.u = None if inputs.u is None else _time_leading(inputs.u, 1, b)
        self.system = _checked_system(model, inputs.u, like) if exact else None
        self.points: UnitPoints | None = None
        if not exact:
            self.points = steps.unit_points(rule, n, like)

    def _u(self, t: Tensor) -> Tensor | None:
        return None if self.u is None else self.u.index_select(0, t)

    def predict(self, belief: Belief, t: Tensor) -> Belief:
        """The belief about ``x_t`` from the one about ``x_{t-1}``, for each row's ``t``
        (``t (T',)`` indexes the time axis of ``belief``, ``(T', *batch, n)``)."""
        u, Q = self._u(t), self.Q.index_select(0, t)
        if self.system is not None:
            A, B = self.system.A, self.system.B
            c = None if B is None or u is None else _mv(B, u)
            exact, _ = kalman_steps.predict(kalman_steps.Belief(belief.mean, belief.cov), A, c, Q)
            return Belief(exact.mean, exact.cov)
        assert self.points is not None
        pred, _ = steps.predict(
            Belief(belief.mean, belief.cov),
            self.model,
            u,
            self.points,
            point_variance=self.point_variance,
            noise=Noise(Q),
        )
        return Belief(pred.mean, pred.cov)

    def output(self, belief: Belief, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The output's mean ``(T', *batch, m)``, covariance with ``R`` and without it
        ``(T', *batch, m, m)`` for the beliefs about ``x_t``."""
        u, R = self._u(t), self.R.index_select(0, t)
        if self.system is not None:
            H, D = self.system.H, self.system.D
            y_mean = _mv(H, belief.mean)
            if D is not None and u is not None:
                y_mean = y_mean + _mv(D, u)
            free = symmetrize(H @ belief.cov @ H.mT)
            return y_mean, free + R, free
        assert self.points is not None
        m = self.model.obs_dim
        zeros = belief.mean.new_zeros(*belief.mean.shape[:-1], m)
        _, stats = steps.update(
            Belief(belief.mean, belief.cov),
            zeros,
            torch.zeros(zeros.shape, dtype=torch.bool, device=zeros.device),
            self.model,
            self.points,
            u=u,
            point_variance=self.point_variance,
            noise=Noise(R),
        )
        return stats.measurement_mean, stats.innovation_cov, stats.innovation_cov - R


def _checked_system(model: StateSpaceModel, u: Tensor | None, like: Tensor) -> LinearSystem:
    """The model's matrices in ``like``'s dtype and device, with the inputs they need checked."""
    system = linear_system(model)
    assert system is not None
    out: list[Tensor | None] = []
    for name, M in zip("AHBD", system, strict=True):
        if M is None:
            out.append(None)
            continue
        M = M.to(dtype=like.dtype, device=like.device)
        if name in "BD":
            if u is None:
                raise InputError("u: the model has an input matrix (B or D); pass the inputs u")
            if M.shape[-1] != u.shape[-1]:
                raise ShapeError(
                    f"u: expected shape (..., T, nu) with nu = {M.shape[-1]} for the model's "
                    f"input matrix {name}, got {tuple(u.shape)}"
                )
        out.append(M)
    return LinearSystem(*out)  # type: ignore[arg-type]


def _count(name: str, value: object, upper: int | None = None) -> int:
    """A non-negative integer argument (at most ``upper``), or an error naming it."""
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise InputTypeError(f"{name} must be an integer, got {type(value).__name__}")
    count = operator.index(value)  # type: ignore[call-overload]
    if count < 0:
        raise InputError(f"{name} must be at least 0, got {count}")
    if upper is not None and count > upper:
        raise InputError(
            f"{name} must be at most T = {upper} (the recording's length), got {count}"
        )
    return int(count)


def _filtered(
    filt: ForecastFilter,
    y: Tensor,
    u: Tensor | None,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None,
    path: Path,
    T: int,
) -> tuple[Tensor, Tensor]:
    """Filtered means ``(T, *batch, n)`` and covariances ``(T, *batch, n, n)`` of the first
    ``T`` steps."""
    ys = y[..., :T, :]
    us = None if u is None else u[..., :T, :]
    ms = None if mask is None else torch.as_tensor(mask)[..., :T, :]
    res = filt.filter(ys, us, x0=x0, P0=P0, mask=ms, path=path, outputs=("mean", "cov"))
    return res.mean.movedim(-2, 0), res.cov.movedim(-3, 0)


def _result(prop: _Propagator, mean: Tensor, cov: Tensor) -> Forecast:
    """Map the time-leading beliefs about ``x_0 .. x_{T-1}`` to the output and lay out a
    :class:`Forecast` with time at ``-2`` / ``-3``."""
    t = torch.arange(mean.shape[0], device=mean.device)
    y_mean, y_cov, y_free = prop.output(Belief(mean, cov), t)
    return Forecast(
        mean.movedim(0, -2),
        cov.movedim(0, -3),
        y_mean.movedim(0, -2),
        y_cov.movedim(0, -3),
        y_free.movedim(0, -3),
    )


def _setup(
    filt: ForecastFilter,
    y: Tensor,
    u: Tensor | None,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None,
    path: Path,
) -> tuple[FilterInputs, _Propagator]:
    """Check a recording and bind the prediction step of ``filt``'s path.

    Raises:
        InputError: bad ``x0``, ``P0``, ``u`` or ``path``.
        ShapeError: shapes that do not fit the model or each other.
        ModelError: ``path="kalman"`` for a model that is not linear.
    """
    inputs = check_inputs(filt.model, y, u, x0, P0, mask)
    exact = exact_path(filt.model, path=path, parallel=False, redraw=filt.redraw)
    prop = _Propagator(filt.model, filt.rule, filt.point_variance, exact, inputs)
    return inputs, prop


def _forecast_filter(filt: ForecastFilter) -> ForecastFilter:
    """``filt``, refused where its step is not the cubature step (whose prediction this uses).

    Raises:
        ModelError: a filter with a step of its own (the constrained CKF's).
    """
    if not isinstance(getattr(filt, "_step", None), CubatureStep):
        raise ModelError(
            f"{type(filt).__name__}: prediction ahead propagates beliefs with the cubature "
            "prediction step; this filter's step is its own (a constrained filter's bounds are "
            "not applied there)"
        )
    return filt


def free_run_with(
    filt: ForecastFilter,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    burn_in: int = 0,
    mask: Tensor | None = None,
    path: Path = "auto",
) -> Forecast:
    """:func:`~torchfilt.filters.free_run` with a filter's options (its rule, point variance, square-root form for
    the burn-in); :meth:`ForecastFilter.free_run <torchfilt.filters.ForecastFilter.free_run>`.

    Args:
        filt: the filter.
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``.
        P0: prior covariance ``(..., n, n)``.
        burn_in: how many leading measurements are filtered.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
        path: ``"auto"``, ``"kalman"`` or ``"cubature"``.

    Returns:
        The :class:`Forecast`, as :func:`~torchfilt.filters.free_run`.

    Raises:
        InputError: ``burn_in`` negative or over ``T``; bad ``x0``, ``P0``, ``u`` or ``path``.
        InputTypeError: ``burn_in`` is not an integer.
        ShapeError: shapes that do not fit the model or each other.
        ModelError: a filter with its own prediction step (constrained), or ``path="kalman"``
            for a model that is not linear.
    """
    filt = _forecast_filter(filt)
    inputs, prop = _setup(filt, y, u, x0, P0, mask, path)
    T = inputs.y.shape[-2]
    burn_in = _count("burn_in", burn_in, T)
    batch, n = inputs.batch, filt.model.state_dim
    means: list[Tensor] = []
    covs: list[Tensor] = []
    belief = Belief(inputs.x0, inputs.P0)
    if burn_in > 0:
        m_f, P_f = _filtered(filt, y, u, x0, P0, mask, path, burn_in)
        means = list(m_f.expand(burn_in, *batch, n).unbind(0))
        covs = list(P_f.expand(burn_in, *batch, n, n).unbind(0))
        belief = Belief(means[-1], covs[-1])
    for t in range(burn_in, T):
        index = torch.tensor([t], device=inputs.x0.device)
        b = prop.predict(Belief(belief.mean.unsqueeze(0), belief.cov.unsqueeze(0)), index)
        belief = Belief(b.mean.squeeze(0), b.cov.squeeze(0))
        means.append(belief.mean.expand(*batch, n))
        covs.append(belief.cov.expand(*batch, n, n))
    return _result(prop, torch.stack(means), torch.stack(covs))


def k_step_ahead_with(
    filt: ForecastFilter,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    horizon: int,
    mask: Tensor | None = None,
    path: Path = "auto",
) -> Forecast:
    """:func:`~torchfilt.filters.k_step_ahead` with a filter's options;
    :meth:`ForecastFilter.k_step_ahead <torchfilt.filters.ForecastFilter.k_step_ahead>`.

    Args:
        filt: the filter.
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``.
        P0: prior covariance ``(..., n, n)``.
        horizon: ``k``, the number of prediction steps ahead.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
        path: ``"auto"``, ``"kalman"`` or ``"cubature"``.

    Returns:
        The :class:`Forecast`, as :func:`~torchfilt.filters.k_step_ahead`.

    Raises:
        InputError: ``horizon`` negative; bad ``x0``, ``P0``, ``u`` or ``path``.
        InputTypeError: ``horizon`` is not an integer.
        ShapeError: shapes that do not fit the model or each other.
        ModelError: a filter with its own prediction step (constrained), or ``path="kalman"``
            for a model that is not linear.
    """
    filt = _forecast_filter(filt)
    k = _count("horizon", horizon)
    inputs, prop = _setup(filt, y, u, x0, P0, mask, path)
    T = inputs.y.shape[-2]
    batch, n = inputs.batch, filt.model.state_dim
    device = inputs.x0.device
    target = torch.arange(T, device=device)
    origin = target - k  # the last measurement each prediction is conditioned on
    prior = origin < 0  # conditioned on none: start from the prior, the belief about x_{-1}
    m_f = inputs.x0.expand(T, *batch, n)
    P_f = inputs.P0.expand(T, *batch, n, n)
    if not bool(prior.all()):
        means, covs = _filtered(filt, y, u, x0, P0, mask, path, T - k)
        start = origin.clamp_min(0)
        m_f = torch.where(prior.view(T, *[1] * (len(batch) + 1)), m_f, means.index_select(0, start))
        P_f = torch.where(prior.view(T, *[1] * (len(batch) + 2)), P_f, covs.index_select(0, start))
    mean, cov = m_f, P_f
    for j in range(1, k + 1):
        t = origin + j  # the time each row predicts at this step
        active = t >= 0  # a row started from the prior skips the steps before time 0
        pred = prop.predict(Belief(mean, cov), t.clamp_min(0))
        pm = pred.mean.expand(T, *batch, n)
        pc = pred.cov.expand(T, *batch, n, n)
        mean = torch.where(active.view(T, *[1] * (len(batch) + 1)), pm, mean)
        cov = torch.where(active.view(T, *[1] * (len(batch) + 2)), pc, cov)
    return _result(prop, mean, cov)
