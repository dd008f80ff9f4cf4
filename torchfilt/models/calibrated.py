"""A learned model whose predictive variance is recalibrated: per-output scales and a noise floor.

A GP fitted on one-step pairs reports the one-step scatter of its targets. When the residuals of
the real system drift slowly (autocorrelated), a filter that takes that variance as its ``Q`` or
``R`` is over-confident. :class:`CalibratedModel` rescales the base model's variance per output and
adds a diagonal floor,

    V'(x, u) = D_s^{1/2} V(x, u) D_s^{1/2},    N' = D_s^{1/2} N D_s^{1/2} + diag(f),

with ``s = exp(log_scale)`` and ``f = exp(log_floor)`` (log parametrisations, so both stay
positive under any optimiser step). A lower bound ``s >= s_min`` is kept by projection
(:meth:`CalibratedModel.project_`, after each optimiser step). With ``s_min = 1`` (what
:func:`torchfilt.training.calibrate` uses by default) calibration can only add uncertainty: it never
makes the filter more confident than its learned models say, which matters where a measurement
likelihood cannot see some states. :func:`torchfilt.training.calibrate` fits ``s`` and ``f`` by the
filter's own innovation likelihood.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction

__all__ = ["CalibratedModel"]


def _per_output(value: Tensor | float | list[float], d: int, name: str, like: Tensor) -> Tensor:
    t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if t.dim() == 0:
        t = t.expand(d)
    if t.shape != (d,):
        raise ShapeError(f"{name}: expected a scalar or shape ({d},), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or bool((t <= 0).any()):
        raise InputError(f"{name}: must be finite and positive, got {t.tolist()}")
    return t.clone()


class CalibratedModel(ConditionalModel):
    """Wrap a model with per-output variance scales and an additive diagonal noise floor.

    The mean is the base model's. Its whole variance is rescaled: the per-point variance
    ``var (..., P, d)`` is multiplied by ``s`` (a per-point covariance ``(..., P, d, d)`` and the
    additive noise ``(d, d)`` by ``s_i^{1/2} s_j^{1/2}``), then ``diag(f)`` is added. A GP keeps its
    noise in the per-point variance; an analytic model in its additive noise: the same wrapper
    calibrates both.

    Args:
        base: the model to calibrate.
        scale: initial variance scales ``s``, a scalar or ``(d,)``, at least ``min_scale``
            (default: ``max(1, min_scale)``).
        floor: initial floor ``f``, a scalar or ``(d,)``, positive (default ``1e-9``: none, in
            practice; a zero floor has no log).
        min_scale: lower bound ``s_min >= 0`` of the scales, kept by :meth:`project_`.
        dtype: dtype of the parameters (default float64).

    Attributes:
        log_scale: learnable ``log s``, shape ``(d,)``.
        log_floor: learnable ``log f``, shape ``(d,)``.

    Raises:
        InputError: ``min_scale`` negative or not finite, or ``scale`` / ``floor`` not finite and
            positive, of the wrong size, or a scale below ``min_scale``.
    """

    def __init__(
        self,
        base: ConditionalModel,
        *,
        scale: Tensor | float | list[float] | None = None,
        floor: Tensor | float | list[float] = 1e-9,
        min_scale: float = 0.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if not isinstance(base, ConditionalModel):
            raise InputError(f"base must be a ConditionalModel, got {type(base).__name__}")
        if base.time_varying_noise:
            raise InputError("base: a model with time-varying noise cannot be calibrated here")
        self.base = base
        self.out_dim, self.in_dim = base.out_dim, base.in_dim
        like = torch.zeros((), dtype=dtype)
        d = self.out_dim
        if not (math.isfinite(min_scale) and min_scale >= 0):
            raise InputError(f"min_scale must be finite and non-negative, got {min_scale}")
        self.min_scale = float(min_scale)
        if scale is None:
            scale = max(1.0, min_scale)
        s0 = _per_output(scale, d, "scale", like)
        if bool((s0 < min_scale).any()):
            raise InputError(f"scale: must be at least min_scale = {min_scale}, got {s0.tolist()}")
        self.log_scale = nn.Parameter(s0.log())
        self.log_floor = nn.Parameter(_per_output(floor, d, "floor", like).log())

    @property
    def scale(self) -> Tensor:
        """Variance scales ``s``, shape ``(d,)``."""
        return self.log_scale.exp()

    @torch.no_grad()
    def project_(self) -> None:
        """Clamp the scales to ``s >= min_scale`` in place (call after an optimiser step)."""
        if self.min_scale > 0:
            self.log_scale.clamp_(min=math.log(self.min_scale))

    @property
    def floor(self) -> Tensor:
        """Noise floor ``f``, shape ``(d,)``."""
        return self.log_floor.exp()

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        pred = self.base.predict(x, u)
        s = self.scale.to(pred.mean.dtype)
        var = None if pred.var is None else pred.var * s
        cov = None
        if pred.cov is not None:
            r = s.sqrt()
            cov = pred.cov * (r.unsqueeze(-1) * r)
        return Prediction(pred.mean, var, cov)

    def predict_mean(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        return self.base.predict_mean(x, u)

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        own = torch.diag(self.floor)
        base = self.base.noise_cov(step)
        if base is None:
            return own
        r = self.scale.sqrt()
        return base.to(own) * (r.unsqueeze(-1) * r) + own

    def summary(self) -> dict[str, Any]:
        """``{"scale": s, "floor": f, "min_scale": s_min}`` as plain values."""
        return {
            "scale": self.scale.detach().tolist(),
            "floor": self.floor.detach().tolist(),
            "min_scale": self.min_scale,
        }
