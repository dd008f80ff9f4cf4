"""Cubature rules: deterministic point sets that integrate against a standard Gaussian.

A rule supplies unit points ``xi`` (``(P, n)``) and weights for ``N(0, I_n)``; a Gaussian filter maps
them through ``mu + S xi`` with ``S S^T = P``. Every filter in torchfilt takes any rule, so the
CKF with :class:`UnscentedRule` is the UKF and with :class:`GaussHermiteRule` the Gauss-Hermite
filter.
"""

from torchfilt.cubature.constrained import ConstrainedPoints, constrained_points
from torchfilt.cubature.rules import (
    CubatureRule,
    GaussHermiteRule,
    SphericalRadialRule,
    UnscentedRule,
    sigma_points,
)

__all__ = [
    "ConstrainedPoints",
    "CubatureRule",
    "GaussHermiteRule",
    "SphericalRadialRule",
    "UnscentedRule",
    "constrained_points",
    "sigma_points",
]
