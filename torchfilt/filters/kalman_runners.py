"""The runners of the closed-form Kalman filter over time: the sequential recursion of the pure
steps, the fast plain recursion and the Riccati runner for covariances that do not depend on the
data. Which one runs is decided by :func:`~torchfilt.filters.plan.plan`; :func:`run_exact`
carries the decision out.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchfilt.filters.kalman_steps import (
    Belief,
    _psd_sqrt_steps,
    predict,
    predict_sqrt,
    update,
    update_sqrt,
)
from torchfilt.filters.linear_data import Data, LinearSteps
from torchfilt.filters.plan import ExecutionPlan
from torchfilt.numerics import gaussian_log_prob, safe_cholesky, symmetrize

__all__ = ["linear_facts", "run_exact"]


def _step(x: Tensor | None, t: int, dim: int) -> Tensor | None:
    return None if x is None else x.select(x.dim() + dim, t)


class _Collect:
    """Per-step outputs gathered along a new time axis: a list stacked at the end while autograd
    records (in-place writes would chain one copy per step into the graph), otherwise written into
    one preallocated tensor, so no second copy of the results is ever held."""

    def __init__(self, T: int, dim: int, inplace: bool) -> None:
        self.T, self.dim, self.inplace = T, dim, inplace
        self.items: list[Tensor] = []
        self.buf: Tensor | None = None

    def put(self, t: int, x: Tensor) -> None:
        if not self.inplace:
            self.items.append(x)
            return
        if self.buf is None:
            at = x.dim() + self.dim + 1
            self.buf = x.new_empty((*x.shape[:at], self.T, *x.shape[at:]))
        self.buf.select(self.buf.dim() + self.dim, t).copy_(x)

    def value(self) -> Tensor:
        if self.inplace:
            assert self.buf is not None
            return self.buf
        return torch.stack(self.items, dim=self.dim)


def _run(
    data: Data, steps: LinearSteps, *, sqrt: bool, keep: frozenset[str], inplace: bool
) -> dict[str, Tensor]:
    """The sequential recursion; returns the kept per-step outputs stacked over time, plus the
    per-step log-likelihood terms when ``'log_likelihood'`` is kept."""
    T = data.y.shape[-2]
    obs = None if data.complete else data.obs
    belief = Belief(data.x0, safe_cholesky(data.P0, name="P0") if sqrt else data.P0)
    Q = _psd_sqrt_steps(steps.Q) if sqrt else steps.Q
    R = _psd_sqrt_steps(steps.R) if sqrt else steps.R
    # what the loop itself must store; the rest is derived afterwards from these, vectorised
    need = {"mean"}
    if {"cov", "cross_cov"} & keep:
        need.add("cov")
    if {
        "predicted_mean",
        "predicted_cov",
        "measurement_mean",
        "innovation",
        "innovation_cov",
    } & keep:
        need |= {"predicted_mean", "predicted_cov"}
    # without stored predicted moments the log-likelihood is summed inside the loop
    loop_ll = "log_likelihood" in keep and "predicted_mean" not in need
    store = {k: _Collect(T, -3 if k.endswith("cov") else -2, inplace) for k in need}
    ll_sum: Tensor | None = None
    e_dtype = data.y.dtype
    for t in range(T):
        A, Q_t, H, R_t = (
            steps.A[..., t, :, :],
            Q[..., t, :, :],
            steps.H[..., t, :, :],
            R[..., t, :, :],
        )
        c, d = _step(steps.c, t, -2), _step(steps.d, t, -2)
        if sqrt:
            pred = predict_sqrt(belief, A, c, Q_t)
            up = update_sqrt(pred, data.y[..., t, :], _step(obs, t, -2), H, d, R_t)
        else:
            pred, _ = predict(belief, A, c, Q_t)
            up = update(pred, data.y[..., t, :], _step(obs, t, -2), H, d, R_t)
        belief = up.belief
        store["mean"].put(t, belief.mean)
        if "cov" in store:
            store["cov"].put(t, belief.cov)
        if "predicted_mean" in store:
            store["predicted_mean"].put(t, pred.mean)
            store["predicted_cov"].put(t, pred.cov)
        if loop_ll:
            dof = up.residual.shape[-1] if obs is None else obs[..., t, :].to(e_dtype).sum(-1)
            term = gaussian_log_prob(up.residual, up.innov_chol, dof)
            ll_sum = term if ll_sum is None else ll_sum + term
    out = {k: v.value() for k, v in store.items()}
    if ll_sum is not None:
        out["log_likelihood"] = ll_sum
    if sqrt:
        for name in ("cov", "predicted_cov"):
            if name in out:
                out[name] = out[name] @ out[name].mT
    return out


def _drifts(dtype: torch.dtype) -> bool:
    """Whether the fast runners symmetrize the filtered covariance every step: below float64 the
    rounding of ``P^- - P^- H^T K^T`` accumulates an antisymmetric part that grows until the
    covariance loses definiteness (over thousands of steps); in float64 it stays at rounding, and
    the runners skip the two operations (float64 results stay as they were)."""
    return dtype != torch.float64


def _per_step(x: Tensor | None, batch: torch.Size, B: int, tail: int) -> list[Tensor] | None:
    """Split ``x (..., T, *tail)`` into ``T`` tensors ``(B, *tail)``, or ``(*tail)`` when ``x``
    has no batch dimensions (they broadcast against the flattened batch)."""
    if x is None:
        return None
    T = x.shape[x.dim() - tail - 1]
    if x.dim() == tail + 1:
        return list(x.unbind(0))
    x = x.expand(*batch, *x.shape[x.dim() - tail - 1 :]).reshape(B, T, *x.shape[x.dim() - tail :])
    return list(x.unbind(1))


#: below this many bytes of innovation factors the log-likelihood is computed after the loop,
#: vectorised over time (fewer operations per step); above it, inside the loop (less memory)
_VECTOR_LL_BYTES = 1 << 24


def _result_bytes(data: Data, keep: frozenset[str]) -> int:
    """Bytes of the per-step fields in ``keep``."""
    n, m = data.x0.shape[-1], data.y.shape[-1]
    per = {"mean": n, "cov": n * n, "predicted_mean": n, "predicted_cov": n * n}
    per |= {"measurement_mean": m, "innovation": m, "innovation_cov": m * m, "cross_cov": n * n}
    size = sum(v for k, v in per.items() if k in keep)
    return data.batch.numel() * data.y.shape[-2] * size * data.y.element_size()


def _masks_per_step(data: Data, B: int) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
    """Per step ``(B, ., .)``: the observed rows ``o``, ``o^T o`` and the unit diagonal of the
    missing components, prepared once so the loop masks with one ``addcmul`` and one product
    (empty lists when all is observed)."""
    if data.complete:
        return [], [], []
    o = data.obs.to(data.y.dtype).unsqueeze(-2)  # (..., T, 1, m)
    rows = _per_step(o, data.batch, B, 2) or []
    outer = _per_step(o.mT * o, data.batch, B, 2) or []
    unit = _per_step(torch.diag_embed(1.0 - o.squeeze(-2)), data.batch, B, 2) or []
    return rows, outer, unit


def _vector_log_likelihood(data: Data, e_all: Tensor, L_all: Tensor) -> Tensor:
    """The summed log-likelihood ``(B,)`` from the residuals ``(B, T, m)`` and innovation factors
    ``(B, T, m, m)`` the fast loop stored, vectorised over time."""
    B, T, m = e_all.shape
    dof = m if data.complete else data.obs.to(e_all.dtype).expand(*data.batch, T, m)
    if isinstance(dof, Tensor):
        dof = dof.reshape(B, T, m).sum(-1)
    return gaussian_log_prob(e_all, L_all, dof, library=True).sum(-1)


def _nan_missing(data: Data, res: dict[str, Tensor], *, inplace: bool) -> None:
    """NaN in the innovations ``res['innovation'] (B, T, m)`` where not observed."""
    B, T, m = res["innovation"].shape
    missing = ~data.obs.expand(*data.batch, T, m).reshape(B, T, m)
    if inplace:
        res["innovation"].masked_fill_(missing, float("nan"))
    else:
        res["innovation"] = res["innovation"].masked_fill(missing, float("nan"))


def _run_fast(
    data: Data, steps: LinearSteps, *, keep: frozenset[str], inplace: bool
) -> dict[str, Tensor] | None:
    """The plain recursion with as few operations per step as possible.

    The batch is flattened to one dimension and means are row vectors ``(B, 1, n)`` (one matmul
    whether or not ``A`` is batched); every returned field is produced inside the loop (the
    cross-covariance ``P A^T``, the innovation and its covariance are intermediate results there
    anyway) and written straight into its output, so nothing of size ``B T`` is allocated beyond
    the results; no host synchronisation inside the loop. Returns ``None`` if some innovation
    covariance failed to factor (the caller then runs :func:`_run`, which adds jitter).
    """
    T, n, m = data.y.shape[-2], data.x0.shape[-1], data.y.shape[-1]
    batch = data.batch
    B = batch.numel()
    mean = data.x0.reshape(B, 1, n)
    P = data.P0.reshape(B, n, n)
    A = _per_step(steps.A, batch, B, 2) or []
    AT = [a.mT for a in A]
    Q = _per_step(steps.Q, batch, B, 2) or []
    H = _per_step(steps.H, batch, B, 2) or []
    HT = [h.mT for h in H]
    R = _per_step(steps.R, batch, B, 2) or []
    c = _per_step(None if steps.c is None else steps.c.unsqueeze(-2), batch, B, 2)
    d = _per_step(None if steps.d is None else steps.d.unsqueeze(-2), batch, B, 2)
    y = _per_step(data.y.unsqueeze(-2), batch, B, 2) or []
    o_rows, o_outer, o_unit = _masks_per_step(data, B)
    want_ll = "log_likelihood" in keep
    vector_ll = want_ll and B * T * m * m * data.y.element_size() < _VECTOR_LL_BYTES
    shapes = {
        "mean": (n,),
        "cov": (n, n),
        "predicted_mean": (n,),
        "predicted_cov": (n, n),
        "measurement_mean": (m,),
        "innovation": (m,),
        "innovation_cov": (m, m),
        "cross_cov": (n, n),
    }
    fields = [k for k in shapes if k in keep]
    if vector_ll:
        fields += ["_chol", "_residual"]
        shapes["_chol"], shapes["_residual"] = (m, m), (m,)
    lists: dict[str, list[Tensor]] = {k: [] for k in fields}
    bufs = {k: mean.new_empty(B, T, *shapes[k]) for k in fields} if inplace else {}
    ll_sum: Tensor | None = None
    infos: list[Tensor] = []
    sym = _drifts(P.dtype)
    # kalman_steps.predict / update written out rather than called: the means are row vectors
    # (one matmul over the batch for a shared A, where _mv broadcasts A to a batched product),
    # the masks are prepared once, the factor is not retried with jitter (a host synchronisation
    # per step; failures are checked once after the loop and the sequential runner takes over),
    # no symmetrization in float64 (see _drifts), and the fields are the loop's intermediate
    # results written in place.
    for t in range(T):
        cross = P @ AT[t]
        mp = mean @ AT[t]
        if c is not None:
            mp = mp + c[t]
        Pp = A[t] @ cross + Q[t]
        PHt = Pp @ HT[t]
        S = H[t] @ PHt + R[t]
        ym = mp @ HT[t]
        if d is not None:
            ym = ym + d[t]
        e = y[t] - ym
        out = {"innovation": e, "innovation_cov": S}
        if not data.complete:
            S = torch.addcmul(o_unit[t], S, o_outer[t])
            PHt = PHt * o_rows[t]
            e = e * o_rows[t]
        L, info = torch.linalg.cholesky_ex(S)
        KT = torch.cholesky_solve(PHt.mT, L)  # (B, m, n)
        mean = mp + e @ KT
        P = Pp - PHt @ KT
        if sym:
            P = symmetrize(P)
        infos.append(info)
        if want_ll and not vector_ll:
            dof = m if data.complete else o_rows[t].sum((-2, -1))
            term = gaussian_log_prob(e.squeeze(-2), L, dof, library=True)
            ll_sum = term if ll_sum is None else ll_sum + term
        out.update(
            mean=mean,
            cov=P,
            predicted_mean=mp,
            predicted_cov=Pp,
            measurement_mean=ym,
            cross_cov=cross,
            _chol=L,
            _residual=e,
        )
        for k in fields:
            v = out[k]
            if inplace:
                bufs[k][:, t].copy_(v.reshape(B, *shapes[k]))
            else:
                lists[k].append(v.reshape(B, 1, *shapes[k]))
    if bool(torch.stack(infos).any()):
        return None
    res = bufs if inplace else {k: torch.cat(v, 1) for k, v in lists.items()}
    if vector_ll:
        ll_sum = _vector_log_likelihood(data, res.pop("_residual"), res.pop("_chol"))
    if "innovation" in res:
        _nan_missing(data, res, inplace=inplace)
    final = {k: v.reshape(*batch, *v.shape[1:]) for k, v in res.items()}
    if ll_sum is not None:
        final["log_likelihood"] = ll_sum.reshape(batch)
    return final


#: the covariance recursion counts as converged when one step changes no entry by more than
#: this many ulps of the largest entry (from then on it only moves by rounding)
_STEADY_ULPS = 4.0
#: converged per-sequence covariances within this many ulps of each other count as one
_AGREE_ULPS = 64.0
#: the converged tail of the mean recursion runs as a doubling scan (about log2(T) batched
#: products instead of T small ones) while ``B n^2 log2(T)`` is at most this; above it the
#: scan's extra arithmetic costs more than the per-step overhead it saves
_DOUBLING_WORK = 4096


def _covariance_batch(data: Data, steps: LinearSteps) -> int | None:
    """How many covariance sequences the Riccati runner keeps: ``1`` when every sequence of the
    batch has the same covariances (all data observed, and ``P0``, ``A``, ``Q``, ``H``, ``R``
    without batch dimensions; ``x0``, ``y``, ``u`` may differ); the batch size when only ``P0``
    differs and the model is time-invariant (each sequence then converges to the same steady
    state, after which nothing changes); ``None`` when neither holds."""
    if not data.complete or not all(x.dim() == 3 for x in (steps.A, steps.Q, steps.H, steps.R)):
        return None
    if all(s == 0 for s in data.P0.stride()[:-2]):
        return 1
    if all(x.stride(-3) == 0 for x in (steps.A, steps.Q, steps.H, steps.R)):
        return data.batch.numel()
    return None


def _rows(x: Tensor, M: Tensor) -> Tensor:
    """Row vectors ``x (L, B, d)`` times ``M (L, Bc, d, e)`` with ``Bc`` 1 (shared) or ``B``."""
    if M.shape[1] == 1:
        return x @ M[:, 0]
    return (x.unsqueeze(-2) @ M).squeeze(-2)


def _rows_const(x: Tensor, M: Tensor) -> Tensor:
    """Row vectors ``x (L, B, d)`` times one ``M (Bc, d, e)`` for every step."""
    if M.shape[0] == 1:
        return x @ M[0]
    return (x.transpose(0, 1) @ M).transpose(0, 1)


def _affine_tail(x: Tensor, F: Tensor) -> None:
    """Solve ``x_t <- x_t + x_{t-1} F`` in place along dim 0 of ``x (L, B, n)`` for one
    ``F (Bc, n, n)``, by doubling: after the pass with offset ``s`` every ``x_t`` holds the sum
    over its last ``2 s`` terms, ``x_t + x_{t-s} F^s`` (Hillis-Steele; ``F^s`` by squaring)."""
    L = x.shape[0]
    power, s = F, 1
    while s < L:
        x[s:] += _rows_const(x[:-s], power)  # the right side is evaluated before the write
        s *= 2
        if s < L:
            power = power @ power


def _affine_head(x: Tensor, F: Tensor) -> None:
    """As :func:`_affine_tail` with one ``F_t (L, n, n)`` per step (shared by the batch): pass
    ``s`` adds ``x_{t-s} F_{t-s+1} ... F_t`` to ``x_t`` and doubles the products' span."""
    L = x.shape[0]
    span, s = F, 1
    while s < L:
        x[s:] += x[:-s] @ span[s:]
        if 2 * s < L:
            span = torch.cat([span[:s], span[:-s] @ span[s:]], 0)
        s *= 2


#: the Riccati runner's covariance fields by the name of their per-step value in its loop
_RICCATI_COVS = {"cov": "cov", "predicted_cov": "pcov", "cross_cov": "cross", "innovation_cov": "S"}


def _time_major(data: Data, steps: LinearSteps) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """``y_t - d_t``, ``c_t`` and ``d_t`` as ``(T, B, .)`` over the flattened batch."""
    batch, T = data.batch, data.y.shape[-2]
    B = batch.numel()

    def tmajor(x: Tensor) -> Tensor:  # (..., T, d) -> (T, B, d)
        d = x.shape[-1]
        return x.expand(*batch, T, d).reshape(B, T, d).transpose(0, 1)

    y_t = tmajor(data.y)
    d_t = None if steps.d is None else tmajor(steps.d)
    c_t = None if steps.c is None else tmajor(steps.c)
    return (y_t if d_t is None else y_t - d_t), c_t, d_t


def _riccati_records(
    keep: frozenset[str], P: Tensor, B: int, T: int, m: int, *, one: bool
) -> tuple[list[str], dict[str, Tensor]]:
    """What the Riccati loop records: a shared sequence records its per-step values (the names
    returned) and stacks them after the loop; one covariance per sequence writes the kept fields
    straight into their outputs ``(B, T, ., .)`` (the dict returned)."""
    n = P.shape[-1]
    names = ["KT", "L"] if one else ["L"]
    names += [name for field, name in _RICCATI_COVS.items() if field in keep] if one else []
    direct = {
        field: P.new_empty(B, T, *((m, m) if field == "innovation_cov" else (n, n)))
        for field in _RICCATI_COVS
        if field in keep and not one
    }
    return names, direct


def _head_factors(
    head: dict[str, Tensor], infos: list[Tensor], *, scalar: bool, late: bool
) -> bool:
    """The innovation factors of the Riccati head, taken after the loop where the loop only
    solved (``m = 1``: a square root; many small systems: one batched Cholesky); False if one
    failed. One host synchronisation for the whole run."""
    if scalar:
        if not bool((head["L"] > 0).all()):
            return False
        head["L"] = head["L"].sqrt()
    elif bool(torch.stack(infos).any()):
        return False
    elif late:
        head["L"], info = torch.linalg.cholesky_ex(head["L"])
        if bool(info.any()):
            return False
    return True


def _head_means(
    m_all: Tensor,
    innov_in: Tensor,
    c_t: Tensor | None,
    x0: Tensor,
    A_h: Tensor,
    H_h: Tensor,
    KT_h: Tensor,
) -> None:
    """The means of the head ``m_all[:k]`` when one covariance sequence serves the batch:
    ``m_t = m_{t-1} F_t + g_t`` with the shared ``F_t = A_t^T (I - H_t^T K_t^T)``. The pure
    :func:`~torchfilt.filters.kalman_steps.update` cannot be used here: it would redo the gain
    solve per sequence, whereas the gains of the shared covariance are already known for all
    steps and the recursion is affine (a doubling scan over ``k`` steps when the batch is small)."""
    k, B, n = KT_h.shape[0], m_all.shape[1], m_all.shape[2]
    eye = torch.eye(n, dtype=KT_h.dtype, device=KT_h.device)
    IKH = eye - H_h.mT @ KT_h
    m_all[:k] = innov_in[:k] @ KT_h
    if c_t is not None:
        m_all[:k] += c_t[:k] @ IKH
    F_h = A_h.mT @ IKH
    m_all[0].addmm_(x0, F_h[0])
    if B * n * n * math.log2(k + 1) <= _DOUBLING_WORK:
        _affine_head(m_all[:k], F_h)
    else:
        for t in range(1, k):
            m_all[t].addmm_(m_all[t - 1], F_h[t])


def _tail_means(
    m_all: Tensor,
    innov_in: Tensor,
    c_t: Tensor | None,
    KT_last: Tensor,
    P: Tensor,
    tol: float,
    AT: Tensor,
    HT: Tensor,
    k: int,
    *,
    one: bool,
) -> Tensor:
    """The means of the converged tail ``m_all[k:]``, where the gain repeats: the affine
    recursion with one constant ``F`` (a doubling scan when the batch is small, else one
    multiply-add per step), which no per-step update expresses. Per-sequence covariances that
    have all reached the same steady state (as they do for a time-invariant model) share one gain:
    one product per step for the batch. Returns the tail's gains ``(Bc', m, n)``."""
    T, B, n = m_all.shape
    KT_c = KT_last.unsqueeze(0) if one else KT_last  # (Bc', m, n)
    tol_agree = _AGREE_ULPS / _STEADY_ULPS * tol * P.abs().amax()
    if not one and bool((P - P[:1]).abs().amax() <= tol_agree):
        KT_c = KT_c[:1]
    eye = torch.eye(n, dtype=P.dtype, device=P.device)
    IKH_c = eye - HT @ KT_c
    F_c = AT @ IKH_c
    if KT_c.shape[0] == 1:
        torch.matmul(innov_in[k:], KT_c[0], out=m_all[k:])
    else:
        m_all[k:] = _rows_const(innov_in[k:], KT_c)
    if c_t is not None:
        m_all[k:] += _rows_const(c_t[k:], IKH_c)
    m_all[k] += _rows_const(m_all[k - 1 : k], F_c)[0]
    if B * n * n * math.log2(T - k + 1) <= _DOUBLING_WORK:
        _affine_tail(m_all[k:], F_c)
    elif F_c.shape[0] == 1:
        for t in range(k + 1, T):
            m_all[t].addmm_(m_all[t - 1], F_c[0])
    else:
        for t in range(k + 1, T):
            m_all[t].unsqueeze(1).baddbmm_(m_all[t - 1].unsqueeze(1), F_c)
    return KT_c


def _innovations(
    m_all: Tensor,
    x0: Tensor,
    innov_in: Tensor,
    c_t: Tensor | None,
    d_t: Tensor | None,
    A_all: Tensor,
    H_all: Tensor,
    *,
    predicted: bool,
) -> tuple[Tensor | None, Tensor | None, Tensor]:
    """Predicted means, measurement means (when ``predicted``) and innovations ``(T, B, .)`` of
    all steps at once from the filtered means (the predict step vectorised over time)."""
    T, B, n = m_all.shape

    def after_prev(M: Tensor) -> Tensor:
        """``x_{t-1} M_t`` for every step, ``x_{-1} = x0``: ``(T, B, M.shape[-1])``."""
        out = x0.new_empty(T, B, M.shape[-1])
        torch.matmul(x0, M if M.dim() == 2 else M[0], out=out[0])
        if M.dim() == 2:  # one product over the stacked rows
            torch.matmul(m_all[:-1].reshape(-1, n), M, out=out[1:].view(-1, M.shape[-1]))
        else:
            torch.matmul(m_all[:-1], M[1:], out=out[1:])
        return out

    mp = ym = None
    if predicted:
        mp = after_prev(A_all.mT)  # m^-_t = m_{t-1} A_t^T + c_t
        if c_t is not None:
            mp += c_t
        ym = mp @ H_all.mT
        e = innov_in - ym  # (T, B, m)
        if d_t is not None:
            ym += d_t
    else:  # straight to the innovations: e_t = (y_t - d_t) - m_{t-1} (H A)^T - c_t H^T
        e = after_prev(A_all.mT @ H_all.mT)
        if c_t is not None:
            e += c_t @ H_all.mT
        torch.sub(innov_in, e, out=e)
    return mp, ym, e


def _riccati_log_likelihood(e: Tensor, L_h: Tensor, L_c: Tensor | None, *, one: bool) -> Tensor:
    """The summed log-likelihood of innovations ``e (T, B, m)``: the head's factors
    ``L_h (k, [B,] m, m)`` per step, then the tail's one factor ``L_c (Bc', m, m)`` (or None)."""
    k = L_h.shape[0]
    ll = gaussian_log_prob(e[:k], L_h.unsqueeze(1) if one else L_h, library=True).sum(0)
    if L_c is None:
        return ll
    if L_c.shape[0] == 1:  # one factor for the batch: the innovations are its columns
        return ll + gaussian_log_prob(e[k:], L_c[0], library=True).sum(0)
    tail = gaussian_log_prob(e[k:].transpose(0, 1), L_c.unsqueeze(1), library=True)
    return ll + tail.sum(-1)


def _repeat_tail(x: Tensor, k: int, T: int, batch: torch.Size, *, one: bool) -> Tensor:
    """A covariance field over all ``T`` steps, its steps ``k ..`` repeating step ``k - 1``:
    from the shared head ``(k, d, d)`` (returned ``(T, d, d)``, for ``assemble`` to expand over
    the batch), or the per-sequence output ``(B, T, d, d)`` filled in place."""
    if one:
        whole = x.new_empty(T, *x.shape[1:])
        whole[:k] = x
        whole[k:] = x[-1]
        return whole
    x[:, k:] = x[:, k - 1 : k]
    return x.reshape(*batch, T, *x.shape[-2:])


def _run_riccati(
    data: Data, steps: LinearSteps, *, keep: frozenset[str], Bc: int
) -> dict[str, Tensor] | None:
    """The plain filter when the covariances do not depend on the measurements (see
    :func:`_covariance_batch`): the Riccati recursion runs on ``Bc`` covariance sequences (one
    for the whole batch, or one per sequence), and for a time-invariant model only until it has
    converged to rounding (``_STEADY_ULPS``), after which gains and covariances repeat.

    The means follow the affine recursion ``m_t = m_{t-1} F_t + g_t`` (row vectors,
    ``F_t = A_t^T (I - H_t^T K_t^T)``, ``g_t = (y_t - d_t) K_t^T + c_t (I - H_t^T K_t^T)``): while
    the gains change, one fused multiply-add per step (a shared sequence) or the predict and
    update inside the covariance loop (one covariance per sequence); for the converged tail a
    doubling scan when the batch is small (:func:`_affine_tail`), else one multiply-add per step.
    Shared covariance fields come back as ``(T, ., .)`` for ``assemble`` to expand over the batch.
    ``None`` if a factorisation failed."""
    T, n, m = data.y.shape[-2], data.x0.shape[-1], data.y.shape[-1]
    batch = data.batch
    B = batch.numel()
    invariant = all(x.stride(-3) == 0 for x in (steps.A, steps.Q, steps.H, steps.R))
    one = Bc == 1  # one shared sequence: 2-D matrices, fused multiply-adds
    P = data.P0.reshape(-1, n, n)[0] if one else data.P0.expand(*batch, n, n).reshape(B, n, n)
    tol = _STEADY_ULPS * torch.finfo(P.dtype).eps

    innov_in, c_t, d_t = _time_major(data, steps)
    x0 = data.x0.reshape(B, n)
    m_all = x0.new_empty(T, B, n)
    covs = _RICCATI_COVS
    names, direct = _riccati_records(keep, P, B, T, m, one=one)
    rec: dict[str, list[Tensor]] = {k: [] for k in names}
    KT_last = P.new_empty(0)
    infos: list[Tensor] = []
    scalar = m == 1
    late = not one and not scalar
    sym = _drifts(P.dtype)
    k = 0  # steps run
    A, Q, H, R = (x.select(-3, 0) for x in (steps.A, steps.Q, steps.H, steps.R))
    AT, HT = A.mT, H.mT
    # The covariance half of kalman_steps.predict / update, without their means: the pure steps
    # cannot be used because they couple the gain to one mean each (here one covariance serves
    # the batch, or the means are run afterwards as an affine recursion), factor with a jitter
    # retry (a host synchronisation per step; here failures are collected and checked once) and
    # symmetrize (two more operations per step, done here below float64 only: see _drifts); the
    # gain solve is batched by the system size.
    for t in range(T):
        if not invariant:
            A, Q, H, R = (x[t] for x in (steps.A, steps.Q, steps.H, steps.R))
            AT, HT = A.mT, H.mT
        cross = P @ AT
        Pp = torch.addmm(Q, A, cross) if one else A @ cross + Q
        PHt = Pp @ HT
        if one:
            S = torch.addmm(R, H, PHt)
        else:  # S^T = PHt^T H^T as one product over the stacked rows (S is symmetric)
            S = (PHt.mT.reshape(-1, n) @ HT).view(-1, m, m) + R
        if scalar:  # m = 1: the gain is a division; the factor is taken after the loop
            KT = PHt.mT / S
        elif late:  # many small systems: one LU solve; the factors are taken after the loop
            KT, info = torch.linalg.solve_ex(S, PHt.mT)
            infos.append(info)
        else:
            L, info = torch.linalg.cholesky_ex(S)
            KT = torch.cholesky_solve(PHt.mT, L)
            infos.append(info)
        P_new = torch.addmm(Pp, PHt, KT, alpha=-1) if one else Pp - PHt @ KT
        if sym:  # below float64 the unsymmetrized recursion drifts off the Riccati solution
            P_new = symmetrize(P_new)
        if not one:  # the means' predict and update with this step's per-sequence gains
            prev = x0 if t == 0 else m_all[t - 1]
            mp_t = prev @ AT if c_t is None else torch.addmm(c_t[t], prev, AT)
            r = torch.addmm(innov_in[t], mp_t, HT, alpha=-1)
            torch.baddbmm(mp_t.unsqueeze(1), r.unsqueeze(1), KT, out=m_all[t].unsqueeze(1))
        now = {
            "KT": KT,
            "L": S if scalar or late else L,
            "cov": P_new,
            "pcov": Pp,
            "cross": cross,
            "S": S,
        }
        for name in names:
            rec[name].append(now[name])
        for field, buf in direct.items():
            buf[:, t] = now[covs[field]]
        KT_last = KT
        k += 1
        # converged: checked every 4th step (steps past convergence only repeat by rounding)
        done = invariant and t >= 2 and t % 4 == 3
        if done and bool((P_new - P).abs().amax() <= tol * P_new.abs().amax()):
            P = P_new
            break
        P = P_new
    # steps k .. T-1 repeat step k-1
    head = {name: torch.stack(vals, 0) for name, vals in rec.items()}  # (k, [B,] ., .)
    if not _head_factors(head, infos, scalar=scalar, late=late):
        return None
    if one:  # the head: m_t = m_{t-1} F_t + g_t with the shared F_t
        _head_means(m_all, innov_in, c_t, x0, steps.A[:k], steps.H[:k], head["KT"])
    if k < T:
        KT_c = _tail_means(m_all, innov_in, c_t, KT_last, P, tol, AT, HT, k, one=one)
        L_c = head["L"][-1:] if one else head["L"][-1][: KT_c.shape[0]]  # (Bc', m, m)
    # (T, ., .) per-step matrices, or one (., .) for a time-invariant model (then the loop's)
    A_all, H_all = (AT.mT, HT.mT) if invariant else (steps.A, steps.H)
    want_pred = "predicted_mean" in keep or "measurement_mean" in keep
    mp, ym, e = _innovations(m_all, x0, innov_in, c_t, d_t, A_all, H_all, predicted=want_pred)
    # log-likelihood: whitened innovations, per step while the gains change, then one factor
    ll = _riccati_log_likelihood(e, head["L"], L_c if k < T else None, one=one)
    res = {"log_likelihood": ll.reshape(batch)}
    means = {"mean": m_all, "predicted_mean": mp, "measurement_mean": ym, "innovation": e}
    for name, v in means.items():
        if v is not None and (name == "mean" or name in keep):
            res[name] = v.transpose(0, 1).reshape(*batch, T, v.shape[-1])
    for field, name in covs.items():
        if field in keep:
            res[field] = _repeat_tail(head[name] if one else direct[field], k, T, batch, one=one)
    return res


def linear_facts(
    data: Data, steps: LinearSteps, keep: frozenset[str]
) -> tuple[int | None, int, bool]:
    """What the plan needs of a checked recording: the Riccati runner's covariance batch (or
    None), the bytes of the kept results, and whether the log-likelihood is the only per-step
    result kept."""
    only = "log_likelihood" in keep and keep <= {"log_likelihood", "observed"}
    return _covariance_batch(data, steps), _result_bytes(data, keep), only


def _riccati(
    data: Data, steps: LinearSteps, keep: frozenset[str], plan: ExecutionPlan
) -> dict[str, Tensor] | None:
    Bc = _covariance_batch(data, steps)
    return None if Bc is None else _run_riccati(data, steps, keep=keep, Bc=Bc)


def _fast(
    data: Data, steps: LinearSteps, keep: frozenset[str], plan: ExecutionPlan
) -> dict[str, Tensor] | None:
    return _run_fast(data, steps, keep=keep, inplace=plan.inplace)


def _sequential(
    data: Data, steps: LinearSteps, keep: frozenset[str], plan: ExecutionPlan
) -> dict[str, Tensor] | None:
    return _run(data, steps, sqrt=plan.sqrt, keep=keep, inplace=not plan.records_grad)


#: the sequential runners by the plan's ``execution``; each returns the kept outputs, or None
#: when a factorisation failed (the caller then plans again without it)
_RUNNERS: dict[
    str, Callable[[Data, LinearSteps, frozenset[str], ExecutionPlan], dict[str, Tensor] | None]
]
_RUNNERS = {"kalman-riccati": _riccati, "kalman-fast": _fast, "kalman-sequential": _sequential}


def run_exact(
    data: Data, steps: LinearSteps, keep: frozenset[str], plan: ExecutionPlan
) -> dict[str, Tensor] | None:
    """Run the sequential exact runner the plan names; None if its factorisation failed."""
    return _RUNNERS[plan.execution](data, steps, keep, plan)
