"""Workflows behind the command line: filter recordings, evaluate estimates, simulate datasets.

Every ``torchfilt`` CLI command has its Python twin here (``torchfilt.pipeline.filter_recordings``
is ``torchfilt filter``, and so on); :mod:`torchfilt.pipeline.distributed` runs filtering and
training as Ray tasks (``--ray``; Ray is the optional extra ``torchfilt[distributed]``).
"""

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

__all__ = [
    "ModelSpec",
    "calibrate_ray",
    "check_device",
    "evaluate_outputs",
    "filter_recordings",
    "filter_recordings_ray",
    "fit_measurement_only_ray",
    "output_names",
    "resolve_model",
    "shard_plan",
    "train_recipe_data_parallel",
    "train_recipes_ray",
]
