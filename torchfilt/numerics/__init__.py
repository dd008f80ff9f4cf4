"""Numerics: the small set of linear-algebra kernels every filter builds on.

Nothing here knows about filters or models. Shapes follow the ``(..., n, n)`` convention: any
number of leading batch dimensions.
"""

from torchfilt.numerics.box import Box
from torchfilt.numerics.dtypes import COMPUTE_DTYPES, check_compute_dtype, check_real_tensor
from torchfilt.numerics.linalg import (
    cholesky_ok,
    no_host_sync,
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
from torchfilt.numerics.missing import observed
from torchfilt.numerics.riccati import (
    SteadyStateKalman,
    check_detectable,
    solve_dare,
    steady_state_kalman,
)
from torchfilt.numerics.small import cholesky_solve, solve_tril
from torchfilt.numerics.stats import chi2_quantile, gaussian_log_prob

__all__ = [
    "COMPUTE_DTYPES",
    "Box",
    "LeastSquaresResult",
    "SolverStatus",
    "SteadyStateKalman",
    "batched_jacobian",
    "bounded_least_squares",
    "check_compute_dtype",
    "check_detectable",
    "check_real_tensor",
    "chi2_quantile",
    "cholesky_ok",
    "cholesky_solve",
    "gaussian_log_prob",
    "no_host_sync",
    "observed",
    "psd_solve",
    "safe_cholesky",
    "solve_dare",
    "solve_tril",
    "steady_state_kalman",
    "symmetrize",
    "tria",
]
