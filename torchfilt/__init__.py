"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems`` / ``training``, ``io``,
``cli``, ``plots``.
"""

from torchfilt import cubature, dmc, exceptions, filters, models, numerics, systems
from torchfilt._version import __version__
from torchfilt.cubature import GaussHermiteRule, SphericalRadialRule, UnscentedRule
from torchfilt.dmc import (
    FOPDT,
    IPDT,
    DMCController,
    LMGPredictor,
    OpenLoopPredictor,
    StepResponseModel,
)
from torchfilt.exceptions import (
    CholeskyJitterWarning,
    ConvergenceWarning,
    DivergenceWarning,
    NotDetectableError,
    NumericsWarning,
    ShapeError,
)
from torchfilt.filters import (
    CKF,
    ConstrainedCKF,
    ConstrainedInfo,
    FilterResult,
    GaussianFilter,
    SmootherResult,
    coverage,
    nees,
    nis,
    rmse,
    rts_smooth,
)
from torchfilt.models import (
    ConditionalModel,
    LinearGaussianModel,
    Prediction,
    StateSpaceModel,
    TimeVarying,
)
from torchfilt.numerics import (
    Box,
    LeastSquaresResult,
    SolverStatus,
    bounded_least_squares,
    solve_dare,
    steady_state_kalman,
)
from torchfilt.systems import simulate

__all__ = [
    "CKF",
    "FOPDT",
    "IPDT",
    "Box",
    "CholeskyJitterWarning",
    "ConditionalModel",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "ConvergenceWarning",
    "DMCController",
    "DivergenceWarning",
    "FilterResult",
    "GaussHermiteRule",
    "GaussianFilter",
    "LMGPredictor",
    "LeastSquaresResult",
    "LinearGaussianModel",
    "NotDetectableError",
    "NumericsWarning",
    "OpenLoopPredictor",
    "Prediction",
    "ShapeError",
    "SmootherResult",
    "SolverStatus",
    "SphericalRadialRule",
    "StateSpaceModel",
    "StepResponseModel",
    "TimeVarying",
    "UnscentedRule",
    "__version__",
    "bounded_least_squares",
    "coverage",
    "cubature",
    "dmc",
    "exceptions",
    "filters",
    "models",
    "nees",
    "nis",
    "numerics",
    "rmse",
    "rts_smooth",
    "simulate",
    "solve_dare",
    "steady_state_kalman",
    "systems",
]
