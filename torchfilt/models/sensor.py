"""A sensor whose map is known up to a learnable gain and offset per channel.

A datasheet gives the structure of a sensor model (a radar measures the range to a known place)
but rarely its calibration: the range reads ``scale * range + bias`` with a gain and an offset to
be learned. :class:`AffineSensor` wraps a known map ``g`` and learns ``scale_j`` and ``bias_j``:

    y_j = scale_j g_j(x, u) + bias_j + v_j

Such a channel still fixes the gauge of a model learned from measurements alone when ``g_j`` is
*non-linear* in the state: no change of state coordinates turns one hyperbola into another one
scaled and shifted. When ``g_j`` is affine in the state it does not: ``x -> a x + c`` is absorbed
by the gain and the offset, so :func:`~torchfilt.training.check_gauge` refuses a learned gain and
offset on an affine known map.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction
from torchfilt.models.functional import FunctionModel

__all__ = ["AffineSensor"]


class AffineSensor(ConditionalModel):
    """``y_j = scale_j g_j(x, u) + bias_j`` for the calibrated channels ``j``; the others pass
    through.

    Args:
        base: the known map ``g``: a :class:`ConditionalModel` or a callable ``g(x, u)``,
            ``(..., n) -> (..., m)`` (then give ``out_dim``). Its noise, if any, is kept.
        out_dim: ``m`` (a callable ``base`` only).
        channels: the calibrated channels (default: all ``m``).
        scale: initial gains, a float or ``(len(channels),)``; learned as ``log |scale|`` with the
            sign fixed.
        bias: initial offsets, a float or ``(len(channels),)``.
        dtype: parameter dtype.

    Attributes:
        log_scale: ``(c,)``, the log of the gains' magnitudes.
        bias: ``(c,)``, the offsets.

    Raises:
        InputError: a callable ``base`` without ``out_dim``, ``channels`` that are not distinct
            indices in ``0..m-1``, or a zero or non-finite scale or non-finite bias.
        ShapeError: ``scale`` or ``bias`` neither one value nor one per channel.
    """

    sign: Tensor
    index: Tensor

    def __init__(
        self,
        base: ConditionalModel | Callable[..., Tensor],
        *,
        out_dim: int | None = None,
        channels: Sequence[int] | None = None,
        scale: float | Tensor = 1.0,
        bias: float | Tensor = 0.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if not isinstance(base, ConditionalModel):
            if out_dim is None:
                raise InputError("out_dim: give the number of channels of a callable base map")
            base = FunctionModel(base, None, out_dim=out_dim, name="measurement")
        self.base = base
        m = int(base.out_dim)
        self.out_dim, self.in_dim = m, base.in_dim
        ch = list(range(m)) if channels is None else [int(c) for c in channels]
        if not ch or len(set(ch)) != len(ch) or any(not 0 <= c < m for c in ch):
            raise InputError(f"channels: expected distinct indices in 0..{m - 1}, got {ch}")
        c = len(ch)
        s = torch.as_tensor(scale, dtype=dtype).expand(c).clone()
        b = torch.as_tensor(bias, dtype=dtype).expand(c).clone()
        if s.shape != (c,) or b.shape != (c,):
            raise ShapeError(f"scale and bias: expected one value or {c}")
        if bool((s == 0).any()) or not bool(torch.isfinite(s).all() & torch.isfinite(b).all()):
            raise InputError("scale must be finite and non-zero, bias finite")
        self.channels = ch
        self.register_buffer("index", torch.tensor(ch, dtype=torch.long))
        self.register_buffer("sign", torch.sign(s))
        self.log_scale = nn.Parameter(s.abs().log())
        self.bias = nn.Parameter(b)

    @property
    def scale(self) -> Tensor:
        """The gains ``(c,)``."""
        return self.sign * self.log_scale.exp()

    def _full(self, values: Tensor, fill: float) -> Tensor:
        out = torch.full((self.out_dim,), fill, dtype=values.dtype, device=values.device)
        return out.index_put((self.index,), values)

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        p = self.base.predict(x, u)
        s = self._full(self.scale, 1.0)
        mean = p.mean * s + self._full(self.bias, 0.0)
        var = None if p.var is None else p.var * s * s
        cov = None if p.cov is None else p.cov * s[:, None] * s[None, :]
        return Prediction(mean, var, cov)

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        return self.base.noise_cov(step)

    @property
    def time_varying_noise(self) -> bool:
        return self.base.time_varying_noise
