"""Models built from plain torch callables, and the state-space composition."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import (
    ConditionalModel,
    Prediction,
    TimeVarying,
    check_noise,
    check_output,
)
from torchfilt.models.params import CovarianceParameter

__all__ = ["FunctionModel", "StateSpaceModel", "as_conditional", "check_output"]

Fn = Callable[..., Tensor]


def _positional_arity(fn: Fn) -> int:
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return 2
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    if any(p.kind == inspect.Parameter.VAR_POSITIONAL for p in params):
        return 2
    return sum(1 for p in params if p.kind in kinds)


Noise = Tensor | TimeVarying | CovarianceParameter


class _NoiseMixin:
    """Stores a constant ``(..., d, d)`` or :class:`TimeVarying` noise as a buffer, or a learnable
    :class:`~torchfilt.models.params.CovarianceParameter` as a submodule."""

    noise_param: CovarianceParameter | None

    def _set_noise(self, noise: Noise | None) -> None:
        self._tv = isinstance(noise, TimeVarying)
        if isinstance(noise, CovarianceParameter):
            self.noise_param = noise  # a submodule: its parameters are the model's
            self.register_buffer("_noise", None)  # type: ignore[attr-defined]
            return
        self.noise_param = None
        value = noise.values if isinstance(noise, TimeVarying) else noise
        self.register_buffer("_noise", value)  # type: ignore[attr-defined]

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        """Additive noise covariance at ``step``.

        Args:
            step: the step (0-based) of a time-varying noise; ``None`` for a constant one.

        Returns:
            The covariance, shape ``(..., d, d)``, or ``None`` for no additive noise.

        Raises:
            InputError: the noise is time-varying and ``step`` is ``None``.
        """
        if self.noise_param is not None:
            return self.noise_param()
        noise: Tensor | None = self._noise  # type: ignore[attr-defined]
        if noise is None or not self._tv:
            return noise
        if step is None:
            raise InputError("this model's noise is time-varying; a step index is required")
        return TimeVarying(noise)(step)

    @property
    def time_varying_noise(self) -> bool:
        return bool(self._tv)

    def _noise_dim(self) -> int | None:
        if self.noise_param is not None:
            return int(self.noise_param.dim)
        noise: Tensor | None = self._noise  # type: ignore[attr-defined]
        return None if noise is None else int(noise.shape[-1])


class FunctionModel(_NoiseMixin, ConditionalModel):
    """A deterministic torch callable plus additive Gaussian noise.

    Args:
        fn: ``fn(x, u)`` mapping ``(..., n)`` (and ``(..., nu)`` or ``None``) to ``(..., d)``. A
            callable of one argument, ``fn(x)``, is accepted too. It must broadcast over leading
            dimensions (use ``x[..., i]``, not ``x[i]``).
        noise: additive covariance, ``(..., d, d)`` constant, :class:`TimeVarying` ``(..., T, d, d)``,
            or a learnable :class:`~torchfilt.models.params.CovarianceParameter`.
        out_dim: output dimension; taken from ``noise`` when omitted.
        in_dim: input (state) dimension, if known, for shape checks.
        name: name used in error messages (``"transition"``, ``"measurement"``).
        noise_name: name of the noise argument in error messages (``"Q"``, ``"R"``).

    Raises:
        InputError: ``fn`` is not callable, ``noise`` is not a valid covariance, or neither
            ``out_dim`` nor ``noise`` gives the output size.
        ShapeError: ``noise`` is not ``(..., d, d)``, or its size is not ``out_dim``.
    """

    def __init__(
        self,
        fn: Fn,
        noise: Noise | None = None,
        *,
        out_dim: int | None = None,
        in_dim: int | None = None,
        name: str = "function",
        noise_name: str | None = None,
    ) -> None:
        super().__init__()
        if not callable(fn):
            raise InputError(
                f"{name} must be callable or a ConditionalModel, got {type(fn).__name__}"
            )
        self.name = name
        self._set_noise(check_noise(noise, noise_name or f"{name} noise"))
        nd = self._noise_dim()
        if out_dim is None:
            if nd is None:
                raise InputError(
                    f"{name}: give out_dim or a noise covariance to fix the output size"
                )
            out_dim = nd
        elif nd is not None and nd != out_dim:
            raise ShapeError(f"{name}: noise is {nd}x{nd} but out_dim is {out_dim}")
        self.out_dim = int(out_dim)
        self.in_dim = in_dim
        self._fn = fn
        self._two_args = _positional_arity(fn) >= 2

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Predictive distribution at points: ``fn``'s value, with no per-point variance.

        Args:
            x: points, shape ``(..., P, n)``.
            u: inputs aligned with the points, shape ``(..., P, nu)``, or ``None``.

        Returns:
            A :class:`Prediction` with mean ``(..., P, d)``.

        Raises:
            ModelError: ``fn`` returned something other than a floating tensor of shape
                ``(..., P, d)``.
        """
        out = self._fn(x, u) if self._two_args else self._fn(x)
        return Prediction(check_output(out, x, self.out_dim, self.name))


class WithNoise(_NoiseMixin, ConditionalModel):
    """Adds an extra noise covariance to another model's own noise."""

    def __init__(self, base: ConditionalModel, noise: Noise, name: str) -> None:
        super().__init__()
        self.base = base
        self._set_noise(check_noise(noise, name))
        if self._noise_dim() != base.out_dim:
            raise ShapeError(
                f"{name} noise is {self._noise_dim()}x{self._noise_dim()} but the model outputs "
                f"{base.out_dim}"
            )
        self.out_dim, self.in_dim = base.out_dim, base.in_dim

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        return self.base.predict(x, u)

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        own = super().noise_cov(step)
        base = self.base.noise_cov(step)
        if base is None:
            return own
        return base if own is None else base + own

    @property
    def time_varying_noise(self) -> bool:
        return bool(self._tv) or self.base.time_varying_noise


def as_conditional(
    obj: ConditionalModel | Fn,
    noise: Noise | None,
    *,
    name: str,
    noise_name: str,
    in_dim: int | None = None,
) -> ConditionalModel:
    """Turn a callable (plus its noise) or a model (plus optional extra noise) into a model.

    Args:
        obj: a :class:`ConditionalModel`, or a callable ``fn(x, u)`` (see :class:`FunctionModel`).
        noise: the callable's additive noise (required), or extra noise added to the model's.
        name: the model's name in error messages (``"transition"``, ``"measurement"``).
        noise_name: the noise argument's name in error messages (``"Q"``, ``"R"``).
        in_dim: input (state) dimension of a callable, if known, for shape checks.

    Returns:
        The model.

    Raises:
        InputError: ``obj`` is a callable and ``noise`` is ``None``, or an invalid argument of
            :class:`FunctionModel`.
    """
    if isinstance(obj, ConditionalModel):
        return obj if noise is None else WithNoise(obj, noise, noise_name)
    if noise is None:
        raise InputError(
            f"{noise_name} is required when {name} is a callable (pass a zero matrix for a "
            "noise-free map)"
        )
    return FunctionModel(obj, noise, in_dim=in_dim, name=name, noise_name=noise_name)


class StateSpaceModel(torch.nn.Module):
    """A nonlinear Gaussian state-space model.

        x_t = f(x_{t-1}, u_t) + w_t,   w ~ N(0, Q + V_f(x, u))
        y_t = h(x_t, u_t) + v_t,       v ~ N(0, R + V_h(x, u))

    ``V_f``, ``V_h`` are the per-point variances a learned (GP) model reports; plain callables have
    none. ``u_t`` is the input row ``u[..., t, :]``, the same row for ``f`` and ``h`` (the input
    convention of :mod:`torchfilt.filters`).

    Args:
        transition: ``f(x, u)``, ``(..., n) -> (..., n)``, or a :class:`ConditionalModel`.
        measurement: ``h(x, u)``, ``(..., n) -> (..., m)``, or a :class:`ConditionalModel`.
        Q: process noise, ``(..., n, n)``, :class:`TimeVarying`, or a learnable
            :class:`~torchfilt.models.params.CovarianceParameter` (see
            :func:`torchfilt.fit_likelihood`); required for a callable transition, optional (extra
            noise) for a model.
        R: measurement noise, ``(..., m, m)`` or :class:`TimeVarying`; likewise.

    Raises:
        ShapeError: the transition does not map ``n`` states to ``n``, the measurement expects
            another state dimension, or a noise of the wrong size.
        InputError: a callable without its noise, or an invalid noise covariance.

    Example:
        >>> import torch, torchfilt
        >>> f = lambda x, u: 0.9 * x
        >>> h = lambda x, u: x[..., :1]
        >>> model = torchfilt.StateSpaceModel(f, h, Q=0.1 * torch.eye(2), R=torch.eye(1))
    """

    def __init__(
        self,
        transition: ConditionalModel | Fn,
        measurement: ConditionalModel | Fn,
        Q: Noise | Any = None,
        R: Noise | Any = None,
    ) -> None:
        super().__init__()
        self.transition = as_conditional(transition, Q, name="transition", noise_name="Q")
        n = self.transition.out_dim
        if self.transition.in_dim is not None and self.transition.in_dim != n:
            raise ShapeError(
                f"transition maps {self.transition.in_dim} states to {n}; it must map n to n"
            )
        self.measurement = as_conditional(
            measurement, R, name="measurement", noise_name="R", in_dim=n
        )
        if self.measurement.in_dim is not None and self.measurement.in_dim != n:
            raise ShapeError(
                f"measurement expects {self.measurement.in_dim} states but the transition has {n}"
            )

    @property
    def state_dim(self) -> int:
        """State dimension ``n``."""
        return int(self.transition.out_dim)

    @property
    def obs_dim(self) -> int:
        """Measurement dimension ``m``."""
        return int(self.measurement.out_dim)
