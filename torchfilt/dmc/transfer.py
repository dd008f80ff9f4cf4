"""Transfer-function entries with dead time and their exactly sampled step responses.

Two entry types cover the process-control models DMC is built from:

    first order plus dead time (FOPDT):        G(s) = K e^{-theta s} / (tau s + 1)
    integrating plus dead time (IPDT):         G(s) = K e^{-theta s} / (s (tau s + 1))

A step applied at ``t = 0`` through a zero-order hold is piecewise constant, so the sampled step
response of the zero-order-hold discretisation equals the continuous step response at the sampling
instants: ``S_i = s(i T)``. The closed forms below are evaluated at ``t = i T`` directly, which is exact
for any dead time, including dead times that are not multiples of ``T`` (no Pade or Thiran
approximation, no rounding of ``theta`` to whole samples). With ``t' = max(t - theta, 0)``:

    FOPDT:  s(t) = K (1 - exp(-t'/tau))                       (tau > 0)
            s(t) = K * [t >= theta]                           (tau = 0, pure gain and delay)
    IPDT:   s(t) = K (t' - tau (1 - exp(-t'/tau)))            (tau > 0)
            s(t) = K t'                                       (tau = 0)

``1 - exp(-x)`` is evaluated as ``-expm1(-x)`` to keep full relative precision for small ``x``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError

__all__ = ["FOPDT", "IPDT", "TransferEntry", "as_entry"]


def _check_number(value: float, name: str, *, nonneg: bool) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputTypeError(f"{name} must be a real number, got {type(value).__name__}") from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {v}")
    if nonneg and v < 0:
        raise InputError(f"{name} must be non-negative, got {v}")
    return v


def _positive_int(value: object, name: str) -> int:
    """``value`` as an ``int >= 1`` (an integral float or a 0-d tensor is accepted).

    Raises:
        InputError: naming ``name``, for anything else (a fraction, NaN, a string, ``< 1``).
    """
    v = math.nan
    if not isinstance(value, str | bytes | bool):
        try:
            v = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError, RuntimeError):
            pass
    if not (math.isfinite(v) and v.is_integer() and v >= 1):
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(v)


@dataclass(frozen=True)
class FOPDT:
    """First-order-plus-dead-time entry ``K e^{-theta s} / (tau s + 1)``.

    Args:
        K: steady-state gain.
        tau: time constant (``>= 0``; ``0`` is a pure gain with dead time).
        theta: dead time (``>= 0``), any real value, not only multiples of the sampling period.

    Raises:
        InputTypeError: a parameter that is not a real number.
        InputError: a parameter that is not finite, a negative ``tau`` or ``theta``, or
            ``tau = theta = 0`` with ``K != 0`` (a direct feed-through, not strictly proper).
    """

    K: float
    tau: float
    theta: float = 0.0

    integrating = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _check_number(self.K, "K", nonneg=False))
        object.__setattr__(self, "tau", _check_number(self.tau, "tau (time constant)", nonneg=True))
        object.__setattr__(
            self, "theta", _check_number(self.theta, "theta (dead time)", nonneg=True)
        )
        if self.tau == 0.0 and self.theta == 0.0 and self.K != 0.0:
            raise InputError(
                "FOPDT: tau = 0 with theta = 0 is a direct feed-through K; a step-response "
                "(DMC) model needs every channel to be strictly proper (S_0 = 0)"
            )

    def step(self, t: Tensor) -> Tensor:
        """Continuous step response ``s(t)``.

        Args:
            t: times, any shape.

        Returns:
            ``s(t)``, of ``t``'s shape (any shape) and dtype.
        """
        tp = (t - self.theta).clamp_min(0.0)
        if self.tau == 0.0:
            return torch.where(t >= self.theta, torch.full_like(t, self.K), torch.zeros_like(t))
        return -self.K * torch.expm1(-tp / self.tau)


@dataclass(frozen=True)
class IPDT:
    """Integrating-plus-dead-time entry ``K e^{-theta s} / (s (tau s + 1))``.

    Args:
        K: integrating gain (slope of the step response once settled, per unit time).
        tau: time constant of the lag (``>= 0``; ``0`` is a pure integrator with dead time).
        theta: dead time (``>= 0``), any real value.

    Raises:
        InputTypeError: a parameter that is not a real number.
        InputError: a parameter that is not finite, or a negative ``tau`` or ``theta``.
    """

    K: float
    tau: float = 0.0
    theta: float = 0.0

    integrating = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _check_number(self.K, "K", nonneg=False))
        object.__setattr__(self, "tau", _check_number(self.tau, "tau (time constant)", nonneg=True))
        object.__setattr__(
            self, "theta", _check_number(self.theta, "theta (dead time)", nonneg=True)
        )

    def step(self, t: Tensor) -> Tensor:
        """Continuous step response ``s(t)``.

        Args:
            t: times, any shape.

        Returns:
            ``s(t)``, of ``t``'s shape (any shape) and dtype.
        """
        tp = (t - self.theta).clamp_min(0.0)
        if self.tau == 0.0:
            return self.K * tp
        return self.K * (tp + self.tau * torch.expm1(-tp / self.tau))


TransferEntry = FOPDT | IPDT


def as_entry(value: object, name: str) -> TransferEntry | None:
    """Accept an entry, ``None`` or ``0`` (no coupling); anything else is an :class:`~torchfilt.exceptions.InputTypeError`."""
    if value is None:
        return None
    if isinstance(value, FOPDT | IPDT):
        return value
    if isinstance(value, int | float) and not isinstance(value, bool) and value == 0:
        return None
    raise InputTypeError(
        f"{name} must be an FOPDT, an IPDT, or None/0 for no coupling; got {value!r}"
    )
