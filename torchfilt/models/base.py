"""The model contract shared by transitions and measurements."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = ["ConditionalModel", "Prediction", "TimeVarying"]


class Prediction(NamedTuple):
    """What a model returns for a set of points.

    Attributes:
        mean: predictive mean per point, shape ``(..., P, d)``.
        var: optional per-point predictive variance (diagonal), shape ``(..., P, d)``. A GP's latent
            variance plus its likelihood noise goes here.
        cov: optional per-point predictive covariance, shape ``(..., P, d, d)`` (correlated outputs).
    """

    mean: Tensor
    var: Tensor | None = None
    cov: Tensor | None = None


class TimeVarying:
    """A per-step noise covariance: ``values[..., k, :, :]`` at step ``k``.

    Args:
        values: covariances, shape ``(..., T, d, d)``.
    """

    def __init__(self, values: Tensor) -> None:
        if values.dim() < 3 or values.shape[-1] != values.shape[-2]:
            raise ShapeError(
                f"TimeVarying values: expected shape (..., T, d, d), got {tuple(values.shape)}"
            )
        self.values = values

    @property
    def dim(self) -> int:
        return int(self.values.shape[-1])

    @property
    def steps(self) -> int:
        return int(self.values.shape[-3])

    def __call__(self, step: int) -> Tensor:
        if not 0 <= step < self.steps:
            raise InputError(f"TimeVarying noise has {self.steps} steps; step {step} requested")
        return self.values[..., step, :, :]

    def to(self, *args: Any, **kwargs: Any) -> TimeVarying:
        return TimeVarying(self.values.to(*args, **kwargs))


class ConditionalModel(nn.Module):
    """A map from points to a Gaussian: ``z = g(x, u) + e``, ``e ~ N(0, V(x, u) + N_k)``.

    ``V(x, u)`` is the optional per-point variance of :meth:`predict`; ``N_k`` the additive noise of
    :meth:`noise_cov`. Subclasses implement :meth:`predict` and set :attr:`out_dim` (and
    :attr:`in_dim` when known).
    """

    #: Output dimension ``d``.
    out_dim: int
    #: Input (state) dimension ``n``, or ``None`` if the model accepts any.
    in_dim: int | None = None

    @abstractmethod
    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Predictive distribution at points.

        Args:
            x: points, shape ``(..., P, n)``.
            u: inputs aligned with the points, shape ``(..., P, nu)``, or ``None``.

        Returns:
            A :class:`Prediction` with mean ``(..., P, d)``.
        """

    def predict_mean(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """The predictive mean alone, ``(..., P, d)``: all that an optimiser over ``x`` needs (the
        constrained CKF's reconciliation calls it many times per step). Equal to
        ``predict(x, u).mean``; models whose variance costs extra override it to skip that work.
        """
        return self.predict(x, u).mean

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        """Additive noise covariance at ``step`` (``(..., d, d)``), or ``None`` for none."""
        return None

    @property
    def time_varying_noise(self) -> bool:
        """Whether :meth:`noise_cov` depends on the step."""
        return False

    def forward(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        return self.predict(x, u)


def check_noise(value: Tensor | TimeVarying | None, name: str) -> Tensor | TimeVarying | None:
    """Validate a noise covariance argument: ``(..., d, d)`` symmetric, or a :class:`TimeVarying`."""
    if value is None:
        return value
    if isinstance(value, TimeVarying):
        check_noise(value.values.flatten(0, -3), name)
        return value
    if not isinstance(value, Tensor):
        try:
            value = torch.as_tensor(value, dtype=torch.get_default_dtype())
        except (TypeError, ValueError, RuntimeError):
            raise InputError(
                f"{name}: expected a covariance tensor, got {type(value).__name__}"
            ) from None
    check_real_tensor(value, name, integers=True)
    if value.dim() == 0:
        value = value.reshape(1, 1)
    if value.dim() < 2 or value.shape[-1] != value.shape[-2]:
        raise ShapeError(
            f"{name}: expected a covariance of shape (..., d, d), got {tuple(value.shape)}"
        )
    if not bool(torch.isfinite(value).all()):
        raise InputError(f"{name} contains non-finite entries")
    if not torch.allclose(value, value.mT, rtol=1e-6, atol=0.0):
        raise InputError(f"{name} is not symmetric")
    evals = torch.linalg.eigvalsh(value.to(torch.float64))
    tol = evals.abs().amax(-1) * 1e-8
    if bool((evals[..., 0] < -tol).any()):
        raise InputError(
            f"{name} is not positive semi-definite: smallest eigenvalue {float(evals[..., 0].min()):.3e}"
        )
    return value
