"""torchfilt: batched, differentiable cubature Kalman filtering with learned models, in PyTorch.

Layers (each imports only from those before it):
``numerics`` -> ``cubature`` -> ``models`` -> ``filters`` -> ``systems``/``dmc`` -> ``io`` ->
``training``/``plots`` -> ``pipeline`` -> ``cli``.

The top level holds what a newcomer needs (``__all__``): the filters, the main models, the fits,
the metrics, the io entry points and the base errors. Everything else lives in its sub-package
(``torchfilt.models``, ``torchfilt.cubature``, ``torchfilt.numerics``, ``torchfilt.exceptions``,
...), and dynamic matrix control in ``torchfilt.dmc``.

The light core (numerics, cubature, models, filters, systems, io) is imported with the package.
The GP models (gpytorch), training, the pipeline, the plots (matplotlib) and ``dmc`` are imported
on first use of one of their names, so that ``import torchfilt`` stays fast.
"""

from typing import TYPE_CHECKING, Any

from torchfilt import cubature as cubature
from torchfilt import exceptions as exceptions
from torchfilt import filters as filters
from torchfilt import io as io
from torchfilt import models as models
from torchfilt import numerics as numerics
from torchfilt import settings as settings
from torchfilt import systems as systems
from torchfilt._version import __version__
from torchfilt.exceptions import DivergenceWarning, InputError, TorchfiltError
from torchfilt.filters import (
    CKF,
    ConstrainedCKF,
    FilterResult,
    GaussianFilter,
    SmootherResult,
    coverage,
    nees,
    nis,
    rmse,
)
from torchfilt.io import Recording, load_dataset, read_recording, write_recording
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import (
    AffineSensor,
    CalibratedModel,
    InducingTransition,
    LinearGaussianModel,
    StateSpaceModel,
    UncertainParameters,
)
from torchfilt.systems import simulate

if TYPE_CHECKING:
    from torchfilt import dmc as dmc
    from torchfilt import pipeline as pipeline
    from torchfilt import plots as plots
    from torchfilt import training as training
    from torchfilt.models.gp import GPMeasurement, GPModel, GPTransition
    from torchfilt.pipeline import load_bundle, load_model, train_recipe
    from torchfilt.training import (
        calibrate,
        fit_em,
        fit_likelihood,
        fit_measurement_only,
        parameter_posterior,
    )

#: Names whose modules need gpytorch or matplotlib: imported on first access (PEP 562).
_LAZY = {
    "GPMeasurement": "torchfilt.models.gp",
    "GPModel": "torchfilt.models.gp",
    "GPTransition": "torchfilt.models.gp",
    "calibrate": "torchfilt.training",
    "fit_em": "torchfilt.training",
    "fit_likelihood": "torchfilt.training",
    "fit_measurement_only": "torchfilt.training",
    "load_bundle": "torchfilt.pipeline",
    "load_model": "torchfilt.pipeline",
    "parameter_posterior": "torchfilt.training",
    "train_recipe": "torchfilt.pipeline",
}
#: Sub-packages imported on first access (heavy dependencies, or outside the estimation core).
_LAZY_MODULES = ("dmc", "pipeline", "plots", "training")
#: Sub-packages reachable as attributes (listed by ``dir``, not in ``__all__``).
_SUBPACKAGES: tuple[str, ...] = (
    *("cubature", "exceptions", "filters", "io", "models", "numerics", "settings", "systems"),
    *_LAZY_MODULES,
)

#: Names removed from the top level, by their home: they still resolve from the top level, with
#: a DeprecationWarning, for one release.
_MOVED_TO = {
    "torchfilt.dmc": (
        "DMCController",
        "FOPDT",
        "IPDT",
        "LMGPredictor",
        "OpenLoopPredictor",
        "StepResponseModel",
    ),
    "torchfilt.exceptions": (
        "BundleError",
        "CholeskyJitterWarning",
        "ConvergenceWarning",
        "DataError",
        "GaugeError",
        "InfeasibleError",
        "ModelError",
        "NotDetectableError",
        "NumericsWarning",
        "RecipeError",
        "RunError",
        "ShapeError",
        "WorkerError",
    ),
    "torchfilt.filters": ("ConstrainedInfo", "rts_smooth"),
    "torchfilt.models": (
        "Bounded",
        "CholeskyCovariance",
        "ConditionalModel",
        "DiagonalCovariance",
        "ParameterPosterior",
        "Positive",
        "Prediction",
        "ScalarCovariance",
        "TimeVarying",
    ),
    "torchfilt.models.gp": ("FitState",),
    "torchfilt.cubature": ("GaussHermiteRule", "SphericalRadialRule", "UnscentedRule"),
    "torchfilt.numerics": (
        "Box",
        "LeastSquaresResult",
        "SolverStatus",
        "bounded_least_squares",
        "solve_dare",
        "steady_state_kalman",
    ),
    "torchfilt.pipeline": ("evaluate_outputs", "filter_recordings"),
    "torchfilt.training": ("Sequences",),
}
_MOVED = {name: home for home, names in _MOVED_TO.items() for name in names}


def __getattr__(name: str) -> Any:
    import importlib

    if name in _LAZY_MODULES:
        return importlib.import_module(f"torchfilt.{name}")
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    if name in _MOVED:
        import sys
        import warnings

        home = _MOVED[name]
        # ``from torchfilt import X`` asks twice (the import system's ``hasattr``, then the
        # statement's own look-up): warn once, on the second.
        if sys._getframe(1).f_code.co_name != "_handle_fromlist":
            warnings.warn(
                f"torchfilt.{name} is deprecated and will be removed in the next release; "
                f"use {home}.{name}",
                DeprecationWarning,
                stacklevel=2,
            )
        return getattr(importlib.import_module(home), name)
    raise AttributeError(f"module 'torchfilt' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(__all__) | set(_SUBPACKAGES))


__all__ = [
    "CKF",
    "AffineSensor",
    "CalibratedModel",
    "ConstrainedCKF",
    "DivergenceWarning",
    "FilterResult",
    "GPMeasurement",
    "GPModel",
    "GPTransition",
    "GaussianFilter",
    "InducingTransition",
    "InputError",
    "LinearGaussianModel",
    "Recording",
    "SmootherResult",
    "StateSpaceModel",
    "TorchfiltError",
    "UncertainParameters",
    "__version__",
    "calibrate",
    "coverage",
    "fit_em",
    "fit_likelihood",
    "fit_measurement_only",
    "load_bundle",
    "load_dataset",
    "load_model",
    "nees",
    "nis",
    "parameter_posterior",
    "read_recording",
    "rmse",
    "simulate",
    "simulate_dataset",
    "train_recipe",
    "write_recording",
]
