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
from torchfilt.models.calibrated import CalibratedModel
from torchfilt.models.functional import FunctionModel, StateSpaceModel, as_conditional
from torchfilt.models.inducing import InducingTransition
from torchfilt.models.integrate import rk4
from torchfilt.models.linear import (
    LinearGaussianModel,
    LinearModel,
    LinearSystem,
    linear_system,
)
from torchfilt.models.params import (
    Bounded,
    CholeskyCovariance,
    CovarianceParameter,
    DiagonalCovariance,
    Positive,
    ScalarCovariance,
)
from torchfilt.models.sensor import AffineSensor
from torchfilt.models.subspace import (
    SubspaceFit,
    SubspaceOrder,
    subspace_identify,
    subspace_order,
    subspace_start,
)
from torchfilt.models.uncertain import ParameterPosterior, UncertainParameters

__all__ = [
    "AffineSensor",
    "Bounded",
    "CalibratedModel",
    "CholeskyCovariance",
    "ConditionalModel",
    "CovarianceParameter",
    "DiagonalCovariance",
    "FunctionModel",
    "InducingTransition",
    "LinearGaussianModel",
    "LinearModel",
    "LinearSystem",
    "ParameterPosterior",
    "Positive",
    "Prediction",
    "ScalarCovariance",
    "StateSpaceModel",
    "SubspaceFit",
    "SubspaceOrder",
    "TimeVarying",
    "UncertainParameters",
    "as_conditional",
    "check_output",
    "check_prediction",
    "linear_system",
    "rk4",
    "subspace_identify",
    "subspace_order",
    "subspace_start",
]
