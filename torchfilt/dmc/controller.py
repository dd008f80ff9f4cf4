"""The dynamic layer of DMC: moves over a control horizon from the open-loop predictions.

At sample ``k``, given the free (open-loop) predictions ``y^ol(k+i|k)``, the last input ``u(k-1)`` and a
steady-state target ``(y_t, u_t)``, choose the moves ``du(k), ..., du(k+M-1)`` (``du = 0`` after) to

    minimise   sum_{i=1}^{P} ||y(k+i|k) - y_t||^2_Q + sum_{j=0}^{M-1} ||du(k+j)||^2_Lambda
               + ||u(k+M-1) - u_t||^2_W
    with       y(k+i|k) = y^ol(k+i|k) + sum_{j=0}^{min(i,M)-1} S^u_{i-j} du(k+j)
    subject to u_min <= u(k+j) <= u_max,   -du_max <= du(k+j) <= du_max,   j = 0..M-1

(``||e||^2_Q = e^T Q e`` with diagonal weights). Stacking ``dU = [du(k); ...; du(k+M-1)]`` and the
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
from torchfilt.exceptions import InfeasibleError, ShapeError
from torchfilt.numerics import psd_solve

__all__ = ["ControlPlan", "DMCController", "InfeasibleError"]


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


def _vector(value: Any, size: int, name: str, dtype: torch.dtype) -> Tensor:
    t = torch.as_tensor(value, dtype=dtype)
    if t.dim() == 0:
        t = t.expand(size)
    if t.shape != (size,):
        raise ShapeError(f"{name}: expected a scalar or shape ({size},), got {tuple(t.shape)}")
    if bool(torch.isnan(t).any()):
        raise ValueError(f"{name} contains NaN")
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
        u_max: upper input bounds, likewise.
        du_max: move bounds ``|du| <= du_max``, scalar or ``(nu,)`` (``> 0``); ``None`` for none.
        tol: QP tolerance.
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
        tol: float = QP_TOL,
    ) -> None:
        if not isinstance(model, StepResponseModel):
            raise TypeError(f"model must be a StepResponseModel, got {type(model).__name__}")
        if int(P) != P or P < 1:
            raise ValueError(f"P (prediction horizon) must be a positive integer, got {P}")
        if int(M) != M or not 1 <= M <= P:
            raise ValueError(f"M (control horizon) must be an integer in 1..P = {P}, got {M}")
        self.model, self.P, self.M, self.tol = model, int(P), int(M), tol
        ny, nu, dt = model.ny, model.nu, model.dtype
        self.Q = _vector(Q, ny, "Q", dt)
        self.Lambda = _vector(Lambda, nu, "Lambda", dt)
        self.W = _vector(W, nu, "W", dt)
        if bool((self.Q < 0).any()) or bool((self.W < 0).any()):
            raise ValueError("Q and W must be non-negative")
        if bool((self.Lambda <= 0).any()):
            raise ValueError("Lambda (move suppression) must be positive")
        inf = float("inf")
        self.u_min = _vector(-inf if u_min is None else u_min, nu, "u_min", dt)
        self.u_max = _vector(inf if u_max is None else u_max, nu, "u_max", dt)
        self.du_max = _vector(inf if du_max is None else du_max, nu, "du_max", dt)
        if bool((self.u_min > self.u_max).any()):
            raise ValueError(f"u_min must not exceed u_max (got {self.u_min} > {self.u_max})")
        if bool((self.du_max <= 0).any()):
            raise ValueError("du_max must be positive")
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
                raise ValueError(f"{name} contains non-finite entries")
        Yol = free[..., : self.P, :]
        err = (Yol - yt.unsqueeze(-2)).flatten(-2)  # (..., P ny)
        f = 2.0 * (err @ self._DtQ.mT + (u_prev - ut) @ self._CtW.mT)
        if not self.constrained:
            dU = -psd_solve(self.Hq, f.unsqueeze(-1), name="DMC Hessian").squeeze(-1)
        else:
            batch = f.shape[:-1]
            reach_lo, reach_hi = self.u_min - self.du_max, self.u_max + self.du_max
            if bool(((u_prev < reach_lo) | (u_prev > reach_hi)).any()):
                raise InfeasibleError(
                    "the DMC problem has no feasible plan: u(k-1) = "
                    f"{u_prev.tolist()} is further than du_max = {self.du_max.tolist()} outside "
                    f"[u_min, u_max] = [{self.u_min.tolist()}, {self.u_max.tolist()}]"
                )
            up_rep = torch.cat([u_prev.expand(*batch, m.nu)] * self.M, dim=-1)  # (..., M nu)
            rows, rhs = [], []
            fin_hi = torch.isfinite(self.u_max.repeat(self.M))
            fin_lo = torch.isfinite(self.u_min.repeat(self.M))
            if bool(fin_hi.any()):
                rows.append(self.Lcum[fin_hi])
                rhs.append((self.u_max.repeat(self.M) - up_rep)[..., fin_hi])
            if bool(fin_lo.any()):
                rows.append(-self.Lcum[fin_lo])
                rhs.append((up_rep - self.u_min.repeat(self.M))[..., fin_lo])
            A = torch.cat(rows, dim=0) if rows else None
            b = torch.cat(rhs, dim=-1) if rhs else None
            dmax = self.du_max.repeat(self.M)
            res = solve_qp(self.Hq, f, A, b, lb=-dmax, ub=dmax, tol=self.tol, max_iter=QP_MAX_ITER)
            if not bool(res.converged.all()):
                raise InfeasibleError(
                    f"the DMC QP did not converge in {QP_MAX_ITER} iterations (tolerance {self.tol})"
                )
            dU = res.x
        du = dU.unflatten(-1, (self.M, m.nu))
        u = u_prev.unsqueeze(-2) + du.cumsum(-2)
        y = Yol + (dU @ self.D.mT).unflatten(-1, (self.P, m.ny))
        cost = 0.5 * (dU * (dU @ self.Hq)).sum(-1) + (f * dU).sum(-1)
        return ControlPlan(du, u, y, cost)

    def move(
        self,
        free: Tensor,
        u_prev: Tensor,
        y_target: Tensor | float = 0.0,
        u_target: Tensor | float | None = None,
    ) -> Tensor:
        """The move ``du(k)`` to apply now, shape ``(..., nu)`` (see :meth:`plan`)."""
        return self.plan(free, u_prev, y_target, u_target).du[..., 0, :]
