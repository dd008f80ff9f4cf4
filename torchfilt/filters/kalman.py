"""The closed-form Kalman filter and Rauch-Tung-Striebel smoother for linear-Gaussian models.

    x_t = A_t x_{t-1} + c_t + w_t,   w_t ~ N(0, Q_t),   c_t = B u_t
    y_t = H_t x_t + d_t + v_t,       v_t ~ N(0, R_t),   d_t = D u_t

    predict:  m^-_t = A_t m_{t-1} + c_t,   P^-_t = A_t P_{t-1} A_t^T + Q_t
    update:   S_t = H_t P^-_t H_t^T + R_t,  K_t = P^-_t H_t^T S_t^{-1} (Cholesky solve),
              m_t = m^-_t + K_t (y_t - H_t m^-_t - d_t),   P_t = P^-_t - K_t S_t K_t^T
    smooth:   G_t = P_t A_{t+1}^T (P^-_{t+1})^{-1},  m^s_t = m_t + G_t (m^s_{t+1} - m^-_{t+1}),
              P^s_t = P_t + G_t (P^s_{t+1} - P^-_{t+1}) G_t^T

(Särkkä & Svensson 2023, thms 6.6 and 12.2.) The square-root form propagates lower Cholesky
factors: the prediction triangularises ``[A S, Q^{1/2}]``, the update triangularises the array
``[[R^{1/2}, H S^-], [0, S^-]]`` into ``[[S^{1/2}, 0], [K S^{1/2}, S]]`` (Grewal & Andrews 2015,
ch. 6), and the smoother ``[(I - G A) S, G Q^{1/2}, G S^s]``.

A missing component (NaN in ``y`` or ``mask`` False) is dropped exactly as the cubature filter
drops it: its row of ``H`` and row and column of ``S`` are left out of the gain and the
log-likelihood. These functions are the exact path that :class:`~torchfilt.filters.GaussianFilter`
takes for a model that :func:`~torchfilt.models.linear_system` recognises as linear.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.filters.inputs import broadcast_batch, check_prior, observed
from torchfilt.filters.linear_data import Data, LinearSteps, SmootherElements
from torchfilt.filters.results import (
    FilterResult,
    KalmanFilterResult,
    ParallelFilterResult,
    SmootherResult,
)
from torchfilt.models import LinearSystem, StateSpaceModel, linear_system
from torchfilt.numerics import cholesky_solve, safe_cholesky, solve_tril, symmetrize, tria

__all__ = [
    "Belief",
    "LinearSteps",
    "kalman_filter",
    "kalman_smoother",
    "linear_steps",
    "predict",
    "predict_sqrt",
    "select_path",
    "update",
    "update_sqrt",
]

_LOG_2PI = math.log(2.0 * math.pi)
#: The tensor fields of a filter result (``numerics`` describes the run, it is not a tensor).
FIELDS = tuple(f for f in FilterResult._fields if f != "numerics")
Path = Literal["auto", "cubature", "kalman"]


class Belief(NamedTuple):
    """A Gaussian belief ``N(mean, cov)``.

    Attributes:
        mean: ``(..., n)``.
        cov: the covariance ``(..., n, n)``, or in the square-root functions its lower Cholesky
            factor.
    """

    mean: Tensor
    cov: Tensor


# ---------------------------------------------------------------------------------- pure steps
def _mv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` for ``M (..., a, b)``, ``v (..., b)`` with broadcasting batch dimensions."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def predict(belief: Belief, A: Tensor, c: Tensor | None, Q: Tensor) -> tuple[Belief, Tensor]:
    """Kalman prediction.

    Args:
        belief: ``N(m, P)`` of ``x_{t-1}``, ``(..., n)`` and ``(..., n, n)``.
        A: ``(..., n, n)``.  c: offset ``(..., n)`` or ``None``.  Q: ``(..., n, n)``.

    Returns:
        The predicted belief of ``x_t`` and the cross-covariance ``Cov(x_{t-1}, x_t) = P A^T``.
    """
    m, P = belief
    mp = _mv(A, m)
    if c is not None:
        mp = mp + c
    cross = P @ A.mT
    return Belief(mp, symmetrize(A @ cross + Q)), cross


def predict_sqrt(belief: Belief, A: Tensor, c: Tensor | None, Q_sqrt: Tensor) -> Belief:
    """Square-root Kalman prediction: ``S^- = tria([A S, Q^{1/2}])``.

    Args:
        belief: mean ``(..., n)`` and lower Cholesky factor ``S (..., n, n)``.
        A: ``(..., n, n)``.  c: ``(..., n)`` or ``None``.  Q_sqrt: ``(..., n, n)``.
    """
    m, S = belief
    mp = _mv(A, m)
    if c is not None:
        mp = mp + c
    AS = A @ S
    batch = torch.broadcast_shapes(AS.shape[:-2], Q_sqrt.shape[:-2])
    return Belief(
        mp,
        tria(
            torch.cat(
                [AS.expand(*batch, *AS.shape[-2:]), Q_sqrt.expand(*batch, *Q_sqrt.shape[-2:])], -1
            )
        ),
    )


class Update(NamedTuple):
    """An update's belief and the factor of its innovation covariance.

    Attributes:
        belief: ``N(m_t, P_t)`` (square-root form: ``S_t``).
        innov_chol: lower Cholesky factor of ``S_t`` restricted to the observed components (unit
            rows and columns for the others), ``(..., m, m)``.
        residual: ``y - H m^- - d`` with zeros where not observed, ``(..., m)``.
    """

    belief: Belief
    innov_chol: Tensor
    residual: Tensor


def update(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
) -> Update:
    """Kalman update with missing components.

    Args:
        belief: predicted ``N(m^-, P^-)``, ``(..., n)`` and ``(..., n, n)``.
        y: measurement ``(..., m)`` (any value where not observed).
        obs: bool ``(..., m)``, ``True`` where observed, or ``None`` for all observed.
        H: ``(..., m, n)``.  d: offset ``(..., m)`` or ``None``.  R: ``(..., m, m)``.
    """
    mp, Pp = belief
    PHt = Pp @ H.mT  # (..., n, m)
    S = H @ PHt + R
    yp = _mv(H, mp)
    if d is not None:
        yp = yp + d
    e = y - yp
    if obs is not None:
        o = obs.to(mp.dtype)
        S = S * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
        PHt = PHt * o.unsqueeze(-2)
        e = e * o
    L = safe_cholesky(S, name="innovation covariance")
    K = cholesky_solve(PHt.mT, L).mT  # (..., n, m)
    m = mp + _mv(K, e)
    P = symmetrize(Pp - K @ PHt.mT)
    return Update(Belief(m, P), L, e)


def update_sqrt(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    H: Tensor,
    d: Tensor | None,
    R_sqrt: Tensor,
) -> Update:
    """Square-root Kalman update by one triangularisation of the array
    ``[[R^{1/2}, H S^-], [0, S^-]]`` (missing rows zeroed, with a unit column each).

    Args as in :func:`update`, with ``belief.cov`` the predicted factor ``S^- (..., n, n)`` and
    ``R_sqrt (..., m, m)`` a square root of ``R``.
    """
    mp, Sp = belief
    n, m = Sp.shape[-1], H.shape[-2]
    HS = H @ Sp
    yp = _mv(H, mp)
    if d is not None:
        yp = yp + d
    e = y - yp
    batch = torch.broadcast_shapes(HS.shape[:-2], R_sqrt.shape[:-2], Sp.shape[:-2])
    top = [R_sqrt.expand(*batch, m, m), HS.expand(*batch, m, n)]
    bottom = [Sp.new_zeros(()).expand(*batch, n, m), Sp.expand(*batch, n, n)]
    if obs is not None:
        o = obs.to(mp.dtype)
        rows = o.unsqueeze(-1)
        top = [top[0] * rows, torch.diag_embed(1.0 - o).expand(*batch, m, m), top[1] * rows]
        bottom = [bottom[0], bottom[0], bottom[1]]
        e = e * o
    post = tria(torch.cat([torch.cat(top, -1), torch.cat(bottom, -1)], -2))
    L = post[..., :m, :m]
    Kb = post[..., m:, :m]  # K L
    S = post[..., m:, m:]
    z = solve_tril(L, e.unsqueeze(-1)).squeeze(-1)
    return Update(Belief(mp + _mv(Kb, z), S), L, e)


# ---------------------------------------------------------------------------------- inputs
def _psd_sqrt(A: Tensor) -> Tensor:
    """A square root of PSD matrices: Cholesky where definite, else the eigen-decomposition."""
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info == 0).all()):
        return L
    evals, evecs = torch.linalg.eigh(symmetrize(A))
    return evecs * evals.clamp_min(0.0).sqrt().unsqueeze(-2)


def noise_steps(side: torch.nn.Module, name: str, T: int, d: int, like: Tensor) -> Tensor:
    """A model side's noise as ``(..., T, d, d)`` (an expanded view when constant)."""
    if side.time_varying_noise:
        try:
            noise = torch.stack([side.noise_cov(t) for t in range(T)], -3)  # type: ignore[operator]
        except IndexError:
            raise ShapeError(
                f"{name}: the time-varying noise has fewer than T = {T} steps"
            ) from None
    else:
        noise = side.noise_cov()  # type: ignore[operator]
        if noise is None:
            noise = like.new_zeros(d, d)
        noise = noise.unsqueeze(-3).expand(*noise.shape[:-2], T, d, d)
    return noise.to(dtype=like.dtype, device=like.device)


def _check(
    model: StateSpaceModel,
    system: LinearSystem | None,
    y: Tensor,
    u: Tensor | None,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None,
) -> tuple[Data, LinearSteps, Tensor | None]:
    n, m = model.state_dim, model.obs_dim
    if not isinstance(y, Tensor):
        raise InputTypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
    if y.dim() < 2 or y.shape[-1] != m:
        raise ShapeError(f"y: expected shape (..., T, m) with m = {m}, got {tuple(y.shape)}")
    if not y.is_floating_point():
        raise InputTypeError(f"y must be floating point, got {y.dtype}")
    T = y.shape[-2]
    if T == 0:
        raise ShapeError("y: the time dimension T must be at least 1")
    device = y.device
    x0 = torch.as_tensor(x0, device=device)
    P0 = torch.as_tensor(P0, device=device)
    dtype = y.dtype
    for t in (x0, P0):
        if t.is_floating_point():
            dtype = torch.promote_types(dtype, t.dtype)
    y, x0, P0 = y.to(dtype), x0.to(dtype), P0.to(dtype)
    check_prior(x0, P0, n)
    obs = observed(y, mask)
    shapes = {"y": y.shape[:-2], "x0": x0.shape[:-1], "P0": P0.shape[:-2]}
    shapes_params: dict[str, torch.Size] = {}
    c = d = None
    uses_u = system is None or system.B is not None or system.D is not None
    if system is not None and uses_u and u is None:
        raise InputError("u: the model has an input matrix (B or D); pass the inputs u")
    if u is not None and uses_u:
        u = torch.as_tensor(u, device=device).to(dtype)
        if u.dim() < 2 or u.shape[-2] != T:
            raise ShapeError(f"u: expected shape (..., T, nu) with T = {T}, got {tuple(u.shape)}")
        if not bool(torch.isfinite(u).all()):
            raise InputError("u contains non-finite entries; inputs cannot be missing")
        shapes["u"] = u.shape[:-2]
        for name, M in () if system is None else (("B", system.B), ("D", system.D)):
            if M is None:
                continue
            M = M.to(dtype=dtype, device=device)
            if M.shape[-1] != u.shape[-1]:
                raise ShapeError(
                    f"u: expected shape (..., nu) with nu = {M.shape[-1]} for the "
                    f"{'transition' if name == 'B' else 'measurement'}'s input matrix, got "
                    f"{tuple(u.shape)}"
                )
            shapes_params[name] = M.shape[:-2]
            off = (M.unsqueeze(-3) @ u.unsqueeze(-1)).squeeze(-1)  # (..., T, rows)
            if name == "B":
                c = off
            else:
                d = off
    shapes["mask"] = obs.shape[:-2]
    Q = noise_steps(model.transition, "Q", T, n, y)
    R = noise_steps(model.measurement, "R", T, m, y)
    shapes["Q"], shapes["R"] = Q.shape[:-3], R.shape[:-3]
    if system is not None:
        A = system.A.to(dtype=dtype, device=device)
        H = system.H.to(dtype=dtype, device=device)
        shapes["A"], shapes["H"] = A.shape[:-2], H.shape[:-2]
    else:  # placeholders: the caller linearises the model itself
        A, H = y.new_zeros(n, n), y.new_zeros(m, n)
    shapes.update(shapes_params)
    batch = broadcast_batch(shapes)
    complete = bool(obs.all())
    if not complete or obs.shape != y.shape:  # else nothing to zero: skip the copy
        y = torch.where(obs, y, torch.zeros((), dtype=dtype, device=device))
    steps = LinearSteps(
        A=A.unsqueeze(-3).expand(*A.shape[:-2], T, n, n),
        c=c,
        Q=Q,
        H=H.unsqueeze(-3).expand(*H.shape[:-2], T, m, n),
        d=d,
        R=R,
    )
    data = Data(y, obs, x0.expand(*batch, n), P0.expand(*batch, n, n), batch, complete)
    return data, steps, u


def check_inputs(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None = None,
) -> tuple[Data, Tensor, Tensor, Tensor | None]:
    """Check the inputs of any model: the data, the noise ``Q (..., T, n, n)`` and
    ``R (..., T, m, m)`` (expanded views when constant) and the inputs ``u (..., T, nu)``."""
    data, steps, u = _check(model, None, y, u, x0, P0, mask)
    return data, steps.Q, steps.R, u


def linear_steps(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None = None,
) -> tuple[Data, LinearSteps]:
    """Check the inputs of a linear model and lay out its per-step parameters.

    Raises:
        ModelError: ``model`` is not linear (see :func:`~torchfilt.models.linear_system`).
    """
    system = linear_system(model)
    if system is None:
        raise ModelError(
            f"{type(model).__name__} is not a linear-Gaussian model: the exact Kalman path needs "
            "a LinearGaussianModel or a model with a linear_system() method"
        )
    data, steps, _ = _check(model, system, y, u, x0, P0, mask)
    return data, steps


# ---------------------------------------------------------------------------------- filter
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
            term = _log_prob(up.residual, up.innov_chol, dof)
            ll_sum = term if ll_sum is None else ll_sum + term
    out = {k: v.value() for k, v in store.items()}
    if ll_sum is not None:
        out["log_likelihood"] = ll_sum
    if sqrt:
        for name in ("cov", "predicted_cov"):
            if name in out:
                out[name] = out[name] @ out[name].mT
    return out


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
    o_rows: list[Tensor] = []
    o_outer: list[Tensor] = []
    o_unit: list[Tensor] = []
    if not data.complete:
        o = data.obs.to(data.y.dtype).unsqueeze(-2)  # (..., T, 1, m)
        o_rows = _per_step(o, batch, B, 2) or []
        o_outer = _per_step(o.mT * o, batch, B, 2) or []
        o_unit = _per_step(torch.diag_embed(1.0 - o.squeeze(-2)), batch, B, 2) or []
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
        infos.append(info)
        if want_ll and not vector_ll:
            z = torch.linalg.solve_triangular(L, e.mT, upper=False)
            dof = m if data.complete else o_rows[t].sum((-2, -1))
            term = -0.5 * (
                (z * z).sum((-2, -1))
                + 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
                + dof * _LOG_2PI
            )
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
        e_all, L_all = res.pop("_residual"), res.pop("_chol")
        dof_all = m if data.complete else data.obs.to(e_all.dtype).sum(-1).reshape(B, T)
        z_all = torch.linalg.solve_triangular(L_all, e_all.unsqueeze(-1), upper=False)
        ll_sum = -0.5 * (
            (z_all * z_all).sum((-2, -1))
            + 2.0 * L_all.diagonal(dim1=-2, dim2=-1).log().sum(-1)
            + dof_all * _LOG_2PI
        ).sum(-1)
    if "innovation" in res:
        missing = ~data.obs.expand(*batch, T, m).reshape(B, T, m)
        if inplace:
            res["innovation"].masked_fill_(missing, float("nan"))
        else:
            res["innovation"] = res["innovation"].masked_fill(missing, float("nan"))
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

    def tmajor(x: Tensor, d: int) -> Tensor:  # (..., T, d) -> (T, B, d)
        return x.expand(*batch, T, d).reshape(B, T, d).transpose(0, 1)

    y_t = tmajor(data.y, m)
    d_t = None if steps.d is None else tmajor(steps.d, m)
    innov_in = y_t if d_t is None else y_t - d_t  # y_t - d_t
    c_t = None if steps.c is None else tmajor(steps.c, n)
    x0 = data.x0.reshape(B, n)
    m_all = x0.new_empty(T, B, n)
    covs = {"cov": "cov", "predicted_cov": "pcov", "cross_cov": "cross", "innovation_cov": "S"}
    # a shared sequence records its per-step values and stacks them after the loop; one
    # covariance per sequence writes the kept ones straight into their outputs (B, T, ., .)
    names = ["KT", "L"] if one else ["L"]
    names += [name for field, name in covs.items() if field in keep] if one else []
    rec: dict[str, list[Tensor]] = {k: [] for k in names}
    direct = {
        field: P.new_empty(B, T, *((m, m) if field == "innovation_cov" else (n, n)))
        for field in covs
        if field in keep and not one
    }
    KT_last = P.new_empty(0)
    infos: list[Tensor] = []
    scalar = m == 1
    late = not one and not scalar
    k = 0  # steps run
    A, Q, H, R = (x.select(-3, 0) for x in (steps.A, steps.Q, steps.H, steps.R))
    AT, HT = A.mT, H.mT
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
    if scalar:
        if not bool((head["L"] > 0).all()):
            return None
        head["L"] = head["L"].sqrt()
    elif bool(torch.stack(infos).any()):
        return None
    elif late:
        head["L"], info = torch.linalg.cholesky_ex(head["L"])
        if bool(info.any()):
            return None
    eye = torch.eye(n, dtype=P.dtype, device=P.device)
    if one:  # the head: m_t = m_{t-1} F_t + g_t with the shared F_t
        A_h, H_h, KT_h = steps.A[:k], steps.H[:k], head["KT"]
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
    if k < T:
        # per-sequence covariances that have all reached the same steady state (as they do for
        # a time-invariant model) share one gain in the tail: one product per step for the batch
        KT_c = KT_last.unsqueeze(0) if one else KT_last  # (Bc', m, n)
        tol_agree = _AGREE_ULPS / _STEADY_ULPS * tol * P.abs().amax()
        if not one and bool((P - P[:1]).abs().amax() <= tol_agree):
            KT_c = KT_c[:1]
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
        L_c = head["L"][-1:] if one else head["L"][-1][: KT_c.shape[0]]  # (Bc', m, m)
    # (T, ., .) per-step matrices, or one (., .) for a time-invariant model (then the loop's)
    A_all, H_all = (AT.mT, HT.mT) if invariant else (steps.A, steps.H)

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
    if "predicted_mean" in keep or "measurement_mean" in keep:
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
    # log-likelihood: whitened innovations, per step while the gains change, then one factor
    L_h = head["L"]  # (k, [B,] m, m)
    if one:
        z_h = torch.linalg.solve_triangular(L_h, e[:k].mT, upper=False)  # (k, m, B)
        sq = z_h.square_().sum((0, 1))
    else:
        z_h = torch.linalg.solve_triangular(L_h, e[:k].unsqueeze(-1), upper=False)
        sq = z_h.square_().sum((0, 2, 3))
    logdet = 2.0 * L_h.diagonal(dim1=-2, dim2=-1).log().sum((0, -1))  # () or (B,)
    if k < T:
        if L_c.shape[0] == 1:
            z_c = torch.linalg.solve_triangular(L_c[0], e[k:].reshape(-1, m).mT, upper=False)
            sq = sq + z_c.square_().reshape(m, T - k, B).sum((0, 1))
        else:
            z_c = torch.linalg.solve_triangular(L_c, e[k:].permute(1, 2, 0), upper=False)
            sq = sq + z_c.square_().sum((1, 2))
        logdet = logdet + (T - k) * 2.0 * L_c.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    ll = -0.5 * (sq + logdet + T * m * _LOG_2PI)
    res = {"log_likelihood": ll.reshape(batch)}
    means = {"mean": m_all, "predicted_mean": mp, "measurement_mean": ym, "innovation": e}
    for name, v in means.items():
        if v is not None and (name == "mean" or name in keep):
            res[name] = v.transpose(0, 1).reshape(*batch, T, v.shape[-1])
    for field, name in covs.items():
        if field not in keep:
            continue
        if one:
            h = head[name]  # (k, d, d)
            whole = h.new_empty(T, *h.shape[1:])
            whole[:k] = h
            whole[k:] = h[-1]
            res[field] = whole  # shared: assemble expands it over the batch
        else:
            whole = direct[field]
            whole[:, k:] = whole[:, k - 1 : k]
            res[field] = whole.reshape(*batch, T, *whole.shape[-2:])
    return res


def _psd_sqrt_steps(X: Tensor) -> Tensor:
    """Square roots of ``(..., T, d, d)``; one factorisation when ``X`` is an expanded constant."""
    if X.stride(-3) == 0:
        base = _psd_sqrt(X.select(-3, 0))
        return base.unsqueeze(-3).expand(X.shape)
    return _psd_sqrt(X)


def _log_prob(e: Tensor, L: Tensor, k: Tensor | int) -> Tensor:
    """``log N(e; 0, L L^T)`` counting ``k`` dimensions."""
    z = solve_tril(L, e.unsqueeze(-1)).squeeze(-1)
    logdet = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return -0.5 * ((z * z).sum(-1) + logdet + k * _LOG_2PI)


def measurement_terms(
    data: Data, steps: LinearSteps, m_pred: Tensor, P_pred: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Predicted measurements, innovations (NaN where missing), innovation covariances and the
    log-likelihood, all at once from the predicted moments ``(..., T, n)``, ``(..., T, n, n)``."""
    H = steps.H
    y_mean = _mv(H, m_pred)
    if steps.d is not None:
        y_mean = y_mean + steps.d
    S = symmetrize(H @ P_pred @ H.mT + steps.R)
    e = data.y - y_mean
    if data.complete:
        L = safe_cholesky(S, name="innovation covariance")
        ll = _log_prob(e, L, e.shape[-1]).sum(-1)
    else:
        o = data.obs.to(S.dtype)
        Sm = S * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
        L = safe_cholesky(Sm, name="innovation covariance")
        ll = _log_prob(e * o, L, o.sum(-1)).sum(-1)
    innovation = torch.where(data.obs, e, torch.full_like(e, float("nan")))
    return y_mean, innovation, S, ll


def shifted(first: Tensor, x: Tensor, dim: int) -> Tensor:
    """``[first, x_0, ..., x_{T-2}]`` along the time axis ``dim`` of ``x``."""
    at = x.dim() + dim
    head = first.unsqueeze(at).expand(*x.shape[:at], 1, *x.shape[at + 1 :])
    return torch.cat([head, x.narrow(at, 0, x.shape[at] - 1)], dim=at)


def assemble(
    data: Data,
    steps: LinearSteps,
    out: dict[str, Tensor],
    keep: frozenset[str],
    cls: type[FilterResult],
) -> FilterResult:
    """Fill a result from the recursion's outputs, deriving the measurement terms and
    cross-covariances; fields not in ``keep`` are empty tensors."""
    res = dict(out)
    if "cross_cov" in keep and "cross_cov" not in out:
        P_prev = shifted(data.P0, out["cov"], -3)
        res["cross_cov"] = P_prev @ steps.A.mT
    if ({"measurement_mean", "innovation", "innovation_cov"} & keep) - set(out) or (
        "log_likelihood" in keep and "log_likelihood" not in out
    ):
        y_mean, innov, S, ll = measurement_terms(
            data, steps, out["predicted_mean"], out["predicted_cov"]
        )
        res.update(measurement_mean=y_mean, innovation=innov, innovation_cov=S)
        res.setdefault("log_likelihood", ll)
    batch, T = data.batch, data.y.shape[-2]
    res["observed"] = data.obs.expand(*batch, *data.obs.shape[-2:])
    empty = data.x0.new_empty(0)
    fields = {}
    for k in FIELDS:
        if k not in keep:
            fields[k] = empty
            continue
        v = res[k]
        if k not in ("observed", "log_likelihood"):
            tail = 2 if k.endswith("cov") else 1
            v = v.expand(*batch, T, *v.shape[v.dim() - tail :])
        fields[k] = v
    return cls(**fields)  # type: ignore[arg-type]


def _keep(outputs: Collection[str] | None) -> frozenset[str]:
    if outputs is None:
        return frozenset(FIELDS)
    if isinstance(outputs, str):
        raise InputError(
            f"outputs: expected a collection of field names, got the string {outputs!r}"
        )
    bad = sorted(set(outputs) - set(FIELDS))
    if bad:
        raise InputError(f"outputs: unknown fields {bad}; choose from {list(FIELDS)}")
    return frozenset(outputs)


def kalman_filter(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None = None,
    sqrt: bool = False,
    parallel: bool = False,
    outputs: Collection[str] | None = None,
) -> FilterResult:
    """The closed-form Kalman filter of a linear-Gaussian model (see the module docstring).

    Step ``t`` predicts from ``x_{t-1}`` with ``u[..., t, :]`` (the prior ``N(x0, P0)`` is
    ``x_{-1}``) and updates with ``y[..., t, :]``, as :meth:`GaussianFilter.filter
    <torchfilt.filters.GaussianFilter.filter>` does.

    Args:
        model: a linear model (:func:`~torchfilt.models.linear_system` returns its matrices).
            ``A, H, B, D`` and the noise may carry batch dimensions; the noise may be
            :class:`~torchfilt.models.TimeVarying`.
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)``; required when the model has ``B`` or ``D``.
        x0: prior mean ``(..., n)``.  P0: prior covariance ``(..., n, n)``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component as missing.
        sqrt: propagate Cholesky factors (square-root filter).
        parallel: run the parallel-in-time filter (associative scan,
            :mod:`torchfilt.filters.parallel`) instead of the sequential recursion.
        outputs: names of the :class:`~torchfilt.filters.FilterResult` fields to return, e.g.
            ``("mean", "log_likelihood")``; the others are empty tensors (shape ``(0,)``) and are
            not stored, which bounds the memory by what is asked for. Default: all.

    Returns:
        A :class:`~torchfilt.filters.KalmanFilterResult` (``path == "kalman"``) or, with
        ``parallel=True``, a :class:`~torchfilt.filters.ParallelFilterResult`
        (``path == "parallel"``); the log-likelihood is differentiable with respect to the model's
        parameters.
    """
    keep = _keep(outputs)
    data, steps = linear_steps(model, y, u, x0=x0, P0=P0, mask=mask)
    return filter_steps(data, steps, sqrt=sqrt, parallel=parallel, keep=keep)


def select_outputs(res: FilterResult, outputs: Collection[str] | None) -> FilterResult:
    """``res`` with the fields not named in ``outputs`` replaced by empty tensors."""
    if outputs is None:
        return res
    keep = _keep(outputs)
    empty = res.mean.new_empty(0)
    return res._replace(**{k: empty for k in FIELDS if k not in keep})  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------- smoother
def smoother_elements(res: FilterResult, steps: LinearSteps) -> SmootherElements:
    """The smoother gains and offsets, all at once from a filter result."""
    m, P, mp, Pp = res.mean, res.cov, res.predicted_mean, res.predicted_cov
    n = m.shape[-1]
    A1 = steps.A[..., 1:, :, :]
    P_now = P[..., :-1, :, :]
    Pp1 = Pp[..., 1:, :, :]
    C = P_now @ A1.mT  # Cov(x_t, x_{t+1} | y_{1:t})
    G = cholesky_solve(C.mT, safe_cholesky(Pp1, name="predicted covariance")).mT
    g = m[..., :-1, :] - _mv(G, mp[..., 1:, :])
    L = symmetrize(P_now - G @ Pp1 @ G.mT)
    E = torch.cat([G, G.new_zeros(()).expand(*G.shape[:-3], 1, n, n)], -3)
    g = torch.cat([g, m[..., -1:, :]], -2)
    L = torch.cat([L, P[..., -1:, :, :]], -3)
    return SmootherElements(E, g, L)


def kalman_smoother(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None = None,
    sqrt: bool = False,
    parallel: bool = False,
) -> SmootherResult:
    """The closed-form Kalman filter followed by the Rauch-Tung-Striebel smoother.

    Arguments as in :func:`kalman_filter`. With ``sqrt=True`` the backward pass propagates
    Cholesky factors, ``S^s_t = tria([(I - G_t A_{t+1}) S_t, G_t Q_{t+1}^{1/2}, G_t S^s_{t+1}])``;
    with ``parallel=True`` both passes are associative scans.

    Returns:
        A :class:`~torchfilt.filters.SmootherResult` with means ``(..., T, n)``, covariances
        ``(..., T, n, n)`` and gains ``(..., T-1, n, n)``; ``result.path`` says which path ran.
    """
    data, steps = linear_steps(model, y, u, x0=x0, P0=P0, mask=mask)
    return smooth_steps(data, steps, sqrt=sqrt, parallel=parallel)


def filter_steps(
    data: Data,
    steps: LinearSteps,
    *,
    sqrt: bool,
    parallel: bool,
    keep: frozenset[str] = frozenset(FIELDS),
) -> FilterResult:
    """:func:`kalman_filter` on already checked inputs."""
    if parallel:
        from torchfilt.filters.parallel import parallel_filter_moments

        m, P = parallel_filter_moments(data, steps)
        m_prev, P_prev = shifted(data.x0, m, -2), shifted(data.P0, P, -3)
        mp = _mv(steps.A, m_prev)
        if steps.c is not None:
            mp = mp + steps.c
        Pp = symmetrize(steps.A @ P_prev @ steps.A.mT + steps.Q)
        out = {"mean": m, "cov": P, "predicted_mean": mp, "predicted_cov": Pp}
        return assemble(data, steps, out, keep, ParallelFilterResult)
    params = [data.x0, data.P0, data.y, *(x for x in steps if x is not None)]
    grad = torch.is_grad_enabled() and any(x.requires_grad for x in params)
    # small results: lists stacked at the end (fewer operations per step); large ones: written
    # into preallocated outputs (no second copy) unless autograd records
    inplace = not grad and _result_bytes(data, keep) > _VECTOR_LL_BYTES
    fast = None
    Bc = None if sqrt or grad else _covariance_batch(data, steps)
    if Bc is not None:
        fast = _run_riccati(data, steps, keep=keep, Bc=Bc)
    if fast is None and not sqrt:
        fast = _run_fast(data, steps, keep=keep, inplace=inplace)
    out = fast if fast is not None else _run(data, steps, sqrt=sqrt, keep=keep, inplace=not grad)
    return assemble(data, steps, out, keep, KalmanFilterResult)


def smooth_steps(data: Data, steps: LinearSteps, *, sqrt: bool, parallel: bool) -> SmootherResult:
    """Filter and smooth already checked inputs."""
    res = filter_steps(data, steps, sqrt=sqrt, parallel=parallel)
    T = res.mean.shape[-2]
    if not sqrt and not parallel and T > 1 and _is_shared(res) and steps.A.dim() == 3:
        grad = torch.is_grad_enabled() and any(
            x.requires_grad for x in res if isinstance(x, torch.Tensor) and x.numel()
        )
        if not grad:
            return _smooth_shared(data, steps, res)
    el = smoother_elements(res, steps)
    if parallel:
        from torchfilt.filters.parallel import parallel_smoother_moments

        ms, Ps = parallel_smoother_moments(el)
    elif sqrt:
        ms, Ps = _smooth_sqrt(res, steps, el)
    else:
        m_s, P_s = el.g[..., -1, :], el.L[..., -1, :, :]
        means, covs = [m_s], [P_s]
        for t in range(T - 2, -1, -1):
            G = el.E[..., t, :, :]
            m_s = el.g[..., t, :] + _mv(G, m_s)
            P_s = symmetrize(el.L[..., t, :, :] + G @ P_s @ G.mT)
            means.append(m_s)
            covs.append(P_s)
        means.reverse()
        covs.reverse()
        ms, Ps = torch.stack(means, -2), torch.stack(covs, -3)
    return SmootherResult(ms, Ps, el.E[..., :-1, :, :], res)


def _is_shared(res: FilterResult) -> bool:
    """Whether the covariance fields of ``res`` are one sequence viewed by the whole batch."""
    return all(st == 0 for x in (res.cov, res.predicted_cov) for st in x.stride()[: x.dim() - 3])


def _const_from(*xs: Tensor) -> int:
    """The first time index from which every ``x (T', ., .)`` repeats its value exactly."""
    same = torch.ones(xs[0].shape[0] - 1, dtype=torch.bool, device=xs[0].device)
    for x in xs:
        same &= (x[1:] == x[:-1]).flatten(1).all(1)
    changed = (~same).nonzero()
    return 0 if changed.numel() == 0 else int(changed.max()) + 1


def _smooth_shared(data: Data, steps: LinearSteps, res: FilterResult) -> SmootherResult:
    """The RTS pass when the filter's covariances are shared by the batch (no autograd): gains and
    the backward covariance recursion run once, on ``(T, n, n)``, and stop once converged to
    rounding where gains repeat; the means follow ``m^s_t = g_t + m^s_{t+1} G_t^T``, one addmm per
    step over the flattened batch."""
    batch, T, n = data.batch, res.mean.shape[-2], res.mean.shape[-1]
    B = batch.numel()
    lead = (0,) * (res.cov.dim() - 3)
    P, Pp, A = res.cov[lead], res.predicted_cov[lead], steps.A
    # gains from step c on repeat when the model is time-invariant and the filter converged
    c = _const_from(P[:-1], Pp[1:]) if A.stride(0) == 0 else T - 2
    h = slice(0, c + 1)
    C = P[h] @ A[1 : c + 2].mT
    G_h = cholesky_solve(C.mT, safe_cholesky(Pp[1 : c + 2], name="predicted covariance")).mT
    L_h = P[h] - G_h @ Pp[1 : c + 2] @ G_h.mT
    G, L = G_h.new_empty(T - 1, n, n), L_h.new_empty(T - 1, n, n)
    G[h], L[h] = G_h, L_h
    G[c + 1 :], L[c + 1 :] = G_h[-1], L_h[-1]
    tol = _STEADY_ULPS * torch.finfo(P.dtype).eps
    P_s = P[-1]
    covs = P.new_empty(T, n, n)
    covs[-1] = P_s
    L = symmetrize(L)
    t = T - 2
    while t >= 0:
        new = symmetrize(L[t] + G[t] @ P_s @ G[t].mT)
        covs[t] = new
        converged = t > c and bool((new - P_s).abs().max() <= tol * new.abs().max())
        P_s = new
        t -= 1
        if converged:  # the gains repeat down to step c: so does the smoothed covariance
            covs[c : t + 1] = P_s
            t = c - 1
    # means, time-major: g_t = m_t - m^-_{t+1} G_t^T
    m = res.mean.reshape(B, T, n).transpose(0, 1)
    mp = res.predicted_mean.reshape(B, T, n).transpose(0, 1)
    ms = m - torch.cat([mp[1:] @ G.mT, torch.zeros_like(mp[:1])], 0)  # (T, B, n), g_t
    for k in range(T - 2, -1, -1):
        ms[k].addmm_(ms[k + 1], G[k].mT)
    mean = ms.transpose(0, 1).reshape(*batch, T, n)
    return SmootherResult(mean, covs.expand(*batch, T, n, n), G.expand(*batch, T - 1, n, n), res)


def _smooth_sqrt(
    res: FilterResult, steps: LinearSteps, el: SmootherElements
) -> tuple[Tensor, Tensor]:
    """Square-root RTS pass: ``S^s_t = tria([(I - G A) S_t, G Q^{1/2}, G S^s_{t+1}])``."""
    T, n = res.mean.shape[-2], res.mean.shape[-1]
    S = safe_cholesky(res.cov, name="filtered covariance")
    Q_sqrt = _psd_sqrt_steps(steps.Q)
    G = el.E[..., :-1, :, :]
    eye = torch.eye(n, dtype=S.dtype, device=S.device)
    fixed = torch.cat(
        [(eye - G @ steps.A[..., 1:, :, :]) @ S[..., :-1, :, :], G @ Q_sqrt[..., 1:, :, :]], -1
    )
    m_s, S_s = el.g[..., -1, :], S[..., -1, :, :]
    means, facs = [m_s], [S_s]
    for t in range(T - 2, -1, -1):
        Gt = G[..., t, :, :]
        m_s = el.g[..., t, :] + _mv(Gt, m_s)
        S_s = tria(torch.cat([fixed[..., t, :, :], Gt @ S_s], -1))
        means.append(m_s)
        facs.append(S_s)
    means.reverse()
    facs.reverse()
    Sf = torch.stack(facs, -3)
    return torch.stack(means, -2), Sf @ Sf.mT


# ---------------------------------------------------------------------------------- dispatch
def select_path(model: StateSpaceModel, *, path: Path, parallel: bool, redraw: bool = True) -> bool:
    """Whether a Gaussian filter should take the exact Kalman path.

    ``"auto"`` takes it for every model :func:`~torchfilt.models.linear_system` recognises (a
    sigma-point filter with re-drawn update points is exact on a linear model, so only the cost
    changes); ``"kalman"`` insists on it and ``"cubature"`` refuses it. ``parallel=True`` needs it.

    Raises:
        InputError: an unknown ``path``, or ``parallel=True`` with ``path="cubature"``.
        ModelError: ``path="kalman"`` or ``parallel=True`` for a model that is not linear.
    """
    if path not in ("auto", "cubature", "kalman"):
        raise InputError(f"path must be 'auto', 'cubature' or 'kalman', got {path!r}")
    if path == "cubature":
        if parallel:
            raise InputError(
                "parallel=True runs the exact Kalman path; it cannot use path='cubature'"
            )
        return False
    linear = linear_system(model) is not None
    if not linear and (path == "kalman" or parallel):
        what = "parallel=True" if parallel else "path='kalman'"
        raise ModelError(
            f"{what} needs a linear-Gaussian model (a LinearGaussianModel or a model with a "
            f"linear_system() method); {type(model).__name__} is not one. For nonlinear models use "
            "torchfilt.filters.iterated_smoother(..., parallel=True)"
        )
    if path == "auto" and not redraw:
        # without re-drawn points the CKF's P_yy misses Q: not the Kalman filter, keep its answer
        return False
    return linear
