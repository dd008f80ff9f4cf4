"""Workflows behind the command line: filter recordings, evaluate estimates, simulate datasets.

Every ``torchfilt`` CLI command has its Python twin here (``torchfilt.pipeline.filter_recordings``
is ``torchfilt filter``, and so on).
"""

from torchfilt.pipeline.evaluate import evaluate_outputs
from torchfilt.pipeline.offline import (
    ModelSpec,
    check_device,
    filter_recordings,
    output_names,
    resolve_model,
)

__all__ = [
    "ModelSpec",
    "check_device",
    "evaluate_outputs",
    "filter_recordings",
    "output_names",
    "resolve_model",
]
