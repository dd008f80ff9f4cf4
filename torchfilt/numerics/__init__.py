"""Numerics: the small set of linear-algebra kernels every filter builds on.

Nothing here knows about filters or models. Shapes follow the ``(..., n, n)`` convention: any
number of leading batch dimensions.
"""

from torchfilt.numerics.box import Box
from torchfilt.numerics.linalg import (
    cholesky_ok,
    psd_solve,
    safe_cholesky,
    symmetrize,
    tria,
)
from torchfilt.numerics.lsq import (
    LeastSquaresResult,
    SolverStatus,
    batched_jacobian,
    bounded_least_squares,
)
from torchfilt.numerics.stats import chi2_quantile, gaussian_log_prob

__all__ = [
    "Box",
    "LeastSquaresResult",
    "SolverStatus",
    "batched_jacobian",
    "bounded_least_squares",
    "chi2_quantile",
    "cholesky_ok",
    "gaussian_log_prob",
    "psd_solve",
    "safe_cholesky",
    "symmetrize",
    "tria",
]
