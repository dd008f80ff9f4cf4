"""Roots of ``(K + s^2 I)^{-1}`` for the predictive variance ``k** - |k*^T R|^2``.

Exact (not built here: the predictor keeps the Cholesky factor ``L`` of ``K + s^2 I`` and solves
``L w = k*``, which reads half the memory of a dense root): ``|w|^2 = k*^T (K + s^2 I)^{-1} k*``.

Low rank: for an orthonormal basis ``Q`` (``S x r``) and the Ritz decomposition
``Q^T (K + s^2 I) Q = V diag(lam) V^T``, ``R = Q V diag(lam)^{-1/2}``. For any basis this gives a
lower bound on the quadratic form (its variational form ``max_v 2 v^T k - v^T (K + s^2 I) v``
restricted to ``span(Q)``), so the low-rank variance is never below the exact one: it errs on the
conservative side. ``Q`` spans the top ``r`` eigenvectors of ``K``, found by randomised subspace
iteration (Halko, Martinsson & Tropp 2011, alg. 4.4) with a fixed seed. This is the role LOVE's
Lanczos root plays in GPyTorch (Pleiss et al. 2018), with one root per output instead of one shared.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["lowrank_root"]

#: Extra basis vectors of the randomised range finder.
OVERSAMPLE = 16
#: Power (subspace) iterations of the randomised range finder.
POWER_ITERS = 3
#: Seed of the range finder's random start (roots are deterministic).
ROOT_SEED = 0


def lowrank_root(Khat: Tensor, rank: int) -> Tensor:
    """A rank-``r`` root ``R`` ``(..., S, r)`` with ``R R^T <= (K + s^2 I)^{-1}`` on ``span(R)``.

    Columns are ordered by decreasing Ritz value, so ``R[..., :q]`` is itself a valid rank-``q``
    root (nested truncation).

    Args:
        Khat: ``K + s^2 I``, shape ``(..., S, S)``.
        rank: ``r`` (clipped to ``S``).

    Returns:
        The root, shape ``(..., S, min(r, S))``.
    """
    S = Khat.shape[-1]
    r = min(rank, S)
    k = min(S, r + OVERSAMPLE)
    gen = torch.Generator(device="cpu").manual_seed(ROOT_SEED)
    omega = torch.randn((*Khat.shape[:-2], S, k), generator=gen, dtype=Khat.dtype)
    Q = torch.linalg.qr(Khat @ omega.to(Khat.device)).Q
    for _ in range(POWER_ITERS):
        Q = torch.linalg.qr(Khat @ Q).Q
    T = Q.mT @ Khat @ Q
    lam, V = torch.linalg.eigh(0.5 * (T + T.mT))
    lam, V = lam.flip(-1)[..., :r], V.flip(-1)[..., :r]  # the r largest, decreasing
    return (Q @ V) * lam.clamp_min(torch.finfo(Khat.dtype).tiny).rsqrt().unsqueeze(-2)
