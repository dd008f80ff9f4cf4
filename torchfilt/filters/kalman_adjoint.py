"""The gradient of the exact filter's log-likelihood by one closed-form backward pass.

For a linear-Gaussian model the score is a function of the smoothing distribution (Fisher's
identity, ``d log p(y) = E[d log p(x, y) | y]``; Segal & Weinstein 1989). Written with the
backward information recursion of the fixed-interval smoother (de Jong 1989; Durbin & Koopman
2012, sec. 4.4 and 7.3.3) it needs no inverse of ``Q``, ``R`` or ``P0`` (so it holds for singular
noises and a known initial state), only the innovation covariances the filter factors anyway:

    r_t = H_t^T S_t^{-1} e_t + F_t^T r_{t+1},        N_t = H_t^T S_t^{-1} H_t + F_t^T N_{t+1} F_t,
    F_t = A_{t+1} (I - K_t H_t),  r_T = 0,  N_T = 0,
    q_t = A_{t+1}^T r_{t+1},  M_t = A_{t+1}^T N_{t+1} A_{t+1}   (zero at t = T-1),
    u_t = S_t^{-1} e_t - K_t^T q_t,                    D_t = S_t^{-1} + K_t^T M_t K_t,

(``r_t``: the smoothed predicted-mean correction, ``m^s_t = m^-_t + P^-_t r_t``; ``N_t``:
``P^s_t = P^-_t - P^-_t N_t P^-_t``) and then, per step and recording,

    dL/dQ_t = (r_t r_t^T - N_t) / 2,            dL/dc_t = r_t,
    dL/dA_t = r_t m_{t-1}^T + (r_t r_t^T - N_t) A_t P_{t-1},
    dL/dR_t = (u_t u_t^T - D_t) / 2,            dL/dd_t = u_t = -dL/dy_t,
    dL/dH_t = u_t (m_t + P_t q_t)^T - K_t^T (I - M_t P_t),
    dL/dx0 = A_0^T r_0,                          dL/dP0 = (A_0^T (r_0 r_0^T - N_0) A_0) / 2,

with ``m_t, P_t`` the filtered moments (``m_{-1} = x0``, ``P_{-1} = P0``, the prior of ``x_{-1}``
in the input convention of :mod:`torchfilt.filters`) and ``S^{-1}``, ``K`` restricted to the
observed components of each step (a missing component has zero rows and columns). The
covariances' gradients are the symmetric ones. The forward pass is the no-graph filter; the
backward pass costs about one smoother. :func:`adjoint_log_likelihood` wraps both into one
``torch.autograd.Function``; :func:`~torchfilt.filters.plan.plan` decides when it serves.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchfilt.filters.kalman_runners import _STEADY_ULPS, _rows
from torchfilt.filters.linear_data import Data, LinearSteps

__all__ = ["adjoint_gradients", "adjoint_log_likelihood"]

#: the filter fields the backward pass needs
NEEDS = frozenset({"mean", "cov", "predicted_cov", "innovation", "log_likelihood"})

#: ``run(data, steps, keep)``: the no-graph filter, returning the fields ``keep`` (a dict-like
#: result with the attributes of a :class:`~torchfilt.filters.FilterResult`)
Run = Callable[[Data, LinearSteps, frozenset[str]], Any]
#: ``replay(data, steps, why)``: the log-likelihood through the recorded (autograd) path
Replay = Callable[[Data, LinearSteps, str], Tensor]


def _tm(x: Tensor, batch: torch.Size, tail: int) -> Tensor:
    """``x (..., T, *tail)`` time-major over the flattened batch: ``(T, 1, *tail)`` (a view) when
    no leading dimension varies (absent or broadcast), else ``(T, B, *tail)``."""
    lead = x.dim() - tail - 1
    if all(x.stride(i) == 0 or x.shape[i] == 1 for i in range(lead)):
        return x[(0,) * lead].unsqueeze(1) if lead else x.unsqueeze(1)
    B, T = batch.numel(), x.shape[lead]
    return x.expand(*batch, *x.shape[lead:]).reshape(B, T, *x.shape[lead + 1 :]).transpose(0, 1)


def _outer(a: Tensor, b: Tensor) -> Tensor:
    return a.unsqueeze(-1) * b.unsqueeze(-2)


def _gram(a: Tensor, b: Tensor, per: bool) -> Tensor:
    """``a_b b_b^T`` for rows ``a (T, B, d)``, ``b (T, B, e)``: per recording ``(T, B, d, e)``,
    or summed over the recordings ``(T, 1, d, e)`` (one batched product)."""
    if per:
        return _outer(a, b)
    return (a.transpose(1, 2) @ b).unsqueeze(1)


class _Weights:
    """The recordings' weights ``g (B,)`` of the log-likelihoods being differentiated."""

    def __init__(self, g: Tensor) -> None:
        self.g = g
        self.total = g.sum()

    def rows(self, x: Tensor) -> Tensor:
        """Weighted rows ``x (T, B, d)``."""
        return x * self.g.unsqueeze(-1)

    def sum(self, X: Tensor, per: bool) -> Tensor:
        """Weighted matrices ``X (T, Bc, d, e)``: per recording ``(T, B, d, e)``, or summed
        ``(T, 1, d, e)``."""
        g = self.g.view(-1, 1, 1)
        if per:
            return X * g
        if X.shape[1] == 1:
            return X * self.total
        return (X * g).sum(1, keepdim=True)


def _finish(grad: Tensor, like: Tensor, batch: torch.Size, tail: int) -> Tensor:
    """A time-major gradient ``(T, 1 or B, *tail)`` in the shape of ``like (..., T, *tail)``,
    summed over the dimensions ``like`` broadcasts."""
    if grad.shape[1] == 1 and like.dim() == tail + 1:
        grad = grad[:, 0]
    else:
        T = grad.shape[0]
        grad = grad.expand(T, batch.numel(), *grad.shape[2:]).transpose(0, 1)
        grad = grad.reshape(*batch, T, *grad.shape[2:])
    shape = torch.broadcast_shapes(grad.shape, like.shape)
    return grad.expand(shape).sum_to_size(like.shape)


def _repeats_from(F: Tensor, J: Tensor) -> int:
    """The first step from which ``F_t`` ``(T-1, ...)`` and ``J_t`` ``(T, ...)`` repeat exactly
    (a time-invariant model whose filter converged: the Riccati runner repeats its covariances);
    ``T - 1`` when they do not."""
    same = (F[1:] == F[:-1]).flatten(1).all(1) & (J[1:-1] == J[:-2]).flatten(1).all(1)
    changed = (~same).nonzero()
    return 0 if changed.numel() == 0 else int(changed.max()) + 1


def _information(J: Tensor, F: Tensor) -> Tensor:
    """``N_t = J_t + F_t^T N_{t+1} F_t`` ``(T, Bc, n, n)`` from ``N_{T-1} = J_{T-1}`` down to 0,
    for ``F (T-1, Bc, n, n)``. Where ``F`` and ``J`` repeat (from step ``c`` on) and ``N`` has
    converged to rounding (``_STEADY_ULPS``, checked every 4th step), the steps down to ``c``
    take the converged value."""
    T = J.shape[0]
    Bc = max(J.shape[1], F.shape[1])
    N = J.expand(T, Bc, *J.shape[2:]).clone()
    c = _repeats_from(F, J) if Bc == 1 and T > 2 else T - 1
    tol = _STEADY_ULPS * torch.finfo(J.dtype).eps
    t = T - 2
    while t >= 0:
        Ft = F[t]
        N[t] += Ft.mT @ (N[t + 1] @ Ft)
        if t > c and t % 4 == 0:
            new = N[t]
            if bool((new - N[t + 1]).abs().amax() <= tol * new.abs().amax()):
                N[c:t] = new
                t = c
        t -= 1
    return N


def _means_back(b: Tensor, F: Tensor) -> Tensor:
    """``r_t = b_t + F_t^T r_{t+1}`` (rows ``(T, B, n)``, ``r_{T-1} = b_{T-1}``) for
    ``F (T-1, Bc, n, n)``: one product per step."""
    r = b.clone()
    shared = F.shape[1] == 1
    for t in range(b.shape[0] - 2, -1, -1):
        if shared:
            r[t].addmm_(r[t + 1], F[t, 0])
        else:
            r[t] += (r[t + 1].unsqueeze(1) @ F[t]).squeeze(1)
    return r


def _shift_back(first: Tensor, x: Tensor) -> Tensor:
    """``[first, x_0, ..., x_{T-2}]`` along dim 0, the second dimensions broadcast."""
    body = x[:-1]
    Bc = max(first.shape[0], body.shape[1])
    head = first.expand(Bc, *first.shape[1:]).unsqueeze(0)
    return torch.cat([head, body.expand(body.shape[0], Bc, *body.shape[2:])], 0)


def _next(x: Tensor) -> Tensor:
    """``[x_1, ..., x_{T-1}, 0]`` along dim 0."""
    return torch.cat([x[1:], x.new_zeros(()).expand(1, *x.shape[1:])], 0)


def adjoint_gradients(
    data: Data, steps: LinearSteps, filt: Any, g: Tensor, needs: tuple[bool, ...]
) -> list[Tensor | None] | None:
    """The gradient of ``sum(g * log_likelihood)`` (see the module docstring).

    Args:
        data: the checked recording (``x0``, ``P0`` the prior of ``x_{-1}``).
        steps: the model's per-step matrices.
        filt: the filter's ``mean``, ``cov``, ``predicted_cov`` and ``innovation`` (NaN where
            missing), expanded over the batch.
        g: weights of the recordings' log-likelihoods, shape ``data.batch``.
        needs: which of ``(x0, P0, y, A, c, Q, H, d, R)`` need a gradient.

    Returns:
        The gradients in that order, each in its input's shape (None where not needed or the
        input is None); None when an innovation covariance fails to factor.
    """
    batch = data.batch
    B, n = batch.numel(), data.x0.shape[-1]
    A, H, R = (_tm(x, batch, 2) for x in (steps.A, steps.H, steps.R))
    P, Pp = _tm(filt.cov, batch, 2), _tm(filt.predicted_cov, batch, 2)
    S = H @ (Pp @ H.mT) + R  # (T, Bc, m, m)
    oo = None
    if not data.complete:
        o = _tm(data.obs, batch, 1).to(S.dtype)
        oo = _outer(o, o)
        S = S * oo + torch.diag_embed(1.0 - o)
    L, info = torch.linalg.cholesky_ex(S)
    if bool(info.any()):
        return None
    Sinv = torch.cholesky_inverse(L)
    if oo is not None:
        Sinv = Sinv * oo  # zero rows and columns of the missing components
    HS = H.mT @ Sinv  # (T, Bc, n, m)
    KT = HS.mT @ Pp  # K_t^T, zero rows where missing
    e = _tm(filt.innovation, batch, 1)
    e = torch.where(_tm(data.obs, batch, 1), e, torch.zeros((), dtype=e.dtype))
    w = _rows(e, Sinv)  # (S^{-1} e)^T, (T, B, m)
    eye = torch.eye(n, dtype=S.dtype, device=S.device)
    F = A[1:] @ (eye - KT[:-1].mT @ H[:-1])
    r, N = _means_back(_rows(w, H), F), _information(HS @ H, F)
    gw = _Weights(g.reshape(B))
    gr = gw.rows(r)
    x0, P0, y, _, c, Q, _, d, _ = (data.x0, data.P0, data.y, *steps)
    need = dict(zip(("x0", "P0", "y", "A", "c", "Q", "H", "d", "R"), needs, strict=True))
    out: dict[str, Tensor] = {}
    X0, P00 = x0.expand(*batch, n).reshape(B, n), _tm(P0.unsqueeze(-3), batch, 2)[0]
    if need["x0"]:
        out["x0"] = (gr[0] @ A[0, 0] if A.shape[1] == 1 else _rows(gr[:1], A[:1])[0]).unsqueeze(0)
    if need["P0"]:
        W0 = _outer(gr[0], r[0]) - gw.sum(N[:1], True)[0]  # (B, n, n)
        out["P0"] = (0.5 * (A[0].mT @ W0 @ A[0])).unsqueeze(0)
    if need["Q"] or need["A"]:
        P_prev = _shift_back(P00, P)
        per_q = steps.Q.dim() > 3
        per_a = steps.A.dim() > 3 or P_prev.shape[1] > 1
        if need["Q"]:
            out["Q"] = 0.5 * (_gram(gr, r, per_q) - gw.sum(N, per_q))
        if need["A"]:
            W = _gram(gr, r, per_a) - gw.sum(N, per_a)
            m_prev = _shift_back(X0, _tm(filt.mean, batch, 1))
            out["A"] = _gram(gr, m_prev, per_a) + W @ A @ P_prev
    if need["c"]:
        out["c"] = gr if steps.c is not None and steps.c.dim() > 2 else gr.sum(1, keepdim=True)
    if need["y"] or need["d"] or need["R"] or need["H"]:
        An = _next(A)  # A_{t+1}, zero at the last step
        q = _rows(_next(r), An)
        M = An.mT @ _next(N) @ An
        u = w - _rows(q, KT.mT)
        gu = gw.rows(u)
        if need["d"] or need["y"]:
            out["d"] = gu
            out["y"] = -gu
        if need["R"]:
            per = steps.R.dim() > 3
            out["R"] = 0.5 * (_gram(gu, u, per) - gw.sum(Sinv + KT @ M @ KT.mT, per))
        if need["H"]:
            per = steps.H.dim() > 3
            ms = _tm(filt.mean, batch, 1) + _rows(q, P)
            out["H"] = _gram(gu, ms, per) - gw.sum(KT - KT @ M @ P, per)
    inputs = {"x0": x0, "P0": P0, "y": y, "A": steps.A, "c": c, "Q": Q, "H": steps.H, "d": d}
    inputs["R"] = steps.R
    tails = {"x0": 1, "P0": 2, "y": 1, "A": 2, "c": 1, "Q": 2, "H": 2, "d": 1, "R": 2}
    return [
        _finish(
            out[k], x.unsqueeze(-tails[k] - 1) if k in ("x0", "P0") else x, batch, tails[k]
        ).reshape(x.shape)
        if k in out and x is not None
        else None
        for k, x in inputs.items()
    ]


class _AdjointLikelihood(torch.autograd.Function):
    """The log-likelihood ``(batch)`` by the no-graph filter; its gradient by
    :func:`adjoint_gradients`, or by replaying the recorded path when that cannot serve (a
    second derivative, or a factorisation that fails)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        data: Data,
        run: Run,
        replay: Replay,
        x0: Tensor,
        P0: Tensor,
        y: Tensor,
        A: Tensor,
        c: Tensor | None,
        Q: Tensor,
        H: Tensor,
        d: Tensor | None,
        R: Tensor,
    ) -> Tensor:
        steps = LinearSteps(A, c, Q, H, d, R)
        res = run(data._replace(x0=x0, P0=P0, y=y), steps, NEEDS)
        ctx.save_for_backward(x0, P0, y, A, c, Q, H, d, R)
        ctx.data, ctx.replay = data, replay
        ctx.filt = res
        return res.log_likelihood.clone()

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x0, P0, y, A, c, Q, H, d, R = ctx.saved_tensors
        data = ctx.data._replace(x0=x0, P0=P0, y=y)
        steps = LinearSteps(A, c, Q, H, d, R)
        needs = tuple(ctx.needs_input_grad[3:])
        create_graph = torch.is_grad_enabled()
        grads = None
        why = "a second derivative needs the recorded graph"
        if not create_graph:
            grads = adjoint_gradients(data, steps, ctx.filt, g, needs)
            why = "an innovation covariance failed to factor in the backward pass"
        if grads is None:
            grads = _replay(ctx.replay, data, steps, g, needs, why, create_graph)
        ctx.filt = None
        return (None, None, None, *grads)


def _replay(
    replay: Replay,
    data: Data,
    steps: LinearSteps,
    g: Tensor,
    needs: tuple[bool, ...],
    why: str,
    create_graph: bool,
) -> list[Tensor | None]:
    """The gradients by autograd through the recorded path (with their own graph when
    ``create_graph``)."""
    inputs = [data.x0, data.P0, data.y, *steps]
    with torch.enable_grad():
        ll = replay(data, steps, why)
        wrt = [x for x, need in zip(inputs, needs, strict=True) if need and x is not None]
        got = iter(torch.autograd.grad(ll, wrt, g, create_graph=create_graph, allow_unused=True))
    return [
        next(got) if need and x is not None else None for x, need in zip(inputs, needs, strict=True)
    ]


def adjoint_log_likelihood(data: Data, steps: LinearSteps, run: Run, replay: Replay) -> Tensor:
    """The summed log-likelihood ``(batch)`` of the exact filter, differentiable by one
    closed-form backward pass (see the module docstring).

    Args:
        data: the checked recording.
        steps: the model's per-step matrices.
        run: the no-graph filter (called with the fields it must return).
        replay: the log-likelihood through the recorded path, for what the closed form does not
            serve (a second derivative; a factorisation that fails).

    Returns:
        The log-likelihood of each recording, shape ``data.batch``.
    """
    out: Tensor = _AdjointLikelihood.apply(data, run, replay, data.x0, data.P0, data.y, *steps)
    return out
