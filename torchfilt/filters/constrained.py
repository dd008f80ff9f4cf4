"""Constrained cubature Kalman filter (CCKF) with box bounds and per-point data reconciliation (NDDR).

Liu, Zhang & Chu, "Cubature Kalman filter with bounded constraints", Periodical of Ocean University
of China 48(6), 2018, restated with its typos fixed in spec ``cckf.md``. Every step, with the box
``lower <= x <= upper``:

    predict:  X_i, omega_i = constrained points/weights of (x+_{k-1}, P+_{k-1})     (spec s.2)
              X*_i = f(X_i, u),   x-_k = sum omega_i X*_i
              P-_k = sum omega_i (X*_i - x-_k)(X*_i - x-_k)^T + sum omega_i V_f(X_i) + Q
    update:   x-_k is projected onto the box,
              X-_i, omega'_i = constrained points/weights of (x-_k, P-_k)
              x_{k,i} = argmin_{lower <= x <= upper} (x - X-_i)^T (P-_k)^{-1} (x - X-_i)
                                                     + (z_k - h(x))^T R_i^{-1} (z_k - h(x))
              x+_k = sum omega'_i x_{k,i}
              P+_k = sum omega'_i (x_{k,i} - x+_k)(x_{k,i} - x+_k)^T             ("paper", eq. (27))
                     [+ K R_tot K^T,  K = P_xz P_zz^{-1}]                         ("corrected")

The paper's eq. (24) omits ``+ Q``; it is kept here (spec s.3). ``V_f``, ``V_h`` are the per-point
variances of learned (GP) models (zero for plain callables): the prediction adds their weighted
average (law of total variance, as :class:`~torchfilt.filters.GaussianFilter`), and each point's
reconciliation weighs the measurement by ``R_i = R + V_h(X-_i)``, the measurement model's
variance at that point's prior location (held fixed during the solve, so each problem stays a
least-squares problem). ``R_tot = R + sum omega'_i V_h(X-_i)`` enters ``P_zz`` and the correction.

For a linear model with no bound in reach, each NDDR problem is the Kalman update of its point and
the corrected covariance is the Joseph form ``(I-KH)P-(I-KH)^T + K R K^T``: the CCKF then equals the
CKF exactly. The paper's covariance lacks ``K R K^T`` and is over-confident.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Collection, Sequence
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchfilt.cubature import SphericalRadialRule, constrained_points
from torchfilt.cubature.constrained import ThetaReading
from torchfilt.exceptions import ConvergenceWarning, InputError, ModelError, ShapeError
from torchfilt.filters.gaussian import FilterState, GaussianFilter
from torchfilt.filters.inputs import FilterInputs, model_noise
from torchfilt.filters.plan import Path, PlanOptions
from torchfilt.filters.results import (
    FilterResult,
    SmootherResult,
    StepRecord,
    stack_records,
    warn_nonfinite,
)
from torchfilt.filters.steps import (
    Belief,
    Noise,
    PredictCache,
    UnitPoints,
    UpdateStats,
    add,
    point_noise,
    unit_points,
)
from torchfilt.models import ConditionalModel, Prediction, StateSpaceModel
from torchfilt.numerics import (
    Box,
    LeastSquaresResult,
    SolverStatus,
    batched_jacobian,
    bounded_least_squares,
    gaussian_log_prob,
    safe_cholesky,
    symmetrize,
)

__all__ = [
    "ConstrainedCKF",
    "ConstrainedInfo",
    "ConstrainedStep",
    "SolverInfo",
    "constrained_predict",
    "constrained_update",
]

CovarianceForm = Literal["paper", "corrected"]

#: Default reading of theta in the weights (chosen by ``scripts/reproduce_cckf.py``; see the class).
DEFAULT_THETA: ThetaReading = "paper"


class ConstrainedInfo(NamedTuple):
    """Diagnostics of a :meth:`ConstrainedCKF.filter_with_info` run.

    Attributes:
        solver_iterations: NDDR solver iterations per step and cubature point, ``(..., T, 2n)``.
        solver_status: :class:`~torchfilt.numerics.SolverStatus` codes, ``(..., T, 2n)``;
            positive means converged.
        projected: whether the predicted mean left the box and was projected, ``(..., T)``.
    """

    solver_iterations: Tensor
    solver_status: Tensor
    projected: Tensor


class SolverInfo(NamedTuple):
    """Diagnostics of one :func:`constrained_update`.

    Attributes:
        iterations: NDDR solver iterations per cubature point, ``(..., 2n)``.
        status: :class:`~torchfilt.numerics.SolverStatus` codes, ``(..., 2n)``.
        projected: whether the predicted mean left the box and was projected, ``(...)``.
    """

    iterations: Tensor
    status: Tensor
    projected: Tensor


def _wmean(w: Tensor, X: Tensor) -> Tensor:
    """``sum_i w_i X_i`` for weights ``(..., P)`` and points ``(..., P, d)``."""
    return torch.einsum("...p,...pd->...d", w, X)


def _per_point_noise(pred: Prediction) -> Tensor | None:
    """Each point's own model covariance ``diag(var_i) + cov_i``, ``(..., P, d, d)``, or None."""
    out = None if pred.var is None else torch.diag_embed(pred.var)
    if pred.cov is not None:
        out = pred.cov if out is None else out + pred.cov
    return out


def _observed_block(A: Tensor, obs_f: Tensor, fill: float) -> Tensor:
    """``A`` on the observed components, ``fill`` on the diagonal of the others (``(..., m, m)``)."""
    keep = obs_f.unsqueeze(-1) * obs_f.unsqueeze(-2)
    return A * keep + fill * torch.diag_embed(1.0 - obs_f)


def _variances(
    side: ConditionalModel,
    X: Tensor,
    w: Tensor,
    center: Tensor,
    uP: Tensor | None,
    pred: Prediction,
    point_variance: Literal["total", "mean"],
) -> tuple[Tensor | None, Tensor | None]:
    """Weighted model variance ``sum_i w_i V(X_i)`` and per-point ``V(X_i)`` (``(..., P, d, d)``).

    With ``point_variance="mean"`` both are the variance at ``center``.
    """
    if pred.var is None and pred.cov is None:
        return None, None
    if point_variance == "mean":
        pm = side.predict(center.unsqueeze(-2), None if uP is None else uP[..., :1, :])
        per = _per_point_noise(pm)
        assert per is not None
        return per.squeeze(-3), per
    return point_noise(pred, w), _per_point_noise(pred)


def constrained_predict(
    belief: Belief,
    model: StateSpaceModel,
    u: Tensor | None,
    box: Box,
    *,
    theta: ThetaReading = DEFAULT_THETA,
    point_variance: Literal["total", "mean"] = "total",
    noise: Noise | None = None,
) -> tuple[Belief, PredictCache]:
    """The CCKF prediction from constrained cubature points of the filtered belief (spec s.2).

    Args:
        belief: filtered ``mean (..., n)`` inside the box and ``cov (..., n, n)``.
        model: the state-space model (its transition).
        u: inputs ``(..., nu)`` or ``None``.
        box: the bounds, in the belief's dtype and device.
        theta: reading of theta in the weights (see :class:`ConstrainedCKF`).
        point_variance: ``"total"`` or ``"mean"``.
        noise: the process noise ``Q`` of the step (``None``: none).

    Returns:
        The predicted belief (its mean not yet projected onto the box) and a
        :class:`~torchfilt.filters.steps.PredictCache` (propagated points, cross-covariance).
    """
    f = model.transition
    mean, cov = belief.mean, belief.cov
    # the reconciled points' spread is exactly singular when they all share a bound
    # (certainty at the bound): factor it with the tiny jitter, without a warning
    S = safe_cholesky(cov, name="filtered covariance", warn=False)
    cp = constrained_points(mean, S, box, theta=theta)
    X, w = cp.points, cp.weights
    uP = None if u is None else u.unsqueeze(-2).expand(*X.shape[:-1], u.shape[-1])
    pf = f.predict(X, uP)
    Xs = pf.mean
    m_pred = _wmean(w, Xs)
    D = Xs - m_pred.unsqueeze(-2)
    Dw = D * w.unsqueeze(-1)
    cross = (X - _wmean(w, X).unsqueeze(-2)).mT @ Dw
    Vf, _ = _variances(f, X, w, mean, uP, pf, point_variance)
    P_pred = symmetrize(add(D.mT @ Dw, Vf, None if noise is None else noise.cov))
    return Belief(m_pred, P_pred), PredictCache(Xs, D, cross, None)


def _reconcile(
    h: ConditionalModel,
    Xu: Tensor,
    uP: Tensor | None,
    y: Tensor,
    obs_f: Tensor,
    S_pred: Tensor,
    R: Tensor | None,
    Vh_pts: Tensor | None,
    box: Box,
    *,
    tol: float | None,
    max_iter: int,
) -> LeastSquaresResult:
    """The NDDR of the points ``Xu (..., 2n, n)``: each point's bounded least-squares problem
    ``min |S^{-1}(x - X_i)|^2 + |R_i^{-1/2}(y - h(x))|^2`` (observed components only) inside the
    box, the whitening formed once per step.

    Raises:
        ModelError: the measurement noise (plus any per-point variance) is not positive definite.
    """
    R_pts = add(None if Vh_pts is None else Vh_pts, None if R is None else R.unsqueeze(-3))
    L_R, bad = torch.linalg.cholesky_ex(_observed_block(R_pts, obs_f.unsqueeze(-2), 1.0))
    if bool((bad > 0).any()):
        raise ModelError(
            "the measurement noise R (plus the model's per-point variance) is not positive "
            "definite: the reconciliation weighs the measurement by its inverse"
        )
    L_P = S_pred.unsqueeze(-3)
    z = y.unsqueeze(-2)
    o = obs_f.unsqueeze(-2)

    # whitening by the inverse Cholesky factors, formed once per step (triangular solves of the
    # identity) so that the solver's many residual calls are cheap products
    n, m = Xu.shape[-1], y.shape[-1]
    W_P = torch.linalg.solve_triangular(
        L_P, torch.eye(n, dtype=Xu.dtype, device=Xu.device), upper=False
    )  # (..., 1, n, n): also the (constant) Jacobian of the prior residual
    W_R = torch.linalg.solve_triangular(
        L_R, torch.eye(m, dtype=Xu.dtype, device=Xu.device), upper=False
    )  # (..., 1 or 2n, m, m)

    ones_n, ones_m = Xu.new_ones(n), Xu.new_ones(m)

    def h_mean(x: Tensor) -> Tensor:  # the solver needs the mean only
        return h.predict_mean(x, uP)

    def residual(x: Tensor) -> Tensor:  # (..., 2n, n) -> (..., 2n, n + m)
        # W v as (W * v) @ 1: much faster than a batched matmul for tiny matrices on CPU
        rp = (W_P * (x - Xu).unsqueeze(-2)) @ ones_n
        rm = (W_R * ((z - h_mean(x)) * o).unsqueeze(-2)) @ ones_m
        return torch.cat([rp, rm], dim=-1)

    def jacobian(x: Tensor) -> Tensor:  # (..., 2n, n + m, n); autograd only through h
        _, Jh = batched_jacobian(h_mean, x)
        Jm = -W_R @ (Jh * o.unsqueeze(-1))
        return torch.cat([W_P.expand(*Jm.shape[:-2], n, n), Jm], dim=-2)

    return bounded_least_squares(
        residual,
        Xu,
        box.unsqueeze(-2),
        jacobian=jacobian,
        tol=tol,
        max_iter=max_iter,
        warn=False,
    )


def constrained_update(
    belief: Belief,
    y: Tensor,
    obs: Tensor | None,
    model: StateSpaceModel,
    box: Box,
    *,
    u: Tensor | None = None,
    theta: ThetaReading = DEFAULT_THETA,
    point_variance: Literal["total", "mean"] = "total",
    covariance: CovarianceForm = "paper",
    noise: Noise | None = None,
    tol: float | None = None,
    max_iter: int = 50,
) -> tuple[Belief, UpdateStats, SolverInfo]:
    """The CCKF update: project the prediction, reconcile every constrained point (NDDR).

    Equations in the module docstring. A step with no observed component keeps the (projected)
    prediction.

    Args:
        belief: the predicted belief ``mean (..., n)``, ``cov (..., n, n)``.
        y: measurement ``(..., m)``; non-finite entries are missing.
        obs: bool ``(..., m)``, False where missing, or ``None`` (the finite entries).
        model: the state-space model (its measurement side).
        box: the bounds, in the belief's dtype and device.
        u: inputs ``(..., nu)`` or ``None``.
        theta: as in :class:`ConstrainedCKF`.
        point_variance: as in :class:`ConstrainedCKF`.
        covariance: as in :class:`ConstrainedCKF`.
        noise: the measurement noise ``R`` of the step (``None``: none).
        tol: as in :class:`ConstrainedCKF`.
        max_iter: as in :class:`ConstrainedCKF`.

    Returns:
        The filtered belief (the projected prediction where nothing was observed; its mean is
        the projected prediction's only there), the step's
        :class:`~torchfilt.filters.steps.UpdateStats` (from the constrained update points) and a
        :class:`SolverInfo`.

    Raises:
        ModelError: the measurement noise (plus any per-point variance) is not positive definite.
    """
    h = model.measurement
    m_pred, P_pred = belief.mean, belief.cov
    R = None if noise is None else noise.cov
    if obs is None:
        obs = torch.isfinite(y)
    y = torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))
    m_proj = box.project(m_pred)
    projected = (m_proj != m_pred).any(-1)
    S_pred = safe_cholesky(P_pred, name="predicted covariance")
    cu = constrained_points(m_proj, S_pred, box, theta=theta)
    Xu, wu = cu.points, cu.weights
    uP = None if u is None else u.unsqueeze(-2).expand(*Xu.shape[:-1], u.shape[-1])
    ph = h.predict(Xu, uP)
    Ys = ph.mean
    y_mean = _wmean(wu, Ys)
    E = Ys - y_mean.unsqueeze(-2)
    Ew = E * wu.unsqueeze(-1)
    Vh, Vh_pts = _variances(h, Xu, wu, m_proj, uP, ph, point_variance)
    if R is None and Vh is None:
        raise ModelError(
            "ConstrainedCKF needs a positive-definite measurement noise R (or a measurement "
            "model with a predictive variance): the reconciliation weighs the measurement by "
            "its inverse"
        )
    R_tot = add(Vh, R)
    P_yy = symmetrize(E.mT @ Ew + R_tot)
    P_xy = (Xu - _wmean(wu, Xu).unsqueeze(-2)).mT @ Ew  # (..., n, m)

    obs_f = obs.to(m_pred.dtype)
    L_yy = safe_cholesky(_observed_block(P_yy, obs_f, 1.0), name="innovation covariance")
    innov = y - y_mean
    e = innov * obs_f
    ll = gaussian_log_prob(e, L_yy, dim=obs_f.sum(-1))

    # ---- NDDR: one bounded least-squares problem per batch element and cubature point
    sol = _reconcile(h, Xu, uP, y, obs_f, S_pred, R, Vh_pts, box, tol=tol, max_iter=max_iter)
    Xk = sol.x
    x_upd = box.project(_wmean(wu, Xk))  # a convex combination; projection only removes round-off
    Dk = Xk - x_upd.unsqueeze(-2)
    P_upd = Dk.mT @ (Dk * wu.unsqueeze(-1))
    if covariance == "corrected":
        K = torch.cholesky_solve((P_xy * obs_f.unsqueeze(-2)).mT, L_yy).mT
        P_upd = P_upd + K @ _observed_block(R_tot, obs_f, 0.0) @ K.mT
    any_obs = obs.any(-1)
    mean_new = torch.where(any_obs.unsqueeze(-1), x_upd, m_proj)
    cov_new = torch.where(any_obs[..., None, None], symmetrize(P_upd), P_pred)
    innov_out = torch.where(obs, innov, torch.full_like(innov, math.nan))
    return (
        Belief(mean_new, cov_new),
        UpdateStats(y_mean, innov_out, P_yy, ll),
        SolverInfo(sol.iterations, sol.status, projected),
    )


#: why the constrained step cannot be captured whole (the plan reads it)
_HOST_DECISIONS = (
    "ConstrainedCKF: the NDDR solver decides on the host when each reconciliation has converged"
)


#: why the constrained step has no exact Kalman path (the plan reads it)
_NO_EXACT = "ConstrainedCKF: the box constraints have no closed-form Kalman counterpart"


class ConstrainedStep:
    """The CCKF step, :func:`constrained_predict` then :func:`constrained_update` with fixed
    options: the :class:`~torchfilt.filters.engine.Step` of :class:`ConstrainedCKF` (the
    engines run it eagerly or as one compiled call per step; online use calls its ``predict``
    and ``update``).

    Args:
        model: the state-space model. box: the bounds.
        covariance, theta, point_variance, tol, max_iter: as in :class:`ConstrainedCKF`.
    """

    sqrt = False

    def __init__(
        self,
        model: StateSpaceModel,
        box: Box,
        *,
        covariance: CovarianceForm,
        theta: ThetaReading,
        point_variance: Literal["total", "mean"],
        tol: float | None,
        max_iter: int,
    ) -> None:
        self.model = model
        self.box = box
        self.covariance: CovarianceForm = covariance
        self.theta: ThetaReading = theta
        self.point_variance: Literal["total", "mean"] = point_variance
        self.tol = tol
        self.max_iter = max_iter
        self.rule = SphericalRadialRule(3)
        self._boxes: dict[tuple[torch.dtype, torch.device], Box] = {}

    def box_for(self, like: Tensor) -> Box:
        """The bounds in ``like``'s dtype and device (cached)."""
        key = (like.dtype, like.device)
        box = self._boxes.get(key)
        if box is None:
            box = self.box.to(dtype=like.dtype, device=like.device)
            self._boxes[key] = box
        return box

    def step(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: Noise,
        R: Noise,
    ) -> tuple[Belief, StepRecord, tuple[Tensor, ...]]:
        """One CCKF step: :func:`constrained_predict` then :func:`constrained_update`.

        Arguments as in :meth:`GaussianFilter.step <torchfilt.filters.GaussianFilter.step>`
        (``points`` is unused: the constrained points are built from each belief). The extra
        outputs are the :class:`SolverInfo` fields ``(iterations, status, projected)``.
        """
        box = self.box_for(belief.mean)
        pred, cache = self.predict(belief, u, points, Q)
        post, stats, info = self._update(pred, y, obs, u, R, box)
        record = StepRecord(
            mean=post.mean,
            cov=post.cov,
            predicted_mean=box.project(pred.mean),
            predicted_cov=pred.cov,
            measurement_mean=stats.measurement_mean,
            innovation=stats.innovation,
            innovation_cov=stats.innovation_cov,
            log_likelihood=stats.log_likelihood,
            cross_cov=cache.cross_cov,
        )
        return post, record, (info.iterations, info.status, info.projected)

    def predict(
        self, belief: Belief, u: Tensor | None, points: UnitPoints, Q: Noise
    ) -> tuple[Belief, PredictCache]:
        """:func:`constrained_predict` (the mean is projected onto the box by the update)."""
        return constrained_predict(
            belief,
            self.model,
            u,
            self.box_for(belief.mean),
            theta=self.theta,
            point_variance=self.point_variance,
            noise=Q,
        )

    def _update(
        self, pred: Belief, y: Tensor, obs: Tensor, u: Tensor | None, R: Noise, box: Box
    ) -> tuple[Belief, UpdateStats, SolverInfo]:
        return constrained_update(
            pred,
            y,
            obs,
            self.model,
            box,
            u=u,
            theta=self.theta,
            point_variance=self.point_variance,
            covariance=self.covariance,
            noise=R,
            tol=self.tol,
            max_iter=self.max_iter,
        )

    def update(
        self,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        points: UnitPoints,
        R: Noise,
        cache: PredictCache | None,
    ) -> tuple[Belief, UpdateStats]:
        """:func:`constrained_update` of one (online) step, ``y`` and ``obs`` broadcast to the
        belief's batch shape."""
        batch, m = belief.mean.shape[:-1], y.shape[-1]
        box = self.box_for(belief.mean)
        post, stats, _ = self._update(belief, y.expand(*batch, m), obs.expand(*batch, m), u, R, box)
        return post, stats

    def prior(self, inputs: FilterInputs) -> Belief:
        """Fresh copies of ``x0`` and ``P0`` (no factor: the step factors the covariance)."""
        return Belief(inputs.x0.clone(), inputs.P0.clone(), None)

    def noise(self, side: torch.nn.Module, t: int, like: Tensor) -> Noise:
        """The noise of ``side`` at step ``t``."""
        return Noise(model_noise(side, t, like), None)

    def points(self, like: Tensor) -> UnitPoints:
        """The degree-3 rule's unit points (unused by the step, carried by the engines)."""
        return unit_points(self.rule, self.model.state_dim, like)


class ConstrainedCKF(GaussianFilter):
    """Cubature Kalman filter with box constraints and per-point NDDR update (CCKF).

    Every predicted and filtered mean, and every cubature point, lies in the box
    ``lower <= x <= upper``. Equations in the module docstring (Liu, Zhang & Chu 2018; spec
    ``cckf.md``). Batched over sequences (any leading batch shape) and over cubature points: each
    step solves all ``(..., 2n)`` reconciliation problems at once with
    :func:`~torchfilt.numerics.bounded_least_squares`.

    :meth:`filter`, :meth:`smooth` and the online :meth:`init` / :meth:`predict` /
    :meth:`update` are the CKF's, run through the same plan and engines with the constrained step
    (:class:`ConstrainedStep`): ``predicted_mean`` is the projected prediction,
    ``measurement_mean`` and ``innovation_cov`` come from the constrained update points, and
    ``log_likelihood`` is the Gaussian approximation ``sum_k log N(z_k; z-_k, P_zz)`` built from
    them. There is no exact Kalman path (``path="kalman"`` and ``parallel=True`` are refused) and
    no CUDA graph (``graphed`` is refused; the plan says why).

    Behaviour at the edges:

    * The prior mean ``x0`` must lie in the box (:class:`~torchfilt.exceptions.InputError` otherwise; project it yourself with
      ``filt.box.project(x0)`` if that is what you want). A predicted mean that ``f`` carries out of
      the box is projected onto it before the update (spec s.2); :class:`ConstrainedInfo` records
      when.
    * Missing measurements (NaN or ``mask``): the reconciliation uses the observed components
      only; a step with none observed skips the update (``x+ = x-``, ``P+ = P-``), as the CKF does.
    * A reconciliation that does not meet the solver tolerance keeps its last iterate (inside the
      box) and one :class:`~torchfilt.exceptions.ConvergenceWarning` per call reports how many.
    * The measurement noise ``R`` (plus any per-point model variance) must be positive definite:
      the NDDR weighs the measurement by its inverse.

    Args:
        model: the state-space model (callables or :class:`~torchfilt.models.ConditionalModel`\\ s,
            learned models with per-point variances included).
        lower: lower bounds, ``(..., n)``, a sequence or a scalar; ``-inf`` entries (or ``None``)
            mean no lower bound.
        upper: upper bounds, ``(..., n)``, a sequence or a scalar; ``+inf`` entries (or
            ``None``) mean no upper bound.
        covariance: ``"paper"`` (spread of the reconciled points, eq. (27)) or ``"corrected"``
            (adds ``K R_tot K^T``; consistent for a linear model).
        theta: ``"paper"`` evaluates the weights at ``F(theta)`` with theta in cubature steps, as
            the paper writes; ``"std"`` at ``F(sqrt(n) theta)``, theta in standard deviations. The
            default is ``"paper"``: on the 2A->B benchmark (``scripts/reproduce_cckf.py``) it gave
            the lower RMSE over the first 20 steps on both starts.
        point_variance: how per-point model variances enter (``"total"``: at every cubature point;
            ``"mean"``: at the mean only), as in :class:`~torchfilt.filters.GaussianFilter`.
        tol: NDDR solver tolerance (``sqrt(delta)``, the remaining Gauss-Newton step in the
            ``J^T J`` metric, i.e. roughly in prior standard deviations); default ``sqrt(eps)``.
        max_iter: NDDR solver iteration limit.
        compile: compile the step (:func:`constrained_predict` + :func:`constrained_update`) with
            ``torch.compile``. The solver's convergence test runs on the host, so the compiled
            step is split into several graphs and the plan runs one compiled call per step (a
            compiled chunk, a while-loop or a CUDA graph cannot hold it: ``graphed`` is refused,
            and the plan says why); as with the CKF, a covariance that fails its Cholesky
            factorisation then turns the sequence to NaN instead of being jittered.

    Example:
        >>> from torchfilt.filters import ConstrainedCKF
        >>> from torchfilt.systems import reaction
        >>> filt = ConstrainedCKF(reaction.model(), lower=[0.0, 0.0], upper=[100.0, 100.0])
        >>> sim = reaction.simulate_truth(runs=4, seed=0)
        >>> res = filt.filter(sim.measurements, x0=reaction.prior_mean(), P0=reaction.prior_cov())
        >>> bool((res.mean >= 0).all())
        True

    Raises:
        InputError: an invalid ``covariance``, ``theta`` or ``max_iter`` (or filter option).
    """

    def __init__(
        self,
        model: StateSpaceModel,
        lower: Tensor | Sequence[float] | float | None,
        upper: Tensor | Sequence[float] | float | None,
        *,
        covariance: CovarianceForm = "paper",
        theta: ThetaReading = DEFAULT_THETA,
        point_variance: Literal["total", "mean"] = "total",
        tol: float | None = None,
        max_iter: int = 50,
        compile: bool = False,
    ) -> None:
        super().__init__(
            model,
            rule=SphericalRadialRule(3),
            point_variance=point_variance,
            compile="step" if compile else False,
        )
        if covariance not in ("paper", "corrected"):
            raise InputError(f"covariance must be 'paper' or 'corrected', got {covariance!r}")
        if theta not in ("paper", "std"):
            raise InputError(f"theta must be 'paper' or 'std', got {theta!r}")
        if max_iter < 1:
            raise InputError(f"max_iter must be >= 1, got {max_iter}")
        self.box = Box(lower, upper, n=model.state_dim)
        self.covariance: CovarianceForm = covariance
        self.theta: ThetaReading = theta
        self.tol = tol
        self.max_iter = int(max_iter)
        step = ConstrainedStep(
            model,
            self.box,
            covariance=covariance,
            theta=theta,
            point_variance=point_variance,
            tol=tol,
            max_iter=self.max_iter,
        )
        options = PlanOptions(
            "step" if compile else None,
            state_dim=model.state_dim,
            obs_dim=model.obs_dim,
            host_decisions=_HOST_DECISIONS,
            no_exact=_NO_EXACT,
        )
        self._setup(step, options)

    def _box_for(self, like: Tensor) -> Box:
        return self._step.box_for(like)  # type: ignore[attr-defined,no-any-return]

    def _prepare(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> FilterInputs:
        """Check a recording as the CKF does, broadcast it against the bounds' batch shape and
        check that ``x0`` lies in the box."""
        inp = super()._prepare(y, u, x0=x0, P0=P0, mask=mask)
        return self._with_box(inp, self._box_for(inp.x0))

    def _run(self, inputs: FilterInputs, keep: Collection[str] | None = None) -> FilterResult:
        """The constrained run of the prepared ``inputs`` (for :meth:`filter`, which is the
        CKF's: ``predicted_mean`` is the projected prediction, ``measurement_mean`` and
        ``innovation_cov`` come from the constrained update points, and ``log_likelihood`` is
        the Gaussian approximation ``sum_k log N(z_k; z-_k, P_zz)`` built from them; ``x0`` must
        lie in the box). A reconciliation that did not converge is reported by one
        :class:`~torchfilt.exceptions.ConvergenceWarning`."""
        return self._result_with_info(inputs, stacklevel=4)[0]

    # ------------------------------------------------------------------ public API
    def filter_with_info(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> tuple[FilterResult, ConstrainedInfo]:
        """:meth:`filter`, plus the solver's iterations and status per step and point.

        Args:
            y: measurements, shape ``(..., T, m)``. Non-finite entries (NaN) are missing.
            u: inputs, shape ``(..., T, nu)``, or ``None``.
            x0: prior mean, shape ``(..., n)``, inside the box.
            P0: prior covariance, shape ``(..., n, n)``, symmetric positive definite.
            mask: optional boolean ``(..., T, m)``; ``False`` marks a component as missing.

        Returns:
            The :class:`~torchfilt.filters.FilterResult` (means ``(..., T, n)``, covariances
            ``(..., T, n, n)``) and the :class:`ConstrainedInfo` of the run.
        """
        inputs = self._prepare(y, u, x0=x0, P0=P0, mask=mask)
        res, info = self._result_with_info(inputs, stacklevel=3)
        warn_nonfinite(res, stacklevel=3)
        return res, info

    def smooth(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
        path: Path = "auto",
        parallel: bool = False,
    ) -> SmootherResult:
        """Filter under the bounds, then the cubature RTS smoother, projected onto the box.

        The backward pass is :func:`~torchfilt.filters.rts_smooth` over this filter's result (its
        cross-covariances come from the constrained prediction points). A Gaussian smoother does
        not know the bounds, so each smoothed mean is then projected onto the box (the
        covariances are left as the RTS pass gives them). For a linear model with no bound in
        reach and ``covariance="corrected"`` this is the CKF's smoother exactly.

        There is no exact path: ``path="kalman"`` and ``parallel=True`` are refused.

        Args:
            y: measurements, shape ``(..., T, m)``. Non-finite entries (NaN) are missing.
            u: inputs, shape ``(..., T, nu)``, or ``None``.
            x0: prior mean, shape ``(..., n)``, inside the box.
            P0: prior covariance, shape ``(..., n, n)``, symmetric positive definite.
            mask: optional boolean ``(..., T, m)``; ``False`` marks a component as missing.
            path: ``"auto"`` or ``"cubature"`` (``"kalman"`` is refused).
            parallel: must be ``False``.

        Returns:
            A :class:`~torchfilt.filters.SmootherResult` with smoothed means ``(..., T, n)``
            (projected onto the box) and covariances ``(..., T, n, n)``.
        """
        from torchfilt.filters.smoother import rts_smooth

        self._exact(path, parallel)  # refuses the exact path
        sm = rts_smooth(self.filter(y, u, x0=x0, P0=P0, mask=mask))
        box = self._box_for(sm.mean)
        return sm._replace(mean=box.project(sm.mean.movedim(-2, 0)).movedim(0, -2))

    # ------------------------------------------------------------------ online use
    def _check_prior_state(self, state: FilterState) -> None:
        """An online prior mean must lie in the box."""
        self._check_in_box(state.mean, self._box_for(state.mean))

    # ------------------------------------------------------------------ internals
    def _result_with_info(
        self, inputs: FilterInputs, *, stacklevel: int
    ) -> tuple[FilterResult, ConstrainedInfo]:
        """The run of ``inputs`` and its solver diagnostics; ``stacklevel`` counts from this
        method (as in :func:`warnings.warn`)."""
        plan, records, extras = self._scan(inputs)
        observed_all = inputs.obs.expand(*inputs.batch, *inputs.obs.shape[-2:])
        res = stack_records(records, observed_all, plan.numerics)
        info = ConstrainedInfo(
            solver_iterations=torch.stack([e[0] for e in extras], dim=-2),
            solver_status=torch.stack([e[1] for e in extras], dim=-2),
            projected=torch.stack([e[2] for e in extras], dim=-1),
        )
        failed = info.solver_status <= 0
        if bool(failed.any()):
            counts = {
                s.name.lower(): int((info.solver_status == s).sum()) for s in SolverStatus if s <= 0
            }
            detail = ", ".join(f"{k}: {v}" for k, v in counts.items() if v)
            warnings.warn(
                f"ConstrainedCKF: {int(failed.sum())} of {failed.numel()} reconciliation problems "
                f"did not converge ({detail}); their last iterates (inside the box) were used",
                ConvergenceWarning,
                stacklevel=stacklevel,
            )
        return res, info

    def _with_box(self, inp: FilterInputs, box: Box) -> FilterInputs:
        """Broadcast the inputs against the bounds' batch shape and check the prior mean."""
        try:
            batch = torch.broadcast_shapes(inp.batch, box.batch_shape)
        except RuntimeError:
            raise ShapeError(
                f"lower/upper: batch shape {tuple(box.batch_shape)} does not broadcast with the "
                f"data's {tuple(inp.batch)}"
            ) from None
        n = inp.x0.shape[-1]
        if batch != inp.batch:
            inp = inp._replace(
                x0=inp.x0.expand(*batch, n), P0=inp.P0.expand(*batch, n, n), batch=batch
            )
        self._check_in_box(inp.x0, box)
        return inp

    @staticmethod
    def _check_in_box(x0: Tensor, box: Box) -> None:
        outside = ~((x0 >= box.lower) & (x0 <= box.upper))
        if bool(outside.any()):
            idx = outside.nonzero()[0].tolist()
            raise InputError(
                f"x0 lies outside the box at index {idx}: x0 = {float(x0[tuple(idx)])}, bounds "
                f"[{float(box.lower.expand_as(x0)[tuple(idx)])}, "
                f"{float(box.upper.expand_as(x0)[tuple(idx)])}]; project it first with "
                "filt.box.project(x0) if that is intended"
            )
