"""Checking a filter's inputs at the boundary: shapes, dtypes, the prior, which components are observed."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, InputTypeError, ShapeError
from torchfilt.models import LinearModel, StateSpaceModel
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = [
    "FilterInputs",
    "check_inputs",
    "check_model_input",
    "check_prior",
    "model_input_width",
    "model_noise",
    "observed",
]


class FilterInputs(NamedTuple):
    """A recording checked and broadcast for a filter run.

    Attributes:
        y: measurements ``(..., T, m)`` with the missing entries replaced by 0.
        obs: which components are observed, bool ``(..., T, m)`` (batch dims broadcast with ``y``).
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(B..., n)``, expanded to the run's batch shape.
        P0: prior covariance ``(B..., n, n)``, expanded likewise.
        batch: the run's batch shape ``B``.
    """

    y: Tensor
    obs: Tensor
    u: Tensor | None
    x0: Tensor
    P0: Tensor
    batch: torch.Size


def observed(y: Tensor, mask: Tensor | None) -> Tensor:
    """Which components of ``y`` are observed: finite, and ``mask`` True where given.

    The mask may add leading batch dimensions, but its trailing ``(T, m)`` must equal ``y``'s: a
    mask never stretches the measurements in time or over components.

    Args:
        y: measurements ``(..., T, m)``.
        mask: bool ``(..., T, m)`` whose batch dims broadcast with ``y``'s, or ``None``.

    Returns:
        Bool tensor of the broadcast shape ``(..., T, m)``.

    Raises:
        InputTypeError: ``mask`` is not boolean.
        ShapeError: ``mask``'s trailing ``(T, m)`` differ from ``y``'s, or its batch dims do not
            broadcast with ``y``'s.
    """
    obs = torch.isfinite(y)
    if mask is None:
        return obs
    mask = torch.as_tensor(mask, device=y.device)
    if mask.dtype != torch.bool:
        raise InputTypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.dim() < 2 or tuple(mask.shape[-2:]) != tuple(y.shape[-2:]):
        raise ShapeError(
            f"mask: shape {tuple(mask.shape)} does not match y {tuple(y.shape)}: its trailing "
            f"(T, m) must equal y's {tuple(y.shape[-2:])} (a mask may add batch dimensions only)"
        )
    try:
        return obs & mask
    except RuntimeError:
        raise ShapeError(
            f"mask: shape {tuple(mask.shape)} does not broadcast with y {tuple(y.shape)}"
        ) from None


def _side_input_width(side: nn.Module) -> int | None:
    """The input width ``nu`` a model side declares (0: it takes no inputs), or None if unknown
    (a callable may read ``u`` or not)."""
    if isinstance(side, LinearModel):
        return 0 if side.D is None else int(side.D.shape[-1])
    for owner in (side, getattr(side, "config", None)):
        width = getattr(owner, "input_dim", None)
        if isinstance(width, int) and not isinstance(width, bool):
            return width
    return None


def model_input_width(model: StateSpaceModel) -> int | None:
    """The input width ``nu`` of a model: 0 when both sides declare that they take no inputs
    (a :class:`~torchfilt.models.LinearGaussianModel` without ``B`` and ``D``, a GP or inducing
    transition with ``input_dim=0``), the one width the sides that take inputs declare, or None
    when a side does not say (a model of callables) or the sides disagree."""
    widths = [_side_input_width(side) for side in (model.transition, model.measurement)]
    if any(w is None for w in widths):
        return None
    used = {w for w in widths if w}
    if not used:
        return 0
    return used.pop() if len(used) == 1 else None


def check_model_input(model: StateSpaceModel, u: Tensor | None, name: str = "u") -> None:
    """Refuse inputs the model would silently drop, or of the wrong width.

    Args:
        model: the state-space model (see :func:`model_input_width`).
        u: the inputs ``(..., nu)`` (per step or over time), or None.
        name: the argument's name, for the message.

    Raises:
        InputError: ``u`` is given but the model takes no inputs.
        ShapeError: ``u``'s last dimension is not the model's input width.
    """
    if u is None:
        return
    width = model_input_width(model)
    shape = tuple(u.shape) if isinstance(u, Tensor) else None
    if width == 0:
        raise InputError(
            f"{name}: the model takes no inputs (its input width is 0), but inputs of shape "
            f"{shape} were given and would be ignored; drop {name}, or give the model its input "
            "matrices (B, D) or input_dim"
        )
    if width is not None and isinstance(u, Tensor) and (u.dim() < 1 or u.shape[-1] != width):
        raise ShapeError(
            f"{name}: expected shape (..., nu) with nu = {width} (the model's input width), "
            f"got {shape}"
        )


def broadcast_batch(shapes: dict[str, torch.Size]) -> torch.Size:
    """The broadcast of named batch shapes (numpy rules), or a :class:`ShapeError` naming them
    all. Plain Python: ``torch.broadcast_shapes`` costs tens of microseconds per call."""
    out: list[int] = []
    for shape in shapes.values():
        for i, d in enumerate(reversed(shape)):
            if i == len(out):
                out.append(d)
            elif out[i] == 1:
                out[i] = d
            elif d != 1 and d != out[i]:
                desc = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
                raise ShapeError(f"batch shapes do not broadcast: {desc}")
    return torch.Size(reversed(out))


def check_prior(x0: Tensor, P0: Tensor, n: int) -> None:
    """Check a prior ``x0 (..., n)``, ``P0 (..., n, n)``: shapes, finiteness, symmetry, PSD.

    Raises:
        ShapeError: wrong shapes. InputError: non-finite, asymmetric or indefinite ``P0``.
    """
    if x0.dim() < 1 or x0.shape[-1] != n:
        raise ShapeError(f"x0: expected shape (..., n) with n = {n}, got {tuple(x0.shape)}")
    if P0.dim() < 2 or P0.shape[-2:] != (n, n):
        raise ShapeError(f"P0: expected shape (..., n, n) with n = {n}, got {tuple(P0.shape)}")
    finite = torch.stack([torch.isfinite(x0).all(), torch.isfinite(P0).all()]).tolist()
    if not finite[0]:
        raise InputError("x0 contains non-finite entries")
    if not finite[1]:
        raise InputError("P0 contains non-finite entries")
    # symmetric to rtol 1e-8 (as torch.allclose(P0, P0.mT, rtol=1e-8, atol=0)) and positive
    # semi-definite, with one host synchronisation for the three answers
    asym = ((P0 - P0.mT).abs() > 1e-8 * P0.mT.abs()).any()
    evals = torch.linalg.eigvalsh(P0)
    tol = evals.abs().amax(-1) * math.sqrt(torch.finfo(P0.dtype).eps)
    indefinite = (evals[..., 0] < -tol).any() | (evals[..., -1] <= 0).any()
    bad = torch.stack([asym, indefinite]).tolist()
    if bad[0]:
        raise InputError("P0 is not symmetric")
    if bad[1]:
        raise InputError(
            f"P0 is not positive semi-definite: smallest eigenvalue {float(evals[..., 0].min()):.3e}"
        )


def model_noise(side: nn.Module, step: int, like: Tensor) -> Tensor | None:
    """The additive noise covariance ``(..., d, d)`` of a model side at ``step`` (or None)."""
    noise = side.noise_cov(step) if side.time_varying_noise else side.noise_cov()  # type: ignore[operator]
    return None if noise is None else noise.to(dtype=like.dtype, device=like.device)


def check_inputs(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None,
) -> FilterInputs:
    """Check and broadcast a recording for a filter run of ``model``.

    Args:
        model: the state-space model (its ``state_dim``, ``obs_dim`` and noise batch shapes).
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``. P0: prior covariance ``(..., n, n)``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.

    Returns:
        The :class:`FilterInputs` of the run.
    """
    n, m = model.state_dim, model.obs_dim
    if not isinstance(y, Tensor):
        raise InputTypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
    if y.dim() < 2 or y.shape[-1] != m:
        raise ShapeError(f"y: expected shape (..., T, m) with m = {m}, got {tuple(y.shape)}")
    check_real_tensor(y, "y")
    dtype, device = y.dtype, y.device
    T = y.shape[-2]
    try:
        x0 = torch.as_tensor(x0, device=device)
        P0 = torch.as_tensor(P0, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(
            f"x0 and P0 must be tensors (or numbers), got {type(x0).__name__} and "
            f"{type(P0).__name__}"
        ) from None
    check_real_tensor(x0, "x0", integers=True)
    check_real_tensor(P0, "P0", integers=True)
    dtype = torch.promote_types(dtype, x0.dtype) if x0.is_floating_point() else dtype
    dtype = torch.promote_types(dtype, P0.dtype) if P0.is_floating_point() else dtype
    y, x0, P0 = y.to(dtype), x0.to(dtype), P0.to(dtype)
    check_prior(x0, P0, n)
    shapes = {"y": y.shape[:-2], "x0": x0.shape[:-1], "P0": P0.shape[:-2]}
    if u is not None:
        u = torch.as_tensor(u, device=device)
        check_real_tensor(u, "u", integers=True)
        check_model_input(model, u)
        u = u.to(dtype)
        if u.dim() < 2 or u.shape[-2] != T:
            raise ShapeError(f"u: expected shape (..., T, nu) with T = {T}, got {tuple(u.shape)}")
        if not bool(torch.isfinite(u).all()):
            raise InputError("u contains non-finite entries; inputs cannot be missing")
        shapes["u"] = u.shape[:-2]
    obs = observed(y, mask)
    shapes["mask"] = obs.shape[:-2]  # y's batch shape broadcast with the mask's
    for name, side in (("Q", model.transition), ("R", model.measurement)):
        noise = side.noise_cov(0) if side.time_varying_noise else side.noise_cov()
        if noise is not None:
            shapes[name] = noise.shape[:-2]
    batch = broadcast_batch(shapes)
    if T == 0:
        raise ShapeError("y: the time dimension T must be at least 1")
    y = torch.where(obs, y, torch.zeros((), dtype=dtype, device=device))
    return FilterInputs(y, obs, u, x0.expand(*batch, n), P0.expand(*batch, n, n), batch)
