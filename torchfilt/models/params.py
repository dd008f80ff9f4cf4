"""Constrained learnable parameters: positive-definite covariances and bounded scalars.

Each class is an :class:`~torch.nn.Module` that holds an unconstrained ``raw`` parameter and maps it
to the constrained value when called, so that any optimiser step keeps the value valid:

======================== ======================================= =======================================
class                    value                                    raw parameter
======================== ======================================= =======================================
:class:`ScalarCovariance` ``exp(r) I``                            ``r = log s``, shape ``(...,)``
:class:`DiagonalCovariance` ``diag(exp(r))``                      ``r = log diag``, shape ``(..., d)``
:class:`CholeskyCovariance` ``L L^T``, ``L`` lower triangular     strict lower part of ``L`` and
                         with diagonal ``exp(r)``                 ``r = log diag L``
:class:`Positive`        ``softplus(r) + low``                    ``r``, any shape
:class:`Bounded`         ``low + (high - low) sigmoid(r)``        ``r``, any shape (logit transform)
======================== ======================================= =======================================

A covariance parameter can stand wherever a model takes a noise covariance (``Q`` or ``R`` of
:class:`~torchfilt.models.StateSpaceModel`, the ``noise`` of a
:class:`~torchfilt.models.FunctionModel`): the model then reads its noise from the module at every
filter call, and the parameter is part of the model's ``parameters()``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from torchfilt.exceptions import InputError, ShapeError

__all__ = [
    "Bounded",
    "CholeskyCovariance",
    "CovarianceParameter",
    "DiagonalCovariance",
    "Positive",
    "ScalarCovariance",
]


def _float(value: Tensor | float | list[float], name: str, dtype: torch.dtype | None) -> Tensor:
    t = torch.as_tensor(value, dtype=dtype)
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype() if dtype is None else dtype)
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name}: the initial value contains non-finite entries")
    return t.detach().clone()


class CovarianceParameter(nn.Module):
    """Base class of the learnable covariances: ``module()`` returns ``(..., d, d)``, symmetric
    positive definite for any value of the raw parameters."""

    #: Dimension ``d``.
    dim: int

    def forward(self) -> Tensor:  # pragma: no cover - abstract
        """The covariance, shape ``(..., d, d)``, symmetric positive definite."""
        raise NotImplementedError  # internal: not a user error (each subclass defines forward)

    @property
    def value(self) -> Tensor:
        """The covariance ``(..., d, d)`` (same as calling the module)."""
        return self()


class ScalarCovariance(CovarianceParameter):
    """``s I`` with ``s = exp(r)``: one learnable variance shared by all ``d`` components.

    Args:
        init: initial variance ``s > 0``, a scalar or a batch ``(...,)``.
        dim: dimension ``d``.
        dtype: dtype of the parameter (default: that of ``init``, or torch's default).

    Raises:
        InputError: ``init`` is not finite or not positive, or ``dim < 1``.
    """

    def __init__(self, init: Tensor | float, dim: int, *, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        s = _float(init, "init", dtype)
        if bool((s <= 0).any()):
            raise InputError(f"init: a variance must be positive, got {s.tolist()}")
        if dim < 1:
            raise InputError(f"dim must be positive, got {dim}")
        self.dim = int(dim)
        self.raw = nn.Parameter(s.log())

    def forward(self) -> Tensor:
        """The covariance ``s I``, shape ``(..., d, d)``."""
        eye = torch.eye(self.dim, dtype=self.raw.dtype, device=self.raw.device)
        return self.raw.exp()[..., None, None] * eye


class DiagonalCovariance(CovarianceParameter):
    """``diag(exp(r))``: independent learnable variances (log-diagonal parametrisation).

    Args:
        init: initial variances ``(..., d)``, all positive, or a diagonal matrix ``(..., d, d)``
            (its diagonal is taken).
        dtype: dtype of the parameter.

    Raises:
        ShapeError: ``init`` is a scalar (no dimension ``d``).
        InputError: ``init`` is not finite, or some variance is not positive.
    """

    def __init__(self, init: Tensor | list[float], *, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        v = _float(init, "init", dtype)
        if v.dim() >= 2 and v.shape[-1] == v.shape[-2]:
            v = v.diagonal(dim1=-2, dim2=-1)
        if v.dim() < 1:
            raise ShapeError(f"init: expected variances (..., d), got shape {tuple(v.shape)}")
        if bool((v <= 0).any()):
            raise InputError(f"init: variances must be positive, got {v.tolist()}")
        self.dim = int(v.shape[-1])
        self.raw = nn.Parameter(v.log())

    @property
    def variances(self) -> Tensor:
        """The diagonal ``(..., d)``."""
        return self.raw.exp()

    def forward(self) -> Tensor:
        """The covariance ``diag(exp(r))``, shape ``(..., d, d)``."""
        return torch.diag_embed(self.raw.exp())


class CholeskyCovariance(CovarianceParameter):
    """``L L^T`` with ``L`` lower triangular and ``diag L = exp(r)``: a full learnable covariance.

    Every raw value gives a positive definite matrix, and every positive definite matrix has
    exactly one raw value.

    Args:
        init: initial covariance, shape ``(..., d, d)``, symmetric positive definite.
        dtype: dtype of the parameter.

    Raises:
        ShapeError: ``init`` is not a square matrix ``(..., d, d)``.
        InputError: ``init`` is not finite or not positive definite.
    """

    _rows: Tensor
    _cols: Tensor

    def __init__(self, init: Tensor, *, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        P = _float(init, "init", dtype)
        if P.dim() < 2 or P.shape[-1] != P.shape[-2]:
            raise ShapeError(f"init: expected a covariance (..., d, d), got {tuple(P.shape)}")
        L, info = torch.linalg.cholesky_ex(0.5 * (P + P.mT))
        if bool((info != 0).any()):
            raise InputError("init: the initial covariance is not positive definite")
        d = P.shape[-1]
        self.dim = int(d)
        self.raw_diag = nn.Parameter(L.diagonal(dim1=-2, dim2=-1).log())
        rows, cols = torch.tril_indices(d, d, -1)
        self.register_buffer("_rows", rows, persistent=False)
        self.register_buffer("_cols", cols, persistent=False)
        self.raw_lower = nn.Parameter(L[..., rows, cols])

    @property
    def factor(self) -> Tensor:
        """The lower-triangular factor ``L``, shape ``(..., d, d)``."""
        d = self.dim
        batch = torch.broadcast_shapes(self.raw_diag.shape[:-1], self.raw_lower.shape[:-1])
        L = self.raw_diag.new_zeros(*batch, d, d)
        L[..., self._rows, self._cols] = self.raw_lower.expand(*batch, -1)
        return L + torch.diag_embed(self.raw_diag.exp())

    def forward(self) -> Tensor:
        """The covariance ``L L^T``, shape ``(..., d, d)``."""
        L = self.factor
        return L @ L.mT


def _softplus_inv(v: Tensor) -> Tensor:
    # log(exp(v) - 1), stable for large v
    return v + torch.log(-torch.expm1(-v))


class Positive(nn.Module):
    """A positive parameter ``softplus(r) + low`` (a drag constant, a gain, a time constant).

    Args:
        init: initial value(s), all ``> low``: a scalar or any shape (the parameter's shape).
        low: lower bound (default 0).
        dtype: dtype of the parameter.

    Raises:
        InputError: ``init`` is not finite or not above ``low``, or ``low`` is not finite.
    """

    def __init__(
        self, init: Tensor | float, *, low: float = 0.0, dtype: torch.dtype | None = None
    ) -> None:
        super().__init__()
        v = _float(init, "init", dtype)
        if not math.isfinite(low):
            raise InputError(f"low must be finite, got {low}")
        if bool((v <= low).any()):
            raise InputError(f"init: must exceed low = {low}, got {v.tolist()}")
        self.low = float(low)
        self.raw = nn.Parameter(_softplus_inv(v - low))

    def forward(self) -> Tensor:
        """The constrained value ``softplus(r) + low``, of ``init``'s shape (any shape)."""
        return F.softplus(self.raw) + self.low

    @property
    def value(self) -> Tensor:
        """The constrained value, of ``init``'s shape (any shape; same as calling the module)."""
        return self()


class Bounded(nn.Module):
    """A parameter in ``(low, high)``: ``low + (high - low) sigmoid(r)`` (logit transform).

    Args:
        init: initial value(s), strictly inside ``(low, high)``: a scalar or any shape (the
            parameter's shape).
        low: the lower bound, finite.
        high: the upper bound, finite, ``low < high``.
        dtype: dtype of the parameter.

    Raises:
        InputError: bounds that are not finite with ``low < high``, or ``init`` not finite or
            not strictly inside them.
    """

    def __init__(
        self, init: Tensor | float, low: float, high: float, *, dtype: torch.dtype | None = None
    ) -> None:
        super().__init__()
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise InputError(f"bounds: need finite low < high, got ({low}, {high})")
        v = _float(init, "init", dtype)
        if bool(((v <= low) | (v >= high)).any()):
            raise InputError(f"init: must lie strictly inside ({low}, {high}), got {v.tolist()}")
        self.low, self.high = float(low), float(high)
        p = (v - low) / (high - low)
        self.raw = nn.Parameter(torch.log(p) - torch.log1p(-p))

    def forward(self) -> Tensor:
        """The constrained value ``low + (high - low) sigmoid(r)``, of ``init``'s shape (any
        shape)."""
        return self.low + (self.high - self.low) * torch.sigmoid(self.raw)

    @property
    def value(self) -> Tensor:
        """The constrained value, of ``init``'s shape (any shape; same as calling the module)."""
        return self()
