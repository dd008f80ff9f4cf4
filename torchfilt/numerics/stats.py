"""Gaussian densities and chi-square quantiles without scipy."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.numerics.small import solve_tril

__all__ = ["chi2_quantile", "gaussian_log_prob"]

_LOG_2PI = math.log(2.0 * math.pi)


def gaussian_log_prob(
    e: Tensor, L: Tensor, dim: Tensor | int | None = None, *, library: bool = False
) -> Tensor:
    """Log density of a zero-mean Gaussian with covariance ``L L^T`` at ``e``: the one
    log-likelihood term of every filter (Kalman runners, cubature and constrained steps, training).

    ``-0.5 (|L^{-1} e|^2 + 2 sum(log diag L) + k log(2 pi))``. Where ``L`` is shared by trailing
    batch dimensions of ``e`` (size 1 there, or fewer dimensions), those residuals are solved as
    the columns of one triangular solve per factor instead of one small solve each, and the
    log-determinant is taken once per factor.

    Args:
        e: residuals, shape ``(..., m)``.
        L: lower Cholesky factors of the covariance, shape ``(..., m, m)``, broadcasting against
            ``e``'s batch dimensions.
        dim: number of dimensions counted in the normalising constant (the observed components
            ``k``), an int or a tensor broadcasting against ``(...)``; defaults to ``m``. Masked
            (unobserved) components carry a unit diagonal in ``L`` and a zero in ``e`` and must
            not be counted.
        library: always solve with ``torch.linalg.solve_triangular``, never with the unrolled
            small-matrix kernels (for callers that factored ``L`` with the library themselves).

    Returns:
        ``log N(e; 0, L L^T)``, shape ``(...)`` (the broadcast batch shape).
    """
    m = e.shape[-1]
    solve = _solve_library if library else solve_tril
    logdet = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)  # L's batch shape
    if L.dim() == e.dim() + 1 and (L.dim() == 2 or L.shape[-3] == e.shape[-2]):
        z = solve(L, e.unsqueeze(-1)).squeeze(-1)  # one factor per residual
        maha = (z * z).sum(-1)
    else:
        maha = _shared_maha(e, L, solve)
    if dim is None:
        dim = m
    elif isinstance(dim, Tensor):  # an integer count would make the constant float32
        dim = dim.to(maha.dtype)
    return -0.5 * (maha + logdet + dim * _LOG_2PI)


def _shared_maha(e: Tensor, L: Tensor, solve: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """``|L^{-1} e|^2`` solving the residuals that share a factor (the trailing batch dimensions
    of ``e`` where ``L`` has size 1 or none) as the columns of one solve."""
    m = e.shape[-1]
    eb, lb = e.shape[:-1], L.shape[:-2]
    j = len(eb)
    if len(lb) > j:  # e broadcasts against L: nothing to share
        z = solve(L, e.unsqueeze(-1)).squeeze(-1)
        return (z * z).sum(-1)
    lb_full = (1,) * (j - len(lb)) + tuple(lb)
    while j > 0 and lb_full[j - 1] == 1:
        j -= 1
    cols = math.prod(eb[j:])
    z = solve(L.reshape(*lb_full[:j], m, m), e.reshape(*eb[:j], cols, m).mT)
    return z.square().sum(-2).reshape(eb)


def _solve_library(L: Tensor, B: Tensor) -> Tensor:
    return torch.linalg.solve_triangular(L, B, upper=False)


def chi2_quantile(p: float | Tensor, dof: float | Tensor, *, iters: int = 200) -> Tensor:
    """Quantile of the chi-square distribution, by bisection on the regularised gamma function.

    Args:
        p: probabilities in (0, 1), a scalar or any shape broadcastable with ``dof``.
        dof: degrees of freedom (> 0), a scalar or any shape broadcastable with ``p``.
        iters: bisection iterations (200 reaches float64 resolution).

    Returns:
        ``x`` with ``P(chi2_dof <= x) = p``, float64, of the broadcast shape of ``p`` and ``dof``
        (any shape; a scalar for scalar arguments).

    Raises:
        InputError: some ``p`` outside (0, 1) or some ``dof`` not positive.
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
