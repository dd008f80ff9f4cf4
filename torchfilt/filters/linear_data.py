"""The data types shared by the exact and the parallel-in-time Kalman filter
(:mod:`torchfilt.filters.kalman`, :mod:`torchfilt.filters.parallel`)."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["Data", "LinearSteps", "SmootherElements"]


class LinearSteps(NamedTuple):
    """Per-step parameters of a linear-Gaussian model, each with a time axis ``T``.

    Constant parameters are expanded views (no copies). Batch dimensions broadcast.

    Attributes:
        A: ``(..., T, n, n)``.  c: transition offsets ``B u_t``, ``(..., T, n)`` or ``None``.
        Q: ``(..., T, n, n)``.  H: ``(..., T, m, n)``.
        d: measurement offsets ``D u_t``, ``(..., T, m)`` or ``None``.  R: ``(..., T, m, m)``.
    """

    A: Tensor
    c: Tensor | None
    Q: Tensor
    H: Tensor
    d: Tensor | None
    R: Tensor


class Data(NamedTuple):
    """Checked inputs: ``y (..., T, m)`` with missing entries set to 0, ``obs (..., T, m)`` bool,
    prior ``x0 (B..., n)``, ``P0 (B..., n, n)`` expanded to the full batch shape ``batch``, and
    ``complete``: whether every component is observed (the masking is then skipped)."""

    y: Tensor
    obs: Tensor
    x0: Tensor
    P0: Tensor
    batch: torch.Size
    complete: bool


class SmootherElements(NamedTuple):
    """The backward recursion ``m^s_t = g_t + E_t m^s_{t+1}``, ``P^s_t = L_t + E_t P^s_{t+1}
    E_t^T`` (Särkkä & García-Fernández 2021, eq. 32): ``E (..., T, n, n)`` (zero at ``T-1``),
    ``g (..., T, n)``, ``L (..., T, n, n)``."""

    E: Tensor
    g: Tensor
    L: Tensor
