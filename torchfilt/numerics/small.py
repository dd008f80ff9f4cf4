"""Unrolled kernels for small matrices (n <= SMALL_MAX).

LAPACK factors a batch of 3x3 matrices one at a time, and every call is a separate kernel that
``torch.compile`` cannot fuse. Written out entry by entry, a small Cholesky factorisation or
triangular solve is a few dozen element-wise operations over the batch: vectorised across the
batch in eager mode, and fused into the surrounding code under ``torch.compile``.

Failure semantics match ``torch.linalg.cholesky_ex``: a matrix that is not positive definite gives
a non-zero ``info`` (its factor contains NaN).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchfilt.settings import current_small_matrix_kernels

__all__ = [
    "SMALL_BATCH",
    "SMALL_MAX",
    "cholesky_ex",
    "cholesky_solve",
    "solve_tril",
    "use_unrolled",
]

#: Largest matrix size handled by the unrolled kernels.
SMALL_MAX = 6
#: In eager mode the unrolled kernels are used from this many matrices in a batch (below it one
#: LAPACK call is cheaper than the unrolled op sequence).
SMALL_BATCH = 64


def use_unrolled(A: Tensor) -> bool:
    """Whether to use the unrolled kernels for ``A`` of shape ``(..., n, k)``.

    Under ``torch.compile`` they always are. Otherwise
    :func:`torchfilt.settings.small_matrix_kernels` chooses; under ``"auto"`` (the default) they
    are used from ``SMALL_BATCH`` matrices on, where they beat the library calls.
    """
    if A.shape[-2] > SMALL_MAX:
        return False
    if torch.compiler.is_compiling():
        return True  # fused into the surrounding kernels; decided at trace time, so no switch
    mode = current_small_matrix_kernels()
    if mode != "auto":
        return mode == "unrolled"
    return A[..., 0, 0].numel() >= SMALL_BATCH


def _assemble(rows: list[list[Tensor]]) -> Tensor:
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def cholesky_ex(A: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor and an ``info`` flag, like ``torch.linalg.cholesky_ex``.

    Args:
        A: symmetric matrices, shape ``(..., n, n)``; only the lower triangle is read.

    Returns:
        ``(L, info)``: ``L`` of shape ``(..., n, n)`` and ``info`` of shape ``(...)``, 0 where the
        factorisation succeeded, else the 1-based index of the first failing pivot.
    """
    if not use_unrolled(A):
        return torch.linalg.cholesky_ex(A)
    n = A.shape[-1]
    L: list[list[Tensor | None]] = [[None] * n for _ in range(n)]
    zero = torch.zeros_like(A[..., 0, 0])
    info = torch.zeros(A.shape[:-2], dtype=torch.int32, device=A.device)
    for j in range(n):
        s = A[..., j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]  # type: ignore[operator]
        bad = ~(s > 0)  # also catches NaN
        info = torch.where(bad & (info == 0), j + 1, info)
        d = torch.sqrt(s)
        L[j][j] = d
        for i in range(j + 1, n):
            s = A[..., i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]  # type: ignore[operator]
            L[i][j] = s / d
    rows = [[L[i][j] if j <= i else zero for j in range(n)] for i in range(n)]
    return _assemble(rows), info  # type: ignore[arg-type]


def solve_tril(L: Tensor, B: Tensor) -> Tensor:
    """Solve ``L X = B`` for lower-triangular ``L`` by forward substitution.

    Args:
        L: lower-triangular matrices, shape ``(..., n, n)``.
        B: right-hand sides, shape ``(..., n, k)``.

    Returns:
        ``X``, shape ``(..., n, k)``.
    """
    if not use_unrolled(L):
        return torch.linalg.solve_triangular(L, B, upper=False)
    n = L.shape[-1]
    xs: list[Tensor] = []
    for i in range(n):
        s = B[..., i, :]
        for k in range(i):
            s = s - L[..., i, k].unsqueeze(-1) * xs[k]
        xs.append(s / L[..., i, i].unsqueeze(-1))
    return torch.stack(xs, dim=-2)


def _solve_triu_of_lower_T(L: Tensor, B: Tensor) -> Tensor:
    """Solve ``L^T X = B`` (back substitution with the transpose of lower-triangular ``L``)."""
    n = L.shape[-1]
    xs: list[Tensor | None] = [None] * n
    for i in range(n - 1, -1, -1):
        s = B[..., i, :]
        for k in range(i + 1, n):
            s = s - L[..., k, i].unsqueeze(-1) * xs[k]  # type: ignore[operator]
        xs[i] = s / L[..., i, i].unsqueeze(-1)
    return torch.stack(xs, dim=-2)  # type: ignore[arg-type]


def cholesky_solve(B: Tensor, L: Tensor) -> Tensor:
    """Solve ``(L L^T) X = B``, like ``torch.cholesky_solve(B, L)``.

    Args:
        B: right-hand sides, shape ``(..., n, k)``.
        L: lower Cholesky factors, shape ``(..., n, n)``.

    Returns:
        ``X``, shape ``(..., n, k)``.
    """
    if not use_unrolled(L):
        return torch.cholesky_solve(B, L)
    batch = torch.broadcast_shapes(B.shape[:-2], L.shape[:-2])
    B = B.expand(*batch, *B.shape[-2:])
    L = L.expand(*batch, *L.shape[-2:])
    return _solve_triu_of_lower_T(L, solve_tril(L, B))
