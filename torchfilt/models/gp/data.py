"""Training pairs for GP models, from flat arrays or lists of recordings, with input checks.

A transition learns ``(x_k, u_k) -> x_{k+1}``, where input row ``k`` is the one that drove the
step from ``x_k`` to ``x_{k+1}`` (the input convention of :mod:`torchfilt.filters`: in a recording
``x[0..T]`` whose row 0 is the prior's time, row ``k`` of the ``T`` inputs); pairs never cross a
recording boundary. A
measurement learns ``(x_k, u_k) -> y_k``; NaN entries of ``y`` are missing measurements and are
dropped per output when fitting.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics.dtypes import check_compute_dtype, check_real_tensor

__all__ = ["PairData", "as_float", "measurement_pairs", "transition_pairs"]

#: Fewest training points a GP output may be fitted on.
MIN_POINTS = 5
#: Training values may not exceed ``sqrt(finfo(dtype).max) / MAGNITUDE_MARGIN`` in magnitude
#: (1.3e150 in float64, 1.8e15 in float32): the model's variances are squares of the data's
#: scale and must stay finite (at |y| ~ 1e154 the standard deviation overflowed and the model
#: predicted NaN).
MAGNITUDE_MARGIN = 1e4


def max_magnitude(dtype: torch.dtype) -> float:
    """The largest training value magnitude accepted in ``dtype`` (see ``MAGNITUDE_MARGIN``)."""
    return float(torch.finfo(dtype).max) ** 0.5 / MAGNITUDE_MARGIN


Recordings = Tensor | Sequence[Tensor]


class PairData(NamedTuple):
    """Training pairs.

    Attributes:
        states: ``x_k``, shape ``(N, n)``.
        inputs: ``u_k``, shape ``(N, nu)``, or ``None``.
        targets: ``x_{k+1}`` or ``y_k``, shape ``(N, d)``; NaN marks a missing measurement.
    """

    states: Tensor
    inputs: Tensor | None
    targets: Tensor

    @property
    def features(self) -> Tensor:
        """``[x_k, u_k]``, shape ``(N, n + nu)``."""
        return self.states if self.inputs is None else torch.cat([self.states, self.inputs], -1)


def as_float(value: Any, name: str, dtype: torch.dtype | None = None) -> Tensor:
    """Convert to a floating tensor, naming ``name`` in the error."""
    try:
        t = value if isinstance(value, Tensor) else torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name}: cannot convert {type(value).__name__} to a tensor") from exc
    check_real_tensor(t, name, integers=True)
    if dtype is not None:
        check_compute_dtype(dtype)
        t = t.to(dtype)
    elif not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


def _finite(t: Tensor, name: str) -> None:
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        rows = bad.reshape(-1, t.shape[-1]).any(-1).nonzero().flatten()[:5].tolist()
        raise InputError(
            f"{name} contains {int(bad.sum())} non-finite entries (first rows: {rows}); "
            "states and inputs cannot be missing"
        )
    _magnitude(t, name)


def _magnitude(t: Tensor, name: str) -> None:
    """Refuse values too large for the model's variances (NaN entries are ignored)."""
    if t.numel() == 0:
        return
    big = float(torch.nan_to_num(t, nan=0.0).abs().max())
    limit = max_magnitude(t.dtype)
    if big > limit:
        raise InputError(
            f"{name}: values up to {big:.3g} in magnitude; a GP in {t.dtype} accepts at most "
            f"{limit:.3g} (its variances are squares of the data's scale): rescale the data"
        )


def _same_width(items: Sequence[Tensor], name: str) -> None:
    """All recordings of one argument must have the same number of columns."""
    widths = [int(t.shape[-1]) for t in items]
    for i, w in enumerate(widths):
        if w != widths[0]:
            raise ShapeError(
                f"{name}[{i}]: {w} columns, expected {widths[0]} like {name}[0] (every recording "
                "must have the same dimension)"
            )


def _is_list(v: Any) -> bool:
    return isinstance(v, (list, tuple))


def _matrix(t: Tensor, name: str, cols: int | None = None, what: str = "(N, n)") -> Tensor:
    if t.dim() < 2 or (cols is not None and t.shape[-1] != cols):
        raise ShapeError(f"{name}: expected shape {what}, got {tuple(t.shape)}")
    return t.reshape(-1, t.shape[-1])


def _list(v: Any, name: str, count: int | None) -> list[Any]:
    items = list(v)
    if count is not None and len(items) != count:
        raise ShapeError(f"{name}: {len(items)} recordings given, expected {count} (one per x)")
    return items


def transition_pairs(
    x: Recordings,
    u: Recordings | None = None,
    x_next: Tensor | None = None,
    *,
    dtype: torch.dtype | None = None,
) -> PairData:
    """Pairs ``(x_k, u_k) -> x_{k+1}``.

    Args:
        x: either states ``x_k`` ``(..., N, n)`` with ``x_next`` given, or recordings without
            ``x_next``: one tensor ``(..., T+1, n)`` (leading dimensions are separate recordings)
            or a list of tensors ``(T_i+1, n)``.
        u: inputs aligned with ``x``: ``(..., N, nu)`` for pairs; for recordings ``(..., T, nu)``
            or ``(..., T+1, nu)`` (the last row is unused), or a list; ``None`` for none.
        x_next: successor states ``(..., N, n)``, or ``None`` for recordings.
        dtype: dtype of the result, float32 or float64 (default: that of ``x``).

    Returns:
        The flattened :class:`PairData`.
    """
    if x_next is not None:
        if _is_list(x):
            raise InputError("x: pass a tensor of states (N, n) with x_next, or recordings alone")
        xs = as_float(x, "x", dtype)
        dtype = xs.dtype
        xs = _matrix(xs, "x")
        n = xs.shape[-1]
        xn = _matrix(as_float(x_next, "x_next", dtype), "x_next", n, f"(N, {n}) like x")
        if xn.shape[0] != xs.shape[0]:
            raise ShapeError(
                f"x_next: {xn.shape[0]} rows, expected {xs.shape[0]} (one successor per state)"
            )
        us = None
        if u is not None:
            if _is_list(u):
                raise InputError("u: pass a tensor (N, nu) aligned with x")
            ut = as_float(u, "u", dtype)
            us = _matrix(ut, "u", what=f"(N, nu) with N = {xs.shape[0]}")
            if us.shape[0] != xs.shape[0]:
                raise ShapeError(f"u: {us.shape[0]} rows, expected {xs.shape[0]} like x")
        pairs = PairData(xs, us, xn)
    else:
        recs = _recordings(x, "x", dtype)
        dtype = recs[0].dtype
        n = recs[0].shape[-1]
        urecs: list[Tensor | None] = [None] * len(recs)
        if u is not None:
            urecs = list(_recordings(u, "u", dtype, count=len(recs)))
            _same_width([t for t in urecs if t is not None], "u")
        xs_l, us_l, xn_l = [], [], []
        for i, (r, ur) in enumerate(zip(recs, urecs, strict=True)):
            if r.shape[-1] != n:
                raise ShapeError(f"x[{i}]: {r.shape[-1]} state components, expected {n}")
            T = r.shape[0] - 1
            if T < 1:
                continue
            xs_l.append(r[:-1])
            xn_l.append(r[1:])
            if ur is not None:
                if ur.shape[0] not in (T, T + 1):
                    raise ShapeError(
                        f"u[{i}]: {ur.shape[0]} rows for a recording of {T + 1} states; "
                        f"expected {T} (or {T + 1}, last unused)"
                    )
                us_l.append(ur[:T])
        if not xs_l:
            raise InputError("x: the recordings hold no transition (each needs two states)")
        pairs = PairData(
            torch.cat(xs_l), torch.cat(us_l) if u is not None else None, torch.cat(xn_l)
        )
    _finite(pairs.states, "x")
    _finite(pairs.targets, "x_next")
    if pairs.inputs is not None:
        _finite(pairs.inputs, "u")
    if pairs.states.shape[0] < MIN_POINTS:
        raise InputError(
            f"x: {pairs.states.shape[0]} transition pairs; at least {MIN_POINTS} are needed"
        )
    return pairs


def measurement_pairs(
    x: Recordings,
    y: Recordings,
    u: Recordings | None = None,
    *,
    dtype: torch.dtype | None = None,
) -> PairData:
    """Pairs ``(x_k, u_k) -> y_k``.

    Args:
        x: states ``(..., N, n)`` or a list of ``(T_i, n)``.
        y: measurements ``(..., N, m)`` or a list of ``(T_i, m)``; NaN marks a missing value.
        u: inputs ``(..., N, nu)``, a list, or ``None``.
        dtype: dtype of the result, float32 or float64 (default: that of ``x``).

    Returns:
        The flattened :class:`PairData`.
    """
    if _is_list(x) != _is_list(y):
        raise InputError("x and y: pass both as tensors or both as lists of recordings")
    if _is_list(x):
        xs = _recordings(x, "x", dtype)
        dtype = xs[0].dtype
        ys = _recordings(y, "y", dtype, count=len(xs))
        _same_width(xs, "x")
        _same_width(ys, "y")
        for i, (a, b) in enumerate(zip(xs, ys, strict=True)):
            if a.shape[0] != b.shape[0]:
                raise ShapeError(f"y[{i}]: {b.shape[0]} rows, expected {a.shape[0]} like x[{i}]")
        xt, yt = torch.cat(xs), torch.cat(ys)
        ut = None
        if u is not None:
            us = _recordings(u, "u", dtype, count=len(xs))
            _same_width(us, "u")
            for i, (a, b) in enumerate(zip(xs, us, strict=True)):
                if a.shape[0] != b.shape[0]:
                    raise ShapeError(
                        f"u[{i}]: {b.shape[0]} rows, expected {a.shape[0]} like x[{i}]"
                    )
            ut = torch.cat(us)
    else:
        xt = _matrix(as_float(x, "x", dtype), "x")
        dtype = xt.dtype
        yt = _matrix(as_float(y, "y", dtype), "y", what="(N, m)")
        if yt.shape[0] != xt.shape[0]:
            raise ShapeError(f"y: {yt.shape[0]} rows, expected {xt.shape[0]} like x")
        ut = None
        if u is not None:
            ut = _matrix(as_float(u, "u", dtype), "u", what="(N, nu)")
            if ut.shape[0] != xt.shape[0]:
                raise ShapeError(f"u: {ut.shape[0]} rows, expected {xt.shape[0]} like x")
    _finite(xt, "x")
    if ut is not None:
        _finite(ut, "u")
    if bool(torch.isinf(yt).any()):
        raise InputError("y contains infinite entries (use NaN for a missing measurement)")
    _magnitude(yt, "y")
    return PairData(xt, ut, yt)


def _recordings(
    v: Recordings, name: str, dtype: torch.dtype | None, count: int | None = None
) -> list[Tensor]:
    if _is_list(v):
        items = _list(v, name, count)
        if not items:
            raise InputError(f"{name}: the list of recordings is empty")
        out = []
        for i, r in enumerate(items):
            t = as_float(r, f"{name}[{i}]", dtype)
            dtype = t.dtype
            if t.dim() != 2:
                raise ShapeError(f"{name}[{i}]: expected shape (T, dim), got {tuple(t.shape)}")
            out.append(t)
        return out
    t = as_float(v, name, dtype)
    if t.dim() < 2:
        raise ShapeError(f"{name}: expected shape (..., T, dim), got {tuple(t.shape)}")
    t = t.reshape(-1, *t.shape[-2:])
    if count is not None and t.shape[0] != count:
        raise ShapeError(f"{name}: {t.shape[0]} recordings, expected {count} like x")
    return list(t.unbind(0))
