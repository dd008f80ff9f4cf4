"""Deprecated: this module moved to :mod:`torchfilt.pipeline.recipe` (remove in the next release).

Importing it warns once (``DeprecationWarning``) and every name resolves to the new module.
"""

import importlib
import warnings
from typing import Any

warnings.warn(
    "torchfilt.training.recipe is deprecated; use torchfilt.pipeline.recipe",
    DeprecationWarning,
    stacklevel=2,
)

# importlib, not an import statement: training (layer 7) must not import pipeline (layer 8), and
# tests/test_architecture.py allows this reference only in the deprecated shims it names.
_NEW = [importlib.import_module(m) for m in ("torchfilt.pipeline.recipe",)]
__all__ = list(_NEW[0].__all__)


def __getattr__(name: str) -> Any:
    for module in _NEW:
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module 'torchfilt.training.recipe' has no attribute {name!r}")
