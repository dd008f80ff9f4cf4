"""Steady-state target layer of double-layered DMC (the interface, and the simplest faithful version).

A target layer maps the open-loop *steady-state* prediction ``y^ol_ss(k)`` (for stable CVs the last
free prediction ``y^ol(k+N|k)``) and the last input ``u(k-1)`` to a consistent target ``(y_t, u_t)``
for the dynamic layer (:class:`~torchfilt.dmc.DMCController`). Any callable with the
:class:`SteadyStateTarget` signature plugs in; the multi-priority target calculation of Li & Ding
(2015) used in the paper's section 3.1 (its Table 1) is :class:`~torchfilt.dmc.MultiPriorityTarget`
(:mod:`torchfilt.dmc.sstc`).

:class:`WeightedTarget` is a simpler, single-QP alternative. With the steady-state model

    y_ss = y^ol_ss + G (u_ss - u(k-1)),       G = S^u_N (steady-state gains)

it solves one QP over ``u_ss`` (and one slack per soft bound row)

    minimise   sum_rows  w_p(row) (violation_row / concern_row)^2  +  eps ||u_ss - u(k-1)||^2
    subject to u_min <= u_ss <= u_max,  |u_ss - u(k-1)| <= du_ss_max

where a row is an ideal value (``violation = a^T [y_ss; u_ss] - value``), a lower or upper bound
(``violation = max(0, ...)``, through a non-negative slack), or a "hold" row (ideal value = the current
value, e.g. a minimum-move MV). Priorities become weights ``w_p = PRIORITY_BASE^(p_max - p)``: a
weighted compromise, not the strict lexicographic order of the original (documented difference). Only
stable CVs are supported (an integrating CV has no steady-state level to target).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal, NamedTuple, Protocol

import torch
from torch import Tensor

from torchfilt.dmc.controller import _real_tensor, _vector
from torchfilt.dmc.qp import solve_qp
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.exceptions import InfeasibleError, InputError, InputTypeError, ShapeError

__all__ = ["FixedTarget", "SteadyStateTarget", "Target", "TargetRow", "WeightedTarget"]

#: Weight ratio between consecutive priority levels of :class:`WeightedTarget`.
PRIORITY_BASE = 10.0
#: Regularisation weight on ``u_ss - u(k-1)`` that makes the target QP strictly convex.
TARGET_REGULARISATION = 1e-6


class Target(NamedTuple):
    """A steady-state target.

    Attributes:
        y: the controlled variables' target, shape ``(ny,)``.
        u: the inputs' target, shape ``(nu,)``.
    """

    y: Tensor
    u: Tensor


class SteadyStateTarget(Protocol):
    """Interface of a steady-state target layer."""

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        """Target from the steady-state open-loop prediction ``(ny,)`` and ``u(k-1)`` ``(nu,)``."""
        ...


class FixedTarget:
    """Constant setpoints ``(y_t, u_t)`` (``u_t`` defaults to ``u(k-1)``, i.e. no input target).

    Args:
        y: the setpoints ``y_t``, a scalar (the same for every CV) or shape ``(ny,)``.
        u: the input targets ``u_t``, a scalar or shape ``(nu,)``; ``None`` holds ``u(k-1)``.
    """

    def __init__(self, y: Tensor | float, u: Tensor | float | None = None) -> None:
        self.y = torch.as_tensor(y, dtype=torch.float64)
        self.u = None if u is None else torch.as_tensor(u, dtype=torch.float64)

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        y = self.y.to(y_ss.dtype).expand(y_ss.shape)
        u = u_prev if self.u is None else self.u.to(u_prev.dtype).expand(u_prev.shape)
        return Target(y.clone(), u.clone())


class _TargetRowFields(NamedTuple):
    variable: tuple[str, Any]
    kind: Literal["ideal", "lower", "upper", "hold"]
    value: float
    concern: float
    priority: int


#: The kinds a :class:`TargetRow` may have.
_ROW_KINDS = ("ideal", "lower", "upper", "hold")


def _real(value: Any, name: str) -> float:
    """``value`` as a float; an InputTypeError naming ``name`` unless it is a real scalar."""
    bad = isinstance(value, str | bytes | bool) or getattr(value, "ndim", 0) != 0
    if not bad:
        try:
            return float(value)
        except (TypeError, ValueError, RuntimeError):
            pass
    raise InputTypeError(f"{name} must be a real number, got {value!r}")


def _check_row(row: Any, where: str) -> TargetRow:
    """Validate a target row (a :class:`TargetRow` or a 5-tuple of its fields).

    Checks what no model makes valid: the variable's form, the kind, and that ``value`` (unless
    the row is a ``"hold"`` row, whose value is ignored), ``concern`` and ``priority`` are finite
    real numbers. What depends on the target (index ranges, the weights' length, ``concern > 0``,
    an integer ``priority >= 1``) is checked by the target.

    Args:
        row: the row.
        where: how the message names the row (``"TargetRow"``, ``"rows[2]"``).

    Returns:
        The row as a :class:`TargetRow` (its fields unchanged).

    Raises:
        InputError: a non-finite number or an unknown kind or variable (naming the field).
        InputTypeError: a field of the wrong type.
    """
    if isinstance(row, str | bytes) or not isinstance(row, Sequence) or len(row) != 5:
        raise InputTypeError(
            f"{where} must be a TargetRow(variable, kind, value, concern, priority), got {row!r}"
        )
    variable, kind, value, concern, priority = row
    if isinstance(variable, str | bytes) or not isinstance(variable, Sequence):
        raise InputTypeError(f"{where}.variable must be a pair (name, index), got {variable!r}")
    if len(variable) != 2 or variable[0] not in ("y", "u", "lin"):
        raise InputError(
            f"{where}.variable must be ('y', j), ('u', i) or ('lin', weights); got {variable!r}"
        )
    name, idx = variable
    if name in ("y", "u") and (isinstance(idx, bool) or not isinstance(idx, int) or idx < 0):
        raise InputError(
            f"{where}.variable: the index of {name!r} must be an int >= 0, got {idx!r}"
        )
    if name == "lin":
        try:
            w = torch.as_tensor(idx, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise InputTypeError(
                f"{where}.variable: the linear weights must be a vector of numbers, got {idx!r}"
            ) from None
        if w.dim() != 1 or not bool(torch.isfinite(w).all()):
            raise InputError(
                f"{where}.variable: the linear weights must be a finite vector, got {idx!r}"
            )
    if not isinstance(kind, str) or kind not in _ROW_KINDS:
        raise InputError(f"{where}.kind must be ideal/lower/upper/hold, got {kind!r}")
    for field, v in (("value", value), ("concern", concern), ("priority", priority)):
        x = _real(v, f"{where}.{field}")
        if not math.isfinite(x) and not (field == "value" and kind == "hold"):
            raise InputError(f"{where}.{field} must be finite, got {x}")
    return row if isinstance(row, TargetRow) else tuple.__new__(TargetRow, tuple(row))


class TargetRow(_TargetRowFields):
    """One row of a target specification.

    Attributes:
        variable: ``("y", j)`` for CV ``j`` or ``("u", i)`` for MV ``i`` (0-based), or a linear
            combination ``("lin", weights)`` with ``weights`` over ``[y_ss; u_ss]`` (``ny + nu``).
        kind: ``"ideal"`` (hit ``value``), ``"lower"``/``"upper"`` (soft bound at ``value``), or
            ``"hold"`` (stay at the current value: ``u(k-1)``, or ``y^ol_ss`` for a CV).
        value: the ideal value or bound (ignored for ``"hold"``).
        concern: equal-concern error (the violation that costs one unit at this priority), ``> 0``.
        priority: 1 is the highest; larger numbers are less important.

    Raises:
        InputError: at construction, a non-finite ``value`` (except for ``"hold"``), ``concern``
            or ``priority``, an unknown ``kind`` or a malformed ``variable`` (naming the field).
        InputTypeError: a field of the wrong type.
    """

    __slots__ = ()

    def __new__(
        cls,
        variable: tuple[str, Any],
        kind: Literal["ideal", "lower", "upper", "hold"],
        value: float,
        concern: float,
        priority: int,
    ) -> TargetRow:
        fields = (variable, kind, value, concern, priority)
        _check_row(fields, "TargetRow")
        return super().__new__(cls, *fields)


class WeightedTarget:
    """Single weighted-QP steady-state target calculation (see the module docstring).

    Args:
        model: step-response model (stable CVs only); ``G = S^u_N``.
        rows: the target rows (:class:`TargetRow`).
        u_min: lower input bounds, scalar or ``(nu,)``.
        u_max: upper input bounds, scalar or ``(nu,)``.
        du_ss_max: bound on ``|u_ss - u(k-1)|``, scalar or ``(nu,)``; ``None`` for none.

    Raises:
        InputTypeError: ``model`` is not a :class:`StepResponseModel`, or a row field or bound of
            the wrong type.
        InputError: an integrating model, ``u_min > u_max``, a negative ``du_ss_max``, no rows,
            or a row with an unknown variable or kind, a non-positive ``concern`` or a priority
            that is not a positive integer.
        ShapeError: a bound that is neither a scalar nor ``(nu,)``, or linear weights that are
            not ``(ny + nu,)``.
    """

    def __init__(
        self,
        model: StepResponseModel,
        rows: Sequence[TargetRow],
        *,
        u_min: float | Tensor,
        u_max: float | Tensor,
        du_ss_max: float | Tensor | None = None,
    ) -> None:
        if not isinstance(model, StepResponseModel):
            raise InputTypeError(f"model must be a StepResponseModel, got {type(model).__name__}")
        if bool(model.integrating.any()):
            raise InputError(
                "model: WeightedTarget supports stable CVs only; CVs "
                f"{model.integrating.nonzero().squeeze(-1).tolist()} are integrating"
            )
        self.model = model
        ny, nu, dt = model.ny, model.nu, model.dtype
        self.G = model.steady_gain("u")
        self.u_min = _vector(u_min, nu, "u_min", dt)
        self.u_max = _vector(u_max, nu, "u_max", dt)
        if bool((self.u_min > self.u_max).any()):
            raise InputError(f"u_min must not exceed u_max (got {self.u_min} > {self.u_max})")
        self.du_ss_max = None if du_ss_max is None else _vector(du_ss_max, nu, "du_ss_max", dt)
        if self.du_ss_max is not None and bool((self.du_ss_max < 0).any()):
            raise InputError(f"du_ss_max must be non-negative, got {self.du_ss_max.tolist()}")
        if isinstance(rows, str | bytes) or not isinstance(rows, Sequence) or not rows:
            raise InputError(f"rows: give a non-empty list of TargetRow, got {rows!r}")
        rows = [_check_row(r, f"rows[{k}]") for k, r in enumerate(rows)]
        pmax = max(r.priority for r in rows)
        self.rows = list(rows)
        a, kinds, values, weights = [], [], [], []
        for k, r in enumerate(rows):
            name, idx = r.variable
            vec = torch.zeros(ny + nu, dtype=dt)
            if name == "y" and isinstance(idx, int) and 0 <= idx < ny:
                vec[idx] = 1.0
            elif name == "u" and isinstance(idx, int) and 0 <= idx < nu:
                vec[ny + idx] = 1.0
            elif name == "lin":
                w = torch.as_tensor(idx, dtype=dt)
                if w.shape != (ny + nu,):
                    raise ShapeError(
                        f"rows[{k}]: linear weights must have shape ({ny + nu},), got {tuple(w.shape)}"
                    )
                vec = w
            else:
                raise InputError(
                    f"rows[{k}].variable must be ('y', 0..{ny - 1}), ('u', 0..{nu - 1}) or "
                    f"('lin', weights); got {r.variable!r}"
                )
            if r.kind not in ("ideal", "lower", "upper", "hold"):
                raise InputError(f"rows[{k}].kind must be ideal/lower/upper/hold, got {r.kind!r}")
            if not r.concern > 0:
                raise InputError(f"rows[{k}].concern must be positive, got {r.concern}")
            if int(r.priority) != r.priority or r.priority < 1:
                raise InputError(f"rows[{k}].priority must be a positive integer, got {r.priority}")
            a.append(vec)
            kinds.append(r.kind)
            values.append(float(r.value))
            weights.append(PRIORITY_BASE ** (pmax - r.priority) / r.concern**2)
        self._a = torch.stack(a)  # (R, ny + nu)
        self._kinds = kinds
        self._values = torch.tensor(values, dtype=dt)
        self._w = torch.tensor(weights, dtype=dt)
        self._soft = [i for i, k in enumerate(kinds) if k in ("lower", "upper")]
        self._quad = [i for i, k in enumerate(kinds) if k in ("ideal", "hold")]

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        """Target from the steady-state open-loop prediction ``(ny,)`` and ``u(k-1)`` ``(nu,)``."""
        ny, nu, dt = self.model.ny, self.model.nu, self.model.dtype
        y_ss = _real_tensor(y_ss, "y_ss", dt)
        u_prev = _real_tensor(u_prev, "u_prev", dt)
        if y_ss.shape != (ny,):
            raise ShapeError(f"y_ss: expected shape ({ny},), got {tuple(y_ss.shape)}")
        if u_prev.shape != (nu,):
            raise ShapeError(f"u_prev: expected shape ({nu},), got {tuple(u_prev.shape)}")
        for name, t in (("y_ss", y_ss), ("u_prev", u_prev)):
            if not bool(torch.isfinite(t).all()):
                raise InputError(f"{name} must be finite, got {t.tolist()}")
        # every row is affine in u_ss: a^T [y; u] = a^T [d + G u; u] = (a_y^T G + a_u^T) u + a_y^T d
        d = y_ss - self.G @ u_prev
        a_y, a_u = self._a[:, :ny], self._a[:, ny:]
        Arow = a_y @ self.G + a_u  # (R, nu)
        brow = a_y @ d  # (R,)
        cur = self._a @ torch.cat([y_ss, u_prev])  # current values, for "hold" rows
        value = torch.tensor(
            [
                float(cur[i]) if k == "hold" else float(self._values[i])
                for i, k in enumerate(self._kinds)
            ],
            dtype=dt,
        )
        ns = len(self._soft)
        nz = nu + ns
        Hq = torch.zeros(nz, nz, dtype=dt)
        f = torch.zeros(nz, dtype=dt)
        # quadratic rows: w (A u + b - value)^2
        qi = self._quad
        if qi:
            Aq, rq, wq = Arow[qi], brow[qi] - value[qi], self._w[qi]
            Hq[:nu, :nu] += 2.0 * (Aq.mT * wq) @ Aq
            f[:nu] += 2.0 * (Aq.mT * wq) @ rq
        # regularisation eps ||u - u_prev||^2
        Hq[:nu, :nu] += 2.0 * TARGET_REGULARISATION * torch.eye(nu, dtype=dt)
        f[:nu] -= 2.0 * TARGET_REGULARISATION * u_prev
        # soft bounds: upper: A u + b - value <= s; lower: value - A u - b <= s; cost w s^2
        rows, rhs = [], []
        for k, i in enumerate(self._soft):
            sign = 1.0 if self._kinds[i] == "upper" else -1.0
            Hq[nu + k, nu + k] = 2.0 * self._w[i]
            row = torch.zeros(nz, dtype=dt)
            row[:nu] = sign * Arow[i]
            row[nu + k] = -1.0
            rows.append(row)
            rhs.append(sign * (value[i] - brow[i]))
        lb = torch.cat([self.u_min, torch.zeros(ns, dtype=dt)])
        ub = torch.cat([self.u_max, torch.full((ns,), float("inf"), dtype=dt)])
        if self.du_ss_max is not None:
            lb[:nu] = torch.maximum(lb[:nu], u_prev - self.du_ss_max)
            ub[:nu] = torch.minimum(ub[:nu], u_prev + self.du_ss_max)
        A = torch.stack(rows) if rows else None
        b = torch.stack(rhs) if rhs else None
        res = solve_qp(Hq, f, A, b, lb=lb, ub=ub)
        if not bool(res.converged):
            raise InfeasibleError(
                "the steady-state target QP did not converge; check that u(k-1) lies within "
                "[u_min, u_max]"
            )
        u_ss = res.x[:nu]
        return Target(d + self.G @ u_ss, u_ss)
