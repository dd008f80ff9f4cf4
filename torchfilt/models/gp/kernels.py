"""Stationary kernels in plain torch, on inputs already divided by their lengthscales.

With ``r^2 = |a - b|^2`` (ARD: each input divided by its own lengthscale first):

    rbf:       k(r) = exp(-r^2 / 2)
    matern12:  k(r) = exp(-r)
    matern32:  k(r) = (1 + sqrt(3) r) exp(-sqrt(3) r)
    matern52:  k(r) = (1 + sqrt(5) r + 5 r^2 / 3) exp(-sqrt(5) r)

(Rasmussen & Williams 2006, eqs. 4.9 and 4.17.) These are the unit-variance correlations; a GP's
kernel is ``outputscale * k``. They match GPyTorch's ``RBFKernel`` and ``MaternKernel``.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from torchfilt.exceptions import InputError

__all__ = ["KERNELS", "KernelName", "correlation", "scaled_sq_dist"]

KernelName = Literal["rbf", "matern12", "matern32", "matern52"]

#: The kernels a GP model may use, and the Matern smoothness ``nu`` of each (``None``: RBF).
KERNELS: dict[str, float | None] = {"rbf": None, "matern12": 0.5, "matern32": 1.5, "matern52": 2.5}

#: ``r`` is computed as ``sqrt(max(r^2, _TINY_SQ))`` so that gradients stay finite at ``r = 0``.
_TINY_SQ = 1e-30


def scaled_sq_dist(a: Tensor, b: Tensor, b_sq: Tensor | None = None) -> Tensor:
    """Squared distances ``|a_i - b_j|^2`` between rows, via ``|a|^2 + |b|^2 - 2 a b^T``.

    Args:
        a: points, shape ``(B, P, D)`` (already divided by lengthscales).
        b: points, shape ``(B, S, D)``.
        b_sq: optional cached ``|b_j|^2``, shape ``(B, S)``.

    Returns:
        Non-negative squared distances, shape ``(B, P, S)``.
    """
    if b_sq is None:
        b_sq = b.pow(2).sum(-1)
    base = a.pow(2).sum(-1, keepdim=True) + b_sq.unsqueeze(-2)
    return torch.baddbmm(base, a, b.mT, alpha=-2.0).clamp_min(0.0)


def correlation(d2: Tensor, kind: str) -> Tensor:
    """Unit-variance kernel value from squared scaled distances.

    Args:
        d2: squared scaled distances ``r^2``, any shape.
        kind: one of :data:`KERNELS`.

    Returns:
        ``k(r)``, same shape as ``d2``.
    """
    if kind == "rbf":
        return torch.exp(-0.5 * d2)
    if kind not in KERNELS:
        raise InputError(f"kernel must be one of {sorted(KERNELS)}, got {kind!r}")
    r = d2.clamp_min(_TINY_SQ).sqrt()
    if kind == "matern12":
        return torch.exp(-r)
    if kind == "matern32":
        s = math.sqrt(3.0) * r
        return (1.0 + s) * torch.exp(-s)
    s = math.sqrt(5.0) * r
    return (1.0 + s + s * s / 3.0) * torch.exp(-s)
