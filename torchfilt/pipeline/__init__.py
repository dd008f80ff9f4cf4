"""Workflows behind the command line: filter recordings, evaluate estimates, simulate datasets.

Every ``torchfilt`` CLI command has its Python twin here (``torchfilt.pipeline.filter_recordings``
is ``torchfilt filter``, and so on).
"""

from torchfilt.pipeline.evaluate import evaluate_outputs
from torchfilt.pipeline.offline import ModelSpec, filter_recordings, resolve_model

__all__ = ["ModelSpec", "evaluate_outputs", "filter_recordings", "resolve_model"]
