"""Linear-Gaussian models, and how a model declares that it is linear.

A model is linear when :func:`linear_system` returns its matrices: a
:class:`LinearGaussianModel`, a :class:`StateSpaceModel` built from two :class:`LinearModel`
maps, or any :class:`StateSpaceModel` with a ``linear_system()`` method returning a
:class:`LinearSystem`. The filters then run the closed-form Kalman recursions on it instead of
pushing cubature points through the maps.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ModelError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction, TimeVarying
from torchfilt.models.functional import FunctionModel, StateSpaceModel, WithNoise
from torchfilt.models.params import CholeskyCovariance
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = ["LinearGaussianModel", "LinearModel", "LinearSystem", "linear_system"]


class LinearSystem(NamedTuple):
    """The matrices of a linear state-space model (its noise stays with the model's maps).

        x_t = A x_{t-1} + B u_t + w_t,   y_t = H x_t + D u_t + v_t

    Attributes:
        A: transition matrix ``(..., n, n)``.
        H: measurement matrix ``(..., m, n)``.
        B: input matrix ``(..., n, nu)`` or ``None``.
        D: feed-through matrix ``(..., m, nu)`` or ``None``.
    """

    A: Tensor
    H: Tensor
    B: Tensor | None = None
    D: Tensor | None = None


def _linear_map(side: ConditionalModel) -> LinearModel | None:
    """The :class:`LinearModel` behind ``side`` (possibly with extra noise), else ``None``."""
    if isinstance(side, WithNoise):
        side = side.base
    return side if isinstance(side, LinearModel) else None


def linear_system(model: StateSpaceModel) -> LinearSystem | None:
    """The matrices of ``model`` if it is linear-Gaussian, else ``None``.

    A model declares itself linear with a ``linear_system()`` method returning a
    :class:`LinearSystem` (its maps must then compute exactly ``A x + B u`` and ``H x + D u``);
    a model whose transition and measurement are :class:`LinearModel` maps is recognised without
    one.

    Args:
        model: any state-space model.

    Returns:
        A :class:`LinearSystem`, or ``None`` for a model that is not known to be linear.

    Raises:
        ModelError: the model's ``linear_system()`` returns something other than a
            :class:`LinearSystem` or ``None``.
    """
    declared = getattr(model, "linear_system", None)
    if callable(declared):
        out = declared()
        if out is not None and not isinstance(out, LinearSystem):
            raise ModelError(
                f"{type(model).__name__}.linear_system() must return a LinearSystem, got "
                f"{type(out).__name__}"
            )
        return out
    f, h = _linear_map(model.transition), _linear_map(model.measurement)
    if f is None or h is None:
        return None
    return LinearSystem(A=f.C, H=h.C, B=f.D, D=h.D)


def _register(module: nn.Module, name: str, value: Tensor | None) -> None:
    """Register ``value`` as a parameter if it is an ``nn.Parameter``, else as a buffer."""
    if isinstance(value, nn.Parameter):
        module.register_parameter(name, value)
    else:
        module.register_buffer(name, value)


def _as_tensor(value: Tensor | object, name: str) -> Tensor:
    try:
        t = (
            value
            if isinstance(value, Tensor)
            else torch.as_tensor(value, dtype=torch.get_default_dtype())
        )
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{name}: expected a matrix, got {type(value).__name__}") from None
    check_real_tensor(t, name, integers=True)
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} contains non-finite entries")
    if t.dim() < 2:
        raise ShapeError(
            f"{name}: expected a matrix of shape (..., rows, cols), got {tuple(t.shape)}"
        )
    return t


class LinearModel(FunctionModel):
    """``z = x C^T + u D^T + e``, ``e ~ N(0, noise)``.

    Args:
        C: state matrix, shape ``(..., d, n)``.
        noise: covariance, ``(..., d, d)`` or :class:`TimeVarying`.
        D: optional input matrix, shape ``(..., d, nu)``.
        name: name used in error messages.
        noise_name: name of the noise argument in error messages (default: from ``name``).

    Raises:
        ShapeError: ``D`` has not the rows of ``C``, or ``noise`` is not ``(..., d, d)``.
        InputError: a matrix that is not a real tensor, or an invalid noise covariance.
    """

    C: Tensor
    D: Tensor | None

    def __init__(
        self,
        C: Tensor,
        noise: Tensor | TimeVarying | None,
        D: Tensor | None = None,
        *,
        name: str = "linear",
        noise_name: str | None = None,
    ) -> None:
        C = _as_tensor(C, f"{name} matrix")
        super().__init__(
            self._linear,
            noise,
            out_dim=C.shape[-2],
            in_dim=C.shape[-1],
            name=name,
            noise_name=noise_name,
        )
        # an nn.Parameter stays one (fitted by the fits, in model.parameters()); any other tensor
        # is a buffer (moves with the model, never fitted)
        _register(self, "C", C)
        _register(self, "D", None if D is None else _as_tensor(D, f"{name} input matrix"))
        if self.D is not None and self.D.shape[-2] != C.shape[-2]:
            raise ShapeError(
                f"{name}: input matrix has {self.D.shape[-2]} rows, expected {C.shape[-2]}"
            )

    def _linear(self, x: Tensor, u: Tensor | None) -> Tensor:
        C = self.C.to(x.dtype)
        out = (C.unsqueeze(-3) @ x.unsqueeze(-1)).squeeze(-1) if C.dim() > 2 else x @ C.mT
        if self.D is not None:
            if u is None:
                raise InputError(f"{self.name} has an input matrix; pass the inputs u")
            if u.shape[-1] != self.D.shape[-1]:
                raise ShapeError(
                    f"u: expected shape (..., nu) with nu = {self.D.shape[-1]} for the "
                    f"{self.name}'s input matrix, got {tuple(u.shape)}"
                )
            D = self.D.to(x.dtype)
            out = out + (
                (D.unsqueeze(-3) @ u.unsqueeze(-1)).squeeze(-1) if D.dim() > 2 else u @ D.mT
            )
        return out

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Predictive distribution at points: ``x C^T + u D^T``, with no per-point variance.

        Args:
            x: points, shape ``(..., P, n)``.
            u: inputs aligned with the points, shape ``(..., P, nu)``; required when the model
                has an input matrix ``D``.

        Returns:
            A :class:`Prediction` with mean ``(..., P, d)``.

        Raises:
            InputError: the model has an input matrix and ``u`` is ``None``.
            ShapeError: ``u``'s last dimension is not ``D``'s ``nu``.
        """
        return Prediction(self._linear(x, u))


class LinearGaussianModel(StateSpaceModel):
    """Linear-Gaussian state-space model.

        x_t = A x_{t-1} + B u_t + w,   w ~ N(0, Q)
        y_t = H x_t + D u_t + v,       v ~ N(0, R)

    ``u_t`` is the input row ``u[..., t, :]`` (the input convention of :mod:`torchfilt.filters`).

    Args:
        A: transition matrix, shape ``(..., n, n)``.
        H: measurement matrix, shape ``(..., m, n)``.
        Q: process noise, ``(..., n, n)`` or :class:`TimeVarying`.
        R: measurement noise, ``(..., m, m)`` or :class:`TimeVarying`.
        B: optional input matrix, shape ``(..., n, nu)``.
        D: optional feed-through matrix, shape ``(..., m, nu)``.

    Raises:
        ShapeError: ``A`` not square, ``H`` not ``(..., m, n)``, or a noise or input matrix of
            the wrong size.
        InputError: a matrix that is not a real tensor, or an invalid noise covariance.
    """

    def __init__(
        self,
        A: Tensor,
        H: Tensor,
        Q: Tensor | TimeVarying,
        R: Tensor | TimeVarying,
        B: Tensor | None = None,
        D: Tensor | None = None,
    ) -> None:
        A = _as_tensor(A, "A")
        if A.shape[-1] != A.shape[-2]:
            raise ShapeError(f"A: expected a square matrix (..., n, n), got {tuple(A.shape)}")
        H = _as_tensor(H, "H")
        if H.shape[-1] != A.shape[-1]:
            raise ShapeError(f"H: expected shape (..., m, {A.shape[-1]}), got {tuple(H.shape)}")
        super().__init__(
            LinearModel(A, Q, B, name="transition", noise_name="Q"),
            LinearModel(H, R, D, name="measurement", noise_name="R"),
        )

    def linear_system(self) -> LinearSystem:
        """The matrices ``A, H, B, D`` (see :func:`linear_system`)."""
        return LinearSystem(A=self.A, H=self.H, B=self.B, D=self.D)

    @property
    def A(self) -> Tensor:
        """The transition matrix, shape ``(..., n, n)``."""
        return self.transition.C  # type: ignore[return-value]

    @property
    def H(self) -> Tensor:
        """The measurement matrix, shape ``(..., m, n)``."""
        return self.measurement.C  # type: ignore[return-value]

    @property
    def B(self) -> Tensor | None:
        """The input matrix, shape ``(..., n, nu)``, or ``None``."""
        return self.transition.D  # type: ignore[return-value]

    @property
    def D(self) -> Tensor | None:
        """The feed-through matrix, shape ``(..., m, nu)``, or ``None``."""
        return self.measurement.D  # type: ignore[return-value]

    def learnable(self, *, fixed: Collection[str] = ("H", "D")) -> LinearGaussianModel:
        """A copy to fit by gradient: the matrices outside ``fixed`` are ``nn.Parameter`` s, the
        noises :class:`~torchfilt.models.CholeskyCovariance` (unless ``"Q"`` or ``"R"`` is
        fixed).

        A closed-form fit (:func:`~torchfilt.training.fit_em`) returns its matrices as plain
        tensors; this makes them something :func:`~torchfilt.training.fit_likelihood` can
        move, e.g. to finish an EM fit with L-BFGS where EM converges slowly (a near
        noise-free system). A noise covariance with a zero eigenvalue (EM sets the negative
        ones to zero) gets ``1e-12`` times its mean variance on the diagonal: a Cholesky factor
        needs a positive definite start.

        Args:
            fixed: the blocks kept as they are, of ``"A"``, ``"B"``, ``"H"``, ``"D"``, ``"Q"``,
                ``"R"`` (default ``H`` and ``D``: a measurement-only fit's gauge).

        Returns:
            A new :class:`LinearGaussianModel` with copies of the values.

        Raises:
            InputError: an unknown name in ``fixed``, or a time-varying noise.
        """
        names = {"A", "B", "H", "D", "Q", "R"}
        if unknown := sorted(set(fixed) - names):
            raise InputError(f"fixed: unknown blocks {unknown}; expected some of {sorted(names)}")

        def matrix(name: str, value: Tensor | None) -> Tensor | None:
            if value is None:
                return None
            v = value.detach().clone()
            return v if name in fixed else nn.Parameter(v)

        def noise(name: str, side: ConditionalModel) -> Tensor | nn.Module:
            cov = side.noise_cov()
            if cov is None or side.time_varying_noise:
                raise InputError(f"{name}: a time-varying noise has no learnable copy here")
            cov = cov.detach().clone()
            if name in fixed:
                return cov
            d = cov.shape[-1]
            mean_var = (
                cov.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(torch.finfo(cov.dtype).tiny)
            )
            jitter = 1e-12 * mean_var[..., None, None] * torch.eye(d, dtype=cov.dtype)
            return CholeskyCovariance(cov + jitter)

        return LinearGaussianModel(
            matrix("A", self.A),  # type: ignore[arg-type]
            matrix("H", self.H),  # type: ignore[arg-type]
            noise("Q", self.transition),  # type: ignore[arg-type]
            noise("R", self.measurement),  # type: ignore[arg-type]
            B=matrix("B", self.B),
            D=matrix("D", self.D),
        )
