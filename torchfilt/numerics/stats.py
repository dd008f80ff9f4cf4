"""Gaussian densities and chi-square quantiles without scipy."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.numerics.small import solve_tril

__all__ = ["chi2_quantile", "gaussian_log_prob"]

_LOG_2PI = math.log(2.0 * math.pi)


def gaussian_log_prob(e: Tensor, L: Tensor, dim: Tensor | int | None = None) -> Tensor:
    """Log density of a zero-mean Gaussian with covariance ``L L^T`` at ``e``.

    Args:
        e: residuals, shape ``(..., m)``.
        L: lower Cholesky factors of the covariance, shape ``(..., m, m)``.
        dim: number of dimensions counted in the normalising constant, an int or a tensor of shape
            ``(...)``; defaults to ``m``. Masked (unobserved) components carry a unit diagonal in
            ``L`` and a zero in ``e`` and must not be counted.

    Returns:
        ``log N(e; 0, L L^T)``, shape ``(...)``.
    """
    z = solve_tril(L, e.unsqueeze(-1)).squeeze(-1)
    maha = (z * z).sum(-1)
    logdet = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    if dim is None:
        dim = e.shape[-1]
    return -0.5 * (maha + logdet + dim * _LOG_2PI)


def chi2_quantile(p: float | Tensor, dof: float | Tensor, *, iters: int = 200) -> Tensor:
    """Quantile of the chi-square distribution, by bisection on the regularised gamma function.

    Args:
        p: probabilities in (0, 1), any shape broadcastable with ``dof``.
        dof: degrees of freedom (> 0).
        iters: bisection iterations (200 reaches float64 resolution).

    Returns:
        ``x`` with ``P(chi2_dof <= x) = p``, float64, broadcast shape of ``p`` and ``dof``.
    """
    p_t = torch.as_tensor(p, dtype=torch.float64)
    k = torch.as_tensor(dof, dtype=torch.float64)
    if bool((p_t <= 0).any() | (p_t >= 1).any()):
        raise InputError(f"p must lie in (0, 1), got {p}")
    if bool((k <= 0).any()):
        raise InputError(f"dof must be positive, got {dof}")
    p_t, k = torch.broadcast_tensors(p_t, k)
    lo = torch.zeros_like(k)
    hi = k + 20.0 * torch.sqrt(2.0 * k) + 100.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        below = torch.special.gammainc(0.5 * k, 0.5 * mid) < p_t
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    return 0.5 * (lo + hi)
