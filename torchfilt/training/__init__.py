"""Training pipeline: recipes, run directories with dataset logs, metrics and checkpoints, bundles.

``train_recipe`` is the Python twin of ``torchfilt train``; ``load_model`` reads a bundle back as a
state-space model ready for the CKF.
"""

from torchfilt.training.bundle import (
    BUNDLE_SCHEMA,
    BundleError,
    ModelSpec,
    load_bundle,
    load_model,
    load_model_spec,
    save_bundle,
    upgrade_bundle,
)
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
from torchfilt.training.recipe import Recipe, RecipeError, load_recipe
from torchfilt.training.run import LOCAL_FITTERS, RunError, StageFitters, train_recipe
from torchfilt.training.uncertainty import parameter_posterior
from torchfilt.training.validation import one_step_metrics

__all__ = [
    "BUNDLE_SCHEMA",
    "LOCAL_FITTERS",
    "BundleError",
    "CalibrationResult",
    "EMFit",
    "EMState",
    "LikelihoodFit",
    "LikelihoodState",
    "MeasurementOnlyFit",
    "ModelSpec",
    "Recipe",
    "RecipeError",
    "RunError",
    "Sequences",
    "SmoothedPairs",
    "StageFitters",
    "calibrate",
    "check_gauge",
    "consistency",
    "fit_em",
    "fit_likelihood",
    "fit_measurement_only",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "load_recipe",
    "one_step_metrics",
    "parameter_posterior",
    "save_bundle",
    "smoothed_pairs",
    "step_log_likelihood",
    "train_recipe",
    "upgrade_bundle",
]
