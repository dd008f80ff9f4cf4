"""Strictly convex quadratic programs of the DMC layers, solved by Clarabel.

    minimise    1/2 x^T G x + c^T x
    subject to  A x <= b,   lb <= x <= ub

``G`` must be symmetric positive definite. The solver is Clarabel (Goulart & Chen, "Clarabel: an
interior-point solver for conic programs with quadratic objectives", 2024; the ``clarabel`` package
on PyPI), a well-kept primal-dual interior-point method with iterative refinement: the DMC problems
are small (tens to a few hundred variables) and solved one at a time, so a library solver serves
better than a hand-written one. A batch is solved problem by problem (the result equals the looped
one by construction); the solve is not differentiable (results are detached).
"""

from __future__ import annotations

from typing import NamedTuple

import clarabel
import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError, ShapeError
from torchfilt.numerics import psd_solve

__all__ = ["QPResult", "solve_qp"]

#: Default tolerance (Clarabel's absolute/relative duality gap and feasibility tolerances).
QP_TOL = 1e-10
#: Default cap on interior-point iterations.
QP_MAX_ITER = 100
#: Relative asymmetry of ``G`` tolerated (rounding from forming ``D^T Q D`` and the like).
SYMMETRY_RTOL = 1e-10


class QPResult(NamedTuple):
    """Solution of a batch of QPs.

    Attributes:
        x: minimisers, shape ``(..., n)``.
        multipliers: Lagrange multipliers of the inequality rows, shape ``(..., m)``, in the order
            ``A x <= b`` rows, then ``x >= lb`` rows, then ``x <= ub`` rows (finite bounds only).
        objective: ``1/2 x^T G x + c^T x``, shape ``(...)``.
        converged: whether each problem met the tolerance, shape ``(...)`` bool. A problem with no
            feasible point does not converge.
        iterations: interior-point iterations used (largest over the batch).
    """

    x: Tensor
    multipliers: Tensor
    objective: Tensor
    converged: Tensor
    iterations: int


def _bound_rows(
    bound: Tensor | None, n: int, sign: float, name: str, like: Tensor
) -> tuple[Tensor, Tensor] | None:
    if bound is None:
        return None
    bt = torch.as_tensor(bound, dtype=like.dtype, device=like.device)
    if bt.dim() == 0:
        bt = bt.expand(n)
    if bt.shape[-1] != n:
        raise ShapeError(f"{name}: expected shape (..., {n}), got {tuple(bt.shape)}")
    finite = torch.isfinite(bt)
    keep = finite.reshape(-1, n).any(0)
    if bool((~finite.reshape(-1, n)[:, keep]).any()):
        raise InputError(
            f"{name}: a bound must be finite for every batch element or infinite for every one"
        )
    if not bool(keep.any()):
        return None
    idx = keep.nonzero().squeeze(-1)
    rows = sign * torch.eye(n, dtype=like.dtype, device=like.device)[idx]
    return rows, sign * bt[..., idx]


def solve_qp(
    G: Tensor,
    c: Tensor,
    A: Tensor | None = None,
    b: Tensor | None = None,
    *,
    lb: Tensor | float | None = None,
    ub: Tensor | float | None = None,
    tol: float = QP_TOL,
    max_iter: int = QP_MAX_ITER,
) -> QPResult:
    """Solve ``min 1/2 x^T G x + c^T x  s.t.  A x <= b, lb <= x <= ub`` (batched).

    Args:
        G: SPD Hessians, shape ``(..., n, n)``.
        c: linear terms, shape ``(..., n)``.
        A: inequality rows, shape ``(..., m, n)``, or ``None``.
        b: right-hand sides, shape ``(..., m)`` (with ``A``).
        lb: lower bounds, a scalar or shape ``(..., n)``; ``-inf`` entries are dropped (the same
            entries in every batch element).
        ub: upper bounds, a scalar or shape ``(..., n)``; ``+inf`` entries are dropped likewise.
        tol: Clarabel's duality-gap and feasibility tolerances.
        max_iter: iteration cap.

    Returns:
        A :class:`QPResult`. Check ``converged``: an infeasible problem returns ``False`` there.

    Raises:
        ShapeError: inconsistent shapes (names the argument).
        InputError: ``G`` not symmetric positive definite, or non-finite data.
        InputTypeError: ``G`` or ``c`` is not a tensor.
    """
    if not isinstance(G, Tensor) or not isinstance(c, Tensor):
        raise InputTypeError(
            f"G and c must be torch.Tensors, got {type(G).__name__} and {type(c).__name__}"
        )
    if G.dim() < 2 or G.shape[-1] != G.shape[-2]:
        raise ShapeError(f"G: expected shape (..., n, n), got {tuple(G.shape)}")
    n = G.shape[-1]
    if c.shape[-1:] != (n,):
        raise ShapeError(f"c: expected shape (..., {n}), got {tuple(c.shape)}")
    dtype = torch.promote_types(G.dtype, c.dtype)
    G, c = G.to(dtype), c.to(dtype)
    if not bool(torch.isfinite(G).all() & torch.isfinite(c).all()):
        raise InputError("G and c must be finite")
    gscale = float(G.abs().amax().clamp_min(1.0))
    if not torch.allclose(G, G.mT, rtol=0.0, atol=SYMMETRY_RTOL * gscale):
        raise InputError("G is not symmetric")
    if not bool((torch.linalg.cholesky_ex(G)[1] == 0).all()):
        raise InputError("G must be positive definite (the QP must be strictly convex)")
    rows: list[Tensor] = []
    rhs: list[Tensor] = []
    if A is not None:
        if b is None:
            raise InputError("b is required with A")
        A = torch.as_tensor(A, dtype=dtype)
        b = torch.as_tensor(b, dtype=dtype)
        if A.dim() < 2 or A.shape[-1] != n:
            raise ShapeError(f"A: expected shape (..., m, {n}), got {tuple(A.shape)}")
        if b.shape[-1:] != A.shape[-2:-1]:
            raise ShapeError(f"b: expected shape (..., {A.shape[-2]}), got {tuple(b.shape)}")
        if not bool(torch.isfinite(A).all() & torch.isfinite(b).all()):
            raise InputError("A and b must be finite")
        rows.append(A)
        rhs.append(b)
    elif b is not None:
        raise InputError("b given without A")
    for bound, sign, name in ((lb, -1.0, "lb"), (ub, 1.0, "ub")):
        got = _bound_rows(bound, n, sign, name, G)  # type: ignore[arg-type]
        if got is not None:
            rows.append(got[0])
            rhs.append(got[1])
    batch = torch.broadcast_shapes(
        G.shape[:-2], c.shape[:-1], *(r.shape[:-2] for r in rows), *(h.shape[:-1] for h in rhs)
    )
    G = G.expand(*batch, n, n)
    c = c.expand(*batch, n)
    if not rows:
        x = -psd_solve(G, c.unsqueeze(-1), name="G").squeeze(-1)
        obj = 0.5 * (x * (G @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) + (c * x).sum(-1)
        return QPResult(x, x.new_zeros(*batch, 0), obj, torch.ones(batch, dtype=torch.bool), 0)
    Am = torch.cat([r.expand(*batch, *r.shape[-2:]) for r in rows], dim=-2)
    bm = torch.cat([h.expand(*batch, h.shape[-1]) for h in rhs], dim=-1)
    return _clarabel(G, c, Am, bm, tol=tol, max_iter=max_iter)


def _settings(tol: float, max_iter: int) -> clarabel.DefaultSettings:
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.max_iter = int(max_iter)
    s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = float(tol)
    s.tol_ktratio = min(s.tol_ktratio, float(tol))
    s.max_threads = 1
    return s


def solve_one(
    G: np.ndarray,
    c: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    *,
    tol: float,
    max_iter: int,
    accept_almost: bool = False,
    n_eq: int = 0,
) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """One QP ``min 1/2 x^T G x + c^T x  s.t.  A x <= b`` by Clarabel (float64 NumPy arrays).

    The first ``n_eq`` rows of ``A x <= b`` are equalities ``A x = b`` instead.

    ``G`` may be positive semi-definite here (callers that need strict convexity check it).

    Returns:
        ``(x, z, solved, iterations)``: the minimiser, the multipliers of ``A x <= b`` (``>= 0``),
        whether Clarabel reported ``Solved`` (or ``AlmostSolved``, the reduced tolerances, with
        ``accept_almost``), and its iteration count.
    """
    P = sp.triu(sp.csc_matrix(G), format="csc")
    cones = []
    if n_eq:
        cones.append(clarabel.ZeroConeT(n_eq))
    if A.shape[0] - n_eq:
        cones.append(clarabel.NonnegativeConeT(A.shape[0] - n_eq))
    solver = clarabel.DefaultSolver(
        P,
        np.ascontiguousarray(c),
        sp.csc_matrix(A),
        np.ascontiguousarray(b),
        cones,
        _settings(tol, max_iter),
    )
    sol = solver.solve()
    ok = [clarabel.SolverStatus.Solved]
    if accept_almost:
        ok.append(clarabel.SolverStatus.AlmostSolved)
    solved = sol.status in ok
    return np.asarray(sol.x), np.asarray(sol.z), bool(solved), int(sol.iterations)


def _clarabel(G: Tensor, c: Tensor, A: Tensor, b: Tensor, *, tol: float, max_iter: int) -> QPResult:
    batch = G.shape[:-2]
    n, m = G.shape[-1], A.shape[-2]
    Gf = G.detach().reshape(-1, n, n).cpu().double().numpy()
    cf = c.detach().reshape(-1, n).cpu().double().numpy()
    Af = A.detach().reshape(-1, m, n).cpu().double().numpy()
    bf = b.detach().reshape(-1, m).cpu().double().numpy()
    xs, zs, ok, its = [], [], [], 0
    for i in range(Gf.shape[0]):
        x, z, solved, it = solve_one(Gf[i], cf[i], Af[i], bf[i], tol=tol, max_iter=max_iter)
        xs.append(x)
        zs.append(z)
        ok.append(solved)
        its = max(its, it)
    x_t = torch.as_tensor(np.stack(xs), dtype=G.dtype, device=G.device).reshape(*batch, n)
    z_t = torch.as_tensor(np.stack(zs), dtype=G.dtype, device=G.device).reshape(*batch, m)
    obj = 0.5 * (x_t * (G @ x_t.unsqueeze(-1)).squeeze(-1)).sum(-1) + (c * x_t).sum(-1)
    conv = torch.as_tensor(ok, dtype=torch.bool, device=G.device).reshape(batch)
    return QPResult(x_t, z_t, obj.detach(), conv, its)
