"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems`` / ``training``, ``io``,
``cli``, ``plots``.
"""

from torchfilt import cubature, dmc, exceptions, filters, models, numerics, systems
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
    DivergenceWarning,
    NotDetectableError,
    NumericsWarning,
    ShapeError,
)
from torchfilt.filters import (
    CKF,
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
from torchfilt.numerics import solve_dare, steady_state_kalman
from torchfilt.systems import simulate

__version__ = "0.1.0"

__all__ = [
    "CKF",
    "FOPDT",
    "IPDT",
    "CholeskyJitterWarning",
    "ConditionalModel",
    "DMCController",
    "DivergenceWarning",
    "FilterResult",
    "GaussHermiteRule",
    "GaussianFilter",
    "LMGPredictor",
    "LinearGaussianModel",
    "NotDetectableError",
    "NumericsWarning",
    "OpenLoopPredictor",
    "Prediction",
    "ShapeError",
    "SmootherResult",
    "SphericalRadialRule",
    "StateSpaceModel",
    "StepResponseModel",
    "TimeVarying",
    "UnscentedRule",
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
