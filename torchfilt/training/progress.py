"""The progress bar moved to :mod:`torchfilt.io.progress`; this path still imports it.

Deprecated: remove after the callers move (``training/likelihood.py`` and
``training/measurement_only.py`` still import it from here, so importing it does not warn yet).
"""

from torchfilt.io.progress import ProgressBar

__all__ = ["ProgressBar"]
