"""Consistency and accuracy metrics: NIS, NEES, RMSE."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.filters.results import FilterResult
from torchfilt.numerics import safe_cholesky, solve_tril

__all__ = ["coverage", "nees", "nis", "rmse"]


def nis(result: FilterResult) -> tuple[Tensor, Tensor]:
    """Normalised innovation squared per step, over the observed components.

    Args:
        result: a filter result.

    Returns:
        ``(nis, dof)``: ``e^T P_yy^{-1} e`` restricted to observed components, shape ``(..., T)``
        (0 where nothing was observed), and the number of observed components, shape ``(..., T)``.
        For a consistent filter ``nis`` is chi-square with ``dof`` degrees of freedom.
    """
    obs = result.observed.to(result.innovation_cov.dtype)
    e = torch.where(result.observed, result.innovation, torch.zeros_like(result.innovation))
    S = result.innovation_cov * (obs.unsqueeze(-1) * obs.unsqueeze(-2)) + torch.diag_embed(1 - obs)
    L = safe_cholesky(S, name="innovation covariance")
    z = solve_tril(L, e.unsqueeze(-1)).squeeze(-1)
    return (z * z).sum(-1), obs.sum(-1)


def nees(x_true: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    """Normalised estimation error squared ``(x - m)^T P^{-1} (x - m)``.

    Args:
        x_true: true states, shape ``(..., T, n)`` (broadcastable).
        mean: estimated means, shape ``(..., T, n)``.
        cov: estimated covariances, shape ``(..., T, n, n)``.

    Returns:
        NEES per step, shape ``(..., T)``; chi-square with ``n`` degrees of freedom when consistent.

    Raises:
        ShapeError: ``x_true``, ``mean`` and ``cov`` are not ``(..., n)``, ``(..., n)`` and
            ``(..., n, n)`` for one ``n``.
    """
    if mean.shape[-1] != x_true.shape[-1] or cov.shape[-2:] != (mean.shape[-1],) * 2:
        raise ShapeError(
            f"nees: x_true {tuple(x_true.shape)}, mean {tuple(mean.shape)} and cov "
            f"{tuple(cov.shape)} must be (..., n), (..., n), (..., n, n)"
        )
    L = safe_cholesky(cov, name="estimate covariance")
    z = solve_tril(L, (x_true - mean).unsqueeze(-1)).squeeze(-1)
    return (z * z).sum(-1)


def _check_pair(x_true: Tensor, mean: Tensor) -> None:
    if not isinstance(x_true, Tensor) or not isinstance(mean, Tensor):
        raise InputError("x_true and mean must be tensors")
    try:
        torch.broadcast_shapes(x_true.shape, mean.shape)
    except RuntimeError:
        raise ShapeError(
            f"x_true {tuple(x_true.shape)} and mean {tuple(mean.shape)} do not broadcast"
        ) from None


def rmse(x_true: Tensor, mean: Tensor, dim: int | tuple[int, ...] = -2) -> Tensor:
    """Root-mean-square error per state component.

    Args:
        x_true: true states, shape ``(..., T, n)``.
        mean: estimates, shape ``(..., T, n)``.
        dim: dimensions averaged over (default: time).

    Returns:
        RMSE, shape of the input with ``dim`` reduced (default ``(..., n)``).

    Raises:
        InputError: ``x_true`` or ``mean`` is not a tensor.
        ShapeError: ``x_true`` and ``mean`` do not broadcast.
    """
    _check_pair(x_true, mean)
    return ((x_true - mean) ** 2).mean(dim=dim).sqrt()


def coverage(x_true: Tensor, mean: Tensor, cov: Tensor, level: float = 0.95) -> Tensor:
    """Fraction of steps whose per-state error lies inside the central ``level`` Gaussian interval.

    Args:
        x_true: true states, shape ``(..., T, n)``.
        mean: estimated means, shape ``(..., T, n)``.
        cov: estimated covariances, shape ``(..., T, n, n)`` (only the diagonal is used).
        level: nominal probability of the interval (default 95%).

    Returns:
        Empirical coverage per state, shape ``(..., n)``; ``level`` when the filter is calibrated.

    Raises:
        InputError: ``level`` outside (0, 1), or ``x_true`` or ``mean`` is not a tensor.
        ShapeError: ``x_true`` and ``mean`` do not broadcast, or ``cov`` is not
            ``(..., T, n, n)`` for ``mean`` of shape ``(..., T, n)``.
    """
    if not 0.0 < level < 1.0:
        raise InputError(f"level must be in (0, 1), got {level}")
    _check_pair(x_true, mean)
    if cov.shape[-2:] != (mean.shape[-1], mean.shape[-1]) or cov.shape[:-1] != mean.shape:
        raise ShapeError(
            f"cov: expected shape {(*mean.shape, mean.shape[-1])} to match mean {tuple(mean.shape)}, "
            f"got {tuple(cov.shape)}"
        )
    z = math.sqrt(2.0) * float(torch.special.erfinv(torch.tensor(level, dtype=torch.float64)))
    sd = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    inside = ((x_true - mean).abs() <= z * sd).to(mean.dtype)
    return inside.mean(dim=-2)
