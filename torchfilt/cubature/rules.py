"""Cubature rule objects.

References:
    I. Arasaratnam, S. Haykin, "Cubature Kalman filters", IEEE TAC 54(6), 2009 (third degree).
    B. Jia, M. Xin, Y. Cheng, "High-degree cubature Kalman filter", Automatica 49(2), 2013 (fifth
    degree).
    S. Julier, J. Uhlmann, "Unscented filtering and nonlinear estimation", Proc. IEEE 92(3), 2004;
    E. Wan, R. van der Merwe, "The unscented Kalman filter", 2000 (scaled form used here).
    S. Särkkä, L. Svensson, "Bayesian Filtering and Smoothing", 2nd ed., 2023, ch. 8 (Gauss-Hermite).
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod

import numpy as np
import torch
from torch import Tensor

from torchfilt.exceptions import InputError

__all__ = [
    "CubatureRule",
    "GaussHermiteRule",
    "SphericalRadialRule",
    "UnscentedRule",
    "sigma_points",
]


class CubatureRule(ABC):
    """Points and weights that approximate expectations under ``N(0, I_n)``.

    ``E[g(x)] ~ sum_i wm_i g(xi_i)`` for means and ``sum_i wc_i (.)(.)^T`` for covariances.
    Subclasses implement :meth:`_unit` in float64 NumPy; this class caches the tensors per
    ``(n, dtype, device)``.
    """

    #: Polynomial degree integrated exactly (total degree for the spherical-radial and unscented
    #: rules; per variable for the tensor-product Gauss-Hermite rule).
    degree: int

    def __init__(self) -> None:
        self._cache: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor, Tensor]] = {}

    @abstractmethod
    def _unit(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``(xi (P, n), wm (P,), wc (P,))`` in float64."""

    def num_points(self, n: int) -> int:
        """Number of points the rule uses in dimension ``n``."""
        return int(self._unit(n)[0].shape[0])

    def weights_nonnegative(self, n: int) -> bool:
        """Whether every covariance weight is >= 0 (required by the square-root filter)."""
        return bool((self._unit(n)[2] >= 0).all())

    def unit_points(
        self, n: int, *, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu"
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Unit points and weights as tensors.

        Args:
            n: dimension (>= 1).
            dtype: floating dtype of the result.
            device: device of the result.

        Returns:
            ``(xi, wm, wc)``: the unit points ``xi``, shape ``(P, n)``, the mean weights ``wm``,
            shape ``(P,)``, and the covariance weights ``wc``, shape ``(P,)``.

        Raises:
            InputError: ``n < 1``, or a rule that cannot be built in dimension ``n`` (an
                unscented rule with ``n + lambda <= 0``, a Gauss-Hermite rule of more than
                ``10**7`` points).
        """
        if n < 1:
            raise InputError(f"n must be >= 1, got {n}")
        device = torch.device(device)
        key = (n, dtype, device)
        hit = self._cache.get(key)
        if hit is None:
            xi, wm, wc = self._unit(n)
            hit = tuple(torch.as_tensor(a, dtype=dtype, device=device) for a in (xi, wm, wc))  # type: ignore[assignment]
            self._cache[key] = hit  # type: ignore[assignment]
        return hit  # type: ignore[return-value]

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def sigma_points(mean: Tensor, sqrt: Tensor, xi: Tensor) -> Tensor:
    """Map unit points through ``mean + S xi``.

    Args:
        mean: means, shape ``(..., n)``.
        sqrt: square roots ``S`` with ``S S^T = P``, shape ``(..., n, n)``.
        xi: unit points, shape ``(P, n)``.

    Returns:
        Points, shape ``(..., P, n)``.
    """
    # Stored component-major: X[..., i] (one state component of every point) is contiguous, so
    # models that index x[..., i] work on contiguous vectors (which torch.compile vectorises).
    Xt = mean.movedim(-1, 0).unsqueeze(-1) + (sqrt @ xi.mT).movedim(-2, 0)  # (n, ..., P)
    return Xt.movedim(0, -1)


class SphericalRadialRule(CubatureRule):
    """Spherical-radial cubature rule of degree 3 (the CKF's, ``2n`` points) or 5 (``2n^2+1``).

    Degree 3: ``xi = +-sqrt(n) e_i``, weights ``1/(2n)`` (Arasaratnam & Haykin 2009).
    Degree 5: the centre with weight ``2/(n+2)``, ``+-sqrt(n+2) e_i`` with ``(4-n)/(2(n+2)^2)`` and
    ``+-sqrt((n+2)/2)(e_k +- e_l)``, ``k < l``, with ``1/(n+2)^2`` (Jia, Xin & Cheng 2013). For
    ``n > 4`` some degree-5 weights are negative.

    Args:
        degree: 3 or 5.

    Raises:
        InputError: ``degree`` is neither 3 nor 5.
    """

    def __init__(self, degree: int = 3) -> None:
        super().__init__()
        if degree not in (3, 5):
            raise InputError(f"degree must be 3 or 5, got {degree}")
        self.degree = degree

    def _unit(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        eye = np.eye(n)
        if self.degree == 3:
            xi = math.sqrt(n) * np.concatenate([eye, -eye])
            w = np.full(2 * n, 1.0 / (2 * n))
            return xi, w, w.copy()
        r = math.sqrt(n + 2.0)
        pts = [np.zeros((1, n)), r * eye, -r * eye]
        wts = [
            np.array([2.0 / (n + 2)]),
            np.full(2 * n, (4.0 - n) / (2.0 * (n + 2) ** 2)),
        ]
        pairs = []
        for k, l in itertools.combinations(range(n), 2):
            for sk, sl in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                p = np.zeros(n)
                p[k], p[l] = sk, sl
                pairs.append(p)
        if pairs:
            pts.append(r / math.sqrt(2.0) * np.array(pairs))
            wts.append(np.full(len(pairs), 1.0 / (n + 2) ** 2))
        xi = np.concatenate(pts)
        w = np.concatenate(wts)
        return xi, w, w.copy()

    def __repr__(self) -> str:
        return f"SphericalRadialRule(degree={self.degree})"


class UnscentedRule(CubatureRule):
    """Scaled unscented transform: ``2n+1`` points.

    ``lambda = alpha^2 (n + kappa) - n``; points ``0`` and ``+-sqrt(n + lambda) e_i``; mean weights
    ``lambda/(n+lambda)`` and ``1/(2(n+lambda))``; the centre's covariance weight adds
    ``1 - alpha^2 + beta``.

    Args:
        alpha: spread (default 1).
        beta: prior-knowledge term (default 0; 2 is optimal for Gaussians with alpha < 1).
        kappa: secondary scaling; ``None`` means ``3 - n``, as in Särkkä & Svensson's examples.

    Raises:
        InputError: ``alpha`` is not positive.
    """

    degree = 3

    def __init__(self, alpha: float = 1.0, beta: float = 0.0, kappa: float | None = None) -> None:
        super().__init__()
        if alpha <= 0:
            raise InputError(f"alpha must be positive, got {alpha}")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), kappa

    def _unit(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        kappa = 3.0 - n if self.kappa is None else float(self.kappa)
        lam = self.alpha**2 * (n + kappa) - n
        if n + lam <= 0:
            raise InputError(f"unscented rule needs n + lambda > 0; got {n + lam} for n={n}")
        eye = np.eye(n)
        c = math.sqrt(n + lam)
        xi = np.concatenate([np.zeros((1, n)), c * eye, -c * eye])
        wm = np.full(2 * n + 1, 1.0 / (2.0 * (n + lam)))
        wm[0] = lam / (n + lam)
        wc = wm.copy()
        wc[0] += 1.0 - self.alpha**2 + self.beta
        return xi, wm, wc

    def __repr__(self) -> str:
        return f"UnscentedRule(alpha={self.alpha}, beta={self.beta}, kappa={self.kappa})"


class GaussHermiteRule(CubatureRule):
    """Tensor-product Gauss-Hermite rule with ``order`` points per dimension (``order**n`` points).

    Exact for polynomials of degree ``2 * order - 1`` in each variable.

    Args:
        order: points per dimension (>= 1).

    Raises:
        InputError: ``order < 1``.
    """

    def __init__(self, order: int = 3) -> None:
        super().__init__()
        if order < 1:
            raise InputError(f"order must be >= 1, got {order}")
        self.order = order
        self.degree = 2 * order - 1

    def _unit(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.order**n > 10**7:
            raise InputError(
                f"GaussHermiteRule(order={self.order}) in {n} dims needs too many points"
            )
        x1, w1 = np.polynomial.hermite_e.hermegauss(self.order)
        w1 = w1 / w1.sum()
        grid = np.array(list(itertools.product(range(self.order), repeat=n)))
        xi = x1[grid]
        w = np.prod(w1[grid], axis=1)
        return xi, w, w.copy()

    def __repr__(self) -> str:
        return f"GaussHermiteRule(order={self.order})"
