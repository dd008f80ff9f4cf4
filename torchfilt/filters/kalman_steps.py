"""The pure steps of the closed-form Kalman filter: predict and update, plain and square-root.

The equations are in :mod:`torchfilt.filters.kalman`; the runners of
:mod:`torchfilt.filters.kalman_runners` run them over time.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.numerics import cholesky_solve, safe_cholesky, solve_tril, symmetrize, tria

__all__ = ["Belief", "Update", "predict", "predict_sqrt", "update", "update_sqrt"]


class Belief(NamedTuple):
    """A Gaussian belief ``N(mean, cov)``.

    Attributes:
        mean: ``(..., n)``.
        cov: the covariance ``(..., n, n)``, or in the square-root functions its lower Cholesky
            factor.
    """

    mean: Tensor
    cov: Tensor


# ---------------------------------------------------------------------------------- pure steps
def _mv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` for ``M (..., a, b)``, ``v (..., b)`` with broadcasting batch dimensions."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def predict(belief: Belief, A: Tensor, c: Tensor | None, Q: Tensor) -> tuple[Belief, Tensor]:
    """Kalman prediction.

    Args:
        belief: ``N(m, P)`` of ``x_{t-1}``, ``(..., n)`` and ``(..., n, n)``.
        A: ``(..., n, n)``.  c: offset ``(..., n)`` or ``None``.  Q: ``(..., n, n)``.

    Returns:
        The predicted belief of ``x_t`` and the cross-covariance ``Cov(x_{t-1}, x_t) = P A^T``.
    """
    m, P = belief
    mp = _mv(A, m)
    if c is not None:
        mp = mp + c
    cross = P @ A.mT
    return Belief(mp, symmetrize(A @ cross + Q)), cross


def predict_sqrt(belief: Belief, A: Tensor, c: Tensor | None, Q_sqrt: Tensor) -> Belief:
    """Square-root Kalman prediction: ``S^- = tria([A S, Q^{1/2}])``.

    Args:
        belief: mean ``(..., n)`` and lower Cholesky factor ``S (..., n, n)``.
        A: ``(..., n, n)``.  c: ``(..., n)`` or ``None``.  Q_sqrt: ``(..., n, n)``.
    """
    m, S = belief
    mp = _mv(A, m)
    if c is not None:
        mp = mp + c
    AS = A @ S
    batch = torch.broadcast_shapes(AS.shape[:-2], Q_sqrt.shape[:-2])
    return Belief(
        mp,
        tria(
            torch.cat(
                [AS.expand(*batch, *AS.shape[-2:]), Q_sqrt.expand(*batch, *Q_sqrt.shape[-2:])], -1
            )
        ),
    )


class Update(NamedTuple):
    """An update's belief and the factor of its innovation covariance.

    Attributes:
        belief: ``N(m_t, P_t)`` (square-root form: ``S_t``).
        innov_chol: lower Cholesky factor of ``S_t`` restricted to the observed components (unit
            rows and columns for the others), ``(..., m, m)``.
        residual: ``y - H m^- - d`` with zeros where not observed, ``(..., m)``.
    """

    belief: Belief
    innov_chol: Tensor
    residual: Tensor


def update(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
) -> Update:
    """Kalman update with missing components.

    Args:
        belief: predicted ``N(m^-, P^-)``, ``(..., n)`` and ``(..., n, n)``.
        y: measurement ``(..., m)`` (any value where not observed).
        obs: bool ``(..., m)``, ``True`` where observed, or ``None`` for all observed.
        H: ``(..., m, n)``.  d: offset ``(..., m)`` or ``None``.  R: ``(..., m, m)``.
    """
    mp, Pp = belief
    PHt = Pp @ H.mT  # (..., n, m)
    S = H @ PHt + R
    yp = _mv(H, mp)
    if d is not None:
        yp = yp + d
    e = y - yp
    if obs is not None:
        o = obs.to(mp.dtype)
        S = S * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
        PHt = PHt * o.unsqueeze(-2)
        e = e * o
    L = safe_cholesky(S, name="innovation covariance")
    K = cholesky_solve(PHt.mT, L).mT  # (..., n, m)
    m = mp + _mv(K, e)
    P = symmetrize(Pp - K @ PHt.mT)
    return Update(Belief(m, P), L, e)


def update_sqrt(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    H: Tensor,
    d: Tensor | None,
    R_sqrt: Tensor,
) -> Update:
    """Square-root Kalman update by one triangularisation of the array
    ``[[R^{1/2}, H S^-], [0, S^-]]`` (missing rows zeroed, with a unit column each).

    Args as in :func:`update`, with ``belief.cov`` the predicted factor ``S^- (..., n, n)`` and
    ``R_sqrt (..., m, m)`` a square root of ``R``.
    """
    mp, Sp = belief
    n, m = Sp.shape[-1], H.shape[-2]
    HS = H @ Sp
    yp = _mv(H, mp)
    if d is not None:
        yp = yp + d
    e = y - yp
    batch = torch.broadcast_shapes(HS.shape[:-2], R_sqrt.shape[:-2], Sp.shape[:-2])
    top = [R_sqrt.expand(*batch, m, m), HS.expand(*batch, m, n)]
    bottom = [Sp.new_zeros(()).expand(*batch, n, m), Sp.expand(*batch, n, n)]
    if obs is not None:
        o = obs.to(mp.dtype)
        rows = o.unsqueeze(-1)
        top = [top[0] * rows, torch.diag_embed(1.0 - o).expand(*batch, m, m), top[1] * rows]
        bottom = [bottom[0], bottom[0], bottom[1]]
        e = e * o
    post = tria(torch.cat([torch.cat(top, -1), torch.cat(bottom, -1)], -2))
    L = post[..., :m, :m]
    Kb = post[..., m:, :m]  # K L
    S = post[..., m:, m:]
    z = solve_tril(L, e.unsqueeze(-1)).squeeze(-1)
    return Update(Belief(mp + _mv(Kb, z), S), L, e)


def _psd_sqrt(A: Tensor) -> Tensor:
    """A square root of PSD matrices: Cholesky where definite, else the eigen-decomposition."""
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info == 0).all()):
        return L
    evals, evecs = torch.linalg.eigh(symmetrize(A))
    return evecs * evals.clamp_min(0.0).sqrt().unsqueeze(-2)


def _psd_sqrt_steps(X: Tensor) -> Tensor:
    """Square roots of ``(..., T, d, d)``; one factorisation when ``X`` is an expanded constant."""
    if X.stride(-3) == 0:
        base = _psd_sqrt(X.select(-3, 0))
        return base.unsqueeze(-3).expand(X.shape)
    return _psd_sqrt(X)
