"""Linear-Gaussian models."""

from __future__ import annotations

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import Prediction, TimeVarying
from torchfilt.models.functional import FunctionModel, StateSpaceModel
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = ["LinearGaussianModel", "LinearModel"]


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
        self.register_buffer("C", C)
        self.register_buffer("D", None if D is None else _as_tensor(D, f"{name} input matrix"))
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
        return Prediction(self._linear(x, u))


class LinearGaussianModel(StateSpaceModel):
    """Linear-Gaussian state-space model.

        x_k = A x_{k-1} + B u_{k-1} + w,   w ~ N(0, Q)
        y_k = H x_k + D u_k + v,           v ~ N(0, R)

    Args:
        A: transition matrix, shape ``(..., n, n)``.
        H: measurement matrix, shape ``(..., m, n)``.
        Q: process noise, ``(..., n, n)`` or :class:`TimeVarying`.
        R: measurement noise, ``(..., m, m)`` or :class:`TimeVarying`.
        B: optional input matrix, shape ``(..., n, nu)``.
        D: optional feed-through matrix, shape ``(..., m, nu)``.
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

    @property
    def A(self) -> Tensor:
        return self.transition.C  # type: ignore[return-value]

    @property
    def H(self) -> Tensor:
        return self.measurement.C  # type: ignore[return-value]

    @property
    def B(self) -> Tensor | None:
        return self.transition.D  # type: ignore[return-value]
