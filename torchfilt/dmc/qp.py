"""A small batched solver for strictly convex quadratic programs (the DMC optimisations).

    minimise    1/2 x^T G x + c^T x
    subject to  A x <= b,   lb <= x <= ub

``G`` must be symmetric positive definite. The method is Mehrotra's predictor-corrector primal-dual
interior-point method (Nocedal & Wright, *Numerical Optimization*, 2nd ed., sec. 16.6) with slacks
``s = b - A x >= 0`` and multipliers ``z >= 0``. Each iteration solves the condensed Newton system

    (G + A^T diag(z / s) A) dx = -r_d - A^T (diag(z / s) r_p - r_sz / s)

by Cholesky (``r_d = G x + c + A^T z``, ``r_p = A x + s - b``, ``r_sz`` the complementarity residual),
so the cost per iteration is one ``n x n`` factorisation whatever the number of constraints. Every
batch element runs its own iterations; converged elements are frozen. The DMC problems are small
(tens of variables, ~100 constraints), where an interior-point method needs 10-20 iterations and
batches naturally, unlike an active-set method.

After convergence the solution is *polished* (as OSQP does): the constraints with ``s_i < z_i`` are
guessed active, the equality-constrained KKT system on them is solved exactly, and the result replaces
the interior-point iterate when it is primal feasible with non-negative multipliers. This removes the
``O(sqrt(mu))`` error an interior-point method leaves on weakly active constraints.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import ShapeError
from torchfilt.numerics import psd_solve, symmetrize

__all__ = ["QPResult", "solve_qp"]

#: Default stopping tolerance on the scaled primal/dual residuals and the complementarity gap.
QP_TOL = 1e-10
#: Default cap on interior-point iterations.
QP_MAX_ITER = 100
#: Fraction of the step to the boundary taken (keeps iterates strictly interior).
STEP_FRACTION = 0.995
#: Relative asymmetry of ``G`` tolerated (rounding from forming ``D^T Q D`` and the like).
SYMMETRY_RTOL = 1e-10
#: A polished solution is accepted if it violates no constraint and no multiplier sign by more than
#: this (relative to the problem scale).
POLISH_TOL = 1e-9


class QPResult(NamedTuple):
    """Solution of a batch of QPs.

    Attributes:
        x: minimisers, shape ``(..., n)``.
        multipliers: Lagrange multipliers of the inequality rows, shape ``(..., m)``, in the order
            ``A x <= b`` rows, then ``x >= lb`` rows, then ``x <= ub`` rows (finite bounds only).
        objective: ``1/2 x^T G x + c^T x``, shape ``(...)``.
        converged: whether each problem met the tolerance, shape ``(...)`` bool. A problem with no
            feasible point does not converge.
        iterations: iterations used (largest over the batch).
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
        raise ValueError(
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
        ub: upper bounds, likewise.
        tol: tolerance on the scaled residuals and the mean complementarity.
        max_iter: iteration cap.

    Returns:
        A :class:`QPResult`. Check ``converged``: an infeasible problem returns ``False`` there.

    Raises:
        ShapeError: inconsistent shapes (names the argument).
        ValueError: ``G`` not symmetric positive definite, or non-finite data.
    """
    if not isinstance(G, Tensor) or not isinstance(c, Tensor):
        raise TypeError("G and c must be torch.Tensors")
    if G.dim() < 2 or G.shape[-1] != G.shape[-2]:
        raise ShapeError(f"G: expected shape (..., n, n), got {tuple(G.shape)}")
    n = G.shape[-1]
    if c.shape[-1:] != (n,):
        raise ShapeError(f"c: expected shape (..., {n}), got {tuple(c.shape)}")
    dtype = torch.promote_types(G.dtype, c.dtype)
    G, c = G.to(dtype), c.to(dtype)
    if not bool(torch.isfinite(G).all() & torch.isfinite(c).all()):
        raise ValueError("G and c must be finite")
    gscale = float(G.abs().amax().clamp_min(1.0))
    if not torch.allclose(G, G.mT, rtol=0.0, atol=SYMMETRY_RTOL * gscale):
        raise ValueError("G is not symmetric")
    if not bool((torch.linalg.cholesky_ex(G)[1] == 0).all()):
        raise ValueError("G must be positive definite (the QP must be strictly convex)")
    rows: list[Tensor] = []
    rhs: list[Tensor] = []
    if A is not None:
        if b is None:
            raise ValueError("b is required with A")
        A = torch.as_tensor(A, dtype=dtype)
        b = torch.as_tensor(b, dtype=dtype)
        if A.dim() < 2 or A.shape[-1] != n:
            raise ShapeError(f"A: expected shape (..., m, {n}), got {tuple(A.shape)}")
        if b.shape[-1:] != A.shape[-2:-1]:
            raise ShapeError(f"b: expected shape (..., {A.shape[-2]}), got {tuple(b.shape)}")
        if not bool(torch.isfinite(A).all() & torch.isfinite(b).all()):
            raise ValueError("A and b must be finite")
        rows.append(A)
        rhs.append(b)
    elif b is not None:
        raise ValueError("b given without A")
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
    return _ipm(G, c, Am, bm, tol=tol, max_iter=max_iter)


def _max_step(v: Tensor, dv: Tensor) -> Tensor:
    """Largest ``alpha in [0, 1]`` with ``v + alpha dv >= 0`` (per batch element)."""
    ratio = torch.where(dv < 0, -v / dv, torch.full_like(v, float("inf")))
    return ratio.amin(-1).clamp(max=1.0)


def _ipm(G: Tensor, c: Tensor, A: Tensor, b: Tensor, *, tol: float, max_iter: int) -> QPResult:
    m = A.shape[-2]
    At = A.mT

    def mv(M: Tensor, v: Tensor) -> Tensor:
        return (M @ v.unsqueeze(-1)).squeeze(-1)

    x = -psd_solve(G, c.unsqueeze(-1), name="G").squeeze(-1)
    s = (b - mv(A, x)).abs().clamp_min(1.0)
    z = torch.ones_like(s)
    scale_d = 1.0 + c.abs().amax(-1) + G.abs().amax((-2, -1))
    scale_p = 1.0 + b.abs().amax(-1)
    done = torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
    it = 0
    for it in range(max_iter + 1):
        r_d = mv(G, x) + c + mv(At, z)
        r_p = mv(A, x) + s - b
        mu = (s * z).sum(-1) / m
        ok = (
            (r_d.abs().amax(-1) <= tol * scale_d)
            & (r_p.abs().amax(-1) <= tol * scale_p)
            & (mu <= tol * (1.0 + (0.5 * (x * mv(G, x)).sum(-1) + (c * x).sum(-1)).abs()))
        )
        done = done | (ok & torch.isfinite(x).all(-1))
        if bool(done.all()) or it == max_iter:
            break
        w = z / s
        K = symmetrize(G + At @ (w.unsqueeze(-1) * A))
        L, info = torch.linalg.cholesky_ex(K)
        bad = info > 0
        if bool(bad.any()):  # rank-deficient normal matrix: regularise those elements slightly
            eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
            reg = torch.finfo(K.dtype).eps * K.diagonal(dim1=-2, dim2=-1).abs().amax(-1)
            L = torch.where(
                bad[..., None, None],
                torch.linalg.cholesky_ex(K + reg[..., None, None] * eye)[0],
                L,
            )

        def direction(r_sz: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            rhs = -r_d - mv(At, w * r_p - r_sz / s)  # noqa: B023 (same iteration)
            dx = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)  # noqa: B023
            dz = w * (mv(A, dx) + r_p) - r_sz / s  # noqa: B023
            ds = -r_p - mv(A, dx)  # noqa: B023
            return dx, ds, dz

        dx, ds, dz = direction(s * z)
        a_aff = torch.minimum(_max_step(s, ds), _max_step(z, dz))
        mu_aff = ((s + a_aff[..., None] * ds) * (z + a_aff[..., None] * dz)).sum(-1) / m
        sigma = (mu_aff / mu).clamp(0.0, 1.0) ** 3
        dx, ds, dz = direction(s * z + ds * dz - (sigma * mu)[..., None])
        alpha = STEP_FRACTION * torch.minimum(_max_step(s, ds), _max_step(z, dz))
        alpha = torch.where(done, torch.zeros_like(alpha), alpha)[..., None]
        x = x + alpha * dx
        s = s + alpha * ds
        z = z + alpha * dz
    x, z = _polish(G, c, A, b, x, s, z, done)
    obj = 0.5 * (x * mv(G, x)).sum(-1) + (c * x).sum(-1)
    return QPResult(x, z, obj, done, it)


def _polish(
    G: Tensor, c: Tensor, A: Tensor, b: Tensor, x: Tensor, s: Tensor, z: Tensor, done: Tensor
) -> tuple[Tensor, Tensor]:
    """Solve the KKT system on the guessed active set; keep it where it is feasible and optimal."""
    n, m = G.shape[-1], A.shape[-2]
    active = s < z  # (..., m)
    act = active.to(G.dtype)
    # rows of active constraints: A_i x = b_i; rows of inactive ones: z_i = 0
    top = torch.cat([G, A.mT * act.unsqueeze(-2)], dim=-1)
    bottom = torch.cat([A * act.unsqueeze(-1), torch.diag_embed(1.0 - act)], dim=-1)
    K = torch.cat([top, bottom], dim=-2)
    rhs = torch.cat([-c, b * act], dim=-1)
    sol, info = torch.linalg.solve_ex(K, rhs.unsqueeze(-1))
    sol = sol.squeeze(-1)
    xp, zp = sol[..., :n], sol[..., n:]
    scale = 1.0 + b.abs().amax(-1) + c.abs().amax(-1)
    viol = ((A @ xp.unsqueeze(-1)).squeeze(-1) - b).amax(-1) if m else torch.zeros_like(scale)
    ok = (
        done
        & (info == 0)
        & torch.isfinite(sol).all(-1)
        & (viol <= POLISH_TOL * scale)
        & (zp.amin(-1) >= -POLISH_TOL * scale)
    )
    x = torch.where(ok[..., None], xp, x)
    z = torch.where(ok[..., None], zp.clamp_min(0.0), z)
    return x, z
