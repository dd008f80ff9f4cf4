"""Gaussian-process transition and measurement models (GPyTorch) with a frozen fast predictor.

:class:`GPTransition` learns ``x_{k+1} = f(x_k, u_k)``, :class:`GPMeasurement` learns
``y_k = h(x_k, u_k)``; both are :class:`~torchfilt.models.ConditionalModel` s whose per-point
predictive variance a :class:`~torchfilt.CKF` turns into ``Q`` and ``R`` (law of total variance).
"""

import warnings

with warnings.catch_warnings():
    # linear_operator decorates functions with torch.jit.script at import, which recent torch
    # deprecates; it is not ours to fix and must not break `-W error` users.
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=".*torch.jit.script")
    import gpytorch  # noqa: F401

from torchfilt.models.gp.config import GPConfig, GroupSpec
from torchfilt.models.gp.measurement import GPMeasurement
from torchfilt.models.gp.model import STATE_FORMAT, GPModel
from torchfilt.models.gp.optimize import FitDivergedError, FitState
from torchfilt.models.gp.predictor import FrozenGP, FrozenOutput
from torchfilt.models.gp.settings import exact_settings, gpytorch_default_settings
from torchfilt.models.gp.standardize import Standardizer
from torchfilt.models.gp.transition import GPTransition

__all__ = [
    "STATE_FORMAT",
    "FitDivergedError",
    "FitState",
    "FrozenGP",
    "FrozenOutput",
    "GPConfig",
    "GPMeasurement",
    "GPModel",
    "GPTransition",
    "GroupSpec",
    "Standardizer",
    "exact_settings",
    "gpytorch_default_settings",
]
