"""Multi-priority steady-state target calculation (SSTC) of double-layered DMC (Li & Ding 2015).

At sample ``k`` the steady-state model predicts, from the open-loop steady-state prediction
``y^ol_ss(k)`` (for stable CVs the last free prediction ``y^ol(k+N|k)`` of the Kalman-filter or
classical prediction module) and the last input ``u(k-1)``,

    y_ss = y^ol_ss + G du_ss,     u_ss = u(k-1) + du_ss,     G = S^u_N (steady-state gains).

**Hard constraints** (never relaxed): ``u_min <= u_ss <= u_max``, ``|du_ss| <= du_ss_max`` and the
hard CV limits ``y_min <= y_ss <= y_max``. When they admit no ``du_ss`` the calculation raises
:class:`~torchfilt.exceptions.InfeasibleError` naming the conflict.

**Feasibility stages** (linear programs, HiGHS through ``scipy.optimize.linprog``). Each soft row
``r`` (a :class:`~torchfilt.dmc.TargetRow`: a limit of type II, ``lower``/``upper``, or an ideal value
of type I, ``ideal``) gets a relaxation ``eps_r >= 0``:

    lower:  f_r >= value - eps_r,     upper:  f_r <= value + eps_r,     ideal:  |f_r - value| <= eps_r

where ``f_r`` is the row's CV, MV or linear combination of ``[y_ss; u_ss]``. Priority by priority,
from 1 (highest) to the second lowest, stage ``p`` solves

    J*_p = min  sum_{r in p} eps_r / e_r      (e_r: the row's equal-concern error)
           s.t. hard constraints, the relaxation inequalities of the rows of priority p, and the
                rows of every earlier priority with their limits moved by the relaxations found
                there (an ideal value met exactly becomes an equality)

so a lower priority is only ever relaxed to spare a higher one (preemptive order; as in industrial
SSTC, the relaxed limits of a solved stage become hard constraints for the stages after it).

**Economic stage** (a QP, by Clarabel). With MV costs ``h`` and the minimum-move MVs ``mm``,

    J(du_ss) = sum_{i not in mm} h_i du_i,ss + sum_{i in mm} h_i |du_i,ss|

(``|du|`` through a split ``du = p - n``, ``p, n >= 0``), it solves

    min  w_J (J - J_min)^2 + sum_{r in lowest priority} (eps_r / e_r)^2 + rho ||z||^2

subject to everything above, where ``z`` are all the QP's variables and ``rho`` =
:data:`SSTC_REGULARISATION` makes the minimiser unique. ``J_min`` is the economic value aimed at (for
the paper's ``h = [-2, 1, 2]`` and ``|du_ss| <= 0.1`` it is the smallest ``J`` the move bounds allow,
``-0.4``), so the stage drives ``J`` down as far as the lowest-priority soft constraints let it. The
rows of the lowest priority are only in this stage (the paper's "QP with the lowest-priority soft
constraints").

The result ``(y_ss, u_ss)`` is handed to the dynamic layer as CV setpoints and MV ideal values.
Soft stages always relax; should the economic QP fail to converge, the last feasibility stage's
target is used with a :class:`~torchfilt.exceptions.ConvergenceWarning`, so the loop never stops
on a numerical failure.
Only stable CVs are supported (an integrating CV has no steady-state level to target).
"""

from __future__ import annotations

import math
import operator
import warnings
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

from torchfilt.dmc.controller import _real_tensor, _vector
from torchfilt.dmc.qp import solve_one
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.dmc.target import Target, TargetRow, _check_row, _real
from torchfilt.exceptions import (
    ConvergenceWarning,
    InfeasibleError,
    InputError,
    InputTypeError,
    RunError,
    ShapeError,
)

__all__ = ["MultiPriorityTarget", "SSTCResult"]

#: Relative (and absolute) margin granted to a relaxed limit in later stages, so that rounding in the
#: LP solutions never makes a later stage infeasible; an ideal value relaxed by no more than this
#: becomes an equality.
STAGE_TOL = 1e-9
#: Regularisation weight of the economic QP (makes its minimiser unique).
SSTC_REGULARISATION = 1e-8
#: A constraint whose slack is below this counts as active; a relaxation above it as relaxed.
ACTIVE_TOL = 1e-7
#: Tolerance of the economic QP (Clarabel's gap and feasibility tolerances; its optimum is flat
#: along the economic direction, where tighter tolerances stall).
SSTC_QP_TOL = 1e-8


class SSTCResult(NamedTuple):
    """One steady-state target calculation.

    Attributes:
        y: CV targets ``y_ss``, shape ``(ny,)``.
        u: MV targets ``u_ss``, shape ``(nu,)``.
        du: ``u_ss - u(k-1)``, shape ``(nu,)``.
        relaxation: ``eps_r`` of every soft row (in the row's units), shape ``(R,)``.
        stage_costs: ``sum eps_r / e_r`` of each priority level, shape ``(levels,)`` (the last is the
            economic stage's lowest-priority rows).
        economic: ``J`` at the solution.
        active: names of the active constraints: hard limits at their bound (``"hard ..."``), soft
            limits held exactly at their bound (``"at ..."``), ideal values met (``"met ..."``) and
            relaxed soft rows (``"relaxed ... by eps"``).
    """

    y: Tensor
    u: Tensor
    du: Tensor
    relaxation: Tensor
    stage_costs: Tensor
    economic: float
    active: list[str]


def _vec(
    value: float | Sequence[float] | Tensor | None, n: int, name: str, default: float
) -> np.ndarray:
    if value is None:
        return np.full(n, default)
    return _vector(value, n, name, torch.float64).numpy()


def _finite_vector(value: Tensor, n: int, name: str) -> np.ndarray:
    """A finite real vector of shape ``(n,)`` as float64 NumPy; the error names ``name``."""
    t = _real_tensor(value, name)
    if t.shape != (n,):
        raise ShapeError(f"{name}: expected shape ({n},), got {tuple(t.shape)}")
    x = t.detach().cpu().double().numpy()
    if not np.isfinite(x).all():
        raise InputError(f"{name} must be finite, got {x.tolist()}")
    return x


def _bounds(
    lo: float | Sequence[float] | Tensor | None,
    hi: float | Sequence[float] | Tensor | None,
    n: int,
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """``name_min`` and ``name_max`` as ``(n,)`` arrays; ``None`` / ``-inf`` / ``+inf`` for none."""
    inf = float("inf")
    lo_a = _vec(lo, n, f"{name}_min", -inf)
    hi_a = _vec(hi, n, f"{name}_max", inf)
    if (lo_a == inf).any():
        raise InputError(f"{name}_min must be finite or -inf (none), got {lo_a.tolist()}")
    if (hi_a == -inf).any():
        raise InputError(f"{name}_max must be finite or +inf (none), got {hi_a.tolist()}")
    if (lo_a > hi_a).any():
        raise InputError(f"{name}_min must not exceed {name}_max (got {lo_a} > {hi_a})")
    return lo_a, hi_a


def _indices(minimum_move: Iterable[int], nu: int) -> list[int]:
    """The minimum-move MV indices, sorted and unique (each an int in ``0..nu-1``)."""
    if isinstance(minimum_move, str | bytes) or not isinstance(minimum_move, Iterable):
        raise InputTypeError(
            f"minimum_move must be a sequence of MV indices, got {type(minimum_move).__name__}"
        )
    given = list(minimum_move)
    out: set[int] = set()
    for i in given:
        try:
            k = -1 if isinstance(i, bool) else operator.index(i)
        except TypeError:
            k = -1
        if not 0 <= k < nu:
            raise InputError(f"minimum_move: MV indices must be ints in 0..{nu - 1}, got {given}")
        out.add(k)
    return sorted(out)


def _fmt(x: float) -> str:
    return f"{x:.4g}"


class MultiPriorityTarget:
    """Multi-priority steady-state target calculation (see the module docstring).

    Args:
        model: step-response model (stable CVs only); ``G = S^u_N``.
        rows: soft rows (:class:`~torchfilt.dmc.TargetRow` with kind ``lower``, ``upper`` or
            ``ideal``); priority 1 is the highest, the largest priority goes to the economic QP.
        u_min: lower MV bounds, scalar or ``(nu,)``.
        u_max: upper MV bounds, scalar or ``(nu,)``.
        du_ss_max: bound on ``|u_ss - u(k-1)|``, scalar or ``(nu,)``; ``None`` for none.
        y_min: hard lower CV limits, scalar or ``(ny,)``; ``None`` for none.
        y_max: hard upper CV limits, scalar or ``(ny,)``; ``None`` for none.
        cost: MV costs ``h``, shape ``(nu,)``; ``None`` for no economic term.
        minimum_move: indices of the minimum-move MVs (cost ``h_i |du_i,ss|``).
        J_min: the economic value aimed at.
        economic_weight: ``w_J``.

    Raises:
        InputError: an integrating model or one that is no :class:`StepResponseModel`, a lower
            bound above its upper bound, a negative ``du_ss_max`` or ``economic_weight``, a
            non-finite cost or ``J_min``, an MV index out of range, no rows, or a row with an
            unknown variable or kind, a non-positive ``concern`` or an invalid priority.
        InputTypeError: a row field or number of the wrong type.
        ShapeError: a bound or cost that is neither a scalar nor one value per channel, or linear
            weights that are not ``(ny + nu,)``.
    """

    def __init__(
        self,
        model: StepResponseModel,
        rows: Sequence[TargetRow],
        *,
        u_min: float | Tensor,
        u_max: float | Tensor,
        du_ss_max: float | Tensor | None = None,
        y_min: float | Tensor | None = None,
        y_max: float | Tensor | None = None,
        cost: Sequence[float] | Tensor | None = None,
        minimum_move: Iterable[int] = (),
        J_min: float = 0.0,
        economic_weight: float = 1.0,
    ) -> None:
        if not isinstance(model, StepResponseModel):
            raise InputError(f"model must be a StepResponseModel, got {type(model).__name__}")
        if bool(model.integrating.any()):
            raise InputError(
                "model: MultiPriorityTarget supports stable CVs only; CVs "
                f"{model.integrating.nonzero().squeeze(-1).tolist()} are integrating"
            )
        ny, nu = model.ny, model.nu
        self.model, self.ny, self.nu = model, ny, nu
        self.G = model.steady_gain("u").detach().cpu().double().numpy()
        inf = float("inf")
        self.u_min, self.u_max = _bounds(u_min, u_max, nu, "u")
        self.du_max = _vec(du_ss_max, nu, "du_ss_max", inf)
        if bool((self.du_max < 0).any()):
            raise InputError(f"du_ss_max must be non-negative, got {self.du_max.tolist()}")
        self.y_min, self.y_max = _bounds(y_min, y_max, ny, "y")
        self.h = _vec(cost, nu, "cost", 0.0)
        if not np.isfinite(self.h).all():
            raise InputError(f"cost must be finite, got {self.h.tolist()}")
        self.mm = _indices(minimum_move, nu)
        self.J_min = _real(J_min, "J_min")
        self.w_J = _real(economic_weight, "economic_weight")
        if not math.isfinite(self.J_min):
            raise InputError(f"J_min must be finite, got {self.J_min}")
        if not (math.isfinite(self.w_J) and self.w_J >= 0):
            raise InputError(f"economic_weight must be finite and non-negative, got {self.w_J}")
        if isinstance(rows, str | bytes) or not isinstance(rows, Sequence) or not rows:
            raise InputError(f"rows: give a non-empty list of soft rows (TargetRow), got {rows!r}")
        rows = [_check_row(r, f"rows[{k}]") for k, r in enumerate(rows)]
        a, kinds, values, concern, prio, names = [], [], [], [], [], []
        for k, r in enumerate(rows):
            name, idx = r.variable
            vec = np.zeros(ny + nu)
            if name == "y" and isinstance(idx, int) and 0 <= idx < ny:
                vec[idx] = 1.0
                label = f"y{idx + 1}"
            elif name == "u" and isinstance(idx, int) and 0 <= idx < nu:
                vec[ny + idx] = 1.0
                label = f"u{idx + 1}"
            elif name == "lin":
                w = np.asarray(idx, dtype=np.float64)
                if w.shape != (ny + nu,):
                    raise ShapeError(
                        f"rows[{k}]: linear weights must have shape ({ny + nu},), got {w.shape}"
                    )
                vec = w.copy()
                label = f"row{k}"
            else:
                raise InputError(
                    f"rows[{k}].variable must be ('y', 0..{ny - 1}), ('u', 0..{nu - 1}) or "
                    f"('lin', weights); got {r.variable!r}"
                )
            if r.kind not in ("ideal", "lower", "upper"):
                raise InputError(f"rows[{k}].kind must be ideal, lower or upper, got {r.kind!r}")
            if not r.concern > 0:
                raise InputError(f"rows[{k}].concern must be positive, got {r.concern}")
            if int(r.priority) != r.priority or r.priority < 1:
                raise InputError(f"rows[{k}].priority must be a positive integer, got {r.priority}")
            a.append(vec)
            kinds.append(r.kind)
            values.append(float(r.value))
            concern.append(float(r.concern))
            prio.append(int(r.priority))
            names.append(f"p{int(r.priority)} {label} {r.kind} {_fmt(float(r.value))}")
        self.rows = list(rows)
        self._a = np.stack(a)  # (R, ny + nu)
        self._kinds, self._names = kinds, names
        self._values = np.asarray(values)
        self._e = np.asarray(concern)
        self._prio = np.asarray(prio)
        self.levels = sorted(set(prio))

    # ------------------------------------------------------------------ building blocks
    def _affine(self, y0: np.ndarray, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows as ``f = F du + g``: ``F (R, nu)``, ``g (R,)``."""
        ny = self.ny
        a_y, a_u = self._a[:, :ny], self._a[:, ny:]
        return a_y @ self.G + a_u, a_y @ y0 + a_u @ u_prev

    def _box(self, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo = np.maximum(self.u_min - u_prev, -self.du_max)
        hi = np.minimum(self.u_max - u_prev, self.du_max)
        return lo, hi

    def _check_hard(self, y0: np.ndarray, u_prev: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        bad = np.nonzero(lo > hi)[0]
        if bad.size:
            i = int(bad[0])
            raise InfeasibleError(
                f"the hard MV constraints admit no steady state: u{i + 1}(k-1) = "
                f"{_fmt(u_prev[i])} is more than du_ss_max = {_fmt(self.du_max[i])} outside "
                f"[u_min, u_max] = [{_fmt(self.u_min[i])}, {_fmt(self.u_max[i])}]"
            )
        # each CV's reachable steady-state range over the move box, against its hard limits
        for j in range(self.ny):
            g = self.G[j]
            reach_lo = y0[j] + np.sum(np.where(g > 0, g * lo, g * hi))
            reach_hi = y0[j] + np.sum(np.where(g > 0, g * hi, g * lo))
            if reach_hi < self.y_min[j] or reach_lo > self.y_max[j]:
                raise InfeasibleError(
                    f"the hard constraints admit no steady state: y{j + 1}_ss can only reach "
                    f"[{_fmt(reach_lo)}, {_fmt(reach_hi)}] within the MV and move bounds, outside "
                    f"its hard limits [y_min, y_max] = [{_fmt(self.y_min[j])}, "
                    f"{_fmt(self.y_max[j])}]"
                )

    def _rows_ub(
        self,
        F: np.ndarray,
        g: np.ndarray,
        sel: np.ndarray,
        nz: int,
        col0: int,
        width: int | None = None,
    ) -> tuple[list[np.ndarray], list[float]]:
        """Relaxation inequalities ``G z <= h`` of the selected rows (slack ``k`` at ``col0 + k``;
        the rows are ``f = F z[:width] + g``)."""
        nu = self.nu if width is None else width
        A: list[np.ndarray] = []
        b: list[float] = []
        for k, r in enumerate(sel):
            kind, v = self._kinds[r], self._values[r]
            for sign in (
                (-1.0, 1.0) if kind == "ideal" else ((-1.0,) if kind == "lower" else (1.0,))
            ):
                row = np.zeros(nz)
                row[:nu] = sign * F[r]  # sign (f - v) <= eps
                row[col0 + k] = -1.0
                A.append(row)
                b.append(sign * (v - g[r]))
        return A, b

    def _fixed_rows(
        self,
        F: np.ndarray,
        g: np.ndarray,
        sel: np.ndarray,
        eps: np.ndarray,
        nz: int,
        width: int | None = None,
    ) -> tuple[list[np.ndarray], list[float], list[np.ndarray], list[float]]:
        """Rows of solved stages, their limits moved by the fixed relaxations ``eps``.

        Returns ``(A_ub, b_ub, A_eq, b_eq)``: an ideal value met exactly becomes an equality.
        """
        nw = self.nu if width is None else width
        A: list[np.ndarray] = []
        b: list[float] = []
        Ae: list[np.ndarray] = []
        be: list[float] = []
        for r in sel:
            kind, v, e = self._kinds[r], self._values[r], eps[r]
            if kind == "ideal" and e <= STAGE_TOL:
                row = np.zeros(nz)
                row[:nw] = F[r]
                Ae.append(row)
                be.append(v - g[r])
                continue
            margin = e + STAGE_TOL * (1.0 + abs(v))
            for sign in (
                (-1.0, 1.0) if kind == "ideal" else ((-1.0,) if kind == "lower" else (1.0,))
            ):
                row = np.zeros(nz)
                row[:nw] = sign * F[r]  # sign (f - v) <= eps
                A.append(row)
                b.append(sign * (v - g[r]) + margin)
        return A, b, Ae, be

    def _hard_ub(
        self, y0: np.ndarray, nz: int, T: np.ndarray | None = None
    ) -> tuple[list[np.ndarray], list[float]]:
        """Hard CV limits as ``G z <= h`` (``du = T z[:nd]`` when ``T`` is given)."""
        A: list[np.ndarray] = []
        b: list[float] = []
        GT = self.G if T is None else self.G @ T
        nd = GT.shape[1]
        for j in range(self.ny):
            if np.isfinite(self.y_max[j]):
                row = np.zeros(nz)
                row[:nd] = GT[j]
                A.append(row)
                b.append(self.y_max[j] - y0[j])
            if np.isfinite(self.y_min[j]):
                row = np.zeros(nz)
                row[:nd] = -GT[j]
                A.append(row)
                b.append(y0[j] - self.y_min[j])
        return A, b

    # ------------------------------------------------------------------ the calculation
    def solve(self, y_ss: Tensor, u_prev: Tensor) -> SSTCResult:
        """Targets from the steady-state open-loop prediction and the last input.

        Args:
            y_ss: the steady-state open-loop prediction ``y^ol(k+N|k)``, shape ``(ny,)``.
            u_prev: ``u(k-1)``, shape ``(nu,)``.

        Returns:
            The :class:`SSTCResult`: the targets and the stages' diagnostics.

        Raises:
            InfeasibleError: the hard constraints admit no steady state.
            ShapeError: wrong input shapes.
            InputError: non-finite inputs.
        """
        y0, up = _finite_vector(y_ss, self.ny, "y_ss"), _finite_vector(u_prev, self.nu, "u_prev")
        lo, hi = self._box(up)
        self._check_hard(y0, up, lo, hi)
        F, g = self._affine(y0, up)
        eps_fixed, du_lp, stage_costs = self._feasibility_stages(y0, up, lo, hi, F, g)
        du = self._economic_stage(y0, lo, hi, F, g, eps_fixed)
        if du is None:  # never crash: keep the feasibility stages' answer and say so
            warnings.warn(
                "the SSTC economic QP did not converge (Clarabel); the target of the last "
                f"feasibility stage is used (y_ol_ss = {np.round(y0, 6).tolist()}, u(k-1) = "
                f"{np.round(up, 6).tolist()})",
                ConvergenceWarning,
                stacklevel=2,
            )
            du = du_lp if du_lp is not None else self._hard_point(y0, lo, hi)
        du = np.clip(du, lo, hi)  # remove interior-point rounding outside the hard box
        return self._result(y0, up, du, F, g, stage_costs)

    def _feasibility_stages(
        self,
        y0: np.ndarray,
        up: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        F: np.ndarray,
        g: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray | None, list[float]]:
        """The LP of every priority but the lowest, in order.

        Returns ``(eps_fixed, du_lp, stage_costs)``: the relaxations fixed by the stages ``(R,)``,
        the last stage's move (the fallback target; ``None`` without LP stages) and their costs.
        """
        nu = self.nu
        R = len(self._kinds)
        eps_fixed = np.zeros(R)  # relaxations fixed by the LP stages
        du_lp: np.ndarray | None = None  # the last LP stage's move (the fallback target)
        stage_costs: list[float] = []
        for p in self.levels[:-1]:
            this = np.nonzero(self._prio == p)[0]
            fixed = np.nonzero(self._prio < p)[0]
            nz = nu + this.size
            A, b = self._hard_ub(y0, nz)
            Ar, br = self._rows_ub(F, g, this, nz, nu)
            Af, bf, Ae, be = self._fixed_rows(F, g, fixed, eps_fixed, nz)
            c = np.zeros(nz)
            c[nu:] = 1.0 / self._e[this]
            bounds = [(float(lo[i]), float(hi[i])) for i in range(nu)] + [(0.0, None)] * int(
                this.size
            )
            res = scipy.optimize.linprog(
                c,
                A_ub=np.stack(A + Ar + Af),
                b_ub=np.asarray(b + br + bf),
                A_eq=np.stack(Ae) if Ae else None,
                b_eq=np.asarray(be) if be else None,
                bounds=bounds,
                method="highs",
            )
            if res.status == 2:
                raise InfeasibleError(
                    "the hard constraints admit no steady state (the LP of priority "
                    f"{p} is infeasible): y_ol_ss = {np.round(y0, 6).tolist()}, u(k-1) = "
                    f"{np.round(up, 6).tolist()}"
                )
            if res.status != 0:
                raise RunError(f"the SSTC LP of priority {p} failed: {res.message}")
            eps_fixed[this] = np.maximum(res.x[nu:], 0.0)
            stage_costs.append(float(res.fun))
            du_lp = res.x[:nu]
        return eps_fixed, du_lp, stage_costs

    def _move_split(self) -> tuple[list[int], np.ndarray, np.ndarray]:
        """The economic QP's move variables ``[du (non-mm), p, n (mm)]``.

        Returns ``(free, T, hcoef)``: the non-minimum-move MVs, ``T (nu, nd)`` with
        ``du = T z[:nd]`` and the cost of each move variable ``(nd,)``.
        """
        nu = self.nu
        free = [i for i in range(nu) if i not in self.mm]
        nd = len(free) + 2 * len(self.mm)
        T = np.zeros((nu, nd))  # du = T z[:nd]
        for k, i in enumerate(free):
            T[i, k] = 1.0
        for k, i in enumerate(self.mm):
            T[i, len(free) + 2 * k] = 1.0
            T[i, len(free) + 2 * k + 1] = -1.0
        hcoef = np.zeros(nd)
        for k, i in enumerate(free):
            hcoef[k] = self.h[i]
        for k, i in enumerate(self.mm):
            hcoef[len(free) + 2 * k : len(free) + 2 * k + 2] = self.h[i]
        return free, T, hcoef

    def _economic_stage(
        self,
        y0: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        F: np.ndarray,
        g: np.ndarray,
        eps_fixed: np.ndarray,
    ) -> np.ndarray | None:
        """The economic QP's move ``du (nu,)``; ``None`` when it did not converge."""
        nu = self.nu
        # economic QP: z = [du (non-mm), p, n (mm), eps (lowest-priority rows)]
        free, T, hcoef = self._move_split()
        nd = T.shape[1]
        lowest = self.levels[-1]
        low = np.nonzero(self._prio == lowest)[0]
        nz = nd + low.size
        FT = F @ T
        A, b = self._hard_ub(y0, nz, T)
        Ar, br = self._rows_ub(FT, g, low, nz, nd, width=nd)
        fixed = np.nonzero(self._prio < lowest)[0]
        Af, bf, Ae, be = self._fixed_rows(FT, g, fixed, eps_fixed, nz, width=nd)
        A, b = A + Ar + Af, b + br + bf
        for i in range(nu):  # the move box, through T
            for sign, bound in ((1.0, hi[i]), (-1.0, -lo[i])):
                if np.isfinite(bound):
                    row = np.zeros(nz)
                    row[:nd] = sign * T[i]
                    A.append(row)
                    b.append(float(bound))
        for k in [*range(len(free), nd), *range(nd, nz)]:  # p, n, eps >= 0
            row = np.zeros(nz)
            row[k] = -1.0
            A.append(row)
            b.append(0.0)
        # objective: w_J (hcoef z - J_min)^2 + sum_lowest (eps / e)^2 + rho ||z||^2
        Hq = 2.0 * SSTC_REGULARISATION * np.eye(nz)
        hz = np.concatenate([hcoef, np.zeros(low.size)])
        Hq += 2.0 * self.w_J * np.outer(hz, hz)
        q = -2.0 * self.w_J * self.J_min * hz
        Hq[nd:, nd:] += np.diag(2.0 / self._e[low] ** 2)
        Aall = np.stack(Ae + A)
        ball = np.asarray(be + b)
        x, _, solved, _ = solve_one(
            Hq,
            q,
            Aall,
            ball,
            tol=SSTC_QP_TOL,
            max_iter=200,
            accept_almost=True,
            n_eq=len(Ae),
        )
        return T @ x[:nd] if solved else None

    def _result(
        self,
        y0: np.ndarray,
        up: np.ndarray,
        du: np.ndarray,
        F: np.ndarray,
        g: np.ndarray,
        stage_costs: list[float],
    ) -> SSTCResult:
        """The targets of the move ``du``, with the relaxations it implies and the active set."""
        # the relaxations implied by du (exact; the QP's slacks can exceed them only by rounding)
        f = F @ du + g
        viol = np.where(
            np.asarray(self._kinds) == "lower",
            np.maximum(self._values - f, 0.0),
            np.where(
                np.asarray(self._kinds) == "upper",
                np.maximum(f - self._values, 0.0),
                np.abs(f - self._values),
            ),
        )
        low_rows = self._prio == self.levels[-1]
        stage_costs = [*stage_costs, float(np.sum(viol[low_rows] / self._e[low_rows]))]
        free = [i for i in range(self.nu) if i not in self.mm]
        J = float(self.h[free] @ du[free] + self.h[self.mm] @ np.abs(du[self.mm]))
        y_new = y0 + self.G @ du
        u_new = up + du
        active = self._active(y_new, u_new, du, viol, f)
        dt = self.model.dtype
        return SSTCResult(
            torch.as_tensor(y_new, dtype=dt),
            torch.as_tensor(u_new, dtype=dt),
            torch.as_tensor(du, dtype=dt),
            torch.as_tensor(viol, dtype=dt),
            torch.as_tensor(stage_costs, dtype=dt),
            J,
            active,
        )

    def _hard_point(self, y0: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """A move that satisfies the hard constraints (LP with a zero objective)."""
        A, b = self._hard_ub(y0, self.nu)
        res = scipy.optimize.linprog(
            np.zeros(self.nu),
            A_ub=np.stack(A) if A else None,
            b_ub=np.asarray(b) if b else None,
            bounds=list(zip(lo.tolist(), hi.tolist(), strict=True)),
            method="highs",
        )
        if res.status != 0:
            raise RunError(f"the SSTC hard-constraint LP failed: {res.message}")
        return np.asarray(res.x)

    def _active(
        self, y: np.ndarray, u: np.ndarray, du: np.ndarray, viol: np.ndarray, f: np.ndarray
    ) -> list[str]:
        out: list[str] = []
        for i in range(self.nu):
            if u[i] >= self.u_max[i] - ACTIVE_TOL:
                out.append(f"hard u{i + 1} upper {_fmt(self.u_max[i])}")
            if u[i] <= self.u_min[i] + ACTIVE_TOL:
                out.append(f"hard u{i + 1} lower {_fmt(self.u_min[i])}")
            if np.isfinite(self.du_max[i]) and abs(du[i]) >= self.du_max[i] - ACTIVE_TOL:
                out.append(f"hard |du{i + 1}_ss| {_fmt(self.du_max[i])}")
        for j in range(self.ny):
            if y[j] >= self.y_max[j] - ACTIVE_TOL:
                out.append(f"hard y{j + 1} upper {_fmt(self.y_max[j])}")
            if y[j] <= self.y_min[j] + ACTIVE_TOL:
                out.append(f"hard y{j + 1} lower {_fmt(self.y_min[j])}")
        for r, name in enumerate(self._names):
            if viol[r] > ACTIVE_TOL:
                out.append(f"relaxed {name} by {_fmt(viol[r])}")
            elif self._kinds[r] == "ideal":
                out.append(f"met {name}")
            elif abs(f[r] - self._values[r]) <= ACTIVE_TOL:
                out.append(f"at {name}")
        return out

    def __call__(self, y_ss: Tensor, u_prev: Tensor) -> Target:
        """The :class:`~torchfilt.dmc.SteadyStateTarget` interface: ``(y_ss, u_ss)`` targets."""
        res = self.solve(y_ss, u_prev)
        return Target(res.y, res.u)
