"""The Gaussian filter as two pure steps: ``predict`` and ``update``.

A belief ``N(m, P)`` (with, in the square-root form, its lower factor ``S``, ``P = S S^T``) is data:
each step takes one and returns a new one, and keeps no state. A whole-recording filter is a scan
of ``predict`` then ``update`` over time (:meth:`torchfilt.filters.GaussianFilter.filter`); an
online tracker calls them one measurement at a time (:meth:`GaussianFilter.predict
<torchfilt.filters.GaussianFilter.predict>`, :meth:`GaussianFilter.update
<torchfilt.filters.GaussianFilter.update>`).

    predict:  X_i = m + S xi_i,   X*_i = f(X_i, u),   m^- = sum wm_i X*_i,
              P^- = sum wc_i (X*_i - m^-)(X*_i - m^-)^T + sum wc_i V_f(X_i) + Q
    update:   X_i = m^- + S^- xi_i (re-drawn),   Y_i = h(X_i, u),   y^- = sum wm_i Y_i,
              P_yy = sum wc_i (Y_i - y^-)(Y_i - y^-)^T + sum wc_i V_h(X_i) + R,
              P_xy = sum wc_i (X_i - m^-)(Y_i - y^-)^T,
              K = P_xy P_yy^{-1} (Cholesky solve),  m = m^- + K (y - y^-),  P = P^- - K P_yy K^T

(Arasaratnam & Haykin, IEEE TAC 54(6), 2009; the V terms are the law of total variance over the
cubature points for models with a per-point variance, e.g. Gaussian processes.) The square-root form
propagates ``S`` with QR triangularisation instead of ``P``. Missing measurement components (``obs``
False) get zero gain and no likelihood term.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchfilt.cubature import CubatureRule, sigma_points
from torchfilt.exceptions import InputError
from torchfilt.filters.inputs import model_noise
from torchfilt.models import Prediction, StateSpaceModel
from torchfilt.numerics import (
    cholesky_solve,
    gaussian_log_prob,
    no_host_sync,
    safe_cholesky,
    symmetrize,
    tria,
)

__all__ = [
    "Belief",
    "Noise",
    "PredictCache",
    "UnitPoints",
    "UpdateStats",
    "lost_definiteness",
    "noise_sqrt",
    "predict",
    "unit_points",
    "update",
]

PointVariance = Literal["total", "mean"]


class Belief(NamedTuple):
    """A Gaussian belief ``N(mean, cov)``.

    Attributes:
        mean: ``(..., n)``.
        cov: ``(..., n, n)``.
        sqrt: lower factor ``(..., n, n)`` with ``sqrt sqrt^T = cov``, or ``None`` (then the steps
            factor ``cov`` themselves). The square-root form propagates it; the plain form
            ignores it.
    """

    mean: Tensor
    cov: Tensor
    sqrt: Tensor | None = None


class UnitPoints(NamedTuple):
    """A cubature rule's unit points and weights.

    Attributes:
        xi: the unit points, shape ``(P, n)``.
        wm: the mean weights, shape ``(P,)``.
        wc: the covariance weights, shape ``(P,)``.
    """

    xi: Tensor
    wm: Tensor
    wc: Tensor


class Noise(NamedTuple):
    """An additive noise covariance and (square-root form) a square root of it.

    Attributes:
        cov: the covariance, shape ``(..., d, d)``, or ``None`` (no additive noise).
        sqrt: a square root of ``cov``, shape ``(..., d, d)``, or ``None``.
    """

    cov: Tensor | None
    sqrt: Tensor | None = None


class PredictCache(NamedTuple):
    """What :func:`predict` computed that :func:`update` or a smoother can reuse.

    Attributes:
        points: the propagated points ``X*_i``, ``(..., P, n)``.
        deviations: ``X*_i - m^-``, ``(..., P, n)``.
        cross_cov: ``Cov(x_{t-1}, x_t)`` from the prediction, ``(..., n, n)`` (RTS smoother).
        extra_sqrt: square root of the added ``sum wc_i V_f + Q`` (square-root form),
            ``(..., n, n)``, or None.
    """

    points: Tensor
    deviations: Tensor
    cross_cov: Tensor
    extra_sqrt: Tensor | None


class UpdateStats(NamedTuple):
    """Per-step statistics of :func:`update`.

    Attributes:
        measurement_mean: predicted measurement ``y^-``, ``(..., m)``.
        innovation: ``y - y^-``, NaN where not observed, ``(..., m)``.
        innovation_cov: ``P_yy`` over all components, noise included, ``(..., m, m)``.
        log_likelihood: ``log N(y; y^-, P_yy)`` over the observed components, ``(...)``.
    """

    measurement_mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor


def unit_points(rule: CubatureRule | UnitPoints, n: int, like: Tensor) -> UnitPoints:
    """The rule's unit points in ``like``'s dtype and device (cached by the rule)."""
    if isinstance(rule, UnitPoints):
        return rule
    return UnitPoints(*rule.unit_points(n, dtype=like.dtype, device=like.device))


def point_noise(pred: Prediction, wc: Tensor) -> Tensor | None:
    """``sum_i wc_i V(X_i)`` as a matrix ``(..., d, d)``, or None when the model has none.

    ``wc`` is ``(P,)`` or batched ``(..., P)``.
    """
    out = None
    if pred.var is not None:
        out = torch.diag_embed(torch.einsum("...p,...pd->...d", wc, pred.var))
    if pred.cov is not None:
        c = torch.einsum("...p,...pij->...ij", wc, pred.cov)
        out = c if out is None else out + c
    return out


def noise_sqrt(A: Tensor) -> Tensor:
    """A square root of a PSD noise matrix ``(..., d, d)`` (Cholesky if definite, else eigen).

    Where no host synchronisation is allowed (``torch.compile``, ``settings.sync_free``) the choice
    cannot be made on the host: the Cholesky factor of ``A + eps * mean|diag A| * I`` is used.
    """
    if no_host_sync():
        n = A.shape[-1]
        eye = torch.eye(n, dtype=A.dtype, device=A.device)
        scale = A.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(torch.finfo(A.dtype).tiny)
        jitter = 16.0 * torch.finfo(A.dtype).eps * scale
        return torch.linalg.cholesky_ex(A + jitter[..., None, None] * eye).L
    if not bool(A.any()):
        return torch.zeros_like(A)
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info == 0).all()):
        return L
    evals, evecs = torch.linalg.eigh(symmetrize(A))
    return evecs * evals.clamp_min(0.0).sqrt().unsqueeze(-2)


def cat_cols(*mats: Tensor | None) -> Tensor:
    """Concatenate matrices ``(..., n, k_j)`` along columns after broadcasting batch dims."""
    ms = [m for m in mats if m is not None]
    batch = torch.broadcast_shapes(*(m.shape[:-2] for m in ms))
    return torch.cat([m.expand(*batch, *m.shape[-2:]) for m in ms], dim=-1)


def add(*terms: Tensor | None) -> Tensor:
    """The sum of the terms that are not None (at least one must be given)."""
    out: Tensor | None = None
    for t in terms:
        if t is not None:
            out = t if out is None else out + t
    assert out is not None
    return out


def lost_definiteness(S: Tensor) -> Tensor:
    """Whether a lower factor ``S (..., n, n)`` of a covariance has lost definiteness, ``(...)``.

    True where a diagonal entry is zero, negative or not finite, or where the factor's condition
    estimate passes what the dtype resolves: ``S_ii <= n * eps * ||S_i,:||`` for some row ``i``
    (the ratio is invariant to the scaling of the state components; a factor carries twice the
    precision of the covariance, so its limit is ``1 / eps``, the covariance's ``1 / eps^2``).
    """
    d = S.diagonal(dim1=-2, dim2=-1)
    rows = torch.linalg.vector_norm(S, dim=-1)
    limit = S.shape[-1] * torch.finfo(S.dtype).eps * rows
    return ~(d > limit).all(-1)


def _noise(
    side: torch.nn.Module, noise: Noise | None, step: int, like: Tensor, sqrt: bool
) -> Noise:
    if noise is not None:
        if sqrt and noise.cov is not None and noise.sqrt is None:
            return Noise(noise.cov, noise_sqrt(noise.cov))
        return noise
    cov = model_noise(side, step, like)
    return Noise(cov, None if cov is None or not sqrt else noise_sqrt(cov))


def predict(
    belief: Belief,
    model: StateSpaceModel,
    u: Tensor | None,
    rule: CubatureRule | UnitPoints,
    *,
    sqrt: bool = False,
    point_variance: PointVariance = "total",
    noise: Noise | None = None,
    step: int = 0,
) -> tuple[Belief, PredictCache]:
    """One prediction ``p(x_t | y_{1:t-1})`` from the belief about ``x_{t-1}``.

    Args:
        belief: ``mean (..., n)``, ``cov (..., n, n)`` (and ``sqrt`` in the square-root form).
        model: the state-space model; its transition is used.
        u: inputs ``(..., nu)`` of this step, or ``None``.
        rule: a cubature rule, or its :class:`UnitPoints`.
        sqrt: square-root form (propagate the factor with QR triangularisation).
        point_variance: ``"total"`` or ``"mean"``, how per-point model variances enter.
        noise: the process noise ``Q`` (and its square root) of this step; default: the model's
            at ``step``.
        step: the time index of the prediction (for time-varying noise).

    Returns:
        The predicted :class:`Belief` (with its factor) and a :class:`PredictCache`.
    """
    f = model.transition
    mean, cov = belief.mean, belief.cov
    pts = unit_points(rule, mean.shape[-1], mean)
    xi, wm, wc = pts
    Qn = _noise(f, noise, step, mean, sqrt)
    if sqrt and belief.sqrt is not None:
        S = belief.sqrt
    else:
        S = safe_cholesky(cov, name="filtered covariance")
    X = sigma_points(mean, S, xi)  # (..., P, n)
    uP = None if u is None else u.unsqueeze(-2).expand(*X.shape[:-1], u.shape[-1])
    pf = f.predict(X, uP)
    Xs = pf.mean
    m_pred = wm @ Xs
    D = Xs - m_pred.unsqueeze(-2)  # (..., P, n)
    Dw = D * wc.unsqueeze(-1)
    cross = (X - mean.unsqueeze(-2)).mT @ Dw  # Cov(x_{t-1}, x_t)
    if point_variance == "mean" and (pf.var is not None or pf.cov is not None):
        pm = f.predict(mean.unsqueeze(-2), None if uP is None else uP[..., :1, :])
        Vf = point_noise(pm, wc.new_ones(1))
    else:
        Vf = point_noise(pf, wc)
    extra_sqrt = None
    if not sqrt:
        P_pred = symmetrize(add(D.mT @ Dw, Vf, Qn.cov))
        S_pred = safe_cholesky(P_pred, name="predicted covariance")
    else:
        if Vf is not None or Qn.sqrt is not None:
            Vf_sqrt = None if Vf is None else noise_sqrt(Vf)
            extra_sqrt = cat_cols(Vf_sqrt, Qn.sqrt)
        S_pred = tria(cat_cols((D * wc.sqrt().unsqueeze(-1)).mT, extra_sqrt))
        P_pred = S_pred @ S_pred.mT
    return Belief(m_pred, P_pred, S_pred), PredictCache(Xs, D, cross, extra_sqrt)


def update(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    model: StateSpaceModel,
    rule: CubatureRule | UnitPoints,
    *,
    u: Tensor | None = None,
    sqrt: bool = False,
    redraw: bool = True,
    point_variance: PointVariance = "total",
    noise: Noise | None = None,
    step: int = 0,
    cache: PredictCache | None = None,
) -> tuple[Belief, UpdateStats]:
    """Condition a predicted belief on one measurement ``y_t``.

    Args:
        belief: the predicted belief, ``mean (..., n)``, ``cov (..., n, n)``; its ``sqrt`` is used
            if given (it is, from :func:`predict`).
        y: the measurement ``(..., m)``; non-finite entries are missing.
        obs: bool ``(..., m)``, False where a component is missing, or ``None`` (finite entries).
        model: the state-space model; its measurement side is used.
        rule: the cubature rule (or its :class:`UnitPoints`) that :func:`predict` used.
        u: inputs ``(..., nu)`` of this step, or ``None``.
        sqrt: square-root form. A filtered factor that has lost definiteness (see
            :func:`lost_definiteness`) makes that sequence NaN, as a failed factorisation does in
            the plain form.
        redraw: re-draw the update's points from the predicted covariance (default); ``False``
            reuses the propagated points of ``cache`` (filterpy's convention).
        point_variance: as in :func:`predict`.
        noise: the measurement noise ``R`` (and its square root); default: the model's at ``step``.
        step: the time index (for time-varying noise).
        cache: the :class:`PredictCache` of the prediction (needed when ``redraw=False``).

    Returns:
        The filtered :class:`Belief` and the step's :class:`UpdateStats`.

    Raises:
        InputError: ``redraw=False`` without the prediction's ``cache``.
    """
    h = model.measurement
    m_pred, P_pred = belief.mean, belief.cov
    pts = unit_points(rule, m_pred.shape[-1], m_pred)
    xi, wm, wc = pts
    Rn = _noise(h, noise, step, m_pred, sqrt)
    R, R_sqrt = Rn.cov, Rn.sqrt
    if obs is None:
        obs = torch.isfinite(y)
    y = torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))
    S_pred = (
        belief.sqrt
        if belief.sqrt is not None
        else safe_cholesky(P_pred, name="predicted covariance")
    )
    if redraw:
        Xu = sigma_points(m_pred, S_pred, xi)
        Xd = Xu - m_pred.unsqueeze(-2)
    else:
        if cache is None:
            raise InputError(
                "cache: update with redraw=False reuses the predicted points; pass cache="
            )
        Xu, Xd = cache.points, cache.deviations
    uP = None if u is None else u.unsqueeze(-2).expand(*Xu.shape[:-1], u.shape[-1])
    ph = h.predict(Xu, uP)
    Ys = ph.mean
    y_mean = wm @ Ys
    E = Ys - y_mean.unsqueeze(-2)  # (..., P, m)
    Ew = E * wc.unsqueeze(-1)
    if point_variance == "mean" and (ph.var is not None or ph.cov is not None):
        pm = h.predict(m_pred.unsqueeze(-2), None if uP is None else uP[..., :1, :])
        Vh = point_noise(pm, wc.new_ones(1))
    else:
        Vh = point_noise(ph, wc)
    R_tot = add(Vh, R) if (Vh is not None or R is not None) else None
    P_yy = E.mT @ Ew if R_tot is None else E.mT @ Ew + R_tot
    P_yy = symmetrize(P_yy)
    P_xy = Xd.mT @ Ew  # (..., n, m)

    obs_f = obs.to(m_pred.dtype)
    unobs_diag = torch.diag_embed(1.0 - obs_f)
    if not sqrt:
        # Restrict P_yy to the observed components (identity on the others): the gain then has
        # zero columns for missing components and the likelihood counts observed ones only.
        P_yy_m = P_yy * (obs_f.unsqueeze(-1) * obs_f.unsqueeze(-2)) + unobs_diag
        L_yy = safe_cholesky(P_yy_m, name="innovation covariance")
        R_sqrt_tot = None
    else:
        R_sqrt_tot = None
        if R_tot is not None:
            R_sqrt_tot = R_sqrt if Vh is None and R_sqrt is not None else noise_sqrt(R_tot)
        rows = obs_f.unsqueeze(-1)
        Z = (E * wc.sqrt().unsqueeze(-1)).mT * rows  # (..., m, P)
        L_yy = tria(cat_cols(Z, None if R_sqrt_tot is None else R_sqrt_tot * rows, unobs_diag))
    P_xy_m = P_xy * obs_f.unsqueeze(-2)
    K = cholesky_solve(P_xy_m.mT, L_yy).mT  # (..., n, m)
    innov = y - y_mean
    e = innov * obs_f
    mean_new = m_pred + (K @ e.unsqueeze(-1)).squeeze(-1)
    if not sqrt:
        cov_new = symmetrize(P_pred - K @ P_yy_m @ K.mT)
        sqrt_new = None  # the plain form re-factors cov at the next step
    else:
        A = (Xd - E @ K.mT) * wc.sqrt().unsqueeze(-1)  # (..., P, n)
        KR = None if R_sqrt_tot is None else K @ R_sqrt_tot
        extra = None if redraw or cache is None else cache.extra_sqrt
        sqrt_new = tria(cat_cols(A.mT, KR, extra))
        cov_new = sqrt_new @ sqrt_new.mT
        # a factor that lost definiteness reports a confident, wrong covariance: the plain form
        # would fail its factorisation there, so do what it does (NaN from here, a warning)
        lost = lost_definiteness(sqrt_new)
        nan = torch.full((), math.nan, dtype=m_pred.dtype, device=m_pred.device)
        mean_new = torch.where(lost.unsqueeze(-1), nan, mean_new)
        cov_new = torch.where(lost[..., None, None], nan, cov_new)
        sqrt_new = torch.where(lost[..., None, None], nan, sqrt_new)
    ll = gaussian_log_prob(e, L_yy, dim=obs_f.sum(-1))
    innov_out = torch.where(obs, innov, torch.full_like(innov, math.nan))
    return Belief(mean_new, cov_new, sqrt_new), UpdateStats(y_mean, innov_out, P_yy, ll)
