"""The iterated posterior-linearisation smoother (IPLS) with cubature linearisation.

García-Fernández, Svensson & Särkkä, "Iterated posterior linearization smoother", IEEE TAC 62(4),
2017; in parallel form Yaghoobi, Corenflos, Hassan & Särkkä, "Parallel iterated extended and
sigma-point Kalman smoothers", ICASSP 2021. Each iteration statistically linearises the model
around the previous smoothed posterior: for a map ``g`` and a Gaussian ``N(mu, Sigma)``, with
cubature points ``X_i``, ``Z_i = g(X_i)``,

    zbar = sum_i w_i Z_i,   P_xz = sum_i w_i (X_i - mu)(Z_i - zbar)^T,   P_zz likewise (+ V(X_i)),
    M = P_xz^T Sigma^{-1},  g(x) ~ M x + (zbar - M mu) + e,  e ~ N(0, P_zz - M Sigma M^T),

so the transition into step ``t`` is linearised around the smoothed ``x_{t-1}`` (for ``t = 0``
around the smoothed prior ``x_{-1}``) and the measurement around the smoothed ``x_t``. The linear
model with these per-step matrices (the linearisation error added to ``Q`` and ``R``) is then
smoothed exactly, sequentially or in parallel (:mod:`torchfilt.filters.parallel`). The fixed
point does not depend on which: the parallel and sequential smoothers converge to the same answer.
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from torchfilt.cubature import CubatureRule, SphericalRadialRule, sigma_points
from torchfilt.exceptions import ConvergenceWarning, InputError
from torchfilt.filters.gaussian import GaussianFilter
from torchfilt.filters.kalman import Data, LinearSteps, check_inputs, smooth_steps
from torchfilt.filters.results import SmootherResult
from torchfilt.models import ConditionalModel, StateSpaceModel
from torchfilt.numerics import psd_solve, safe_cholesky, symmetrize

__all__ = ["iterated_smoother", "statistical_linearisation"]


def statistical_linearisation(
    side: ConditionalModel,
    mean: Tensor,
    cov: Tensor,
    u: Tensor | None,
    rule: CubatureRule,
) -> tuple[Tensor, Tensor, Tensor]:
    """Statistical linear regression of ``side`` with respect to ``N(mean, cov)``.

    Args:
        side: the map (transition or measurement), ``(..., P, n) -> (..., P, d)``.
        mean: ``(..., n)``.  cov: ``(..., n, n)``.  u: inputs ``(..., nu)`` or ``None``.
        rule: the cubature rule.

    Returns:
        ``M (..., d, n)``, offset ``(..., d)`` and the linearisation error covariance
        ``(..., d, d)`` (the model's per-point variance included, its additive noise not).
    """
    n = mean.shape[-1]
    xi, wm, wc = rule.unit_points(n, dtype=mean.dtype, device=mean.device)
    X = sigma_points(mean, safe_cholesky(cov, name="smoothed covariance"), xi)  # (..., P, n)
    uP = None if u is None else u.unsqueeze(-2).expand(*X.shape[:-1], u.shape[-1])
    pred = side.predict(X, uP)
    Z = pred.mean
    zbar = torch.einsum("p,...pd->...d", wm, Z)
    dZ = Z - zbar.unsqueeze(-2)
    dX = X - mean.unsqueeze(-2)
    dZw = dZ * wc.unsqueeze(-1)
    Pxz = dX.mT @ dZw
    Pzz = dZ.mT @ dZw
    if pred.var is not None:
        Pzz = Pzz + torch.diag_embed(torch.einsum("p,...pd->...d", wc, pred.var))
    if pred.cov is not None:
        Pzz = Pzz + torch.einsum("p,...pij->...ij", wc, pred.cov)
    M = psd_solve(cov, Pxz, name="smoothed covariance").mT  # (..., d, n)
    offset = zbar - (M @ mean.unsqueeze(-1)).squeeze(-1)
    return M, offset, symmetrize(Pzz - M @ cov @ M.mT)


def _linearise(
    model: StateSpaceModel,
    data: Data,
    Q: Tensor,
    R: Tensor,
    u: Tensor | None,
    sm: SmootherResult,
    rule: CubatureRule,
) -> LinearSteps:
    """Per-step matrices linearised around the smoothed trajectory ``sm`` (and smoothed prior)."""
    m, P = sm.mean, sm.cov
    m_prev, P_prev = _smoothed_prior(data, sm)
    m_before = torch.cat([m_prev.unsqueeze(-2), m[..., :-1, :]], -2)
    P_before = torch.cat([P_prev.unsqueeze(-3), P[..., :-1, :, :]], -3)
    A, c, Lam = statistical_linearisation(model.transition, m_before, P_before, u, rule)
    H, d, Om = statistical_linearisation(model.measurement, m, P, u, rule)
    return LinearSteps(A=A, c=c, Q=symmetrize(Q + Lam), H=H, d=d, R=symmetrize(R + Om))


def _smoothed_prior(data: Data, sm: SmootherResult) -> tuple[Tensor, Tensor]:
    """One RTS step back from ``x_0`` to the prior ``x_{-1}``, from the smoother's own moments."""
    f = sm.filtered
    C = f.cross_cov[..., 0, :, :]  # Cov(x_{-1}, x_0) = P0 A_0^T
    Pp = f.predicted_cov[..., 0, :, :]
    G = psd_solve(Pp, C.mT, name="predicted covariance").mT
    m = data.x0 + (G @ (sm.mean[..., 0, :] - f.predicted_mean[..., 0, :]).unsqueeze(-1)).squeeze(-1)
    P = symmetrize(data.P0 + G @ (sm.cov[..., 0, :, :] - Pp) @ G.mT)
    return m, P


def iterated_smoother(
    model: StateSpaceModel,
    y: Tensor,
    u: Tensor | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    mask: Tensor | None = None,
    rule: CubatureRule | None = None,
    parallel: bool = False,
    max_iter: int = 20,
    tol: float = 1e-10,
    init: SmootherResult | None = None,
) -> SmootherResult:
    """Iterated posterior-linearisation smoother (see the module docstring).

    Args:
        model: any state-space model (its maps are evaluated at cubature points).
        y: measurements ``(..., T, m)``; NaN entries are missing.
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior mean ``(..., n)``.
        P0: prior covariance ``(..., n, n)``.
        mask: optional bool ``(..., T, m)``; ``False`` marks a component as missing.
        rule: cubature rule of the linearisation; default third-degree spherical-radial.
        parallel: smooth each linearised model by associative scan
            (:mod:`torchfilt.filters.parallel`).
        max_iter: most linearise-and-smooth iterations.
        tol: stop when no smoothed mean moves by more than ``tol * (1 + |mean|)``.
        init: the trajectory of the first linearisation; default the cubature RTS smoother's.

    Returns:
        The :class:`~torchfilt.filters.SmootherResult` of the last linearised model: means
        ``(..., T, n)``, covariances ``(..., T, n, n)``; its ``filtered`` pass and
        ``log_likelihood`` are those of the linearised model. A
        :class:`~torchfilt.exceptions.ConvergenceWarning` says if ``tol`` was not met.

    Raises:
        InputError: an invalid ``rule`` or ``max_iter``, or invalid data (non-finite prior,
            ``P0`` not symmetric).
        InputTypeError: a tensor argument of the wrong dtype (such as complex).
        ShapeError: ``y``, ``u``, ``x0``, ``P0`` or ``mask`` of the wrong shape.
    """
    rule = rule if rule is not None else SphericalRadialRule(3)
    if not isinstance(rule, CubatureRule):
        raise InputError(f"rule must be a CubatureRule, got {type(rule).__name__}")
    if max_iter < 1:
        raise InputError(f"max_iter must be at least 1, got {max_iter}")
    data, Q, R, u_checked = check_inputs(model, y, u, x0=x0, P0=P0, mask=mask)
    if init is None:
        init = GaussianFilter(model, rule=rule).smooth(
            y, u, x0=x0, P0=P0, mask=mask, path="cubature"
        )
    sm = init
    for _ in range(max_iter):
        steps = _linearise(model, data, Q, R, u_checked, sm, rule)
        new = smooth_steps(data, steps, sqrt=False, parallel=parallel)
        step = (new.mean - sm.mean).abs() / (1.0 + sm.mean.abs())
        sm = new
        if not bool(torch.isfinite(step).all()):
            break
        if float(step.max()) <= tol:
            return sm
    warnings.warn(
        f"iterated_smoother: the smoothed means moved by more than tol = {tol:g} in the last of "
        f"{max_iter} iterations",
        ConvergenceWarning,
        stacklevel=2,
    )
    return sm
