"""The model contract shared by transitions and measurements."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ModelError, ShapeError
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = [
    "ConditionalModel",
    "Prediction",
    "TimeVarying",
    "check_noise",
    "check_output",
    "check_prediction",
]


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

    Raises:
        ShapeError: ``values`` is not ``(..., T, d, d)``.
    """

    def __init__(self, values: Tensor) -> None:
        if values.dim() < 3 or values.shape[-1] != values.shape[-2]:
            raise ShapeError(
                f"TimeVarying values: expected shape (..., T, d, d), got {tuple(values.shape)}"
            )
        self.values = values

    @property
    def dim(self) -> int:
        """The dimension ``d`` of the covariances."""
        return int(self.values.shape[-1])

    @property
    def steps(self) -> int:
        """The number of steps ``T``."""
        return int(self.values.shape[-3])

    def __call__(self, step: int) -> Tensor:
        if not 0 <= step < self.steps:
            raise InputError(f"TimeVarying noise has {self.steps} steps; step {step} requested")
        return self.values[..., step, :, :]

    def to(self, *args: Any, **kwargs: Any) -> TimeVarying:
        """A copy with the values moved or cast by ``Tensor.to(*args, **kwargs)``."""
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
        """The predictive mean alone: all that an optimiser over ``x`` needs (the constrained
        CKF's reconciliation calls it many times per step). Equal to ``predict(x, u).mean``;
        models whose variance costs extra override it to skip that work.

        Args:
            x: points, shape ``(..., P, n)``.
            u: inputs aligned with the points, shape ``(..., P, nu)``, or ``None``.

        Returns:
            The predictive mean, shape ``(..., P, d)``.
        """
        return self.predict(x, u).mean

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        """Additive noise covariance at ``step``.

        Args:
            step: the step (0-based) of a time-varying noise; ``None`` for a constant one.

        Returns:
            The covariance, shape ``(..., d, d)``, or ``None`` for no additive noise.
        """
        return None

    @property
    def time_varying_noise(self) -> bool:
        """Whether :meth:`noise_cov` depends on the step."""
        return False

    def forward(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Same as :meth:`predict` (calling the module).

        Args:
            x: points, shape ``(..., P, n)``.
            u: inputs aligned with the points, shape ``(..., P, nu)``, or ``None``.

        Returns:
            A :class:`Prediction` with mean ``(..., P, d)``.
        """
        return self.predict(x, u)


def check_noise(value: Any, name: str) -> Any:
    """Validate a noise covariance argument: ``(..., d, d)`` symmetric, or a :class:`TimeVarying`."""
    if value is None or isinstance(value, torch.nn.Module):
        return value  # a learnable covariance parameter is positive definite by construction
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


def check_output(out: Any, x: Tensor, out_dim: int, name: str) -> Tensor:
    """Check a model's output against its points and declared output dimension.

    The rule: ``out`` is a floating tensor of shape ``(..., P, d)`` whose every dimension is at least
    that of the points ``x (..., P, n)`` (leading dimensions may be *larger*, for a model with
    batched parameters, but no dimension is ever broadcast up to fit: an output of shape
    ``(..., 1)`` for ``d = 3`` or ``(1, d)`` for ``P`` points is an error, not ``P`` copies). A
    floating output of another dtype is cast to ``x.dtype``; any other dtype is an error. Only
    metadata is read: no host synchronisation, static under ``torch.compile`` and CUDA graphs.

    Args:
        out: what the model returned.
        x: the points it was given, shape ``(..., P, n)``.
        out_dim: the declared output dimension ``d``.
        name: the model's name, for the message.

    Returns:
        ``out``, shape ``(..., P, d)`` (cast to ``x.dtype`` if needed).

    Raises:
        ModelError: ``out`` is not a tensor, is not floating point, or has the wrong shape.
    """
    if not isinstance(out, Tensor):
        raise ModelError(f"{name} returned {type(out).__name__}, expected a torch.Tensor")
    want = (*x.shape[:-1], out_dim)
    shape = tuple(out.shape)
    if shape != want:
        ok = len(shape) >= len(want) and shape[-1] == out_dim
        if ok:
            try:
                ok = tuple(torch.broadcast_shapes(out.shape, want)) == shape
            except RuntimeError:
                ok = False
        if not ok:
            raise ModelError(
                f"{name} returned shape {shape} for points of shape {tuple(x.shape)}; expected "
                f"{want}, i.e. (..., P, d) with d = {out_dim} (an output is never broadcast to "
                "fit: index components with x[..., i], not x[i])"
            )
    if out.dtype != x.dtype:
        if not out.is_floating_point():
            raise ModelError(
                f"{name} returned dtype {out.dtype} for {x.dtype} points; a model must return "
                "floating-point values"
            )
        out = out.to(x.dtype)
    return out


def check_prediction(pred: Any, x: Tensor, out_dim: int, name: str) -> Prediction:
    """Check a :class:`Prediction` of any :class:`ConditionalModel` against its points.

    The mean follows :func:`check_output`; ``var`` must have the mean's shape and ``cov`` the
    mean's shape plus ``d``. Metadata only (cheap, static under ``torch.compile``): a filter may
    call it on every step.

    Args:
        pred: what ``model.predict(x, u)`` returned.
        x: the points, shape ``(..., P, n)``.
        out_dim: the model's declared ``out_dim``.
        name: the model's name, for the message.

    Returns:
        The prediction, with every part cast to ``x.dtype``.

    Raises:
        ModelError: not a Prediction, or a part with the wrong shape or dtype.
    """
    if not isinstance(pred, Prediction):
        raise ModelError(f"{name}.predict returned {type(pred).__name__}, expected a Prediction")
    mean = check_output(pred.mean, x, out_dim, name)
    var, cov = pred.var, pred.cov
    if var is not None:
        var = check_output(var, x, out_dim, f"{name} (variance)")
        if var.shape != mean.shape:
            raise ModelError(
                f"{name} (variance): shape {tuple(var.shape)}, expected the mean's "
                f"{tuple(mean.shape)}"
            )
    if cov is not None:
        if not isinstance(cov, Tensor) or tuple(cov.shape) != (*mean.shape, out_dim):
            got = tuple(cov.shape) if isinstance(cov, Tensor) else type(cov).__name__
            raise ModelError(f"{name} (covariance): shape {got}, expected {(*mean.shape, out_dim)}")
        if not cov.is_floating_point():
            raise ModelError(f"{name} (covariance): dtype {cov.dtype}, expected floating point")
        cov = cov.to(x.dtype)
    return Prediction(mean, var, cov)
