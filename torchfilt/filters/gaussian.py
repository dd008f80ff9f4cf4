"""The batched cubature (sigma-point) Gaussian filter.

    predict:  X_i = m + S xi_i,   X*_i = f(X_i, u),   m^- = sum wm_i X*_i,
              P^- = sum wc_i (X*_i - m^-)(X*_i - m^-)^T + sum wc_i V_f(X_i) + Q
    update:   X_i = m^- + S^- xi_i (re-drawn),   Y_i = h(X_i, u),   y^- = sum wm_i Y_i,
              P_yy = sum wc_i (Y_i - y^-)(Y_i - y^-)^T + sum wc_i V_h(X_i) + R,
              P_xy = sum wc_i (X_i - m^-)(Y_i - y^-)^T,
              K = P_xy P_yy^{-1} (Cholesky solve),  m = m^- + K (y - y^-),  P = P^- - K P_yy K^T

(Arasaratnam & Haykin, IEEE TAC 54(6), 2009; the V terms are the law of total variance over the
cubature points for models with a per-point variance, e.g. Gaussian processes.) The square-root form
propagates ``S`` with QR triangularisation instead of ``P``.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule, SphericalRadialRule, sigma_points
from torchfilt.exceptions import DivergenceWarning, ShapeError
from torchfilt.filters.results import FilterResult, SmootherResult
from torchfilt.models import Prediction, StateSpaceModel
from torchfilt.numerics import (
    cholesky_solve,
    gaussian_log_prob,
    no_host_sync,
    safe_cholesky,
    symmetrize,
    tria,
)

if TYPE_CHECKING:
    from torchfilt.filters.graphed import GraphedFilter

__all__ = ["CKF", "GaussianFilter"]

_LOG_2PI = math.log(2.0 * math.pi)
#: Steps run with Dynamo's guard checks before a compiled step skips them (see ``_scan``).
_GUARD_WARMUP_STEPS = 2


class _Inputs(NamedTuple):
    y: Tensor  # (..., T, m), NaN replaced by 0
    obs: Tensor  # (..., T, m) bool
    u: Tensor | None  # (..., T, nu)
    x0: Tensor  # (B..., n)
    P0: Tensor  # (B..., n, n)
    batch: torch.Size


def _observed(y: Tensor, mask: Tensor | None) -> Tensor:
    """Which components of ``y`` are observed: finite, and ``mask`` True where given.

    Args:
        y: measurements ``(..., T, m)``.
        mask: bool ``(..., T, m)`` broadcastable with ``y``, or ``None``.

    Returns:
        Bool tensor of the broadcast shape.
    """
    obs = torch.isfinite(y)
    if mask is None:
        return obs
    mask = torch.as_tensor(mask, device=y.device)
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    try:
        return obs & mask
    except RuntimeError:
        raise ShapeError(
            f"mask: shape {tuple(mask.shape)} does not broadcast with y {tuple(y.shape)}"
        ) from None


def _warn_nonfinite(res: FilterResult, *, stacklevel: int) -> None:
    """Emit a :class:`DivergenceWarning` if some sequences of ``res`` are non-finite.

    ``stacklevel`` counts from this function (as in :func:`warnings.warn`)."""
    finite = torch.isfinite(res.mean).all(-1).all(-1)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        warnings.warn(
            f"{bad} of {finite.numel()} sequences produced non-finite estimates "
            "(covariance lost definiteness or the model returned non-finite values)",
            DivergenceWarning,
            stacklevel=stacklevel,
        )


class _Step(NamedTuple):
    mean: Tensor
    cov: Tensor
    sqrt: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    y_mean: Tensor
    innovation: Tensor
    innov_cov: Tensor
    loglik: Tensor
    cross: Tensor


def _point_noise(pred: Prediction, wc: Tensor) -> Tensor | None:
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


def _noise_sqrt(A: Tensor) -> Tensor:
    """A square root of a PSD noise matrix (Cholesky if definite, else eigen-decomposition).

    Where no host synchronisation is allowed (``torch.compile``, ``sync_free``) the choice
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


def _cat_cols(*mats: Tensor | None) -> Tensor:
    """Concatenate matrices ``(..., n, k_j)`` along columns after broadcasting batch dims."""
    ms = [m for m in mats if m is not None]
    batch = torch.broadcast_shapes(*(m.shape[:-2] for m in ms))
    return torch.cat([m.expand(*batch, *m.shape[-2:]) for m in ms], dim=-1)


def _add(*terms: Tensor | None) -> Tensor:
    out: Tensor | None = None
    for t in terms:
        if t is not None:
            out = t if out is None else out + t
    assert out is not None
    return out


class GaussianFilter(nn.Module):
    """Batched, differentiable sigma-point Gaussian filter and RTS smoother.

    With the default third-degree spherical-radial rule this is the cubature Kalman filter (CKF);
    with :class:`~torchfilt.cubature.UnscentedRule` it is the UKF, with
    :class:`~torchfilt.cubature.GaussHermiteRule` the Gauss-Hermite filter.

    Args:
        model: the state-space model.
        rule: cubature rule; default :class:`~torchfilt.cubature.SphericalRadialRule` (degree 3).
        sqrt: propagate Cholesky factors with QR triangularisation (square-root CKF, Arasaratnam &
            Haykin 2009). Needs non-negative covariance weights.
        redraw: re-draw the update's points from the predicted covariance (default, as Arasaratnam &
            Haykin). ``False`` reuses the propagated points, as filterpy's CubatureKalmanFilter
            does: then ``P_yy`` and ``P_xy`` miss the spread that ``Q`` adds between the two stages.
        point_variance: how per-point model variances (GP) enter Q and R: ``"total"`` averages them
            over the cubature points (law of total variance), ``"mean"`` evaluates them at the mean
            only.
        compile: compile the per-step function with ``torch.compile`` (worth it for one or a few
            sequences, where per-op overhead dominates). Under compilation a covariance that fails
            its Cholesky factorisation turns the sequence to NaN instead of being jittered.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        rule: CubatureRule | None = None,
        sqrt: bool = False,
        redraw: bool = True,
        point_variance: Literal["total", "mean"] = "total",
        compile: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(model, StateSpaceModel):
            raise TypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")
        if point_variance not in ("total", "mean"):
            raise ValueError(f"point_variance must be 'total' or 'mean', got {point_variance!r}")
        self.model = model
        self.rule = rule if rule is not None else SphericalRadialRule(3)
        if not isinstance(self.rule, CubatureRule):
            raise TypeError(f"rule must be a CubatureRule, got {type(self.rule).__name__}")
        self.sqrt = bool(sqrt)
        self.redraw = bool(redraw)
        self.point_variance = point_variance
        n = model.state_dim
        if self.sqrt and not self.rule.weights_nonnegative(n):
            raise ValueError(
                f"sqrt=True needs non-negative covariance weights; {self.rule!r} has a negative "
                f"weight in dimension {n}"
            )
        self._compiled = bool(compile)
        self._compiled_steps: dict[str, Callable[..., _Step]] = {}

    def _step_for(self, device: torch.device) -> Callable[..., _Step]:
        """The per-step function: compiled (once per device type) when ``compile=True``."""
        if not self._compiled:
            return self._step
        fn = self._compiled_steps.get(device.type)
        if fn is None:
            # On the CPU a C++ wrapper around the generated kernels removes most of the per-call
            # Python overhead, which dominates when few sequences are filtered.
            options: dict[str, Any] | None = {"cpp_wrapper": True} if device.type == "cpu" else None
            fn = torch.compile(self._step, dynamic=False, options=options)
            self._compiled_steps[device.type] = fn
        return fn

    # ------------------------------------------------------------------ input checking
    def _check(
        self, y: Tensor, u: Tensor | None, x0: Tensor, P0: Tensor, mask: Tensor | None
    ) -> _Inputs:
        n, m = self.model.state_dim, self.model.obs_dim
        if not isinstance(y, Tensor):
            raise TypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        if y.dim() < 2 or y.shape[-1] != m:
            raise ShapeError(f"y: expected shape (..., T, m) with m = {m}, got {tuple(y.shape)}")
        if not y.is_floating_point():
            raise TypeError(f"y must be floating point, got {y.dtype}")
        dtype, device = y.dtype, y.device
        T = y.shape[-2]
        x0 = torch.as_tensor(x0, device=device)
        P0 = torch.as_tensor(P0, device=device)
        dtype = torch.promote_types(dtype, x0.dtype) if x0.is_floating_point() else dtype
        dtype = torch.promote_types(dtype, P0.dtype) if P0.is_floating_point() else dtype
        y, x0, P0 = y.to(dtype), x0.to(dtype), P0.to(dtype)
        if x0.dim() < 1 or x0.shape[-1] != n:
            raise ShapeError(f"x0: expected shape (..., n) with n = {n}, got {tuple(x0.shape)}")
        if P0.dim() < 2 or P0.shape[-2:] != (n, n):
            raise ShapeError(f"P0: expected shape (..., n, n) with n = {n}, got {tuple(P0.shape)}")
        if not bool(torch.isfinite(x0).all()):
            raise ValueError("x0 contains non-finite entries")
        if not bool(torch.isfinite(P0).all()):
            raise ValueError("P0 contains non-finite entries")
        if not torch.allclose(P0, P0.mT, rtol=1e-8, atol=0.0):
            raise ValueError("P0 is not symmetric")
        evals = torch.linalg.eigvalsh(P0)
        tol = evals.abs().amax(-1) * math.sqrt(torch.finfo(dtype).eps)
        if bool((evals[..., 0] < -tol).any()) or bool((evals[..., -1] <= 0).any()):
            raise ValueError(
                f"P0 is not positive semi-definite: smallest eigenvalue {float(evals[..., 0].min()):.3e}"
            )
        shapes = {"y": y.shape[:-2], "x0": x0.shape[:-1], "P0": P0.shape[:-2]}
        if u is not None:
            u = torch.as_tensor(u, device=device).to(dtype)
            if u.dim() < 2 or u.shape[-2] != T:
                raise ShapeError(
                    f"u: expected shape (..., T, nu) with T = {T}, got {tuple(u.shape)}"
                )
            if not bool(torch.isfinite(u).all()):
                raise ValueError("u contains non-finite entries; inputs cannot be missing")
            shapes["u"] = u.shape[:-2]
        obs = _observed(y, mask)
        shapes["mask"] = obs.shape[:-2]  # y's batch shape broadcast with the mask's
        for name, side in (("Q", self.model.transition), ("R", self.model.measurement)):
            if side.time_varying_noise:
                noise = side.noise_cov(0)
                assert noise is not None
                shapes[name] = noise.shape[:-2]
            else:
                noise = side.noise_cov()
                if noise is not None:
                    shapes[name] = noise.shape[:-2]
        try:
            batch = torch.broadcast_shapes(*shapes.values())
        except RuntimeError:
            desc = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
            raise ShapeError(f"batch shapes do not broadcast: {desc}") from None
        y = torch.where(obs, y, torch.zeros((), dtype=dtype, device=device))
        x0 = x0.expand(*batch, n)
        P0 = P0.expand(*batch, n, n)
        return _Inputs(y, obs, u, x0, P0, batch)

    # ------------------------------------------------------------------ noise access
    def _noise(self, side: nn.Module, step: int, like: Tensor) -> Tensor | None:
        noise = side.noise_cov(step) if side.time_varying_noise else side.noise_cov()  # type: ignore[operator]
        return None if noise is None else noise.to(dtype=like.dtype, device=like.device)

    # ------------------------------------------------------------------ one step
    def _step(
        self,
        xi: Tensor,
        wm: Tensor,
        wc: Tensor,
        mean: Tensor,
        cov: Tensor,
        sqrt: Tensor,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: Tensor | None,
        Q_sqrt: Tensor | None,
        R: Tensor | None,
        R_sqrt: Tensor | None,
    ) -> _Step:
        """One predict + update; ``xi (P, n)``, ``wm (P,)``, ``wc (P,)`` are the rule's unit points."""
        f, h = self.model.transition, self.model.measurement
        if not self.sqrt:
            sqrt = safe_cholesky(cov, name="filtered covariance")

        # ---- predict
        X = sigma_points(mean, sqrt, xi)  # (..., P, n)
        uP = None if u is None else u.unsqueeze(-2).expand(*X.shape[:-1], u.shape[-1])
        pf = f.predict(X, uP)
        Xs = pf.mean
        m_pred = wm @ Xs
        D = Xs - m_pred.unsqueeze(-2)  # (..., P, n)
        Dw = D * wc.unsqueeze(-1)
        cross = (X - mean.unsqueeze(-2)).mT @ Dw  # Cov(x_{t-1}, x_t)
        if self.point_variance == "mean" and (pf.var is not None or pf.cov is not None):
            pm = f.predict(mean.unsqueeze(-2), None if uP is None else uP[..., :1, :])
            Vf = _point_noise(pm, wc.new_ones(1))
        else:
            Vf = _point_noise(pf, wc)
        if not self.sqrt:
            P_pred = symmetrize(_add(D.mT @ Dw, Vf, Q))
            S_pred = safe_cholesky(P_pred, name="predicted covariance")
            extra_sqrt = None
        else:
            extra_sqrt = None
            if Vf is not None or Q_sqrt is not None:
                Vf_sqrt = None if Vf is None else _noise_sqrt(Vf)
                extra_sqrt = _cat_cols(Vf_sqrt, Q_sqrt)
            S_pred = tria(_cat_cols((D * wc.sqrt().unsqueeze(-1)).mT, extra_sqrt))
            P_pred = S_pred @ S_pred.mT

        # ---- update
        if self.redraw:
            Xu = sigma_points(m_pred, S_pred, xi)
            Xd = Xu - m_pred.unsqueeze(-2)
        else:
            Xu, Xd = Xs, D
        ph = h.predict(Xu, uP)
        Ys = ph.mean
        y_mean = wm @ Ys
        E = Ys - y_mean.unsqueeze(-2)  # (..., P, m)
        Ew = E * wc.unsqueeze(-1)
        if self.point_variance == "mean" and (ph.var is not None or ph.cov is not None):
            pm = h.predict(m_pred.unsqueeze(-2), None if uP is None else uP[..., :1, :])
            Vh = _point_noise(pm, wc.new_ones(1))
        else:
            Vh = _point_noise(ph, wc)
        R_tot = _add(Vh, R) if (Vh is not None or R is not None) else None
        P_yy = E.mT @ Ew if R_tot is None else E.mT @ Ew + R_tot
        P_yy = symmetrize(P_yy)
        P_xy = Xd.mT @ Ew  # (..., n, m)

        obs_f = obs.to(mean.dtype)
        unobs_diag = torch.diag_embed(1.0 - obs_f)
        if not self.sqrt:
            # Restrict P_yy to the observed components (identity on the others): the gain then has
            # zero columns for missing components and the likelihood counts observed ones only.
            P_yy_m = P_yy * (obs_f.unsqueeze(-1) * obs_f.unsqueeze(-2)) + unobs_diag
            L_yy = safe_cholesky(P_yy_m, name="innovation covariance")
            R_sqrt_tot = None
        else:
            R_sqrt_tot = None
            if R_tot is not None:
                R_sqrt_tot = R_sqrt if Vh is None and R_sqrt is not None else _noise_sqrt(R_tot)
            rows = obs_f.unsqueeze(-1)
            Z = (E * wc.sqrt().unsqueeze(-1)).mT * rows  # (..., m, P)
            L_yy = tria(_cat_cols(Z, None if R_sqrt_tot is None else R_sqrt_tot * rows, unobs_diag))
        P_xy_m = P_xy * obs_f.unsqueeze(-2)
        K = cholesky_solve(P_xy_m.mT, L_yy).mT  # (..., n, m)
        innov = y - y_mean
        e = innov * obs_f
        mean_new = m_pred + (K @ e.unsqueeze(-1)).squeeze(-1)
        if not self.sqrt:
            cov_new = symmetrize(P_pred - K @ P_yy_m @ K.mT)
            sqrt_new = S_pred  # unused: the plain form re-factors cov at the next step
        else:
            A = (Xd - E @ K.mT) * wc.sqrt().unsqueeze(-1)  # (..., P, n)
            KR = None if R_sqrt_tot is None else K @ R_sqrt_tot
            sqrt_new = tria(_cat_cols(A.mT, KR, None if self.redraw else extra_sqrt))
            cov_new = sqrt_new @ sqrt_new.mT
        ll = gaussian_log_prob(e, L_yy, dim=obs_f.sum(-1))
        innov_out = torch.where(obs, innov, torch.full_like(innov, float("nan")))
        return _Step(
            mean_new, cov_new, sqrt_new, m_pred, P_pred, y_mean, innov_out, P_yy, ll, cross
        )

    # ------------------------------------------------------------------ public API
    def filter(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> FilterResult:
        """Filter measurement sequences.

        Step ``t`` predicts from ``x_{t-1}`` with ``u[..., t, :]`` (the prior ``N(x0, P0)`` is
        ``x_{-1}``) and then updates with ``y[..., t, :]``.

        Args:
            y: measurements, shape ``(..., T, m)``. Non-finite entries (NaN) are missing.
            u: inputs, shape ``(..., T, nu)``, or ``None``.
            x0: prior mean, shape ``(..., n)``.
            P0: prior covariance, shape ``(..., n, n)``, symmetric positive definite.
            mask: optional boolean ``(..., T, m)``; ``False`` marks a component as missing.

        Returns:
            A :class:`~torchfilt.filters.FilterResult`. A step with no observed component is a
            pure prediction (its log-likelihood term is 0). A sequence whose covariance cannot be
            factored even with jitter becomes NaN from that step on and a
            :class:`~torchfilt.exceptions.DivergenceWarning` is emitted; the rest of the batch is
            unaffected.
        """
        inp = self._check(y, u, x0, P0, mask)
        outs = self._scan(inp, self._step_for(inp.y.device))
        return self._assemble(inp, outs, stacklevel=3)

    def _scan(self, inp: _Inputs, step_fn: Callable[..., _Step]) -> list[_Step]:
        """Run ``step_fn`` over time from the prior, handing it each step's data and noise."""
        T = inp.y.shape[-2]
        if T == 0:
            raise ShapeError("y: the time dimension T must be at least 1")
        mean, cov = inp.x0.contiguous(), inp.P0.contiguous()
        sqrt = safe_cholesky(cov, name="P0")
        f, h = self.model.transition, self.model.measurement
        const_Q = None if f.time_varying_noise else self._noise(f, 0, mean)
        const_R = None if h.time_varying_noise else self._noise(h, 0, mean)
        const_Qs = None if const_Q is None or not self.sqrt else _noise_sqrt(const_Q)
        const_Rs = None if const_R is None or not self.sqrt else _noise_sqrt(const_R)
        pts = self.rule.unit_points(mean.shape[-1], dtype=mean.dtype, device=mean.device)
        # A compiled step sees tensors of identical shape, dtype, device and strides at every step
        # once the first steps have fixed the strides, so Dynamo's guard checks (~0.1 ms per call)
        # can be skipped from then on: the model is not modified inside this loop.
        compiled = step_fn in self._compiled_steps.values()
        outs: list[_Step] = []
        with contextlib.ExitStack() as stance:
            for t in range(T):
                if compiled and t == _GUARD_WARMUP_STEPS:
                    stance.enter_context(torch.compiler.set_stance(skip_guard_eval_unsafe=True))
                if f.time_varying_noise:
                    Q = self._noise(f, t, mean)
                    Qs = None if Q is None or not self.sqrt else _noise_sqrt(Q)
                else:
                    Q, Qs = const_Q, const_Qs
                if h.time_varying_noise:
                    R = self._noise(h, t, mean)
                    Rs = None if R is None or not self.sqrt else _noise_sqrt(R)
                else:
                    R, Rs = const_R, const_Rs
                ut = None if inp.u is None else inp.u[..., t, :]
                st = step_fn(
                    *pts, mean, cov, sqrt, inp.y[..., t, :], inp.obs[..., t, :], ut, Q, Qs, R, Rs
                )
                outs.append(st)
                mean, cov, sqrt = st.mean, st.cov, st.sqrt
        return outs

    def _assemble(self, inp: _Inputs, outs: list[_Step], *, stacklevel: int) -> FilterResult:
        """Stack per-step outputs into a :class:`FilterResult`; warn about non-finite sequences."""
        res = self._stack(inp, outs)
        _warn_nonfinite(res, stacklevel=stacklevel + 1)
        return res

    @staticmethod
    def _stack(inp: _Inputs, outs: list[_Step]) -> FilterResult:
        """Stack per-step outputs into a :class:`FilterResult` (no host synchronisation)."""

        def stack(i: int, dim: int) -> Tensor:
            return torch.stack([o[i] for o in outs], dim=dim)

        res = FilterResult(
            mean=stack(0, -2),
            cov=stack(1, -3),
            predicted_mean=stack(3, -2),
            predicted_cov=stack(4, -3),
            measurement_mean=stack(5, -2),
            innovation=stack(6, -2),
            innovation_cov=stack(7, -3),
            observed=inp.obs.expand(*inp.batch, *inp.obs.shape[-2:]),
            log_likelihood=torch.stack([o.loglik for o in outs], dim=-1).sum(-1),
            cross_cov=stack(9, -3),
        )
        return res

    def graphed(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        warmup: int = 2,
    ) -> GraphedFilter:
        """Capture a whole filtering run of this shape into a CUDA graph (GPU only).

        The returned :class:`~torchfilt.filters.GraphedFilter` replays all ``T`` steps with one
        graph launch; its ``filter(y, u, mask=...)`` takes new data of the same shape. Combine with
        ``compile=True`` for fused kernels. See :mod:`torchfilt.filters.graphed` for the limits.

        Args:
            y: example measurements ``(..., T, m)`` on a CUDA device.
            u: example inputs ``(..., T, nu)`` or ``None``.
            x0: prior mean ``(..., n)``. P0: prior covariance ``(..., n, n)``; both fixed.
            warmup: eager runs before the capture.
        """
        from torchfilt.filters.graphed import GraphedFilter

        return GraphedFilter(self, y, u, x0=x0, P0=P0, warmup=warmup)

    def smooth(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> SmootherResult:
        """Filter, then run the cubature Rauch-Tung-Striebel smoother backwards.

        Arguments as in :meth:`filter`. Returns a :class:`~torchfilt.filters.SmootherResult` with
        smoothed means ``(..., T, n)`` and covariances ``(..., T, n, n)``.
        """
        from torchfilt.filters.smoother import rts_smooth

        return rts_smooth(self.filter(y, u, x0=x0, P0=P0, mask=mask))


class CKF(GaussianFilter):
    """Cubature Kalman filter: :class:`GaussianFilter` with the third-degree spherical-radial rule.

    ``CKF(model, rule=UnscentedRule())`` is the UKF; any :class:`~torchfilt.cubature.CubatureRule`
    may be given.

    Example:
        >>> import torch, torchfilt
        >>> model = torchfilt.LinearGaussianModel(
        ...     A=torch.eye(2), H=torch.eye(1, 2), Q=0.01 * torch.eye(2), R=torch.eye(1))
        >>> y = torch.randn(8, 50, 1)                      # 8 sequences of 50 steps
        >>> res = torchfilt.CKF(model).filter(y, x0=torch.zeros(2), P0=torch.eye(2))
        >>> res.mean.shape
        torch.Size([8, 50, 2])
    """
