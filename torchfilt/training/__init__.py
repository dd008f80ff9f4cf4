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
from torchfilt.training.recipe import Recipe, RecipeError, load_recipe
from torchfilt.training.run import RunError, train_recipe
from torchfilt.training.validation import one_step_metrics

__all__ = [
    "BUNDLE_SCHEMA",
    "BundleError",
    "CalibrationResult",
    "LikelihoodFit",
    "LikelihoodState",
    "ModelSpec",
    "Recipe",
    "RecipeError",
    "RunError",
    "Sequences",
    "calibrate",
    "consistency",
    "fit_likelihood",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "load_recipe",
    "one_step_metrics",
    "save_bundle",
    "step_log_likelihood",
    "train_recipe",
    "upgrade_bundle",
]
