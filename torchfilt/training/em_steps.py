"""The E-step and M-steps of :func:`~torchfilt.training.fit_em` (see
:mod:`torchfilt.training.measurement_only` for the method): the smoothed pairs of consecutive
states, the closed-form M-step of a linear-Gaussian model, and the gradient M-step (L-BFGS on the
cubature expectation of the complete-data log-likelihood) of any other model."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule, sigma_points
from torchfilt.exceptions import GaugeError, InputError, ModelError, RunError
from torchfilt.filters import CKF, FilterResult, SmootherResult, rts_smooth
from torchfilt.models import (
    CovarianceParameter,
    LinearGaussianModel,
    StateSpaceModel,
    linear_system,
)
from torchfilt.numerics import gaussian_log_prob, psd_solve, safe_cholesky, symmetrize
from torchfilt.optim import DEFAULTS, make_optimizer
from torchfilt.training.em_exact import exact_smoother
from torchfilt.training.em_noise import closed_form_noise

__all__ = ["SmoothedPairs", "smoothed_pairs"]

#: The M-step's parameter blocks of a non-linear model, tried in this order until one raises the
#: filter likelihood: the joint step, the maps alone, the noises alone.
_M_STEP_BLOCKS: tuple[tuple[str, ...], ...] = (("noise", "maps", "noise"), ("maps",), ("noise",))

#: ECM: a maps block whose gain in ``Q`` is at most this share of its M-step's whole gain found
#: nothing worth its cost (on the near-noise-free robot-arm GP of ``scripts/bench_real_logs.py``
#: its 20 L-BFGS iterations, 24 evaluations of ``Q``, raised ``Q`` by 1.5e-6 per measurement at
#: every M-step while the noise step moved the likelihood by a nat; leaving it out cut 30
#: iterations from 36.1 s to 22.7 s)...
MAPS_IDLE_SHARE = 0.01
#: ... and is left out of the joint step of the next M-steps: 1 after the first idle block, twice
#: as many after each further one in a row, at most this many; then it is tried again
MAPS_PAUSE_MAX = 8


# ----------------------------------------------------------------------------------- E-step
class SmoothedPairs(NamedTuple):
    """Smoothed moments of every transition ``x_{t-1} -> x_t``, ``t = 0..T-1`` (``x_{-1}`` is the
    prior).

    Attributes:
        prev_mean: ``E[x_{t-1} | y]``, shape ``(..., T, n)``.
        prev_cov: ``Cov(x_{t-1} | y)``, shape ``(..., T, n, n)``.
        mean: ``E[x_t | y]``, shape ``(..., T, n)``.
        cov: ``Cov(x_t | y)``, shape ``(..., T, n, n)``.
        cross_cov: ``Cov(x_{t-1}, x_t | y) = G_{t-1} P^s_t`` ``(..., T, n, n)``.
    """

    prev_mean: Tensor
    prev_cov: Tensor
    mean: Tensor
    cov: Tensor
    cross_cov: Tensor


def smoothed_pairs(res: FilterResult, x0: Tensor, P0: Tensor) -> SmoothedPairs:
    """RTS-smooth a filter result, the prior state ``x_{-1}`` included, with lag-one covariances.

    Args:
        res: a filter result ``(..., T, ...)``.
        x0: the prior mean the filter started from, ``(..., n)``.
        P0: the prior covariance, ``(..., n, n)``.

    Returns:
        A :class:`SmoothedPairs`.
    """
    return _pairs(rts_smooth(res), x0, P0)


def _pairs(sm: SmootherResult, x0: Tensor, P0: Tensor) -> SmoothedPairs:
    """:func:`smoothed_pairs` from a smoother result ``sm`` (its forward pass included). Where
    the covariances are one sequence viewed by the whole batch (the exact smoother of a model
    without batch dimensions on complete data), the covariance fields are computed once and
    returned as views expanded over the batch."""
    res = sm.filtered
    covs = (sm.cov, sm.gain, res.predicted_cov, res.cross_cov)
    lead: tuple[int, ...] = ()
    if all(st == 0 for st in P0.stride()[: P0.dim() - 2]) and all(_expanded(x) for x in covs):
        lead = (0,) * (sm.cov.dim() - 3)
        P0 = P0[(0,) * (P0.dim() - 2)]
    P_s, gain, Pp, cross = (x[lead] for x in covs)
    Pp0 = Pp[..., 0, :, :]
    G0 = psd_solve(Pp0, cross[..., 0, :, :].mT, name="predicted covariance").mT
    ms0, Ps0 = sm.mean[..., 0, :], P_s[..., 0, :, :]
    m_prev0 = x0 + (G0 @ (ms0 - res.predicted_mean[..., 0, :]).unsqueeze(-1)).squeeze(-1)
    P_prev0 = symmetrize(P0 + G0 @ (Ps0 - Pp0) @ G0.mT)
    gains = torch.cat([G0.unsqueeze(-3), gain], -3)  # G_{t-1}, t = 0..T-1
    prev_mean = torch.cat([m_prev0.unsqueeze(-2), sm.mean[..., :-1, :]], -2)
    prev_cov = torch.cat([P_prev0.unsqueeze(-3), P_s[..., :-1, :, :]], -3)
    shape = sm.cov.shape
    return SmoothedPairs(
        prev_mean, prev_cov.expand(shape), sm.mean, sm.cov, (gains @ P_s).expand(shape)
    )


def _expanded(x: Tensor) -> bool:
    """Whether ``x (..., T, n, n)`` is one sequence viewed along all its leading dimensions."""
    return x.dim() > 3 and all(st == 0 for st in x.stride()[: x.dim() - 3])


# ----------------------------------------------------------------------------------- M-steps
class _Lin(NamedTuple):
    A: Tensor
    H: Tensor
    Q: Tensor
    R: Tensor
    B: Tensor | None
    D: Tensor | None


def _summed(all_reduce: Callable[[Tensor], None] | None, *values: Tensor) -> list[Tensor]:
    """The values in float64, summed over the processes of a data-parallel fit with one
    collective (unchanged without ``all_reduce``)."""
    vals = [v.detach().to(torch.float64) for v in values]
    if all_reduce is None:
        return vals
    flat = torch.cat([v.reshape(-1) for v in vals])
    all_reduce(flat)
    out, offset = [], 0
    for v in vals:
        out.append(flat[offset : offset + v.numel()].reshape(v.shape))
        offset += v.numel()
    return out


def _cov_sum(P: Tensor, keep: Tensor) -> Tensor:
    """The sum of the covariances ``P (..., T, n, n)`` over the steps where ``keep (..., T)``
    (float64): a weighted sum over ``T`` of the one sequence where ``P`` is that sequence viewed
    by the whole batch."""
    n, T = P.shape[-1], P.shape[-3]
    if _expanded(P):
        w = keep.reshape(-1, T).sum(0).to(torch.float64)
        return (w @ P[(0,) * (P.dim() - 3)].reshape(T, n * n).to(torch.float64)).reshape(n, n)
    return P.reshape(-1, n, n)[keep.reshape(-1)].to(torch.float64).sum(0)


def _linear_stats(
    sp: SmoothedPairs, Y: Tensor, U: Tensor | None, valid: Tensor, with_B: bool, D: Tensor | None
) -> list[Tensor]:
    """The expected sufficient statistics of :func:`_linear_m_step` (float64): ``N, Sxx, Spp,
    Sxp`` (then ``Spu, Suu, Sxu`` with ``B``), then the observed rows' ``n_ok, Sxx_o, Sxy,
    Syy``. The second moments of the means come from one product of the stacked
    ``[m_t, m_{t-1}, u_t, y_t - D u_t]`` where every kept step is observed."""
    n, f64 = sp.mean.shape[-1], torch.float64
    keep = valid.reshape(-1)
    m_prev = sp.prev_mean.reshape(-1, n)[keep].to(f64)
    m_cur = sp.mean.reshape(-1, n)[keep].to(f64)
    u = U.reshape(-1, U.shape[-1])[keep].to(f64) if U is not None else None
    y = Y.reshape(-1, Y.shape[-1])[keep].to(f64)
    if D is not None:
        assert u is not None
        y = y - u @ D.to(f64).mT
    ok_rt = valid & torch.isfinite(Y).all(-1)
    ok = ok_rt.reshape(-1)[keep]
    every = bool(ok.all())
    cols = [m_cur, m_prev, *([u] if with_B and u is not None else []), *([y] if every else [])]
    Z = torch.cat(cols, -1)
    M = Z.mT @ Z
    cur, prev = slice(0, n), slice(n, 2 * n)
    stats = [
        torch.tensor(float(m_cur.shape[0]), dtype=f64),  # N
        _cov_sum(sp.cov, valid) + M[cur, cur],  # Sxx
        _cov_sum(sp.prev_cov, valid) + M[prev, prev],  # Spp
        _cov_sum(sp.cross_cov, valid).mT + M[cur, prev],  # Sxp = E[x_t x_{t-1}^T]
    ]
    if with_B:
        nu = U.shape[-1]  # type: ignore[union-attr]
        ub = slice(2 * n, 2 * n + nu)
        stats += [M[prev, ub], M[ub, ub], M[cur, ub]]  # Spu, Suu, Sxu
    if every:  # measurement: every kept row is observed
        yb = slice(M.shape[-1] - y.shape[-1], None)
        return [*stats, stats[0], stats[1], M[cur, yb], M[yb, yb]]
    # measurement: rows with every component observed
    yo, mo = y[ok], m_cur[ok]
    return [
        *stats,
        torch.tensor(float(ok.sum()), dtype=f64),  # observed rows
        _cov_sum(sp.cov, ok_rt) + mo.mT @ mo,  # Sxx_o
        mo.mT @ yo,  # Sxy
        yo.mT @ yo,  # Syy
    ]


def _linear_m_step(
    lin: _Lin,
    sp: SmoothedPairs,
    Y: Tensor,
    U: Tensor | None,
    valid: Tensor,
    known: list[int],
    learn_R: bool,
    all_reduce: Callable[[Tensor], None] | None = None,
    fixed: frozenset[str] = frozenset(),
) -> _Lin:
    """Closed-form M-step of a linear-Gaussian model (Shumway & Stoffer 1982; Ghahramani &
    Hinton 1996), with inputs, known rows of ``H`` and missing measurement rows.

    The expected sufficient statistics (float64) are sums over the steps ``valid (R, T)`` (a
    padded step past a recording's end is no transition of it), so a data-parallel fit sums them
    over the processes (one collective) before the closed form.

    The blocks named in ``fixed`` (of ``A, B, Q, H, R``) keep their values, and the free ones
    take their closed form given them (the conditional maximisation: ``B`` given a fixed ``A``,
    ``Q`` from the residuals of the ``A, B`` used, ``R`` from the ``H`` used)."""
    n, dtype = lin.A.shape[-1], lin.A.dtype
    with_B = lin.B is not None and U is not None
    D = lin.D if U is not None else None
    Uu = U if with_B or D is not None else None
    stats = _summed(all_reduce, *_linear_stats(sp, Y, Uu, valid, with_B, D))
    N, Sxx, Spp, Sxp = stats[:4]
    if with_B:
        Spu, Suu, Sxu = stats[4:7]
        Szz = torch.cat([torch.cat([Spp, Spu], -1), torch.cat([Spu.mT, Suu], -1)], -2)
        Sxz = torch.cat([Sxp, Sxu], -1)
    else:
        Szz, Sxz = Spp, Sxp
    n_ok, Sxx_o, Sxy, Syy = stats[-4:]
    AB = psd_solve(Szz, Sxz.mT, name="expected state second moment").mT
    if fixed & {"A", "B"}:
        AB = _fixed_transition(lin, AB, Sxz, Szz, n, with_B, fixed)
        S = Sxx - AB @ Sxz.mT - Sxz @ AB.mT + AB @ Szz @ AB.mT
    else:
        S = Sxx - AB @ Sxz.mT
    Q = lin.Q if "Q" in fixed else _psd_part(S / N).to(dtype)
    A = AB[:, :n].to(dtype)
    B = AB[:, n:].to(dtype) if with_B else lin.B
    H, R = lin.H, lin.R
    if float(n_ok) > 0:
        Hd = H.to(torch.float64)
        unknown = [j for j in range(H.shape[0]) if j not in known]
        if unknown and "H" not in fixed:
            Hu = psd_solve(Sxx_o, Sxy[:, unknown], name="state second moment").mT
            Hd = Hd.clone()
            Hd[unknown] = Hu
            H = Hd.to(dtype)
        if learn_R and "R" not in fixed:
            # sum_t E[(y_t - H x_t)(y_t - H x_t)^T] from the sums
            R = _psd_part((Syy - Hd @ Sxy - Sxy.mT @ Hd.mT + Hd @ Sxx_o @ Hd.mT) / n_ok).to(dtype)
    return _Lin(A, H, Q, R, B, lin.D)


def _psd_part(S: Tensor) -> Tensor:
    """The symmetric part of a closed-form noise covariance ``S (n, n)`` (float64), with its
    negative eigenvalues set to zero. ``S`` is a difference of second moments: semi-definite in
    exact arithmetic, but indefinite by cancellation where a direction has (almost) no noise
    (on a real log, -2e-11 against a largest eigenvalue under 2e-3), which the model's noise
    check would refuse. Unchanged where no eigenvalue is negative or an entry is not finite."""
    S = symmetrize(S)
    if not bool(torch.isfinite(S).all()):
        return S  # refused by the model's noise check, which names it
    evals, vecs = torch.linalg.eigh(S)
    if float(evals.min()) >= 0.0:
        return S
    return symmetrize((vecs * evals.clamp_min(0.0).unsqueeze(-2)) @ vecs.mT)


def _fixed_transition(
    lin: _Lin, AB: Tensor, Sxz: Tensor, Szz: Tensor, n: int, with_B: bool, fixed: frozenset[str]
) -> Tensor:
    """``[A B]`` with the fixed blocks at their values and a free one at its closed form given
    the fixed one (float64)."""
    f64 = torch.float64
    A = lin.A.to(f64)
    if not with_B:
        return A if "A" in fixed else AB
    assert lin.B is not None
    B = lin.B.to(f64)
    if "A" in fixed and "B" in fixed:
        return torch.cat([A, B], -1)
    Spp, Spu, Suu = Szz[:n, :n], Szz[:n, n:], Szz[n:, n:]
    Sxp, Sxu = Sxz[:, :n], Sxz[:, n:]
    if "A" in fixed:  # B = (Sxu - A Spu) Suu^-1
        B = psd_solve(Suu, (Sxu - A @ Spu).mT, name="input second moment").mT
    else:  # A = (Sxp - B Spu^T) Spp^-1
        A = psd_solve(Spp, (Sxp - B @ Spu.mT).mT, name="expected state second moment").mT
    return torch.cat([A, B], -1)


def _point_cov(side: Any, pred: Any) -> Tensor:
    """Per-point covariance ``(..., P, d, d)`` of a side's output: its additive noise plus the
    covariance (or variance) its prediction ``pred`` reports."""
    d = pred.mean.shape[-1]
    noise = side.noise_cov()
    dtype = pred.mean.dtype
    cov = torch.zeros(d, d, dtype=dtype) if noise is None else noise.to(dtype)
    cov = cov.expand(*pred.mean.shape[:-1], d, d)
    if pred.cov is not None:
        return cov + pred.cov
    if pred.var is not None:
        return cov + torch.diag_embed(pred.var)
    return cov


class _PairPoints(NamedTuple):
    """What ``Q(theta)`` needs of the smoothed pairs that does not depend on the parameters:
    the cubature points of every counted transition and of every observed step, computed once per
    M-step instead of at every L-BFGS evaluation."""

    xa: Tensor  # (N, P, n): the points of x_{t-1}
    xb: Tensor  # (N, P, n): those of x_t
    wm: Tensor  # (P,)
    uu: Tensor | None  # (N, P, nu)
    p1: Tensor | None  # (K, P1, n): the points of x_t at the steps with an observed component
    u1: Tensor | None  # (K, P1, nu)
    wm1: Tensor | None  # (P1,)
    o: Tensor | None  # (K, 1, m): the observed components
    both: Tensor | None  # (K, 1, m, m)
    unit: Tensor | None  # (K, 1, m, m): unit variance of the missing components
    y: Tensor | None  # (K, 1, m): the measurements (0 where missing)
    all_seen: bool = False  # every component of those steps observed


def _pair_points(
    n: int,
    sp: SmoothedPairs,
    Y: Tensor,
    U: Tensor | None,
    rule: CubatureRule,
    measurement_term: bool,
    valid: Tensor,
) -> _PairPoints:
    """The parameter-free part of :func:`_expected_loglik` (see :class:`_PairPoints`)."""
    dtype = sp.mean.dtype
    keep = valid.reshape(-1)
    mean2 = torch.cat([sp.prev_mean, sp.mean], -1).reshape(-1, 2 * n)[keep]
    cov2 = torch.cat(
        [
            torch.cat([sp.prev_cov, sp.cross_cov], -1),
            torch.cat([sp.cross_cov.mT, sp.cov], -1),
        ],
        -2,
    ).reshape(-1, 2 * n, 2 * n)[keep]
    xi, wm, _ = rule.unit_points(2 * n, dtype=dtype, device=mean2.device)
    S = safe_cholesky(symmetrize(cov2), name="smoothed pair covariance")
    pts = sigma_points(mean2, S, xi)  # (N, P, 2n)
    uu = None
    if U is not None:
        uu = U.reshape(-1, U.shape[-1])[keep].unsqueeze(-2).expand(-1, pts.shape[-2], -1)
    if not measurement_term:
        return _PairPoints(
            pts[..., :n], pts[..., n:], wm, uu, None, None, None, None, None, None, None
        )
    m = Y.shape[-1]
    y = Y.reshape(-1, m)
    seen = torch.isfinite(y) & keep.unsqueeze(-1)  # (N, m): the observed components
    ok = seen.any(-1)
    xi1, wm1, _ = rule.unit_points(n, dtype=dtype, device=mean2.device)
    S1 = safe_cholesky(symmetrize(sp.cov.reshape(-1, n, n)[ok]), name="smoothed covariance")
    p1 = sigma_points(sp.mean.reshape(-1, n)[ok], S1, xi1)
    u1 = None
    if U is not None:
        u1 = U.reshape(-1, U.shape[-1])[ok].unsqueeze(-2).expand(-1, p1.shape[-2], -1)
    o = seen[ok].unsqueeze(-2)  # (K, 1, m)
    both = o.unsqueeze(-1) & o.unsqueeze(-2)
    unit = torch.diag_embed((~o).to(dtype))
    return _PairPoints(
        pts[..., :n], pts[..., n:], wm, uu, p1, u1, wm1, o, both, unit,
        y[ok].nan_to_num().unsqueeze(-2), bool(o.all()),
    )  # fmt: skip


def _point_chol(side: Any, pred: Any, name: str) -> Tensor:
    """The Cholesky factor of :func:`_point_cov`: one ``(d, d)`` factor of the noise, shared by
    every point, when the prediction reports no per-point variance and the noise is one matrix
    (the same matrix at every point, factored once); else one factor per point."""
    noise = side.noise_cov()
    if pred.cov is None and pred.var is None and noise is not None and noise.dim() == 2:
        return safe_cholesky(noise.to(pred.mean.dtype), name=name)
    return safe_cholesky(_point_cov(side, pred), name=name)


def _expected_loglik(
    model: StateSpaceModel,
    sp: SmoothedPairs | _PairPoints,
    Y: Tensor,
    U: Tensor | None,
    rule: CubatureRule,
    measurement_term: bool,
    valid: Tensor,
) -> Tensor:
    """``Q(theta)``: the cubature expectation of the complete-data log-likelihood over the steps
    ``valid (R, T)``; ``sp`` the smoothed pairs or their points from :func:`_pair_points` (the
    same arguments), which an M-step computes once for all its evaluations."""
    pp = (
        sp
        if isinstance(sp, _PairPoints)
        else _pair_points(model.state_dim, sp, Y, U, rule, measurement_term, valid)
    )
    pred = model.transition.predict(pp.xa, pp.uu)
    L = _point_chol(model.transition, pred, "transition covariance")
    q = (gaussian_log_prob(pp.xb - pred.mean, L) * pp.wm).sum()
    if measurement_term:
        assert pp.p1 is not None and pp.o is not None and pp.both is not None
        assert pp.unit is not None and pp.y is not None and pp.wm1 is not None
        hp = model.measurement.predict(pp.p1, pp.u1)
        # the marginal density of the observed components of a partly observed step: a missing
        # component gets residual 0, unit variance and no covariance with the others, and is
        # not counted in the normalising constant (as in the filter's masked update)
        r = torch.where(pp.o, pp.y - hp.mean, 0.0)
        if pp.all_seen:  # every component observed: no masking, C is the point covariance
            Lr = _point_chol(model.measurement, hp, "measurement covariance")
        else:
            C = torch.where(pp.both, _point_cov(model.measurement, hp), 0.0) + pp.unit
            Lr = safe_cholesky(C, name="measurement covariance")
        lp = gaussian_log_prob(r, Lr, dim=pp.o.sum(-1))
        q = q + (lp * pp.wm1).sum()
    return q


class _MStepFailed(RunError):
    """A process of a data-parallel gradient M-step failed to evaluate ``Q``: all undo it (a
    :class:`~torchfilt.exceptions.RunError` where it escapes, at the M-step's start)."""


class _Reducer:
    """``all_reduce`` that remembers whether a collective itself failed (a lost process), so that
    such a failure is never mistaken for a failed M-step and swallowed."""

    def __init__(self, all_reduce: Callable[[Tensor], None] | None) -> None:
        self.all_reduce, self.broken = all_reduce, False

    def __call__(self, flat: Tensor) -> None:
        assert self.all_reduce is not None
        try:
            self.all_reduce(flat)
        except BaseException:
            self.broken = True
            raise


def _gradient_m_step(
    model: StateSpaceModel,
    plist: list[nn.Parameter],
    sp: SmoothedPairs,
    Y: Tensor,
    U: Tensor | None,
    valid: Tensor,
    rule: CubatureRule,
    measurement_term: bool,
    iterations: int,
    all_reduce: Callable[[Tensor], None] | None = None,
    *,
    blocks: tuple[str, ...] = ("noise", "maps", "noise"),
    skip_maps: bool = False,
) -> tuple[float, float] | None:
    """Block coordinate L-BFGS on ``-Q(theta)`` over ``blocks`` in turn: by default the noise
    covariances, then the other parameters (the maps), then the noise again (the maps'
    gradients dwarf the noises', so a joint step leaves ``Q`` and ``R`` almost where they
    were); undone if ``Q`` does not improve (generalised EM). ``skip_maps`` leaves the maps
    block out (ECM, see :data:`MAPS_IDLE_SHARE`).

    Returns the maps block's gain in ``Q`` and the whole step's (``None`` where the maps block
    did not run or the step was undone).

    Data-parallel (``all_reduce``): every evaluation of ``Q`` and its gradient is one collective
    that sums them over the processes (whatever the local outcome: a process whose evaluation
    failed sends NaN and a flag, and then every process undoes the step), so all take the same
    L-BFGS steps."""
    reduce = None if all_reduce is None else _Reducer(all_reduce)
    scale = float(_summed(reduce, torch.tensor(float(valid.sum())))[0])
    before = [p.detach().clone() for p in plist]
    noise_ids = {
        id(p)
        for mod in model.modules()
        if isinstance(mod, CovarianceParameter)
        for p in mod.parameters()
    }
    noise = [p for p in plist if id(p) in noise_ids]
    rest = [p for p in plist if id(p) not in noise_ids]
    with torch.no_grad():  # the points of the smoothed pairs: the same at every evaluation
        pts = _pair_points(model.state_dim, sp, Y, U, rule, measurement_term, valid)

    def q_value() -> float:
        """``Q`` at the current parameters, summed over the processes."""
        failed = False
        with torch.no_grad():
            try:
                q = _expected_loglik(model, pts, Y, U, rule, measurement_term, valid).detach()
            except (RuntimeError, ValueError):
                if reduce is None:
                    raise
                q, failed = torch.tensor(math.nan), True
        total, flag = _summed(reduce, q.reshape(()), torch.tensor(float(failed)))
        if float(flag) > 0:
            raise _MStepFailed(
                "fit_em: the M-step's Q could not be evaluated on some process of the "
                "data-parallel fit"
            )
        return float(total)

    q0 = q_value()

    def run(group: list[nn.Parameter]) -> None:
        opt = make_optimizer(group, replace(DEFAULTS["em"].optimizer, max_iter=iterations))

        def closure() -> Tensor:
            opt.zero_grad()
            if reduce is None:
                loss = -_expected_loglik(model, pts, Y, U, rule, measurement_term, valid) / scale
                loss.backward()
                return loss.detach()
            # data-parallel: local sums, then one collective for the value and the gradient
            # (on every process whatever its outcome, so that none waits forever)
            failed = False
            try:
                local = -_expected_loglik(model, pts, Y, U, rule, measurement_term, valid)
                local.backward()
                value = local.detach()
            except (RuntimeError, ValueError):
                value, failed = torch.tensor(math.nan), True
            grads = [
                torch.full_like(p, math.nan)
                if failed
                else (torch.zeros_like(p) if p.grad is None else p.grad)
                for p in group
            ]
            total, flag, *summed = _summed(
                reduce, value.reshape(()), torch.tensor(float(failed)), *grads
            )
            if float(flag) > 0:
                raise _MStepFailed(
                    "fit_em: the M-step's Q could not be evaluated on some process of the "
                    "data-parallel fit"
                )
            for p, g in zip(group, summed, strict=True):
                p.grad = (g / scale).to(p.dtype)
            return (total / scale).to(before[0].dtype)

        opt.step(closure)  # type: ignore[arg-type]

    maps_gain: float | None = None
    try:
        for b in blocks:
            if b == "noise" and noise:
                done = _closed_form_noises(model, plist, pts, measurement_term, reduce)
                others = [p for p in noise if id(p) not in done]
                if others:
                    run(others)
            elif b == "maps" and rest and not skip_maps:
                q_maps = q_value()
                run(rest)
                maps_gain = q_value() - q_maps
        q1 = q_value()
        ok = math.isfinite(q1) and q1 >= q0
    except (RuntimeError, ValueError, IndexError):  # a failed factorisation, or torch's
        # strong-Wolfe search left without a finite bracket, on a wild line-search step
        if reduce is not None and reduce.broken:
            raise  # a lost process, not a bad step
        ok = False
    if not ok:
        with torch.no_grad():
            for p, v in zip(plist, before, strict=True):
                p.copy_(v)
        return None
    return None if maps_gain is None else (maps_gain, q1 - q0)


def _closed_form_noises(
    model: StateSpaceModel,
    plist: list[nn.Parameter],
    pts: _PairPoints,
    measurement_term: bool,
    reduce: _Reducer | None,
) -> set[int]:
    """Set the noises that have a closed form given the maps (:mod:`em_noise`); the ``id`` of
    every parameter set (the others keep their L-BFGS block)."""
    free = {id(p) for p in plist}
    t_noise = getattr(model.transition, "noise_param", None)
    if t_noise is not None and t_noise is getattr(model.measurement, "noise_param", None):
        return set()  # one covariance shared by both sides: no single residual

    def summed(*v: Tensor) -> list[Tensor]:
        return _summed(reduce, *v)

    done = closed_form_noise(model.transition, pts.xa, pts.uu, pts.xb, pts.wm, free, summed)
    if measurement_term and pts.all_seen and pts.p1 is not None:
        assert pts.y is not None and pts.wm1 is not None
        done += closed_form_noise(model.measurement, pts.p1, pts.u1, pts.y, pts.wm1, free, summed)
    return {id(p) for p in done}


def _linear_start(model: StateSpaceModel, dtype: torch.dtype, known: list[int]) -> _Lin | None:
    """The matrices of a model that :func:`~torchfilt.models.linear_system` recognises (copies,
    in ``dtype``), for the closed-form M-step; ``None`` for any other model."""
    sys = linear_system(model)
    if sys is None:
        return None
    Qm, Rm = model.transition.noise_cov(), model.measurement.noise_cov()
    if Qm is None or Rm is None:
        raise ModelError("fit_em: a linear model needs both Q and R")
    lin = _Lin(
        sys.A.detach().to(dtype).clone(),
        sys.H.detach().to(dtype).clone(),
        Qm.detach().to(dtype).clone(),
        Rm.detach().to(dtype).clone(),
        None if sys.B is None else sys.B.detach().to(dtype).clone(),
        None if sys.D is None else sys.D.detach().to(dtype).clone(),
    )
    if not bool((lin.H[known] != 0).any()):
        raise GaugeError(
            f"known_channels {known}: the known rows of H are all zero, so they pin no state "
            "coordinate; give channels whose measurement map sees the state"
        )
    return lin


def compile_mode(compile: object) -> Literal[False, "step", "loop"]:
    """``fit_em``'s ``compile`` option normalised: ``True`` is ``"loop"``.

    Raises:
        InputError: not ``False``, ``True``, ``"step"`` or ``"loop"``.
    """
    if compile is True:
        return "loop"
    if compile is False or compile in ("step", "loop"):
        return compile  # type: ignore[return-value]
    raise InputError(f"compile: expected False, True, 'step' or 'loop', got {compile!r}")


class _EMProblem:
    """The state of an EM fit between iterations: the parameters (the matrices ``lin`` of a
    linear-Gaussian model, else the model's parameters ``plist``) and the data; an E-step and an
    M-step on them."""

    def __init__(
        self,
        model: StateSpaceModel,
        lin: _Lin | None,
        plist: list[nn.Parameter],
        recs: Any,
        valid: Tensor,
        known: list[int],
        rule: CubatureRule,
        reduce: _Reducer | None,
        learn_R: bool,
        m_step_iterations: int,
        backtracks: int,
        fixed: frozenset[str] = frozenset(),
        compile: Literal[False, "step", "loop"] = False,
    ) -> None:
        self.fixed = fixed
        # one filter for the whole fit, so that a compiled one compiles once (the parameters
        # change in place between runs and are inputs of the compiled graph)
        self.ckf = None if lin is not None else CKF(model, rule=rule, compile=compile)
        self.model, self.lin, self.plist = model, lin, plist
        self.Y, self.U = recs.y, recs.u
        self.X0, self.C0 = recs.x0.detach(), recs.P0.detach()
        self.valid, self.known, self.rule, self.reduce = valid, known, rule, reduce
        self.learn_R, self.m_step_iterations, self.backtracks = (
            learn_R,
            m_step_iterations,
            backtracks,
        )
        #: the part of the iteration under way, for an error's message
        self.phase = "E-step"
        #: ECM (:data:`MAPS_IDLE_SHARE`): the M-steps whose joint step still leaves the maps
        #: out, and how many the next idle maps block leaves out
        self.maps_pause, self.maps_next = 0, 1

    def current(self) -> StateSpaceModel:
        """The model at the current parameters."""
        lin = self.lin
        if lin is None:
            return self.model
        return LinearGaussianModel(lin.A, lin.H, lin.Q, lin.R, lin.B, lin.D)

    def state(self) -> list[Tensor]:
        """Copies of the current parameters."""
        if self.lin is not None:
            return [t.clone() for t in self.lin if t is not None]
        return [p.detach().clone() for p in self.plist]

    def load(self, values: list[Tensor]) -> None:
        """Set the parameters to ``values`` (from :meth:`state`)."""
        if self.lin is not None:
            it = iter(values)
            self.lin = _Lin(*(None if t is None else next(it) for t in self.lin))  # type: ignore[arg-type]
            return
        with torch.no_grad():
            for p, v in zip(self.plist, values, strict=True):
                p.copy_(v)

    def filtered(self) -> tuple[float, FilterResult]:
        """A non-linear model's filter log-likelihood (summed over the processes) and the CKF's
        result (a linear model's E-step smooths in one go: :meth:`e_step`)."""
        self.phase = "E-step (the filter)"
        with torch.no_grad():
            assert self.ckf is not None  # a linear model's E-step is exact: see e_step
            res = self.ckf.filter(self.Y, self.U, x0=self.X0, P0=self.C0)
            ll = _summed(self.reduce, res.log_likelihood.sum())[0]
            return float(ll), res

    def smoothed(self, res: FilterResult) -> SmoothedPairs:
        """The smoothed pairs of a filter result of :meth:`filtered`."""
        self.phase = "E-step (the smoother)"
        with torch.no_grad():
            return smoothed_pairs(res, self.X0, self.C0)

    def e_step(self) -> tuple[float, SmoothedPairs]:
        """The filter log-likelihood (summed over the processes) and the smoothed pairs."""
        if self.lin is not None:
            self.phase = "E-step (the Kalman smoother)"
            with torch.no_grad():
                # the exact Kalman filter and RTS smoother (batched over the recordings: no
                # cubature points, and one backward recursion of the shared covariances)
                # (the square-root form where rounding broke the standard one: em_exact)
                sm = exact_smoother(self.current(), self.Y, self.U, self.X0, self.C0)
                total = _summed(self.reduce, sm.filtered.log_likelihood.sum())[0]
                return float(total), _pairs(sm, self.X0, self.C0)
        ll, res = self.filtered()
        return ll, self.smoothed(res)

    def closed_form(self, sp: SmoothedPairs) -> None:
        """A linear-Gaussian model's closed-form M-step from the smoothed pairs ``sp`` (no
        E-step after it)."""
        assert self.lin is not None  # only a linear-Gaussian model has the closed form
        self.phase = "M-step"
        self.lin = _linear_m_step(
            self.lin, sp, self.Y, self.U, self.valid, self.known, self.learn_R, self.reduce,
            self.fixed,
        )  # fmt: skip

    def m_step(self, ll: float, sp: SmoothedPairs) -> tuple[float, SmoothedPairs, bool]:
        """One M-step from the E-step ``(ll, sp)`` and the E-step after it: the new
        log-likelihood and smoothed pairs, and whether no M-step raised the likelihood (then the
        parameters are back where they were and ``(ll, sp)`` is returned)."""
        if self.lin is not None:
            self.closed_form(sp)
            return (*self.e_step(), False)
        before = self.state()
        self.phase = "M-step"
        # The E-step of a non-linear model is the CKF's Gaussian approximation, so a better Q need
        # not mean a better likelihood: halve the step until it is (safeguarded GEM). If the joint
        # step still lowers it, try the maps alone, then the noises alone (expectation-conditional
        # maximisation): a wrong model's smoothed states look noisy, and the noise step alone can
        # be what lowers the likelihood.
        skip, self.maps_pause = self.maps_pause > 0, max(0, self.maps_pause - 1)
        for blocks in _M_STEP_BLOCKS:
            gains = _gradient_m_step(
                self.model, self.plist, sp, self.Y, self.U, self.valid, self.rule, self.learn_R,
                self.m_step_iterations, self.reduce, blocks=blocks,
                skip_maps=skip and blocks is _M_STEP_BLOCKS[0],
            )  # fmt: skip
            if gains is not None and blocks is _M_STEP_BLOCKS[0]:
                self._pace_maps(*gains)
            # smoothed only once a step is kept: a rejected trial needs its likelihood alone
            ll_new, res_new = self.trial()
            after = self.state()
            for k in range(1, self.backtracks + 1):
                if ll_new >= ll:
                    break
                t = 0.5**k
                self.load([b + t * (a - b) for a, b in zip(after, before, strict=True)])
                ll_new, res_new = self.trial()
            if ll_new >= ll and res_new is not None:
                return ll_new, self.smoothed(res_new), False
            self.load(before)
        return ll, sp, True

    def _pace_maps(self, maps_gain: float, total: float) -> None:
        """After a joint step whose maps block ran: pause the maps block where it found nothing
        (:data:`MAPS_IDLE_SHARE`), for twice as many M-steps as the last pause in a row."""
        if maps_gain <= MAPS_IDLE_SHARE * max(total, 0.0):
            self.maps_pause = self.maps_next
            self.maps_next = min(2 * self.maps_next, MAPS_PAUSE_MAX)
        else:
            self.maps_next = 1

    def ecm_state(self) -> list[int]:
        """What a checkpoint keeps of the maps block's pauses: ``[maps_pause, maps_next]``."""
        return [self.maps_pause, self.maps_next]

    def ecm_load(self, values: list[int]) -> None:
        """Continue from :meth:`ecm_state`."""
        self.maps_pause, self.maps_next = int(values[0]), int(values[1])

    def trial(self) -> tuple[float, FilterResult | None]:
        """The filter log-likelihood of an M-step's trial parameters (``-inf``, no result, where
        a factorisation in the model failed there: the trial is rejected like a worse one)."""
        try:
            return self.filtered()
        except torch.linalg.LinAlgError:
            if self.reduce is not None:  # join the others' collective: all reject the trial
                _summed(self.reduce, torch.tensor(math.nan, dtype=torch.float64))
            return -math.inf, None
        finally:
            self.phase = "M-step"
