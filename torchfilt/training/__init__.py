"""Fitting algorithms: the filter likelihood (``fit_likelihood``), the calibration of variance
scales and floors (``calibrate``), learning from measurements alone (``fit_measurement_only``,
``fit_em``), the parameter posterior and the one-step validation metrics.

Recipes, run directories and model bundles are pipeline work: they live in
:mod:`torchfilt.pipeline` (``train_recipe``, ``load_bundle``, ``load_model``, ``Recipe``, ...).
Their old names here (``torchfilt.training.train_recipe`` and the modules
``torchfilt.training.recipe``, ``.run``, ``.bundle``) still work for one release, with a
``DeprecationWarning``.
"""

import importlib
import warnings
from typing import Any

from torchfilt.exceptions import BundleError, RecipeError, RunError
from torchfilt.training.calibrate import CalibrationResult, calibrate, consistency
from torchfilt.training.likelihood import (
    LikelihoodFit,
    LikelihoodState,
    Sequences,
    fit_likelihood,
    step_log_likelihood,
)
from torchfilt.training.measurement_only import (
    EMFit,
    EMState,
    MeasurementOnlyFit,
    SmoothedPairs,
    check_gauge,
    fit_em,
    fit_measurement_only,
    smoothed_pairs,
)
from torchfilt.training.noise_scale import (
    NoiseScale,
    held_out_noise_scale,
    with_process_noise_scale,
)
from torchfilt.training.uncertainty import parameter_posterior
from torchfilt.training.validation import one_step_metrics

__all__ = [
    "BundleError",
    "CalibrationResult",
    "EMFit",
    "EMState",
    "LikelihoodFit",
    "LikelihoodState",
    "MeasurementOnlyFit",
    "NoiseScale",
    "RecipeError",
    "RunError",
    "Sequences",
    "SmoothedPairs",
    "calibrate",
    "check_gauge",
    "consistency",
    "fit_em",
    "fit_likelihood",
    "fit_measurement_only",
    "held_out_noise_scale",
    "one_step_metrics",
    "parameter_posterior",
    "smoothed_pairs",
    "step_log_likelihood",
    "with_process_noise_scale",
]

#: Names that moved to :mod:`torchfilt.pipeline` (deprecated here; remove in the next release).
_MOVED_TO_PIPELINE = (
    "BUNDLE_SCHEMA",
    "LOCAL_FITTERS",
    "ModelSpec",
    "Recipe",
    "StageFitters",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "load_recipe",
    "save_bundle",
    "train_recipe",
    "upgrade_bundle",
)


def __getattr__(name: str) -> Any:
    """The deprecated names of :data:`_MOVED_TO_PIPELINE`, with a ``DeprecationWarning``.

    They are looked up with ``importlib`` when first used, not imported: ``training`` (layer 7)
    must not import ``pipeline`` (layer 8), and ``tests/test_architecture.py`` allows this
    reference only in the deprecated shims it names."""
    if name in _MOVED_TO_PIPELINE:
        warnings.warn(
            f"torchfilt.training.{name} is deprecated; use torchfilt.pipeline.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module("torchfilt.pipeline"), name)
    raise AttributeError(f"module 'torchfilt.training' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_MOVED_TO_PIPELINE))
