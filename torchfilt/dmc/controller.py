"""The dynamic layer of DMC: moves over a control horizon from the open-loop predictions.

At sample ``k``, given the free (open-loop) predictions ``y^ol(k+i|k)``, the last input ``u(k-1)`` and a
steady-state target ``(y_t, u_t)``, choose the moves ``du(k), ..., du(k+M-1)`` (``du = 0`` after) to

    minimise   sum_{i=1}^{P} ||y(k+i|k) - y_t||^2_Q + sum_{j=0}^{M-1} ||du(k+j)||^2_Lambda
               + ||u(k+M-1) - u_t||^2_W
    with       y(k+i|k) = y^ol(k+i|k) + sum_{j=0}^{min(i,M)-1} S^u_{i-j} du(k+j)
    subject to u_min <= u(k+j) <= u_max,   -du_max <= du(k+j) <= du_max,   j = 0..M-1

(``||e||^2_Q = e^T Q e`` with diagonal weights).

Optional CV constraints on the predictions (the dynamic layer of double-layered DMC, Li & Ding
2015), each with a non-negative slack per prediction step and CV:

    soft:  z_min - s_lo <= y(k+i|k) <= z_max + s_hi,   cost sum_i q_lo s_lo^2 + q_hi s_hi^2
    hard:  y_min - t_lo <= y(k+i|k) <= y_max + t_hi,   cost HARD_CV_LINEAR t + HARD_CV_QUADRATIC t^2

The hard CV limits are an exact penalty: ``t = 0`` (the limit holds) whenever some plan keeps the
prediction inside, and the smallest violation otherwise (e.g. within a dead time no move can act
on), so the QP never becomes infeasible. Stacking ``dU = [du(k); ...; du(k+M-1)]`` and the
dynamic matrix ``D`` (block ``(i, j)`` is ``S_{i-j+1}`` for ``i >= j``) this is the QP

    minimise 1/2 dU^T Hq dU + f^T dU,   Hq = 2 (D^T Q D + Lambda + C^T W C),
                                        f  = 2 (D^T Q (Y^ol - Y_t) + C^T W (u(k-1) - u_t)),

``C = [I ... I]``; the input bounds are ``u(k-1) + (lower-triangular block of I) dU`` in range. Without
constraints it is solved in closed form (one Cholesky solve), with them by
:func:`~torchfilt.dmc.qp.solve_qp`. Only ``du(k)`` is applied (receding horizon).

The target comes from a steady-state target layer (:mod:`torchfilt.dmc.target`): this layer only
tracks whatever ``(y_t, u_t)`` it is handed, so a multi-priority target calculation can replace the
simple one without touching it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchfilt.dmc.qp import QP_MAX_ITER, QP_TOL, solve_qp
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.dmc.transfer import _positive_int
from torchfilt.exceptions import InfeasibleError, InputError, InputTypeError, ShapeError
from torchfilt.numerics import psd_solve

__all__ = ["ControlPlan", "DMCController", "InfeasibleError"]

#: Linear weight of the exact penalty on hard CV limit violations (larger than any multiplier the
#: tracking costs produce, so the limit holds whenever it can).
HARD_CV_LINEAR = 1e4
#: Quadratic weight of the hard CV limit violations (keeps the QP strictly convex).
HARD_CV_QUADRATIC = 1e4


class ControlPlan(NamedTuple):
    """The optimal plan at one sample.

    Attributes:
        du: moves ``du(k..k+M-1)``, shape ``(..., M, nu)``; ``du[..., 0, :]`` is applied.
        u: inputs ``u(k..k+M-1)``, shape ``(..., M, nu)``.
        y: predicted outputs ``y(k+1..k+P|k)`` under the plan, shape ``(..., P, ny)``.
        cost: objective value (without the constant term), shape ``(...)``.
    """

    du: Tensor
    u: Tensor
    y: Tensor
    cost: Tensor


def _real_tensor(value: Any, name: str, dtype: torch.dtype | None = None) -> Tensor:
    """``value`` as a real tensor (of ``dtype`` if given); an InputTypeError naming ``name`` for
    anything that is not real numbers (strings, complex values, ragged lists)."""
    if isinstance(value, str | bytes) or (
        isinstance(value, Tensor) and (value.is_complex() or value.dtype == torch.bool)
    ):
        raise InputTypeError(f"{name} must be real numbers, got {value!r}")
    try:
        t = torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        raise InputTypeError(f"{name} must be real numbers, got {value!r}") from None
    if t.is_complex() or t.dtype == torch.bool:
        raise InputTypeError(f"{name} must be real numbers, got dtype {t.dtype}")
    return t


def _vector(value: Any, size: int, name: str, dtype: torch.dtype) -> Tensor:
    t = _real_tensor(value, name, dtype)
    if t.dim() == 0:
        t = t.expand(size)
    if t.shape != (size,):
        raise ShapeError(f"{name}: expected a scalar or shape ({size},), got {tuple(t.shape)}")
    if bool(torch.isnan(t).any()):
        raise InputError(f"{name} contains NaN")
    return t.clone()


class DMCController:
    """Dynamic matrix control over prediction horizon ``P`` and control horizon ``M``.

    Args:
        model: the step-response model (MV channels).
        P: prediction horizon (``>= 1``; beyond the model horizon the settling rules extend ``S``).
        M: control horizon, ``1 <= M <= P``.
        Q: CV tracking weights, a scalar or shape ``(ny,)`` (``>= 0``).
        Lambda: move-suppression weights, a scalar or shape ``(nu,)`` (``> 0``).
        W: weights on ``u(k+M-1) - u_t``, a scalar or shape ``(nu,)`` (``>= 0``); default 0.
        u_min: lower input bounds, scalar or ``(nu,)``; ``None`` (or ``-inf``) for none.
        u_max: upper input bounds, scalar or ``(nu,)``; ``None`` (or ``inf``) for none.
        du_max: move bounds ``|du| <= du_max``, scalar or ``(nu,)`` (``> 0``); ``None`` for none.
        y_min: hard lower CV limits on ``y(k+i|k)``, scalar or ``(ny,)``; ``None`` for none.
        y_max: hard upper CV limits, scalar or ``(ny,)``; ``None`` for none.
        z_min: soft lower CV bounds, scalar or ``(ny,)``; ``None`` for none.
        z_max: soft upper CV bounds, scalar or ``(ny,)``; ``None`` for none.
        q_lower: weights of the soft lower-bound violations, scalar or ``(ny,)`` (``> 0``).
        q_upper: weights of the soft upper-bound violations, scalar or ``(ny,)`` (``> 0``).
        tol: QP tolerance.

    Raises:
        InputTypeError: ``model`` is not a :class:`StepResponseModel`, or a weight or bound that
            is not real numbers.
        InputError: horizons that are not integers with ``1 <= M <= P``, a weight or bound of the
            wrong sign or NaN, or a lower bound above its upper bound.
        ShapeError: a weight or bound that is neither a scalar nor one value per channel.
    """

    def __init__(
        self,
        model: StepResponseModel,
        P: int,
        M: int,
        *,
        Q: float | Tensor = 1.0,
        Lambda: float | Tensor = 1.0,
        W: float | Tensor = 0.0,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        du_max: float | Tensor | None = None,
        y_min: float | Tensor | None = None,
        y_max: float | Tensor | None = None,
        z_min: float | Tensor | None = None,
        z_max: float | Tensor | None = None,
        q_lower: float | Tensor = 1.0,
        q_upper: float | Tensor = 1.0,
        tol: float = QP_TOL,
    ) -> None:
        if not isinstance(model, StepResponseModel):
            raise InputTypeError(f"model must be a StepResponseModel, got {type(model).__name__}")
        P = _positive_int(P, "P (prediction horizon)")
        M = _positive_int(M, "M (control horizon)")
        if M > P:
            raise InputError(f"M (control horizon) must be an integer in 1..P = {P}, got {M}")
        self.model, self.P, self.M, self.tol = model, P, M, tol
        ny, nu, dt = model.ny, model.nu, model.dtype
        self.Q = _vector(Q, ny, "Q", dt)
        self.Lambda = _vector(Lambda, nu, "Lambda", dt)
        self.W = _vector(W, nu, "W", dt)
        if bool((self.Q < 0).any()) or bool((self.W < 0).any()):
            raise InputError(
                f"Q and W must be non-negative, got Q = {self.Q.tolist()}, W = {self.W.tolist()}"
            )
        if bool((self.Lambda <= 0).any()):
            raise InputError(
                f"Lambda (move suppression) must be positive, got {self.Lambda.tolist()}"
            )
        inf = float("inf")
        self.u_min = _vector(-inf if u_min is None else u_min, nu, "u_min", dt)
        self.u_max = _vector(inf if u_max is None else u_max, nu, "u_max", dt)
        self.du_max = _vector(inf if du_max is None else du_max, nu, "du_max", dt)
        if bool((self.u_min > self.u_max).any()):
            raise InputError(f"u_min must not exceed u_max (got {self.u_min} > {self.u_max})")
        if bool((self.du_max <= 0).any()):
            raise InputError(f"du_max must be positive, got {self.du_max.tolist()}")
        self.y_min = _vector(-inf if y_min is None else y_min, ny, "y_min", dt)
        self.y_max = _vector(inf if y_max is None else y_max, ny, "y_max", dt)
        self.z_min = _vector(-inf if z_min is None else z_min, ny, "z_min", dt)
        self.z_max = _vector(inf if z_max is None else z_max, ny, "z_max", dt)
        self.q_lower = _vector(q_lower, ny, "q_lower", dt)
        self.q_upper = _vector(q_upper, ny, "q_upper", dt)
        for lo, hi, name in ((self.y_min, self.y_max, "y"), (self.z_min, self.z_max, "z")):
            if bool((lo > hi).any()):
                raise InputError(f"{name}_min must not exceed {name}_max (got {lo} > {hi})")
        if bool((self.q_lower <= 0).any()) or bool((self.q_upper <= 0).any()):
            raise InputError(
                "q_lower and q_upper (soft CV bound weights) must be positive, got "
                f"{self.q_lower.tolist()} and {self.q_upper.tolist()}"
            )
        # dynamic matrix D (P ny x M nu), time-major blocks
        S = model.coefficients(self.P, "u")  # (P, ny, nu)
        D = S.new_zeros(self.P, ny, self.M, nu)
        for i in range(self.P):
            for j in range(min(i + 1, self.M)):
                D[i, :, j, :] = S[i - j]
        self.D = D.reshape(self.P * ny, self.M * nu)
        eye = torch.eye(nu, dtype=dt)
        self.C = eye.repeat(1, self.M)  # (nu, M nu): u(k+M-1) - u(k-1)
        self.Lcum = torch.kron(torch.tril(torch.ones(self.M, self.M, dtype=dt)), eye)
        Qbd = self.Q.repeat(self.P)
        self._DtQ = self.D.mT * Qbd  # (M nu, P ny)
        Wm = torch.diag(self.W)
        self.Hq = 2.0 * (
            self._DtQ @ self.D + torch.diag(self.Lambda.repeat(self.M)) + self.C.mT @ Wm @ self.C
        )
        self._CtW = self.C.mT @ Wm
        self.constrained = bool(
            torch.isfinite(self.u_min).any()
            | torch.isfinite(self.u_max).any()
            | torch.isfinite(self.du_max).any()
        )
        # CV constraint groups: (bound, +1 upper / -1 lower, quadratic weight, linear weight)
        groups = []
        for bound, sign, wq, wl in (
            (self.z_min, -1.0, 2.0 * self.q_lower, 0.0 * self.q_lower),
            (self.z_max, 1.0, 2.0 * self.q_upper, 0.0 * self.q_upper),
            (self.y_min, -1.0, torch.full_like(self.Q, 2.0 * HARD_CV_QUADRATIC), None),
            (self.y_max, 1.0, torch.full_like(self.Q, 2.0 * HARD_CV_QUADRATIC), None),
        ):
            fin = torch.isfinite(bound)
            if bool(fin.any()):
                lin = torch.full_like(self.Q, HARD_CV_LINEAR) if wl is None else wl
                groups.append((bound, sign, fin, wq, lin))
        self._cv_groups = groups

    def plan(
        self,
        free: Tensor,
        u_prev: Tensor,
        y_target: Tensor | float = 0.0,
        u_target: Tensor | float | None = None,
    ) -> ControlPlan:
        """Optimal moves for one sample (batched over leading dimensions).

        Args:
            free: open-loop predictions ``y^ol(k+1..k+P'|k)`` with ``P' >= P``, shape ``(..., P', ny)``
                (e.g. :meth:`OpenLoopPredictor.update`'s output; the first ``P`` rows are used).
            u_prev: ``u(k-1)``, shape ``(..., nu)``.
            y_target: CV target ``y_t``, scalar or shape ``(..., ny)``.
            u_target: MV target ``u_t``, shape ``(..., nu)``; default ``u(k-1)`` (only matters with
                ``W > 0``).

        Returns:
            The :class:`ControlPlan`.

        Raises:
            InfeasibleError: the input/move constraints admit no plan (e.g. ``u(k-1)`` outside the
                bounds by more than ``M`` moves can recover).
            ShapeError: an argument whose shape is not the one given above.
            InputError: an argument with non-finite entries.
        """
        m, dt = self.model, self.model.dtype
        free = torch.as_tensor(free, dtype=dt)
        if free.dim() < 2 or free.shape[-1] != m.ny or free.shape[-2] < self.P:
            raise ShapeError(
                f"free: expected shape (..., P', {m.ny}) with P' >= P = {self.P}, got "
                f"{tuple(free.shape)}"
            )
        u_prev = torch.as_tensor(u_prev, dtype=dt)
        if u_prev.shape[-1:] != (m.nu,):
            raise ShapeError(f"u_prev: expected shape (..., {m.nu}), got {tuple(u_prev.shape)}")
        yt = torch.as_tensor(y_target, dtype=dt)
        yt = yt.expand(m.ny) if yt.dim() == 0 else yt
        if yt.shape[-1:] != (m.ny,):
            raise ShapeError(f"y_target: expected shape (..., {m.ny}), got {tuple(yt.shape)}")
        ut = u_prev if u_target is None else torch.as_tensor(u_target, dtype=dt)
        ut = ut.expand(m.nu) if ut.dim() == 0 else ut
        if ut.shape[-1:] != (m.nu,):
            raise ShapeError(f"u_target: expected shape (..., {m.nu}), got {tuple(ut.shape)}")
        for name, t in (("free", free), ("u_prev", u_prev), ("y_target", yt), ("u_target", ut)):
            if not bool(torch.isfinite(t).all()):
                raise InputError(f"{name} contains non-finite entries")
        Yol = free[..., : self.P, :]
        err = (Yol - yt.unsqueeze(-2)).flatten(-2)  # (..., P ny)
        f = 2.0 * (err @ self._DtQ.mT + (u_prev - ut) @ self._CtW.mT)
        if not self.constrained and not self._cv_groups:
            dU = -psd_solve(self.Hq, f.unsqueeze(-1), name="DMC Hessian").squeeze(-1)
            extra = torch.zeros_like(f[..., 0])
        else:
            dU, extra = self._solve_constrained(f, u_prev, Yol)
        du = dU.unflatten(-1, (self.M, m.nu))
        u = u_prev.unsqueeze(-2) + du.cumsum(-2)
        y = Yol + (dU @ self.D.mT).unflatten(-1, (self.P, m.ny))
        cost = 0.5 * (dU * (dU @ self.Hq)).sum(-1) + (f * dU).sum(-1) + extra
        return ControlPlan(du, u, y, cost)

    def _solve_constrained(self, f: Tensor, u_prev: Tensor, Yol: Tensor) -> tuple[Tensor, Tensor]:
        """The QP with input/move limits and CV constraints: ``dU`` and the slacks' cost."""
        m, dt = self.model, self.model.dtype
        batch = f.shape[:-1]
        reach_lo, reach_hi = self.u_min - self.du_max, self.u_max + self.du_max
        if bool(((u_prev < reach_lo) | (u_prev > reach_hi)).any()):
            raise InfeasibleError(
                "the DMC problem has no feasible plan: u(k-1) = "
                f"{u_prev.tolist()} is further than du_max = {self.du_max.tolist()} outside "
                f"[u_min, u_max] = [{self.u_min.tolist()}, {self.u_max.tolist()}]"
            )
        nd = self.M * m.nu
        # slacks: one per (prediction step, CV) of each finite CV bound
        Yflat = Yol.flatten(-2)  # (..., P ny)
        fin_rows = [g[2].repeat(self.P) for g in self._cv_groups]
        ns = sum(int(r.sum()) for r in fin_rows)
        nz = nd + ns
        H = torch.zeros(nz, nz, dtype=dt)
        H[:nd, :nd] = self.Hq
        fz = torch.cat([f, f.new_zeros(*batch, ns)], dim=-1)
        rows, rhs = [], []
        up_rep = torch.cat([u_prev.expand(*batch, m.nu)] * self.M, dim=-1)  # (..., M nu)
        fin_hi = torch.isfinite(self.u_max.repeat(self.M))
        fin_lo = torch.isfinite(self.u_min.repeat(self.M))
        pad = torch.zeros(self.Lcum.shape[0], ns, dtype=dt)
        if bool(fin_hi.any()):
            rows.append(torch.cat([self.Lcum, pad], dim=-1)[fin_hi])
            rhs.append((self.u_max.repeat(self.M) - up_rep)[..., fin_hi])
        if bool(fin_lo.any()):
            rows.append(torch.cat([-self.Lcum, pad], dim=-1)[fin_lo])
            rhs.append((up_rep - self.u_min.repeat(self.M))[..., fin_lo])
        col = nd
        for (bound, sign, _, wq, wl), fin in zip(self._cv_groups, fin_rows, strict=True):
            k = int(fin.sum())
            Dk = self.D[fin]  # (k, nd)
            S = torch.zeros(k, nz, dtype=dt)
            S[:, :nd] = sign * Dk
            S[:, col : col + k] = -torch.eye(k, dtype=dt)
            rows.append(S)
            # sign (Yol + D dU - bound) <= s
            rhs.append(sign * (bound.repeat(self.P)[fin] - Yflat[..., fin]))
            idx = torch.arange(col, col + k)
            H[idx, idx] = wq.repeat(self.P)[fin]
            fz[..., col : col + k] = wl.repeat(self.P)[fin]
            col += k
        A = torch.cat(rows, dim=0)
        b = torch.cat([r.expand(*batch, r.shape[-1]) for r in rhs], dim=-1)
        inf = float("inf")
        dmax = self.du_max.repeat(self.M)
        lb = torch.cat([-dmax, torch.zeros(ns, dtype=dt)])
        ub = torch.cat([dmax, torch.full((ns,), inf, dtype=dt)])
        res = solve_qp(H, fz, A, b, lb=lb, ub=ub, tol=self.tol, max_iter=QP_MAX_ITER)
        if not bool(res.converged.all()):
            raise InfeasibleError(
                f"the DMC QP did not converge in {QP_MAX_ITER} iterations (tolerance {self.tol})"
            )
        z = res.x
        sl = z[..., nd:]
        extra = 0.5 * (sl * (sl @ H[nd:, nd:])).sum(-1) + (fz[..., nd:] * sl).sum(-1)
        return z[..., :nd], extra

    def move(
        self,
        free: Tensor,
        u_prev: Tensor,
        y_target: Tensor | float = 0.0,
        u_target: Tensor | float | None = None,
    ) -> Tensor:
        """The move ``du(k)`` to apply now: the first move of :meth:`plan`.

        Args:
            free: open-loop predictions, shape ``(..., P', ny)`` with ``P' >= P``.
            u_prev: ``u(k-1)``, shape ``(..., nu)``.
            y_target: CV target ``y_t``, scalar or shape ``(..., ny)``.
            u_target: MV target ``u_t``, shape ``(..., nu)``; default ``u(k-1)``.

        Returns:
            ``du(k)``, shape ``(..., nu)``.

        Raises:
            InfeasibleError: the input/move constraints admit no plan.
            ShapeError: an argument of the wrong shape.
            InputError: an argument with non-finite entries.
        """
        return self.plan(free, u_prev, y_target, u_target).du[..., 0, :]
