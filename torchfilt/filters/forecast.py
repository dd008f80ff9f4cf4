"""Prediction ahead: free-run simulation and k-step-ahead prediction of the state and the output.

The call a system-identification user evaluates a model with. Both functions filter the recording
with the filter's own engine (the exact Kalman filter for a linear model, the cubature filter
otherwise) and then propagate the filtered beliefs with the filter's own prediction step, without
measurements:

* :func:`free_run` filters the first ``burn_in`` measurements and then predicts every later step
  from them alone: a simulation of the model driven by ``u``, started from what the burn-in
  measurements say.
* :func:`k_step_ahead` gives, for every time ``t``, the prediction of ``x_t`` and ``y_t`` from the
  measurements up to ``t - k``: each filtered belief is propagated ``k`` prediction steps, all
  ``t`` at once.

Input convention (:mod:`torchfilt.filters`): the step that predicts ``x_t`` from ``x_{t-1}``
takes the input row ``u[..., t, :]``, and so does the output ``y_t``. A linear model takes the closed form (``A x + B u``, ``A P A^T + Q``,
``H x + D u``, ``H P H^T + R``); any other model the cubature prediction of
:func:`~torchfilt.filters.predict` and the cubature measurement mapping of
:func:`~torchfilt.filters.update` (with no component observed), with the filter's rule.
"""

from __future__ import annotations

from torch import Tensor

from torchfilt.cubature import CubatureRule
from torchfilt.filters.forecast_core import Forecast, free_run_with, k_step_ahead_with
from torchfilt.filters.gaussian import GaussianFilter
from torchfilt.filters.plan import Path
from torchfilt.filters.steps import PointVariance
from torchfilt.models import StateSpaceModel

__all__ = ["Forecast", "free_run", "k_step_ahead"]


def _filter_of(
    model: StateSpaceModel, rule: CubatureRule | None, point_variance: PointVariance
) -> GaussianFilter:
    return GaussianFilter(model, rule, point_variance=point_variance)


def free_run(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    burn_in: int = 0,
    mask: Tensor | None = None,
    rule: CubatureRule | None = None,
    point_variance: PointVariance = "total",
    path: Path = "auto",
) -> Forecast:
    """Free-run simulation after a burn-in: filter ``y[..., :burn_in, :]``, then predict the
    rest of the recording from those measurements alone, driven by ``u``.

    Step ``t < burn_in`` of the result is the filtered belief ``p(x_t | y_{0:t})`` and step
    ``t >= burn_in`` the prediction ``p(x_t | y_{0:burn_in-1})`` (with ``burn_in = 0`` a pure
    simulation from the prior ``N(x0, P0)``, the belief about ``x_{-1}``); the output moments
    are those of ``y_t`` under that belief. The measurements after the burn-in are not used (they
    only fix ``T``: to predict past the data, pad ``y`` with NaN and give ``u`` for those steps).
    Input convention (:mod:`torchfilt.filters`): the step that predicts ``x_t`` from ``x_{t-1}``
    takes the input row ``u[..., t, :]``, and so does the output ``y_t``.

    Args:
        model: the state-space model (linear: the exact Kalman path; else the cubature rule).
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``, the belief about ``x_{-1}``.
        P0: prior covariance ``(..., n, n)``.
        burn_in: how many leading measurements are filtered, ``0 <= burn_in <= T``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
        rule: cubature rule of a nonlinear model; default third-degree spherical-radial (CKF).
        point_variance: ``"total"`` or ``"mean"``, as in :class:`~torchfilt.filters.GaussianFilter`.
        path: ``"auto"`` (exact for a linear model), ``"kalman"`` or ``"cubature"``.

    Returns:
        A :class:`Forecast` with state moments ``(..., T, n)``, ``(..., T, n, n)`` and output
        moments ``(..., T, m)``, ``(..., T, m, m)`` (with and without ``R``).

    Raises:
        InputError: ``burn_in`` negative or over ``T``; bad ``x0``, ``P0``, ``u`` or ``path``.
        InputTypeError: ``burn_in`` is not an integer, or ``model`` not a model.
        ShapeError: shapes that do not fit the model or each other.
        ModelError: ``path="kalman"`` for a model that is not linear.

    Example:
        >>> import torch, torchfilt
        >>> from torchfilt.filters import free_run
        >>> model = torchfilt.LinearGaussianModel(
        ...     A=0.9 * torch.eye(1), H=torch.eye(1), Q=0.1 * torch.eye(1), R=torch.eye(1))
        >>> y = torch.randn(100, 1)
        >>> sim = free_run(model, y, x0=torch.zeros(1), P0=torch.eye(1), burn_in=20)
        >>> sim.output_mean.shape, sim.output_cov.shape
        (torch.Size([100, 1]), torch.Size([100, 1, 1]))
    """
    filt = _filter_of(model, rule, point_variance)
    return free_run_with(filt, y, u, x0=x0, P0=P0, burn_in=burn_in, mask=mask, path=path)


def k_step_ahead(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    horizon: int,
    mask: Tensor | None = None,
    rule: CubatureRule | None = None,
    point_variance: PointVariance = "total",
    path: Path = "auto",
) -> Forecast:
    """``k``-step-ahead prediction: for every time ``t``, the prediction of ``x_t`` and ``y_t``
    from the measurements up to ``t - k``.

    The result is aligned with the data: step ``t`` holds ``p(x_t | y_{0:t-k})`` and the moments
    of ``y_t`` under it, so ``y - output_mean`` is the ``k``-step prediction error. ``k = 0`` is
    the filtered belief mapped to the output, ``k = 1`` the filter's one-step prediction; a step
    ``t < k`` is conditioned on no measurement (the prior ``N(x0, P0)``, the belief about
    ``x_{-1}``, predicted ``t + 1`` steps). The recording is filtered once and every filtered
    belief propagated ``k`` steps, all times at once. Input convention
    (:mod:`torchfilt.filters`): the step that predicts ``x_t`` from ``x_{t-1}`` takes the input
    row ``u[..., t, :]``, and so does the output ``y_t``.

    Args:
        model: the state-space model (linear: the exact Kalman path; else the cubature rule).
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``, the belief about ``x_{-1}``.
        P0: prior covariance ``(..., n, n)``.
        horizon: ``k >= 0``, the number of prediction steps ahead.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
        rule: cubature rule of a nonlinear model; default third-degree spherical-radial (CKF).
        point_variance: ``"total"`` or ``"mean"``, as in :class:`~torchfilt.filters.GaussianFilter`.
        path: ``"auto"`` (exact for a linear model), ``"kalman"`` or ``"cubature"``.

    Returns:
        A :class:`Forecast` with state moments ``(..., T, n)``, ``(..., T, n, n)`` and output
        moments ``(..., T, m)``, ``(..., T, m, m)`` (with and without ``R``).

    Raises:
        InputError: ``horizon`` negative; bad ``x0``, ``P0``, ``u`` or ``path``.
        InputTypeError: ``horizon`` is not an integer, or ``model`` not a model.
        ShapeError: shapes that do not fit the model or each other.
        ModelError: ``path="kalman"`` for a model that is not linear.

    Example:
        >>> import torch, torchfilt
        >>> from torchfilt.filters import k_step_ahead
        >>> model = torchfilt.LinearGaussianModel(
        ...     A=0.9 * torch.eye(1), H=torch.eye(1), Q=0.1 * torch.eye(1), R=torch.eye(1))
        >>> y = torch.randn(4, 100, 1)
        >>> ahead = k_step_ahead(model, y, x0=torch.zeros(1), P0=torch.eye(1), horizon=5)
        >>> ahead.mean.shape, ahead.output_cov.shape
        (torch.Size([4, 100, 1]), torch.Size([4, 100, 1, 1]))
    """
    filt = _filter_of(model, rule, point_variance)
    return k_step_ahead_with(filt, y, u, x0=x0, P0=P0, horizon=horizon, mask=mask, path=path)
