"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems``/``dmc`` -> ``io`` ->
``training``/``plots`` -> ``pipeline`` -> ``cli``.

The light core (numerics, cubature, models, filters, systems, dmc, io) is imported with the
package. The GP models (gpytorch), training, the pipeline and the plots (matplotlib) are imported on
first use of one of their names, so that ``import torchfilt`` stays fast.
"""

from typing import TYPE_CHECKING, Any

from torchfilt import cubature, dmc, exceptions, filters, models, numerics, settings, systems
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
    GaugeError,
    InfeasibleError,
    InputError,
    ModelError,
    NotDetectableError,
    NumericsWarning,
    RecipeError,
    RunError,
    ShapeError,
    TorchfiltError,
    WorkerError,
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
    AffineSensor,
    Bounded,
    CalibratedModel,
    CholeskyCovariance,
    ConditionalModel,
    DiagonalCovariance,
    InducingTransition,
    LinearGaussianModel,
    ParameterPosterior,
    Positive,
    Prediction,
    ScalarCovariance,
    StateSpaceModel,
    TimeVarying,
    UncertainParameters,
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

if TYPE_CHECKING:
    from torchfilt.models.gp import FitState, GPMeasurement, GPModel, GPTransition
    from torchfilt.pipeline import evaluate_outputs, filter_recordings
    from torchfilt.training import (
        Sequences,
        calibrate,
        fit_em,
        fit_likelihood,
        fit_measurement_only,
        load_bundle,
        load_model,
        parameter_posterior,
        train_recipe,
    )

#: Names whose modules need gpytorch or matplotlib: imported on first access (PEP 562).
_LAZY = {
    "FitState": "torchfilt.models.gp",
    "GPMeasurement": "torchfilt.models.gp",
    "GPModel": "torchfilt.models.gp",
    "GPTransition": "torchfilt.models.gp",
    "evaluate_outputs": "torchfilt.pipeline",
    "filter_recordings": "torchfilt.pipeline",
    "Sequences": "torchfilt.training",
    "calibrate": "torchfilt.training",
    "fit_em": "torchfilt.training",
    "fit_likelihood": "torchfilt.training",
    "fit_measurement_only": "torchfilt.training",
    "load_bundle": "torchfilt.pipeline",
    "load_model": "torchfilt.pipeline",
    "parameter_posterior": "torchfilt.training",
    "train_recipe": "torchfilt.pipeline",
}
_LAZY_MODULES = ("pipeline", "plots", "training")


def __getattr__(name: str) -> Any:
    import importlib

    if name in _LAZY_MODULES:
        return importlib.import_module(f"torchfilt.{name}")
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchfilt' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | set(_LAZY_MODULES))


__all__ = [
    "CKF",
    "FOPDT",
    "IPDT",
    "AffineSensor",
    "Bounded",
    "Box",
    "BundleError",
    "CalibratedModel",
    "CholeskyCovariance",
    "CholeskyJitterWarning",
    "ConditionalModel",
    "ConstrainedCKF",
    "ConstrainedInfo",
    "ConvergenceWarning",
    "DMCController",
    "DataError",
    "DiagonalCovariance",
    "DivergenceWarning",
    "FilterResult",
    "FitState",
    "GPMeasurement",
    "GPModel",
    "GPTransition",
    "GaugeError",
    "GaussHermiteRule",
    "GaussianFilter",
    "InducingTransition",
    "InfeasibleError",
    "InputError",
    "LMGPredictor",
    "LeastSquaresResult",
    "LinearGaussianModel",
    "ModelError",
    "NotDetectableError",
    "NumericsWarning",
    "OpenLoopPredictor",
    "ParameterPosterior",
    "Positive",
    "Prediction",
    "RecipeError",
    "Recording",
    "RunError",
    "ScalarCovariance",
    "Sequences",
    "ShapeError",
    "SmootherResult",
    "SolverStatus",
    "SphericalRadialRule",
    "StateSpaceModel",
    "StepResponseModel",
    "TimeVarying",
    "TorchfiltError",
    "UncertainParameters",
    "UnscentedRule",
    "WorkerError",
    "__version__",
    "bounded_least_squares",
    "calibrate",
    "coverage",
    "cubature",
    "dmc",
    "evaluate_outputs",
    "exceptions",
    "filter_recordings",
    "filters",
    "fit_em",
    "fit_likelihood",
    "fit_measurement_only",
    "load_bundle",
    "load_dataset",
    "load_model",
    "models",
    "nees",
    "nis",
    "numerics",
    "parameter_posterior",
    "read_recording",
    "rmse",
    "rts_smooth",
    "settings",
    "simulate",
    "simulate_dataset",
    "solve_dare",
    "steady_state_kalman",
    "systems",
    "train_recipe",
    "write_recording",
]
