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

from collections.abc import Sequence
from typing import Any, Literal, NamedTuple, Protocol

import torch
from torch import Tensor

from torchfilt.dmc.qp import solve_qp
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.exceptions import ShapeError

__all__ = ["FixedTarget", "SteadyStateTarget", "Target", "TargetRow", "WeightedTarget"]

#: Weight ratio between consecutive priority levels of :class:`WeightedTarget`.
PRIORITY_BASE = 10.0
#: Regularisation weight on ``u_ss - u(k-1)`` that makes the target QP strictly convex.
TARGET_REGULARISATION = 1e-6


class Target(NamedTuple):
    """A steady-state target: ``y`` shape ``(ny,)``, ``u`` shape ``(nu,)``."""

    y: Tensor
    u: Tensor


class SteadyStateTarget(Protocol):
    """Interface of a steady-state target layer."""

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        """Target from the steady-state open-loop prediction ``(ny,)`` and ``u(k-1)`` ``(nu,)``."""
        ...


class FixedTarget:
    """Constant setpoints ``(y_t, u_t)`` (``u_t`` defaults to ``u(k-1)``, i.e. no input target)."""

    def __init__(self, y: Tensor | float, u: Tensor | float | None = None) -> None:
        self.y = torch.as_tensor(y, dtype=torch.float64)
        self.u = None if u is None else torch.as_tensor(u, dtype=torch.float64)

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        y = self.y.to(y_ss.dtype).expand(y_ss.shape)
        u = u_prev if self.u is None else self.u.to(u_prev.dtype).expand(u_prev.shape)
        return Target(y.clone(), u.clone())


class TargetRow(NamedTuple):
    """One row of a target specification.

    Attributes:
        variable: ``("y", j)`` for CV ``j`` or ``("u", i)`` for MV ``i`` (0-based), or a linear
            combination ``("lin", weights)`` with ``weights`` over ``[y_ss; u_ss]`` (``ny + nu``).
        kind: ``"ideal"`` (hit ``value``), ``"lower"``/``"upper"`` (soft bound at ``value``), or
            ``"hold"`` (stay at the current value: ``u(k-1)``, or ``y^ol_ss`` for a CV).
        value: the ideal value or bound (ignored for ``"hold"``).
        concern: equal-concern error (the violation that costs one unit at this priority), ``> 0``.
        priority: 1 is the highest; larger numbers are less important.
    """

    variable: tuple[str, Any]
    kind: Literal["ideal", "lower", "upper", "hold"]
    value: float
    concern: float
    priority: int


class WeightedTarget:
    """Single weighted-QP steady-state target calculation (see the module docstring).

    Args:
        model: step-response model (stable CVs only); ``G = S^u_N``.
        rows: the target rows (:class:`TargetRow`).
        u_min: lower input bounds, scalar or ``(nu,)``.
        u_max: upper input bounds, scalar or ``(nu,)``.
        du_ss_max: bound on ``|u_ss - u(k-1)|``, scalar or ``(nu,)``; ``None`` for none.
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
        if bool(model.integrating.any()):
            raise ValueError(
                "WeightedTarget supports stable CVs only; CVs "
                f"{model.integrating.nonzero().squeeze(-1).tolist()} are integrating"
            )
        self.model = model
        ny, nu, dt = model.ny, model.nu, model.dtype
        self.G = model.steady_gain("u")
        self.u_min = torch.as_tensor(u_min, dtype=dt).expand(nu).clone()
        self.u_max = torch.as_tensor(u_max, dtype=dt).expand(nu).clone()
        if bool((self.u_min > self.u_max).any()):
            raise ValueError("u_min must not exceed u_max")
        self.du_ss_max = (
            None if du_ss_max is None else torch.as_tensor(du_ss_max, dtype=dt).expand(nu).clone()
        )
        if not rows:
            raise ValueError("rows: give at least one target row")
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
                raise ValueError(
                    f"rows[{k}].variable must be ('y', 0..{ny - 1}), ('u', 0..{nu - 1}) or "
                    f"('lin', weights); got {r.variable!r}"
                )
            if r.kind not in ("ideal", "lower", "upper", "hold"):
                raise ValueError(f"rows[{k}].kind must be ideal/lower/upper/hold, got {r.kind!r}")
            if not r.concern > 0:
                raise ValueError(f"rows[{k}].concern must be positive, got {r.concern}")
            if int(r.priority) != r.priority or r.priority < 1:
                raise ValueError(f"rows[{k}].priority must be a positive integer, got {r.priority}")
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
        y_ss = torch.as_tensor(y_ss, dtype=dt)
        u_prev = torch.as_tensor(u_prev, dtype=dt)
        if y_ss.shape != (ny,):
            raise ShapeError(f"y_ss: expected shape ({ny},), got {tuple(y_ss.shape)}")
        if u_prev.shape != (nu,):
            raise ShapeError(f"u_prev: expected shape ({nu},), got {tuple(u_prev.shape)}")
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
            raise RuntimeError(
                "the steady-state target QP did not converge; check that u(k-1) lies within "
                "[u_min, u_max]"
            )
        u_ss = res.x[:nu]
        return Target(d + self.G @ u_ss, u_ss)
