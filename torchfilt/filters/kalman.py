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

The pure steps are in :mod:`torchfilt.filters.kalman_steps`, the runners over time (sequential,
fast, Riccati) in :mod:`torchfilt.filters.kalman_runners`; which runner serves a recording is
decided by :func:`torchfilt.filters.plan.plan` and recorded in the result's ``numerics``.
"""

from __future__ import annotations

import math
from collections.abc import Collection

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.filters import kalman_runners as _runners
from torchfilt.filters.inputs import broadcast_batch, check_model_input, check_prior, observed
from torchfilt.filters.kalman_adjoint import adjoint_log_likelihood
from torchfilt.filters.kalman_checks import warn_precision
from torchfilt.filters.kalman_runners import _DOUBLING_WORK, _STEADY_ULPS, _affine_tail
from torchfilt.filters.kalman_steps import (
    Belief,
    _mv,
    _psd_sqrt_steps,
    predict,
    predict_sqrt,
    update,
    update_sqrt,
)
from torchfilt.filters.linear_data import Data, LinearSteps, SmootherElements
from torchfilt.filters.plan import Fallback, LinearFacts, Path, PlanOptions, exact_path, plan
from torchfilt.filters.results import (
    FilterResult,
    KalmanFilterResult,
    ParallelFilterResult,
    SmootherResult,
)
from torchfilt.models import LinearSystem, StateSpaceModel, linear_system
from torchfilt.numerics import (
    cholesky_solve,
    gaussian_log_prob,
    safe_cholesky,
    symmetrize,
    tria,
)
from torchfilt.numerics.dtypes import check_real_tensor
from torchfilt.settings import NumericsPath

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

#: The tensor fields of a filter result (``numerics`` describes the run, it is not a tensor).
FIELDS = tuple(f for f in FilterResult._fields if f != "numerics")


# ---------------------------------------------------------------------------------- inputs
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
    check_real_tensor(y, "y")
    T = y.shape[-2]
    if T == 0:
        raise ShapeError("y: the time dimension T must be at least 1")
    device = y.device
    x0 = torch.as_tensor(x0, device=device)
    P0 = torch.as_tensor(P0, device=device)
    check_real_tensor(x0, "x0", integers=True)
    check_real_tensor(P0, "P0", integers=True)
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
    if u is not None:
        u = torch.as_tensor(u, device=device)
        check_real_tensor(u, "u", integers=True)
        check_model_input(model, u)
        if not uses_u:
            raise InputError(
                f"u: the model takes no inputs (no input matrix B or D), but inputs of shape "
                f"{tuple(u.shape)} were given and would be ignored; drop u"
            )
    if u is not None and uses_u:
        u = u.to(dtype)
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
        ll = gaussian_log_prob(e, L).sum(-1)
    else:
        o = data.obs.to(S.dtype)
        Sm = S * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
        L = safe_cholesky(Sm, name="innovation covariance")
        ll = gaussian_log_prob(e * o, L, o.sum(-1)).sum(-1)
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
    numerics: NumericsPath | None = None,
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
    return cls(**fields, numerics=numerics)  # type: ignore[arg-type]


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

    Input convention (:mod:`torchfilt.filters`): step ``t`` predicts ``x_t`` from ``x_{t-1}``
    with the input row ``u[..., t, :]`` and updates with ``y[..., t, :]``, passing the same row
    to the measurement; the prior ``N(x0, P0)`` is the belief about ``x_{-1}``.

    Args:
        model: a linear model (:func:`~torchfilt.models.linear_system` returns its matrices).
            ``A, H, B, D`` and the noise may carry batch dimensions; the noise may be
            :class:`~torchfilt.models.TimeVarying`.
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)``; required when the model has ``B`` or ``D``.
        x0: prior mean ``(..., n)``.
        P0: prior covariance ``(..., n, n)``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component as missing.
        sqrt: propagate Cholesky factors (square-root filter).
        parallel: run the parallel-in-time filter (associative scan,
            :mod:`torchfilt.filters.parallel`) instead of the sequential recursion.
        outputs: names of the :class:`~torchfilt.filters.FilterResult` fields to return, e.g.
            ``("mean", "log_likelihood")``; the others are empty tensors (shape ``(0,)``) and are
            not stored, which bounds the memory by what is asked for. Default: all. With
            ``("log_likelihood",)`` while autograd records, the gradient comes from one
            closed-form backward pass (:mod:`torchfilt.filters.kalman_adjoint`) instead of
            autograd through the per-step loop.

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

    With ``sqrt=True`` the backward pass propagates Cholesky factors,
    ``S^s_t = tria([(I - G_t A_{t+1}) S_t, G_t Q_{t+1}^{1/2}, G_t S^s_{t+1}])``; with
    ``parallel=True`` both passes are associative scans.

    Args:
        model: a linear model, as in :func:`kalman_filter`.
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)``; required when the model has ``B`` or ``D``.
        x0: prior mean ``(..., n)``.
        P0: prior covariance ``(..., n, n)``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component as missing.
        sqrt: propagate Cholesky factors (square-root filter and smoother).
        parallel: run both passes as associative scans.

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
    fallbacks: tuple[Fallback, ...] = (),
) -> FilterResult:
    """:func:`kalman_filter` on already checked inputs, by the runner that
    :func:`~torchfilt.filters.plan.plan` names (a runner whose factorisation fails hands over to
    the next one the plan names, and the result's ``numerics.fallback`` says so; ``fallbacks``:
    those known to have failed already). Results that the working precision made unreliable
    (:mod:`torchfilt.filters.kalman_checks`) come with a
    :class:`~torchfilt.exceptions.PrecisionWarning`."""
    params = [data.x0, data.P0, data.y, *(x for x in steps if x is not None)]
    grad = torch.is_grad_enabled() and any(x.requires_grad for x in params)
    facts = LinearFacts(*_runners.linear_facts(data, steps, keep)) if not parallel else None
    options = PlanOptions(sqrt=sqrt, state_dim=data.x0.shape[-1], obs_dim=data.y.shape[-1])
    while True:
        p = plan(
            None,
            options,
            batch=data.batch,
            records_grad=grad,
            device=data.y.device,
            path="kalman",
            parallel=parallel,
            linear=facts,
            fallbacks=fallbacks,
        )
        if p.parallel:
            res = _parallel_filter(data, steps, keep, p.numerics)
            warn_precision(res, sqrt=sqrt, stacklevel=3)
            return res
        if p.adjoint:  # the no-graph filter warns; the result holds no covariance to check
            ll = adjoint_log_likelihood(data, steps, _no_graph, _recorded)
            return assemble(
                data, steps, {"log_likelihood": ll}, keep, KalmanFilterResult, p.numerics
            )
        out = _runners.run_exact(data, steps, keep, p)
        if out is not None:
            res = assemble(data, steps, out, keep, KalmanFilterResult, p.numerics)
            warn_precision(res, sqrt=sqrt, stacklevel=3)
            return res
        fallbacks += (Fallback(p.execution, "a covariance failed to factor"),)


def _no_graph(data: Data, steps: LinearSteps, keep: frozenset[str]) -> FilterResult:
    """The filter without a graph (the forward pass of the adjoint's log-likelihood)."""
    with torch.no_grad():
        return filter_steps(data, steps, sqrt=False, parallel=False, keep=keep)


def _recorded(data: Data, steps: LinearSteps, why: str) -> Tensor:
    """The log-likelihood through the recorded path, once the adjoint has failed for ``why``."""
    only = frozenset({"log_likelihood"})
    res = filter_steps(
        data, steps, sqrt=False, parallel=False, keep=only,
        fallbacks=(Fallback("kalman-adjoint", why),),
    )  # fmt: skip
    return res.log_likelihood


def _parallel_filter(
    data: Data, steps: LinearSteps, keep: frozenset[str], numerics: NumericsPath
) -> FilterResult:
    """The parallel-in-time filter's moments, then the fields derived from them."""
    from torchfilt.filters.parallel import parallel_filter_moments

    m, P = parallel_filter_moments(data, steps)
    m_prev, P_prev = shifted(data.x0, m, -2), shifted(data.P0, P, -3)
    mp = _mv(steps.A, m_prev)
    if steps.c is not None:
        mp = mp + steps.c
    Pp = symmetrize(steps.A @ P_prev @ steps.A.mT + steps.Q)
    out = {"mean": m, "cov": P, "predicted_mean": mp, "predicted_cov": Pp}
    return assemble(data, steps, out, keep, ParallelFilterResult, numerics)


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
    start = T - 2
    if c < T - 2 and B * n * n * math.log2(T - c) <= _DOUBLING_WORK:
        # from step c on the gain repeats: the backward recursion there is affine with one
        # matrix, a doubling scan over the reversed tail
        tail = ms[c:].flip(0)
        _affine_tail(tail, G[c].mT.unsqueeze(0))
        ms[c:] = tail.flip(0)
        start = c - 1
    for k in range(start, -1, -1):
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
    """Whether a Gaussian filter takes the exact Kalman path: :func:`torchfilt.filters.plan.exact_path`."""
    return exact_path(model, path=path, parallel=parallel, redraw=redraw)
