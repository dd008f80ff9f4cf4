"""Box constraints ``lower <= x <= upper`` with infinite (one-sided or absent) bounds allowed.

A :class:`Box` is the constraint object the bounded least-squares solver and the constrained
cubature points take. It validates its bounds once (shape, NaN, ``lower > upper``) so that bad
bounds fail with a clear message instead of deep inside torch.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError

__all__ = ["Box"]

BoundLike = Tensor | Sequence[float] | float | None


def _to_tensor(value: BoundLike) -> Tensor | None:
    if value is None:
        return None
    t = value if isinstance(value, Tensor) else torch.as_tensor(value, dtype=torch.float64)
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def _as_bound(t: Tensor | None, fill: float, n: int | None, name: str) -> Tensor:
    if t is None:
        if n is None:
            raise InputError(f"{name}: give the bound or the dimension n")
        return torch.full((n,), fill, dtype=torch.float64)
    if t.dim() == 0:
        if n is None:
            raise InputError(f"{name}: a scalar bound needs the dimension n")
        t = t.expand(n)
    if n is not None and t.shape[-1] != n:
        raise ShapeError(f"{name}: expected shape (..., n) with n = {n}, got {tuple(t.shape)}")
    if bool(torch.isnan(t).any()):
        raise InputError(f"{name} contains NaN; use -inf / +inf for an absent bound")
    return t


class Box:
    """The box ``{x : lower <= x <= upper}``, batched: bounds of shape ``(..., n)``.

    Infinite entries are allowed (``-inf`` lower, ``+inf`` upper: no bound on that side), so
    one-sided and unbounded components are expressed directly.

    Args:
        lower: lower bounds, shape ``(..., n)``, a sequence, a scalar (needs ``n``) or ``None``
            (no lower bound; needs ``n`` unless ``upper`` fixes it).
        upper: upper bounds, same forms.
        n: the dimension, needed when both bounds are scalars or ``None``.

    Raises:
        ShapeError: the bounds' last dimensions differ from each other or from ``n``, or their
            batch shapes do not broadcast.
        ValueError: a bound is NaN, ``lower > upper`` somewhere, ``lower = +inf`` or
            ``upper = -inf`` (an empty box).
    """

    def __init__(self, lower: BoundLike = None, upper: BoundLike = None, *, n: int | None = None):
        lo_t, hi_t = _to_tensor(lower), _to_tensor(upper)
        if n is None:
            n = next(
                (int(t.shape[-1]) for t in (lo_t, hi_t) if t is not None and t.dim() > 0), None
            )
        lo = _as_bound(lo_t, float("-inf"), n, "lower")
        hi = _as_bound(hi_t, float("inf"), n, "upper")
        if lo.shape[-1] != hi.shape[-1]:
            raise ShapeError(
                f"lower has shape {tuple(lo.shape)} and upper {tuple(hi.shape)}: both must be "
                "(..., n) with the same n"
            )
        try:
            torch.broadcast_shapes(lo.shape, hi.shape)
        except RuntimeError:
            raise ShapeError(
                f"lower {tuple(lo.shape)} and upper {tuple(hi.shape)} do not broadcast"
            ) from None
        dtype = torch.promote_types(lo.dtype, hi.dtype)
        lo, hi = lo.to(dtype), hi.to(device=lo.device, dtype=dtype)
        bad = lo > hi
        if bool(bad.any()):
            idx = bad.nonzero()[0].tolist()
            raise InputError(
                f"lower > upper at index {idx}: {float(lo.expand_as(bad)[tuple(idx)])} > "
                f"{float(hi.expand_as(bad)[tuple(idx)])}"
            )
        if bool((lo == float("inf")).any()) or bool((hi == float("-inf")).any()):
            raise InputError("the box is empty: a lower bound is +inf or an upper bound is -inf")
        self.lower: Tensor = lo
        self.upper: Tensor = hi

    @property
    def dim(self) -> int:
        """The dimension ``n``."""
        return int(self.lower.shape[-1])

    @property
    def batch_shape(self) -> torch.Size:
        """The broadcast batch shape of the bounds."""
        return torch.broadcast_shapes(self.lower.shape[:-1], self.upper.shape[:-1])

    @property
    def bounded(self) -> bool:
        """Whether any bound is finite."""
        return bool(torch.isfinite(self.lower).any() or torch.isfinite(self.upper).any())

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Box:
        """A copy with bounds cast to ``dtype`` and moved to ``device``."""
        out = Box.__new__(Box)
        out.lower = self.lower.to(device=device, dtype=dtype)
        out.upper = self.upper.to(device=device, dtype=dtype)
        return out

    def unsqueeze(self, dim: int) -> Box:
        """A box whose bounds gain a size-1 batch dimension at ``dim`` (counted in ``(..., n)``).

        Args:
            dim: where the new dimension goes, negative and before the last (state) dimension.

        Returns:
            The new :class:`Box`.

        Raises:
            InputError: ``dim`` is not negative, or is -1 (the state dimension).
        """
        if dim >= 0 or dim == -1:
            raise InputError("unsqueeze: give a negative dim before the last (state) dimension")
        out = Box.__new__(Box)
        out.lower = self.lower.unsqueeze(dim)
        out.upper = self.upper.unsqueeze(dim)
        return out

    def project(self, x: Tensor) -> Tensor:
        """Euclidean projection onto the box, ``min(max(x, lower), upper)``.

        Args:
            x: points, shape ``(..., n)`` broadcastable with the bounds.

        Returns:
            The projected points, shape ``(..., n)`` (differentiable; the gradient flows to ``x``
            where it is inside and to the active bound where it is clipped).
        """
        return torch.clamp(x, min=self.lower.to(x), max=self.upper.to(x))

    def contains(self, x: Tensor) -> Tensor:
        """Whether each point lies in the box (closed; no tolerance).

        Args:
            x: points, shape ``(..., n)``.

        Returns:
            Boolean tensor, shape ``(...)``.
        """
        return ((x >= self.lower.to(x)) & (x <= self.upper.to(x))).all(-1)

    def __repr__(self) -> str:
        return f"Box(lower={self.lower.tolist()}, upper={self.upper.tolist()})"
