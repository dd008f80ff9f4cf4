"""Batched bounded nonlinear least squares: projected Gauss-Newton with Levenberg-Marquardt damping.

Solves, independently for every batch element,

    min_x  F(x) = 1/2 ||r(x)||^2   subject to   lower <= x <= upper,

for a residual ``r: (..., n) -> (..., k)``. Each iteration (Bertsekas' projected Newton method,
"Projected Newton methods for optimization problems with simple constraints", SIAM J. Control
Optim. 20(2), 1982, with the Gauss-Newton matrix in place of the Hessian):

    g = J^T r,   A = J^T J,   s = g / diag(A)                       (J = dr/dx at x)
    binding set B = {j : g_j > 0 and x_j - lower_j <= s_j} U {j : g_j < 0 and upper_j - x_j <= -s_j}
    free set F: (A_FF + mu diag(A_FF)) d_F = -g_F,   d_B = -s_B
    x+ = P(x + alpha d),   alpha = 1, 1/2, 1/4, ... until  F(x+) <= F(x) + sigma g^T (x+ - x)

``P`` is the projection onto the box. The damping ``mu`` starts at 0 (pure Gauss-Newton, so a
linear residual is solved exactly once its active set is found); it grows when a full step is
rejected or decreases the cost by less than a quarter of what the Gauss-Newton model predicted, and
shrinks after full steps that achieve more than three quarters (Levenberg-Marquardt gain-ratio
rule, Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems", 2004).

Stopping rule (the stated tolerance): with ``d0`` the undamped step,

    delta = -g_F^T d0_F + sum_{j in B} g_j (x_j - P(x - s)_j)      (>= 0; 0 exactly at a KKT point)

is twice the cost decrease the Gauss-Newton model predicts, i.e. ``sqrt(delta)`` is the remaining
step length in the ``J^T J`` metric. A problem has converged when ``sqrt(delta) <= tol`` or when
``delta / 2 <= ROUNDOFF * eps * F`` (the predicted decrease is below the cost's round-off) or an
accepted step changes no coordinate by more than ``ROUNDOFF * eps * |x_j|`` (the step is below
the resolution of ``x``, as happens for priors whose precision spans the whole float range).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import ConvergenceWarning, InputError, ShapeError
from torchfilt.numerics import small
from torchfilt.numerics.box import Box
from torchfilt.numerics.dtypes import check_real_tensor

__all__ = [
    "LeastSquaresResult",
    "SolverStatus",
    "batched_jacobian",
    "bounded_least_squares",
]

#: Armijo sufficient-decrease constant of the projected line search.
ARMIJO = 1e-4
#: Step-length factor per backtracking step.
BACKTRACK = 0.5
#: Damping set when a full step is first rejected (relative to diag(J^T J)).
MU_INIT = 1e-3
#: Damping growth after a rejected full step, and shrink after an accepted one.
MU_GROW, MU_SHRINK = 4.0, 3.0
#: A full step whose actual/predicted decrease ratio is above GAIN_HIGH shrinks the damping; below
#: GAIN_LOW (an overshooting step, even if accepted) grows it.
GAIN_LOW, GAIN_HIGH = 0.25, 0.75
#: Damping below this is reset to 0 (pure Gauss-Newton).
MU_MIN = 1e-9
#: A problem whose line search fails with damping above this has stalled.
MU_MAX = 1e10
#: Predicted decrease below ``ROUNDOFF * eps * F`` counts as converged (cost round-off).
ROUNDOFF = 16.0

Residual = Callable[[Tensor], Tensor]


class SolverStatus(IntEnum):
    """Why :func:`bounded_least_squares` stopped for a problem (positive: converged)."""

    #: The residual or its Jacobian was non-finite at an accepted iterate.
    NONFINITE = -2
    #: No decrease was found even with the largest damping.
    STALLED = -1
    #: ``max_iter`` iterations without meeting the tolerance.
    MAX_ITER = 0
    #: ``sqrt(delta) <= tol``.
    CONVERGED = 1
    #: The predicted decrease, or the step, is below floating-point resolution.
    ROUNDOFF = 2


class LeastSquaresResult(NamedTuple):
    """Result of :func:`bounded_least_squares`.

    Attributes:
        x: solutions, shape ``(..., n)``, inside the box.
        cost: ``1/2 ||r(x)||^2``, shape ``(...)``.
        optimality: ``sqrt(delta)`` at ``x`` (see the module docstring), shape ``(...)``.
        iterations: Gauss-Newton iterations taken, shape ``(...)`` (int64).
        status: a :class:`SolverStatus` code per problem, shape ``(...)`` (int64).
    """

    x: Tensor
    cost: Tensor
    optimality: Tensor
    iterations: Tensor
    status: Tensor

    @property
    def converged(self) -> Tensor:
        """Whether each problem met the tolerance, shape ``(...)``."""
        return self.status > 0


def batched_jacobian(
    fn: Residual, x: Tensor, *, create_graph: bool = False
) -> tuple[Tensor, Tensor]:
    """Value and Jacobian of a batched map by reverse-mode autograd (one backward pass per output).

    ``fn`` must act independently on every batch element (as any broadcasting function does), so
    that the gradient of ``fn(x)[..., i].sum()`` with respect to ``x`` is row ``i`` of each
    element's Jacobian.

    Args:
        fn: map ``(..., n) -> (..., k)`` with the batch shape of ``x``.
        x: points, shape ``(..., n)``.
        create_graph: keep the graph of the Jacobian (for higher derivatives).

    Returns:
        ``(fn(x), J)``: the values, shape ``(..., k)``, and ``J``, shape ``(..., k, n)``.

    Raises:
        ShapeError: ``fn`` returns values whose batch shape is not that of ``x``.
    """
    with torch.enable_grad():
        xr = x if create_graph and x.requires_grad else x.detach().requires_grad_(True)
        r = fn(xr)
        if r.shape[:-1] != x.shape[:-1]:
            raise ShapeError(
                f"residual returned shape {tuple(r.shape)} for points {tuple(x.shape)}; "
                "expected (..., k) with the points' batch shape"
            )
        k = r.shape[-1]
        if not r.requires_grad:
            return r, r.new_zeros(*r.shape, x.shape[-1])
        rows = []
        for i in range(k):
            (gi,) = torch.autograd.grad(
                r[..., i].sum(), xr, retain_graph=True, create_graph=create_graph, allow_unused=True
            )
            rows.append(torch.zeros_like(x) if gi is None else gi)
    J = torch.stack(rows, dim=-2)
    return (r, J) if create_graph else (r.detach(), J.detach())


def _check_residual(r: object, x: Tensor, name: str) -> Tensor:
    """The residual's value must be a real tensor ``(..., k)`` of ``x``'s dtype."""
    if not isinstance(r, Tensor):
        raise InputError(
            f"{name} returned {type(r).__name__}; expected a torch.Tensor of shape (..., k) "
            "computed with torch operations (autograd differentiates it)"
        )
    if r.dim() < 1:
        raise ShapeError(
            f"{name} returned a scalar (shape ()); expected the residual vector (..., k), "
            "not the cost (return r, not (r**2).sum())"
        )
    if not r.is_floating_point():
        raise InputError(f"{name} returned dtype {r.dtype}; expected {x.dtype}")
    return r


def _first_residual(residual: Residual, x: Tensor, *, differentiable: bool) -> Tensor:
    """The residual at the start point, checked: a real tensor ``(..., k)`` and, when autograd
    is to give the Jacobian (``differentiable``), one that depends differentiably on ``x``
    (otherwise the Jacobian reads as zero and the start point passes as optimal)."""
    if not differentiable:
        return _check_residual(residual(x), x, "residual")
    with torch.enable_grad():
        r = _check_residual(residual(x.detach().requires_grad_(True)), x, "residual")
    if not r.requires_grad:
        raise InputError(
            "residual: its output does not depend differentiably on x (it ends in .detach(), "
            "goes through numpy or Python floats, or ignores x), so autograd would give a zero "
            "Jacobian and the start point would pass as optimal; write it with torch operations "
            "or pass jacobian="
        )
    return r.detach()


def _evaluate(
    residual: Residual, jacobian: Residual | None, x: Tensor, r: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Residual and Jacobian at ``x`` (``r``: the residual there, if already known)."""
    if jacobian is None:
        return batched_jacobian(residual, x)
    r = residual(x) if r is None else r
    J = jacobian(x)
    if J.shape != (*r.shape, x.shape[-1]):
        raise ShapeError(
            f"jacobian returned shape {tuple(J.shape)}; expected (..., k, n) = "
            f"{(*r.shape, x.shape[-1])}"
        )
    return r.detach(), J.detach()


#: Up to this many residuals, J^T J and J^T r are formed as sums of outer products (torch's batched
#: products and last-dimension reductions of tiny matrices are an order of magnitude slower on CPU).
SMALL_K = 8


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """``sum_j a_j b_j`` over the last dimension (broadcasting), shape ``(...)``."""
    p = a * b
    return p @ p.new_ones(p.shape[-1])


def _normal_equations(J: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """``A = J^T J`` ``(..., n, n)`` and ``g = J^T r`` ``(..., n)`` for ``J (..., k, n)``."""
    k = J.shape[-2]
    if k > SMALL_K:
        return J.mT @ J, (J.mT @ r.unsqueeze(-1)).squeeze(-1)
    A = J[..., 0, :, None] * J[..., 0, None, :]
    g = J[..., 0, :] * r[..., :1]
    for i in range(1, k):
        Ji = J[..., i, :]
        A = A + Ji.unsqueeze(-1) * Ji.unsqueeze(-2)
        g = g + Ji * r[..., i : i + 1]
    return A, g


def _reduced_solve(A: Tensor, dA: Tensor, free: Tensor, rhs: Tensor, mu: Tensor | None) -> Tensor:
    """Solve ``(A_FF + mu diag(A_FF)) d_F = rhs_F`` (``d = 0`` off the free set).

    The system is Jacobi-scaled first (``D^{-1/2} A D^{-1/2}``, ``D = diag(A)``), so its
    conditioning is that of the correlations, not of the variables' units (a filter's prior
    precision easily spans 1e17); a relative ridge of ``eps`` keeps a rank-deficient block solvable.
    """
    eps = torch.finfo(A.dtype).eps
    sc = dA.rsqrt()
    As = A * sc.unsqueeze(-1) * sc.unsqueeze(-2)
    ff = free.unsqueeze(-1) & free.unsqueeze(-2)
    ridge = eps if mu is None else eps + mu.unsqueeze(-1)
    diag = torch.where(free, ridge + torch.zeros_like(dA), torch.ones_like(dA))
    M = torch.where(ff, As, torch.zeros_like(As)) + torch.diag_embed(diag)
    L, info = small.cholesky_ex(M)
    if bool((info > 0).any()):  # numerically singular free block: a larger relative ridge
        bump = torch.where(free, math.sqrt(eps) + torch.zeros_like(dA), torch.zeros_like(dA))
        L2, _ = small.cholesky_ex(M + torch.diag_embed(bump))
        L = torch.where((info > 0)[..., None, None], L2, L)
    y = small.cholesky_solve((sc * torch.where(free, rhs, torch.zeros_like(rhs))).unsqueeze(-1), L)
    return sc * y.squeeze(-1)


def bounded_least_squares(
    residual: Residual,
    x0: Tensor,
    bounds: Box | None = None,
    *,
    jacobian: Residual | None = None,
    tol: float | None = None,
    max_iter: int = 50,
    max_backtracks: int = 30,
    warn: bool = True,
) -> LeastSquaresResult:
    """Solve a batch of bounded nonlinear least-squares problems at once.

        x* = argmin_{lower <= x <= upper} 1/2 ||r(x)||^2

    by projected Gauss-Newton / Levenberg-Marquardt with a backtracking (Armijo) line search along
    the projection arc; the equations and the stopping rule are in the module docstring. Every
    problem of the batch iterates in lock-step; converged problems stop moving. Like every
    Gauss-Newton method it converges quadratically on small-residual problems and only linearly
    where the residual is large and strongly curved at the solution; raise ``max_iter`` there.

    For an affine residual ``r(x) = A x - b`` with ``A`` of full column rank this is an exact
    active-set method for the box-constrained QP: once the active set is right, the next step
    lands on the solution.

    Gradients: when autograd is on and the residual depends on tensors that require grad (or the
    bounds do), the returned ``x`` carries the implicit-function derivative of the solution (from
    autograd through ``residual``, twice differentiable, even when ``jacobian`` is given):
    ``dx_F = -H_FF^{-1} d(grad_F)`` on the free coordinates (``H`` the exact Hessian of ``F``
    from autograd, falling back to ``J^T J``), and the bound's own gradient on active ones. The
    iterations themselves are not differentiated.

    Other constraint types (``c(x) <= 0``, ``e(x) = 0``) are not supported yet; they would come as
    further keyword arguments beside ``bounds``.

    Args:
        residual: ``r(x)``, mapping ``(..., n)`` to ``(..., k)`` independently per batch element
            (it may broadcast ``x`` against fixed data of a larger batch shape). Must be
            differentiable by autograd unless ``jacobian`` is given.
        x0: starting points, shape ``(..., n)``; projected onto the box first.
        bounds: the :class:`Box`; ``None`` for an unconstrained problem.
        jacobian: optional ``J(x)``, ``(..., n) -> (..., k, n)``; default: autograd on
            ``residual`` (``k`` backward passes per iteration).
        tol: tolerance on ``sqrt(delta)``; default ``sqrt(eps)`` of the dtype (1.5e-8 in float64,
            3.5e-4 in float32).
        max_iter: iteration limit.
        max_backtracks: line-search halvings per iteration.
        warn: emit a :class:`~torchfilt.exceptions.ConvergenceWarning` when a problem did not
            converge.

    Returns:
        A :class:`LeastSquaresResult`: ``x (..., n)``, ``cost``, ``optimality``, ``iterations`` and
        ``status`` (each ``(...)``).

    Raises:
        ShapeError: ``x0`` or ``bounds`` have the wrong shape (the bounds' batch shape must
            broadcast with ``x0``'s), the residual returns a scalar, or its batch shape does not
            broadcast with theirs.
        InputError: ``x0`` is not a float32/float64 tensor; the residual returns something other
            than a floating tensor, or (without ``jacobian``) an output autograd cannot
            differentiate with respect to ``x`` (``.detach()``, numpy, Python floats).
    """
    box, tol = _check_arguments(x0, bounds, tol, max_iter, max_backtracks)
    lo_in, hi_in = box.lower.to(x0), box.upper.to(x0)
    with torch.no_grad():
        state, r, J, lo, hi = _start(residual, jacobian, x0, box, lo_in, hi_in)
        _iterate(residual, jacobian, state, r, J, lo, hi, tol, max_iter, max_backtracks)
    x = _attach_gradient(residual, jacobian, state.x, lo_in, hi_in)
    if warn:
        _warn_unconverged(state.status, tol)
    return LeastSquaresResult(x, state.F.detach(), state.opt, state.iters, state.status)


def _check_arguments(
    x0: Tensor, bounds: Box | None, tol: float | None, max_iter: int, max_backtracks: int
) -> tuple[Box, float]:
    """The checked arguments of :func:`bounded_least_squares`: the box and the tolerance."""
    if not isinstance(x0, Tensor) or x0.dim() < 1:
        raise InputError("x0 must be a floating-point tensor of shape (..., n)")
    check_real_tensor(x0, "x0")
    if bounds is not None and not isinstance(bounds, Box):
        raise InputError(f"bounds must be a Box or None, got {type(bounds).__name__}")
    n = x0.shape[-1]
    box = Box(n=n) if bounds is None else bounds
    if box.dim != n:
        raise ShapeError(f"bounds: dimension {box.dim} does not match x0's n = {n}")
    try:
        torch.broadcast_shapes(x0.shape[:-1], box.batch_shape)
    except RuntimeError:
        raise ShapeError(
            f"bounds: batch shape {tuple(box.batch_shape)} does not broadcast with x0's "
            f"{tuple(x0.shape[:-1])}"
        ) from None
    if max_iter < 0 or max_backtracks < 1:
        raise InputError("max_iter must be >= 0 and max_backtracks >= 1")
    eps = torch.finfo(x0.dtype).eps
    tol = math.sqrt(eps) if tol is None else float(tol)
    if not tol > 0 or not math.isfinite(tol):
        raise InputError(f"tol must be positive and finite, got {tol}")
    return box, tol


@dataclass
class _State:
    """The iterates of :func:`bounded_least_squares`: ``x (..., n)``, the rest ``(...)``."""

    x: Tensor
    F: Tensor
    status: Tensor
    iters: Tensor
    mu: Tensor
    done: Tensor
    opt: Tensor


class _Model(NamedTuple):
    """The Gauss-Newton model at an iterate (module docstring): ``A = J^T J``, ``g = J^T r``, the
    scaling ``dA`` and step ``s = g / dA``, the binding and free sets, the undamped step ``d0``
    and which problems converged there (``conv``)."""

    A: Tensor
    g: Tensor
    dA: Tensor
    s: Tensor
    bind: Tensor
    free: Tensor
    d0: Tensor
    conv: Tensor


def _start(
    residual: Residual,
    jacobian: Residual | None,
    x0: Tensor,
    box: Box,
    lo_in: Tensor,
    hi_in: Tensor,
) -> tuple[_State, Tensor, Tensor, Tensor, Tensor]:
    """The start point projected onto the box and expanded to the common batch shape, with
    ``(state, r, J, lo, hi)``: the residual and Jacobian there and the bounds, expanded."""
    n, dtype = x0.shape[-1], x0.dtype
    x = torch.clamp(x0.detach(), lo_in, hi_in)
    r = _first_residual(residual, x, differentiable=jacobian is None)
    try:
        batch = torch.broadcast_shapes(x.shape[:-1], r.shape[:-1], box.batch_shape)
    except RuntimeError:
        raise ShapeError(
            f"residual batch shape {tuple(r.shape[:-1])}, x0 {tuple(x.shape[:-1])} and "
            f"bounds {tuple(box.batch_shape)} do not broadcast"
        ) from None
    expanded = x.shape[:-1] != batch
    x = x.expand(*batch, n).clone()
    r, J = _evaluate(residual, jacobian, x, None if expanded else r)
    lo, hi = lo_in.detach().expand(*batch, n), hi_in.detach().expand(*batch, n)
    state = _State(
        x=x,
        F=0.5 * _dot(r, r),
        status=torch.full(batch, int(SolverStatus.MAX_ITER), dtype=torch.long, device=x.device),
        iters=torch.zeros(batch, dtype=torch.long, device=x.device),
        mu=torch.zeros(batch, dtype=dtype, device=x.device),
        done=torch.zeros(batch, dtype=torch.bool, device=x.device),
        opt=torch.zeros(batch, dtype=dtype, device=x.device),
    )
    return state, r, J, lo, hi


def _iterate(
    residual: Residual,
    jacobian: Residual | None,
    st: _State,
    r: Tensor,
    J: Tensor,
    lo: Tensor,
    hi: Tensor,
    tol: float,
    max_iter: int,
    max_backtracks: int,
) -> None:
    """Run the iterations on ``st`` in place (``r``, ``J``: residual and Jacobian at ``st.x``)."""
    for it in range(max_iter + 1):
        m = _gauss_newton_model(st, r, J, lo, hi, tol)
        # problems still iterating take a step; converged ones take one last undamped step
        # (polish: for an affine residual it lands exactly on the solution) if it helps
        stepping = m.conv if it == max_iter else st.done.logical_not()
        if not bool(stepping.any()):
            break
        d = _direction(m, st.mu)
        x_new, F_new, full, need = _line_search(
            residual, st, m, d, lo, hi, stepping, max_backtracks
        )
        _accept(st, m, stepping, x_new, F_new, full, need)
        if bool(st.done.all()) or it == max_iter:
            break
        r, J = _evaluate(residual, jacobian, st.x)
        st.F = 0.5 * _dot(r, r)


def _gauss_newton_model(
    st: _State, r: Tensor, J: Tensor, lo: Tensor, hi: Tensor, tol: float
) -> _Model:
    """The model at ``st.x``; marks non-finite and converged problems in ``st`` and records
    their optimality."""
    x, F = st.x, st.F
    n, dtype = x.shape[-1], x.dtype
    eps = torch.finfo(dtype).eps
    A, g = _normal_equations(J, r)
    finite = torch.isfinite(F) & torch.isfinite(g).all(-1) & torch.isfinite(A).all(-1).all(-1)
    bad = finite.logical_not() & st.done.logical_not()
    st.status = torch.where(bad, int(SolverStatus.NONFINITE), st.status)
    st.done = st.done | bad
    g = torch.where(finite.unsqueeze(-1), g, torch.zeros_like(g))
    A = torch.where(finite[..., None, None], A, torch.eye(n, dtype=dtype, device=x.device))
    diag = A.diagonal(dim1=-2, dim2=-1)
    # a zero column (x_j does not enter the residual) borrows the largest curvature
    scale = diag.amax(-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)
    dA = torch.where(diag > 0, diag, scale)
    s = g / dA
    bind = ((g > 0) & (x - lo <= s)) | ((g < 0) & (hi - x <= -s))
    free = bind.logical_not()
    d0 = _reduced_solve(A, dA, free, -g, None)
    xb = torch.clamp(x - s, lo, hi)
    delta = _dot(g, torch.where(bind, x - xb, -d0))
    delta = delta.clamp_min(0.0)
    st.opt = torch.where(st.done, st.opt, delta.sqrt())
    by_tol = delta.sqrt() <= tol
    by_round = 0.5 * delta <= ROUNDOFF * eps * F
    conv = st.done.logical_not() & (by_tol | by_round)
    st.status = torch.where(
        conv & by_tol,
        int(SolverStatus.CONVERGED),
        torch.where(conv, int(SolverStatus.ROUNDOFF), st.status),
    )
    return _Model(A, g, dA, s, bind, free, d0, conv)


def _direction(m: _Model, mu: Tensor) -> Tensor:
    """The search direction: damped on the free set (undamped where converged), ``-s`` on the
    binding set."""
    if bool((mu > 0).any()):
        d = _reduced_solve(m.A, m.dA, m.free, -m.g, mu)
        d = torch.where(m.conv.unsqueeze(-1), m.d0, d)
    else:
        d = m.d0
    return torch.where(m.bind, -m.s, d)


def _line_search(
    residual: Residual,
    st: _State,
    m: _Model,
    d: Tensor,
    lo: Tensor,
    hi: Tensor,
    stepping: Tensor,
    max_backtracks: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projected backtracking line search along ``d`` from ``st.x``.

    Returns ``(x_new, F_new, full, need)``: the accepted points and costs (the old ones where no
    step was accepted), whether the full step was accepted, and which problems found no step.
    """
    x, F, g, conv = st.x, st.F, m.g, m.conv
    batch, dtype = x.shape[:-1], x.dtype
    eps = torch.finfo(dtype).eps
    alpha = torch.ones(batch, dtype=dtype, device=x.device)
    need = stepping
    x_new, F_new = x.clone(), F.clone()
    full = torch.zeros_like(need)
    for bt in range(max_backtracks):
        xt = torch.clamp(x + alpha.unsqueeze(-1) * d, lo, hi)
        rt = residual(xt)
        Ft = 0.5 * _dot(rt, rt).expand(batch)
        armijo = Ft <= F + ARMIJO * _dot(g, xt - x)
        polish = Ft <= F + ROUNDOFF * eps * F.abs()
        ok = need & torch.isfinite(Ft) & torch.where(conv, polish, armijo)
        x_new = torch.where(ok.unsqueeze(-1), xt, x_new)
        F_new = torch.where(ok, Ft, F_new)
        if bt == 0:
            full = ok
        need = need & ok.logical_not() & conv.logical_not()
        if not bool(need.any()):
            break
        alpha = alpha * BACKTRACK
    return x_new, F_new, full, need


def _accept(
    st: _State,
    m: _Model,
    stepping: Tensor,
    x_new: Tensor,
    F_new: Tensor,
    full: Tensor,
    need: Tensor,
) -> None:
    """Move ``st`` to the line search's points: update the damping by the gain ratio, mark
    stalled, frozen and converged problems, count the iterations."""
    dtype = st.x.dtype
    eps = torch.finfo(dtype).eps
    x, F, g, A = st.x, st.F, m.g, m.A
    moving = stepping & m.conv.logical_not()
    # gain ratio of the accepted step: actual over model-predicted decrease
    step = x_new - x
    pred = -(_dot(g, step) + 0.5 * _dot(step, _dot(A, step.unsqueeze(-2))))
    gain = (F - F_new) / pred.clamp_min(torch.finfo(dtype).tiny)
    mu = st.mu
    mu = torch.where(
        full & (gain > GAIN_HIGH),
        mu / MU_SHRINK,
        torch.where(full & (gain >= GAIN_LOW), mu, torch.clamp(mu * MU_GROW, min=MU_INIT)),
    )
    mu = torch.where(mu < MU_MIN, torch.zeros_like(mu), mu)
    st.mu = mu
    stalled = need & (mu > MU_MAX)
    st.status = torch.where(stalled, int(SolverStatus.STALLED), st.status)
    # an accepted step below the resolution of x: no further progress is representable
    frozen = moving & need.logical_not()
    frozen = frozen & ((x_new - x).abs() <= ROUNDOFF * eps * x.abs()).all(-1)
    st.status = torch.where(frozen, int(SolverStatus.ROUNDOFF), st.status)
    st.done = st.done | stalled | m.conv | frozen
    st.iters = st.iters + moving.long()
    st.x, st.F = x_new, F_new


def _warn_unconverged(status: Tensor, tol: float) -> None:
    """The :class:`ConvergenceWarning` of :func:`bounded_least_squares` (at its caller), if a
    problem did not converge."""
    if bool((status > 0).all()):
        return
    counts = {s.name.lower(): int((status == s).sum()) for s in SolverStatus if s <= 0}
    detail = ", ".join(f"{k}: {v}" for k, v in counts.items() if v)
    warnings.warn(
        f"bounded_least_squares: {int((status <= 0).sum())} of {status.numel()} problems did "
        f"not converge to tol={tol:.1e} ({detail})",
        ConvergenceWarning,
        stacklevel=3,
    )


def _attach_gradient(
    residual: Residual, jacobian: Residual | None, x: Tensor, lo: Tensor, hi: Tensor
) -> Tensor:
    """Give the (detached) solution the implicit-function derivative; its value is unchanged.

    Free coordinates solve ``grad_F F(x_F, x_B = bound) = 0``, so ``dx_F = -H_FF^{-1} d(grad_F)``
    where the differential of the gradient covers the residual's parameters and the active bounds;
    active coordinates equal their bound.
    """
    if not torch.is_grad_enabled():
        return x
    at_lo, at_hi = x <= lo, x >= hi
    at_hi = at_hi & at_lo.logical_not()
    free = (at_lo | at_hi).logical_not()
    bound_grad = lo.requires_grad or hi.requires_grad
    if not residual(x).requires_grad and not bound_grad:
        return x
    lo_b, hi_b = lo.expand_as(x), hi.expand_as(x)
    with torch.enable_grad():
        xi = x.detach().requires_grad_(True)
        x_eval = torch.where(at_lo, lo_b, torch.where(at_hi, hi_b, xi))
        out = torch.where(at_lo, lo_b, torch.where(at_hi, hi_b, x))
        if not bool(free.any()):
            return out
        r = residual(x_eval)
        (grad,) = torch.autograd.grad(0.5 * (r * r).sum(), xi, create_graph=True)
        rows = []
        for j in range(x.shape[-1]):
            (hj,) = torch.autograd.grad(
                grad[..., j].sum(), xi, retain_graph=True, allow_unused=True
            )
            rows.append(torch.zeros_like(x) if hj is None else hj)
    H = torch.stack(rows, dim=-2).detach()
    H = 0.5 * (H + H.mT)
    ff = free.unsqueeze(-1) & free.unsqueeze(-2)
    eye_b = torch.diag_embed(free.logical_not().to(H))
    L, info = torch.linalg.cholesky_ex(torch.where(ff, H, torch.zeros_like(H)) + eye_b)
    if bool((info > 0).any()):  # not strictly convex there: fall back to the Gauss-Newton matrix
        _, Jd = _evaluate(residual, jacobian, x)
        G = Jd.mT @ Jd
        Lg, _ = torch.linalg.cholesky_ex(torch.where(ff, G, torch.zeros_like(G)) + eye_b)
        L = torch.where((info > 0)[..., None, None], Lg, L)
    step = torch.cholesky_solve(
        torch.where(free, grad, torch.zeros_like(grad)).unsqueeze(-1), L
    ).squeeze(-1)
    return out - (step - step.detach())
