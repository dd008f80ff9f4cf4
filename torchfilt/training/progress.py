"""Deprecated: the progress bar moved to :mod:`torchfilt.io.progress` (remove in the next release).

Importing this module warns once (``DeprecationWarning``); :class:`ProgressBar` is the same class.
"""

import warnings

from torchfilt.io.progress import ProgressBar

warnings.warn(
    "torchfilt.training.progress is deprecated; use torchfilt.io.progress",
    DeprecationWarning,
    stacklevel=2,
)

__all__ = ["ProgressBar"]
