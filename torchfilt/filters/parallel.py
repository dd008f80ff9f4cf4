"""Parallel-in-time Kalman filtering and RTS smoothing by associative scan.

Särkkä & García-Fernández, "Temporal parallelization of Bayesian smoothers", IEEE TAC 66(1), 2021,
sec. IV. Each step ``t`` becomes an element ``(A_t, b_t, C_t, eta_t, J_t)``: the conditional
``p(x_t | x_{t-1}, y_t) = N(A_t x_{t-1} + b_t, C_t)`` and the likelihood of ``y_t`` as a function of
``x_{t-1}``, ``N_I(x_{t-1}; eta_t, J_t)`` (information form). With ``S = H Q H^T + R``,
``K = Q H^T S^{-1}`` and ``e = y - H c - d``:

    A_t = (I - K H) A,  b_t = c + K e,  C_t = (I - K H) Q,
    eta_t = A^T H^T S^{-1} e,  J_t = A^T H^T S^{-1} H A,

and the first element folds in the prior (``A_0 = 0``, ``b_0 = m_0``, ``C_0 = P_0``). Two elements,
``i`` before ``j``, combine as (eqs. 14-15)

    M = I + C_i J_j,
    A_ij = A_j M^{-1} A_i,   b_ij = A_j M^{-1} (b_i + C_i eta_j) + b_j,
    C_ij = A_j M^{-1} C_i A_j^T + C_j,
    eta_ij = A_i^T M^{-T} (eta_j - J_j b_i) + eta_i,   J_ij = A_i^T M^{-T} J_j A_i + J_i,

and the inclusive scan's ``(b_t, C_t)`` are the filtered moments. The smoother's elements
``(E_t, g_t, L_t)`` (:func:`~torchfilt.filters.kalman.smoother_elements`) combine as
``E_ij = E_i E_j``, ``g_ij = E_i g_j + g_i``, ``L_ij = E_i L_j E_i^T + L_i`` in a reverse scan.
A missing component has its row of ``H`` and its residual zeroed and a unit diagonal in ``S``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.filters.linear_data import Data, LinearSteps, SmootherElements
from torchfilt.numerics import cholesky_solve, safe_cholesky, symmetrize
from torchfilt.numerics.scan import associative_scan

__all__ = ["parallel_filter_moments", "parallel_smoother_moments"]


class FilterElement(NamedTuple):
    """Leaves ``(T, ..., n, n)``, ``(T, ..., n)``, ... with time leading (the scanned axis)."""

    A: Tensor
    b: Tensor
    C: Tensor
    eta: Tensor
    J: Tensor


def _mv(M: Tensor, v: Tensor) -> Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _combine_filter(a: FilterElement, b: FilterElement) -> FilterElement:
    """``a`` (earlier) then ``b`` (later), batched over the leading axis."""
    n = a.A.shape[-1]
    eye = torch.eye(n, dtype=a.A.dtype, device=a.A.device)
    M = eye + a.C @ b.J
    LU, piv = torch.linalg.lu_factor(M)
    X = torch.linalg.lu_solve(LU, piv, b.A.mT, adjoint=True).mT  # A_j M^{-1}
    Y = torch.linalg.lu_solve(LU, piv, a.A).mT  # A_i^T M^{-T}
    A = X @ a.A
    bb = _mv(X, a.b + _mv(a.C, b.eta)) + b.b
    C = symmetrize(X @ a.C @ b.A.mT + b.C)
    eta = _mv(Y, b.eta - _mv(b.J, a.b)) + a.eta
    J = symmetrize(Y @ b.J @ a.A + a.J)
    return FilterElement(A, bb, C, eta, J)


def _front(x: Tensor, tail: int) -> Tensor:
    """Move the time axis (just before the ``tail`` trailing dims) to the front."""
    return x.movedim(x.dim() - tail - 1, 0)


def _back(x: Tensor, tail: int) -> Tensor:
    return x.movedim(0, x.dim() - tail - 1)


def filter_elements(data: Data, steps: LinearSteps) -> FilterElement:
    """The elements of every step, ``(..., T, ...)`` with the data's full batch shape."""
    A, Q = steps.A, steps.Q
    T, n = A.shape[-3], A.shape[-1]
    batch = data.batch
    A = A.expand(*batch, T, n, n)
    c = A.new_zeros(()).expand(*batch, T, n) if steps.c is None else steps.c.expand(*batch, T, n)
    Q = Q.expand(*batch, T, n, n)
    # the first element starts from the prior: A_0 = 0, and "c", "Q" are the predicted moments
    m_first = _mv(A[..., 0, :, :], data.x0) + c[..., 0, :]
    P_first = symmetrize(A[..., 0, :, :] @ data.P0 @ A[..., 0, :, :].mT + Q[..., 0, :, :])
    c = torch.cat([m_first.unsqueeze(-2), c[..., 1:, :]], -2)
    Q = torch.cat([P_first.unsqueeze(-3), Q[..., 1:, :, :]], -3)
    A = torch.cat([torch.zeros_like(A[..., :1, :, :]), A[..., 1:, :, :]], -3)
    H, R = steps.H, steps.R
    S = H @ Q @ H.mT + R
    e = data.y - _mv(H, c)
    if steps.d is not None:
        e = e - steps.d
    if not data.complete:
        o = data.obs.to(S.dtype)
        S = S * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
        H = H * o.unsqueeze(-1)
        e = e * o
    L = safe_cholesky(symmetrize(S), name="innovation covariance")
    QHt = Q @ H.mT
    K = cholesky_solve(QHt.mT, L).mT  # (..., T, n, m)
    HA = H @ A
    Ael = A - K @ HA
    b = c + _mv(K, e)
    C = symmetrize(Q - K @ QHt.mT)
    Sinv_e = cholesky_solve(e.unsqueeze(-1), L).squeeze(-1)
    eta = _mv(HA.mT, Sinv_e)
    J = symmetrize(HA.mT @ cholesky_solve(HA, L))
    m = H.shape[-2]
    del m
    return FilterElement(
        Ael.expand(*batch, T, n, n),
        b.expand(*batch, T, n),
        C.expand(*batch, T, n, n),
        eta.expand(*batch, T, n),
        J.expand(*batch, T, n, n),
    )


def parallel_filter_moments(data: Data, steps: LinearSteps) -> tuple[Tensor, Tensor]:
    """Filtered means ``(..., T, n)`` and covariances ``(..., T, n, n)`` by an associative scan."""
    el = filter_elements(data, steps)
    tails = (2, 1, 2, 1, 2)
    front = FilterElement(*(_front(x, k) for x, k in zip(el, tails, strict=True)))
    out = associative_scan(_combine_filter, front)
    return _back(out.b, 1), _back(out.C, 2)


def _combine_smoother(a: SmootherElements, b: SmootherElements) -> SmootherElements:
    """``a`` (earlier) with ``b`` (later) in the backward recursion."""
    return SmootherElements(a.E @ b.E, _mv(a.E, b.g) + a.g, symmetrize(a.E @ b.L @ a.E.mT + a.L))


def parallel_smoother_moments(el: SmootherElements) -> tuple[Tensor, Tensor]:
    """Smoothed means ``(..., T, n)`` and covariances ``(..., T, n, n)`` by a reverse scan."""
    tails = (2, 1, 2)
    front = SmootherElements(*(_front(x, k) for x, k in zip(el, tails, strict=True)))
    out = associative_scan(_combine_smoother, front, reverse=True)
    return _back(out.g, 1), _back(out.L, 2)
