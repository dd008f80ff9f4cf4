"""Workflows behind the command line: train recipes into model bundles, filter recordings,
evaluate estimates.

Every ``torchfilt`` CLI command has its Python twin here (``torchfilt.pipeline.filter_recordings``
is ``torchfilt filter``, ``torchfilt.pipeline.train_recipe`` is ``torchfilt train``, and so on).
:mod:`~torchfilt.pipeline.recipe` reads and checks recipes, :mod:`~torchfilt.pipeline.run` runs one
into a run directory (its stages in :mod:`~torchfilt.pipeline.run_stages`, the checks against the
dataset in :mod:`~torchfilt.pipeline.run_checks`), :mod:`~torchfilt.pipeline.bundle` writes and
verifies model bundles, :mod:`~torchfilt.pipeline.offline` filters recordings, and
:mod:`torchfilt.pipeline.distributed` runs filtering and training as Ray tasks (``--ray``; Ray is
the optional extra ``torchfilt[distributed]``). The fitting algorithms the stages call live in
:mod:`torchfilt.training`.
"""

from torchfilt.exceptions import BundleError, RecipeError, RunError
from torchfilt.pipeline.bundle import (
    BUNDLE_SCHEMA,
    load_bundle,
    load_model,
    load_model_spec,
    save_bundle,
    upgrade_bundle,
)
from torchfilt.pipeline.distributed import (
    calibrate_ray,
    filter_recordings_ray,
    fit_measurement_only_ray,
    train_recipe_data_parallel,
    train_recipes_ray,
)
from torchfilt.pipeline.evaluate import evaluate_outputs
from torchfilt.pipeline.offline import (
    ModelSpec,
    check_device,
    filter_recordings,
    output_names,
    resolve_model,
    shard_plan,
)
from torchfilt.pipeline.recipe import Recipe, load_recipe
from torchfilt.pipeline.run import LOCAL_FITTERS, StageFitters, train_recipe

__all__ = [
    "BUNDLE_SCHEMA",
    "LOCAL_FITTERS",
    "BundleError",
    "ModelSpec",
    "Recipe",
    "RecipeError",
    "RunError",
    "StageFitters",
    "calibrate_ray",
    "check_device",
    "evaluate_outputs",
    "filter_recordings",
    "filter_recordings_ray",
    "fit_measurement_only_ray",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "load_recipe",
    "output_names",
    "resolve_model",
    "save_bundle",
    "shard_plan",
    "train_recipe",
    "train_recipe_data_parallel",
    "train_recipes_ray",
    "upgrade_bundle",
]
