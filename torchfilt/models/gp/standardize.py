"""Per-column affine standardisation, stored as buffers so that ``state_dict`` round-trips."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError

__all__ = ["Standardizer"]

#: A column whose standard deviation is below ``CONSTANT_RTOL * max(1, |mean|)`` is treated as
#: constant: its scale is set to 1 so that standardising it gives exact zeros instead of noise.
CONSTANT_RTOL = 1e-12


class Standardizer(nn.Module):
    """``z = (v - shift) / scale`` column by column.

    Args:
        shift: per-column shift, shape ``(F,)``.
        scale: per-column positive scale, shape ``(F,)``.
        constant: per-column flag, shape ``(F,)``: the column had no spread in the data.

    Raises:
        InputError: ``shift`` and ``scale`` are not vectors of one shape, or ``scale`` is not
            positive.
    """

    shift: Tensor
    scale: Tensor
    constant: Tensor

    def __init__(self, shift: Tensor, scale: Tensor, constant: Tensor | None = None) -> None:
        super().__init__()
        if shift.shape != scale.shape or shift.dim() != 1:
            raise InputError(
                f"shift and scale must be vectors of one shape, got {tuple(shift.shape)} and "
                f"{tuple(scale.shape)}"
            )
        if not bool((scale > 0).all()):
            raise InputError("scale must be positive")
        self.register_buffer("shift", shift.clone())
        self.register_buffer("scale", scale.clone())
        if constant is None:
            constant = torch.zeros(shift.shape, dtype=torch.bool, device=shift.device)
        self.register_buffer("constant", constant.clone())

    @classmethod
    def fit(cls, values: Tensor, valid: Tensor | None = None) -> Standardizer:
        """Mean and standard deviation of each column.

        Args:
            values: data, shape ``(N, F)``.
            valid: optional boolean mask ``(N, F)``; statistics of column ``j`` use the rows where
                ``valid[:, j]`` holds (missing measurements).

        Returns:
            The standardiser.
        """
        if valid is None:
            valid = torch.ones_like(values, dtype=torch.bool)
        w = valid.to(values.dtype)
        count = w.sum(0).clamp_min(1.0)
        v = torch.where(valid, values, torch.zeros((), dtype=values.dtype))
        mean = v.sum(0) / count
        var = (((v - mean) * w) ** 2).sum(0) / (count - 1.0).clamp_min(1.0)
        std = var.sqrt()
        const = std <= CONSTANT_RTOL * mean.abs().clamp_min(1.0)
        return cls(mean, torch.where(const, torch.ones_like(std), std), const)

    @property
    def size(self) -> int:
        """Number of columns ``F``."""
        return int(self.shift.shape[0])

    def forward(self, v: Tensor) -> Tensor:
        """Standardise.

        Args:
            v: values, shape ``(..., F)``.

        Returns:
            ``(v - shift) / scale``, shape ``(..., F)``.
        """
        return (v - self.shift) / self.scale

    def inverse(self, z: Tensor) -> Tensor:
        """Undo :meth:`forward`.

        Args:
            z: standardised values, shape ``(..., F)``.

        Returns:
            ``z * scale + shift``, shape ``(..., F)``.
        """
        return z * self.scale + self.shift
