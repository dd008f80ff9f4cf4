"""Positive-definite linear algebra: symmetrisation, a jittered Cholesky, PSD solves, triangularisation.

Filters never form an explicit inverse: gains come from :func:`psd_solve`, square roots from
:func:`safe_cholesky` or :func:`tria`.
"""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from torch import Tensor

from torchfilt.exceptions import CholeskyJitterWarning, InputError
from torchfilt.numerics import small
from torchfilt.settings import is_sync_free, sync_free

__all__ = [
    "cholesky_ok",
    "no_host_sync",
    "psd_solve",
    "safe_cholesky",
    "symmetrize",
    "sync_free",
    "tria",
]

#: Jitter added on the k-th retry is ``eps(dtype) * mean|diag| * JITTER_BASE**(k+1)``.
JITTER_BASE = 10.0
#: Number of jitter retries before giving up (largest jitter is eps * 1e6 relative to the diagonal).
MAX_JITTER_TRIES = 6


def symmetrize(A: Tensor) -> Tensor:
    """Return ``(A + A^T) / 2``.

    Args:
        A: square matrices, shape ``(..., n, n)``.

    Returns:
        The symmetric part of ``A``, shape ``(..., n, n)``.
    """
    return 0.5 * (A + A.mT)


def no_host_sync() -> bool:
    """True where a host synchronisation is not allowed: under ``torch.compile`` tracing, or
    inside :func:`torchfilt.settings.sync_free` (CUDA-graph warm-up and capture)."""
    return torch.compiler.is_compiling() or is_sync_free()


def safe_cholesky(
    A: Tensor,
    *,
    max_tries: int = MAX_JITTER_TRIES,
    on_failure: Literal["nan", "raise"] = "nan",
    name: str = "matrix",
    warn: bool = True,
) -> Tensor:
    """Lower Cholesky factor of symmetric positive (semi-)definite matrices, adding jitter if needed.

    Each batch element is factored independently. Elements that fail are retried with a diagonal
    jitter ``eps(dtype) * mean|diag(A)| * 10**k`` for ``k = 1..max_tries``; a
    :class:`~torchfilt.exceptions.CholeskyJitterWarning` reports that jitter was used and how much.
    Elements that still fail (or contain non-finite values) are set to NaN (``on_failure="nan"``,
    the default, so one bad sequence does not stop a batch) or raise
    :class:`~torchfilt.exceptions.InputError` (a ``ValueError``).

    Inside ``torch.compile`` and :func:`~torchfilt.settings.sync_free` (CUDA-graph capture) the retries (which need a
    host synchronisation) are skipped and failed factors are NaN.

    Args:
        A: symmetric matrices, shape ``(..., n, n)``.
        max_tries: number of jitter retries.
        on_failure: ``"nan"`` or ``"raise"``.
        name: name of the matrix in warnings and errors.
        warn: emit the jitter warning (``False`` where a singular ``A`` is a legitimate result,
            e.g. a covariance that is exactly singular by construction).

    Returns:
        Lower-triangular ``L`` with ``L L^T = A (+ jitter I)``, shape ``(..., n, n)``.

    Raises:
        InputError: ``on_failure="raise"`` and some matrix is not positive definite (or not
            finite) even with jitter.
    """
    L, info = small.cholesky_ex(A)
    if no_host_sync():
        bad = info > 0
        return torch.where(bad[..., None, None], torch.full_like(L, float("nan")), L)
    if info.numel() == 0:
        return L
    # one read for the common case: 0 exactly when every entry is finite (their sum is, so
    # ``0 * sum`` is 0, not NaN) and every factor succeeded; anything else (a failure, a
    # non-finite entry, or a sum that overflowed) takes the per-element check below
    if float(A.detach().sum() * 0.0 + info.max()) == 0.0:
        return L
    finite = torch.isfinite(A).all(dim=-1).all(dim=-1)
    bad = (info > 0) | ~finite
    if not bool(bad.any()):
        return L
    n = A.shape[-1]
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    scale = A.diagonal(dim1=-2, dim2=-1).abs().mean(-1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale)) * torch.finfo(A.dtype).eps
    retry = bad & finite
    used = 0.0
    found = torch.zeros_like(scale)  # the jitter that factors each element (0: none needed)
    with torch.no_grad():  # the search only picks the jitter
        for k in range(max_tries):
            if not bool(retry.any()):
                break
            jitter = scale * JITTER_BASE ** (k + 1)
            _, info2 = small.cholesky_ex(A + jitter[..., None, None] * eye)
            ok = retry & (info2 == 0)
            found = torch.where(ok, jitter, found)
            if bool(ok.any()):
                used = max(used, float((jitter / scale * torch.finfo(A.dtype).eps)[ok].max()))
            retry = retry & ~ok
    if used > 0.0:
        # one factorisation with the jitter found: its gradient does not pass through the failed
        # first factor (whose NaN would poison it through torch.where)
        L, _ = small.cholesky_ex(A + found.detach()[..., None, None] * eye)
    failed = retry | ~finite
    if used > 0.0 and warn:
        warnings.warn(
            f"{name} was not numerically positive definite; added diagonal jitter up to "
            f"{used:.1e} x mean|diag| to factor it",
            CholeskyJitterWarning,
            stacklevel=2,
        )
    if bool(failed.any()):
        if on_failure == "raise":
            idx = failed.nonzero().tolist()
            raise InputError(
                f"{name} is not positive definite (or not finite) at batch index "
                f"{idx[:5]}{'...' if len(idx) > 5 else ''}, even with jitter"
            )
        L = torch.where(failed[..., None, None], torch.full_like(L, float("nan")), L)
    return L


def cholesky_ok(A: Tensor) -> Tensor:
    """Whether each matrix is finite and numerically positive definite (no jitter tried).

    Args:
        A: symmetric matrices, shape ``(..., n, n)``.

    Returns:
        Boolean tensor, shape ``(...)``.
    """
    _, info = small.cholesky_ex(A)
    return (info == 0) & torch.isfinite(A).all(dim=-1).all(dim=-1)


def psd_solve(A: Tensor, B: Tensor, *, L: Tensor | None = None, name: str = "matrix") -> Tensor:
    """Solve ``A X = B`` for symmetric positive-definite ``A`` through its Cholesky factor.

    Args:
        A: SPD matrices, shape ``(..., n, n)``.
        B: right-hand sides, shape ``(..., n, k)``.
        L: optional precomputed lower Cholesky factor of ``A``, shape ``(..., n, n)``.
        name: name of ``A`` in warnings and errors.

    Returns:
        ``X = A^{-1} B``, shape ``(..., n, k)``.
    """
    if L is None:
        L = safe_cholesky(symmetrize(A), name=name)
    return small.cholesky_solve(B, L)


def tria(A: Tensor) -> Tensor:
    """Triangularise: a lower-triangular ``S`` with ``S S^T = A A^T`` and non-negative diagonal.

    This is the "Tria" operation of the square-root cubature Kalman filter (Arasaratnam & Haykin,
    2009), computed from a QR decomposition of ``A^T``. For a full-rank ``A`` the result is exactly
    the Cholesky factor of ``A A^T``.

    Args:
        A: compound matrices, shape ``(..., n, k)``; any ``k`` (padded with zeros if ``k < n``).

    Returns:
        Lower-triangular factor, shape ``(..., n, n)``.
    """
    n, k = A.shape[-2], A.shape[-1]
    if k < n:
        A = torch.cat([A, A.new_zeros(*A.shape[:-1], n - k)], dim=-1)
    R = torch.linalg.qr(A.mT, mode="reduced").R  # (..., n, n), A A^T = R^T R
    d = R.diagonal(dim1=-2, dim2=-1)
    sign = torch.where(d < 0, -torch.ones_like(d), torch.ones_like(d))
    return (sign.unsqueeze(-1) * R).mT
