"""Models: transition and measurement maps that a Gaussian filter can push cubature points through.

The contract (:class:`ConditionalModel`) maps points ``(..., P, n)`` and inputs ``(..., P, nu)`` to a
:class:`Prediction` with a mean ``(..., P, d)`` and, optionally, a per-point variance ``(..., P, d)``
or covariance ``(..., P, d, d)`` (how a GP supplies Q and R), plus an additive noise covariance.
"""

from torchfilt.models.base import (
    ConditionalModel,
    Prediction,
    TimeVarying,
    check_output,
    check_prediction,
)
from torchfilt.models.functional import FunctionModel, StateSpaceModel, as_conditional
from torchfilt.models.integrate import rk4
from torchfilt.models.linear import (
    LinearGaussianModel,
    LinearModel,
    LinearSystem,
    linear_system,
)

__all__ = [
    "ConditionalModel",
    "FunctionModel",
    "LinearGaussianModel",
    "LinearModel",
    "LinearSystem",
    "Prediction",
    "StateSpaceModel",
    "TimeVarying",
    "as_conditional",
    "check_output",
    "check_prediction",
    "linear_system",
    "rk4",
]
