"""Roots of ``(K + s^2 I)^{-1}`` for the predictive variance ``k** - |k*^T R|^2``.

Exact (not built here: the predictor keeps the Cholesky factor ``L`` of ``K + s^2 I`` and solves
``L w = k*``, which reads half the memory of a dense root): ``|w|^2 = k*^T (K + s^2 I)^{-1} k*``.

Low rank: for an orthonormal basis ``Q`` (``S x r``) and the Ritz decomposition
``Q^T (K + s^2 I) Q = V diag(lam) V^T``, ``R = Q V diag(lam)^{-1/2}``. For any basis this gives a
lower bound on the quadratic form (its variational form ``max_v 2 v^T k - v^T (K + s^2 I) v``
restricted to ``span(Q)``), so the low-rank variance is never below the exact one: it errs on the
conservative side. ``Q`` joins approximate top eigenvectors of ``K`` (randomised subspace iteration,
Halko, Martinsson & Tropp 2011, alg. 4.4, fixed seed) and "anchor" directions
``(K + s^2 I)^{-1} k(X, z)`` for a random subset ``z`` of the training inputs: top eigenvectors alone
miss the fine structure that dominates the variance of a nearly noise-free GP near its data (on the
re-entry transition a rank-512 eigen root was off by 6x, the joined basis by 0.7 %). This is the
role LOVE's Lanczos root plays in GPyTorch (Pleiss et al. 2018), with one root per output instead of
one shared.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["anchor_basis", "eigen_basis", "lowrank_root", "ritz_root"]

#: Extra basis vectors of the randomised range finder.
OVERSAMPLE = 16
#: Power (subspace) iterations of the randomised range finder.
POWER_ITERS = 3
#: One in this many basis vectors of a low-rank root is an anchor direction.
ANCHOR_SHARE = 4
#: Seed of the range finder's random start (roots are deterministic).
ROOT_SEED = 0


def eigen_basis(Khat: Tensor, count: int) -> Tensor:
    """Orthonormal approximations of the top ``count`` eigenvectors of ``Khat`` ``(..., S, S)``,
    by randomised subspace iteration; columns in decreasing order of their Ritz values."""
    S = Khat.shape[-1]
    r = min(count, S)
    k = min(S, r + OVERSAMPLE)
    gen = torch.Generator(device="cpu").manual_seed(ROOT_SEED)
    omega = torch.randn((*Khat.shape[:-2], S, k), generator=gen, dtype=Khat.dtype)
    Q = torch.linalg.qr(Khat @ omega.to(Khat.device)).Q
    for _ in range(POWER_ITERS):
        Q = torch.linalg.qr(Khat @ Q).Q
    T = Q.mT @ Khat @ Q
    _, V = torch.linalg.eigh(0.5 * (T + T.mT))
    return (Q @ V.flip(-1))[..., :r]


def anchor_basis(K: Tensor, L: Tensor, count: int) -> Tensor:
    """``(K + s^2 I)^{-1} K[:, Z]`` for ``count`` anchor inputs ``Z`` (a fixed random subset of the
    training inputs): with it in the basis, the low-rank variance is exact at the anchors.

    Args:
        K: noise-free kernel matrix ``(..., S, S)``.
        L: Cholesky factor of ``K + s^2 I``.
        count: number of anchors.
    """
    S = K.shape[-1]
    gen = torch.Generator(device="cpu").manual_seed(ROOT_SEED + 1)
    idx = torch.randperm(S, generator=gen)[: min(count, S)].to(K.device)
    return torch.cholesky_solve(K[..., idx], L)


def ritz_root(Khat: Tensor, basis: Tensor) -> Tensor:
    """``R = Q V diag(lam)^{-1/2}`` from ``Q = orth(basis)``, ``Q^T Khat Q = V diag(lam) V^T``."""
    Q = torch.linalg.qr(basis).Q
    T = Q.mT @ Khat @ Q
    lam, V = torch.linalg.eigh(0.5 * (T + T.mT))
    return (Q @ V) * lam.clamp_min(torch.finfo(Khat.dtype).tiny).rsqrt().unsqueeze(-2)


def lowrank_root(K: Tensor, Khat: Tensor, L: Tensor, rank: int) -> Tensor:
    """A rank-``r`` root ``R`` ``(..., S, r)``: ``|R^T k*|^2 <= k*^T (K + s^2 I)^{-1} k*``.

    The basis joins ``r - r/4`` approximate top eigenvectors (the smooth, global part) and ``r/4``
    anchor directions (:func:`anchor_basis`: the fine structure near the data, which top
    eigenvectors miss when the noise is small).

    Args:
        K: noise-free kernel matrix ``(..., S, S)``.
        Khat: ``K + s^2 I``.
        L: Cholesky factor of ``Khat``.
        rank: ``r`` (clipped to ``S``).

    Returns:
        The root, shape ``(..., S, min(r, S))``.
    """
    r = min(rank, Khat.shape[-1])
    n_anchor = r // ANCHOR_SHARE
    parts = [eigen_basis(Khat, r - n_anchor)]
    if n_anchor:
        parts.append(anchor_basis(K, L, n_anchor))
    return ritz_root(Khat, torch.cat(parts, -1))
