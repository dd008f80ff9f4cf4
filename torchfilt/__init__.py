"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems`` / ``training``, ``io``,
``cli``, ``plots``.
"""

from torchfilt import cubature, exceptions, filters, models, numerics, systems
from torchfilt.cubature import GaussHermiteRule, SphericalRadialRule, UnscentedRule
from torchfilt.exceptions import (
    CholeskyJitterWarning,
    DivergenceWarning,
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
from torchfilt.systems import simulate

__version__ = "0.1.0"

__all__ = [
    "CKF",
    "CholeskyJitterWarning",
    "ConditionalModel",
    "DivergenceWarning",
    "FilterResult",
    "GaussHermiteRule",
    "GaussianFilter",
    "LinearGaussianModel",
    "NumericsWarning",
    "Prediction",
    "ShapeError",
    "SmootherResult",
    "SphericalRadialRule",
    "StateSpaceModel",
    "TimeVarying",
    "UnscentedRule",
    "coverage",
    "cubature",
    "exceptions",
    "filters",
    "models",
    "nees",
    "nis",
    "numerics",
    "rmse",
    "rts_smooth",
    "simulate",
    "systems",
]
