"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems``/``dmc`` -> ``io`` ->
``training``/``plots`` -> ``pipeline`` -> ``cli``.
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
    BundleError,
    CholeskyJitterWarning,
    ConvergenceWarning,
    DataError,
    DivergenceWarning,
    InfeasibleError,
    InputError,
    ModelError,
    NotDetectableError,
    NumericsWarning,
    RecipeError,
    RunError,
    ShapeError,
    TorchfiltError,
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
from torchfilt.io import Recording, load_dataset, read_recording, write_recording
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import (
    ConditionalModel,
    LinearGaussianModel,
    Prediction,
    StateSpaceModel,
    TimeVarying,
)
from torchfilt.models.gp import FitState, GPMeasurement, GPModel, GPTransition
from torchfilt.numerics import (
    Box,
    LeastSquaresResult,
    SolverStatus,
    bounded_least_squares,
    solve_dare,
    steady_state_kalman,
)
from torchfilt.pipeline import evaluate_outputs, filter_recordings
from torchfilt.systems import simulate
from torchfilt.training import load_bundle, load_model, train_recipe

__all__ = [
    "CKF",
    "FOPDT",
    "IPDT",
    "Box",
    "BundleError",
    "CholeskyJitterWarning",
    "ConditionalModel",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "ConvergenceWarning",
    "DMCController",
    "DataError",
    "DivergenceWarning",
    "FilterResult",
    "FitState",
    "GPMeasurement",
    "GPModel",
    "GPTransition",
    "GaussHermiteRule",
    "GaussianFilter",
    "InfeasibleError",
    "InputError",
    "LMGPredictor",
    "LeastSquaresResult",
    "LinearGaussianModel",
    "ModelError",
    "NotDetectableError",
    "NumericsWarning",
    "OpenLoopPredictor",
    "Prediction",
    "RecipeError",
    "Recording",
    "RunError",
    "ShapeError",
    "SmootherResult",
    "SolverStatus",
    "SphericalRadialRule",
    "StateSpaceModel",
    "StepResponseModel",
    "TimeVarying",
    "TorchfiltError",
    "UnscentedRule",
    "__version__",
    "bounded_least_squares",
    "coverage",
    "cubature",
    "dmc",
    "evaluate_outputs",
    "exceptions",
    "filter_recordings",
    "filters",
    "load_bundle",
    "load_dataset",
    "load_model",
    "models",
    "nees",
    "nis",
    "numerics",
    "read_recording",
    "rmse",
    "rts_smooth",
    "simulate",
    "simulate_dataset",
    "solve_dare",
    "steady_state_kalman",
    "systems",
    "train_recipe",
    "write_recording",
]
