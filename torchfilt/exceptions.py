"""Named warnings and errors raised by torchfilt.

Every layer may import this module; it imports nothing from torchfilt.
"""

from __future__ import annotations

__all__ = [
    "CholeskyJitterWarning",
    "ConvergenceWarning",
    "DivergenceWarning",
    "NotDetectableError",
    "NumericsWarning",
    "ShapeError",
    "TorchfiltWarning",
]


class TorchfiltWarning(UserWarning):
    """Base class of every warning torchfilt emits."""


class NumericsWarning(TorchfiltWarning, RuntimeWarning):
    """A numerical safeguard changed the computation (jitter, projection, clipping)."""


class CholeskyJitterWarning(NumericsWarning):
    """A matrix was not numerically positive definite and jitter was added to factor it."""


class ConvergenceWarning(NumericsWarning):
    """An iterative solver stopped before meeting its tolerance for some problems of a batch."""


class DivergenceWarning(NumericsWarning):
    """A filter produced non-finite estimates for some sequences of a batch."""


class ShapeError(ValueError):
    """An argument has the wrong shape. The message names the argument and the expected shape."""


class NotDetectableError(ValueError):
    """A state-space pair is not detectable (or not stabilisable): no steady-state gain exists."""
