"""Calibration of learned models by the filter likelihood: honest ``Q`` and ``R`` on real data.

A GP fitted on one-step pairs reports the one-step scatter of its residuals; when real residuals
drift slowly, a filter that takes that variance as its ``Q`` and ``R`` is over-confident.
:func:`calibrate` wraps both sides of a model in a :class:`~torchfilt.models.CalibratedModel`
(per-output variance scales ``s`` and an additive diagonal floor ``f``, both log-parametrised) and
fits ``s`` and ``f`` by :func:`~torchfilt.training.likelihood.fit_likelihood` on recordings of
measurements and inputs: no logged states are needed. By default the GP means are left as they
are and the gradient flows through the frozen predictor (its caches are constants, the cubature
points are not). With ``gp="noise"`` or ``gp="all"`` the GP likelihood noises (and the kernel
hyperparameters) are fitted too, through the frozen predictor's differentiable twin.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.filters import CKF, coverage, nees, nis
from torchfilt.filters.inputs import check_model_input
from torchfilt.io import Recording
from torchfilt.models import CalibratedModel, ConditionalModel, StateSpaceModel
from torchfilt.models.drift import DriftMeasurement, DriftModel, DriftTransition
from torchfilt.numerics.dtypes import check_compute_dtype
from torchfilt.optim import (
    DEFAULTS,
    CheckpointOptions,
    FitHooks,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
    deprecated_fit_keywords,
    resolve_options,
)
from torchfilt.training.data import FitData, as_sequences
from torchfilt.training.likelihood import LikelihoodFit, LikelihoodState, _fit_likelihood

__all__ = [
    "CalibrationResult",
    "calibrate",
    "calibration_entry",
    "consistency",
]

#: Initial floor, relative to the side's typical variance: small, but reachable in a few dozen
#: Adam steps on its log (a floor started at 1e-9 would need hundreds).
FLOOR_INIT = 1e-2
#: The floor's reference variance of an output that has none (a noise-free state).
NEGLIGIBLE_VARIANCE = 1e-12


@dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    Attributes:
        model: the calibrated model (both sides wrapped in
            :class:`~torchfilt.models.CalibratedModel`; the base models are shared, not copied,
            except GPs whose hyperparameters were refitted, ``gp != "none"``: those are copies).
        fit: the likelihood fit.
        parameters: ``{"transition": {"scale", "floor"}, "measurement": {...}}`` as lists.
        refit: the GP models whose hyperparameters were refitted, by side (frozen again with
            their original options); empty when ``gp="none"``.
    """

    model: StateSpaceModel
    fit: LikelihoodFit
    parameters: dict[str, dict[str, Any]]
    refit: dict[str, Any] = field(default_factory=dict)


def _typical_variance(side: ConditionalModel, x: Tensor, u: Tensor | None) -> Tensor:
    """A variance scale per output ``(d,)`` for the floor's start: a GP's likelihood noise (the
    one-step scatter of its targets), else the additive noise's diagonal, else the predictive
    variance at the prior mean ``x (1, n)`` (inputs ``u (1, nu)``). Not the variance at spread
    points: far from a GP's data it reverts to the prior variance, orders of magnitude too large."""
    d = side.out_dim
    with torch.no_grad():
        nv = getattr(side, "noise_variance", None)
        if isinstance(nv, Tensor) and nv.shape == (d,):
            var = nv.to(x.dtype)
        else:
            noise = side.noise_cov(0) if side.time_varying_noise else side.noise_cov()
            if noise is not None:
                var = noise.to(x).reshape(-1, d, d).diagonal(dim1=-2, dim2=-1).mean(0)
            else:
                pred = side.predict(x[:1].unsqueeze(0), None if u is None else u[:1].unsqueeze(0))
                var = x.new_zeros(d)
                if pred.var is not None:
                    var = var + pred.var.reshape(-1, d).mean(0)
                if pred.cov is not None:
                    var = var + pred.cov.reshape(-1, d, d).diagonal(dim1=-2, dim2=-1).mean(0)
        # an output without noise (a noise-free state of the dynamics): its variance at the
        # mean, and if that is zero too, a negligible start (the floor then stays negligible
        # unless the likelihood asks for it)
        tiny = torch.finfo(var.dtype).tiny
        if not bool((var > tiny).all()):
            pred = side.predict(x[:1].unsqueeze(0), None if u is None else u[:1].unsqueeze(0))
            at_mean = pred.var.reshape(-1, d)[0] if pred.var is not None else torch.zeros_like(var)
            var = torch.where(var > tiny, var, at_mean.to(var))
    return torch.where(var > tiny, var, torch.full_like(var, NEGLIGIBLE_VARIANCE))


def _refit_copy(side: ConditionalModel, name: str) -> Any:
    """A copy of a GP side whose hyperparameters calibration may refit (``None``: not a GP)."""
    from torchfilt.models.gp import GPModel  # lazy: GPyTorch loads only when GPs are used

    if not isinstance(side, GPModel):
        return None
    if not side.has_twin:
        raise InputError(
            f"gp: refitting GP hyperparameters needs independent exact GPs; the {name} GP has "
            f"structure {side.config.structure!r} (use gp = 'none')"
        )
    return copy.deepcopy(side)


@deprecated_fit_keywords("calibrate")
def calibrate(
    model: StateSpaceModel,
    y: FitData,
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    fixed: Collection[str] = (),
    validation: FitData | None = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    hooks: FitHooks | None = None,
    progress: bool = False,
    callback: Callable[[LikelihoodState], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    sqrt: bool = False,
    compile: bool = False,
    sides: Sequence[Literal["transition", "measurement"]] = ("transition", "measurement"),
    inflate_only: bool = True,
    gp: Literal["none", "noise", "all"] = "none",
) -> CalibrationResult:
    """Calibrate a model's predictive variances by the filter likelihood on recordings.

    A :class:`~torchfilt.models.drift.DriftModel` (sensor drift states, from
    :func:`~torchfilt.models.drift.with_sensor_drift`) keeps its drift states, and their time
    constants and standard deviations are fitted too.

    Each side in ``sides`` is wrapped in a :class:`~torchfilt.models.CalibratedModel` whose
    variance scales (start just above 1) and diagonal floor (start ``FLOOR_INIT`` x the side's mean variance)
    are fitted; the other side is left as it is.

    The flat keywords of before (``window``, ``burn_in``, ``lr``, ``patience``, ``rtol``,
    ``rtol_window``, ``checkpoint_every``, ``resume``, ``all_reduce``) and ``recordings=`` (now
    ``y``) still work for one release, with a ``DeprecationWarning`` naming their new spelling.

    Args:
        model: the model to calibrate (typically GP transition and measurement). It is not
            modified; the result shares its base models.
        y: the training data, as every fit takes it (:mod:`torchfilt.training.data`):
            measurements ``(..., T, m)``, a list of ``(T_i, m)``, a
            :class:`~torchfilt.training.data.Sequences`, or a list of
            :class:`~torchfilt.io.Recording` (row 0 is each one's prior time, as in
            :func:`~torchfilt.pipeline.filter_recordings`: ``y = measurements[1:]``,
            ``u = inputs[:-1]``).
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None`` (``None`` when ``y`` is
            a ``Sequences`` or recordings, which carry their own).
        x0: prior mean ``(n,)`` (or one per recording ``(..., n)``; a ``Sequences``' own
            ``x0``, when given, is used instead).
        P0: prior covariance ``(n, n)`` (or one per recording ``(..., n, n)``; likewise).
        fixed: names of parameters of the calibrated model (``result.model.named_parameters()``,
            e.g. ``"transition.log_scale"``) held fixed; an unknown name is an ``InputError``.
        validation: held-out data for early stopping (optional), of any kind ``y`` accepts.
        iterations: iteration budget (default 100).
        optimizer: :class:`~torchfilt.optim.OptimizerOptions` or its name (default Adam on the
            log parameters, ``lr`` 0.1).
        windows: windows of the likelihood, :class:`~torchfilt.optim.WindowOptions` (default
            100 steps, 20 of burn-in, and ``per_iteration=64``: with more windows each Adam
            iteration steps on a random subset of 64 and the full objective is evaluated every
            ``full_every`` iterations; with L-BFGS all windows; see
            :mod:`torchfilt.training.likelihood`). Below 64 windows a step of all of them costs
            about what one of 16 does (the GP kernels' dispatch, not their arithmetic,
            dominates: 1.05 times on Plaza2's 23), and the random subsets' noise is gone.
        stopping: :class:`~torchfilt.optim.StoppingOptions` (default ``patience`` 15, acting
            only with ``validation``; convergence as in
            :func:`~torchfilt.training.fit_likelihood`).
        checkpoint: :class:`~torchfilt.optim.CheckpointOptions` or the file's path; a resumed
            calibration equals an uninterrupted one.
        hooks: :class:`~torchfilt.optim.FitHooks`: ``project`` and ``prepare`` run after the
            calibration's own (which keep the scales feasible and rebuild refitted GPs);
            ``all_reduce``: data-parallel calibration, each process with its own recordings (see
            :func:`~torchfilt.training.likelihood.fit_likelihood`). Every process must start
            from the same parameters: a floor starts from the side's noise variance, or, for a
            side that reports none, from its variance at the first recording's prior mean and
            input, which then must be the same in every process.
        progress: show a progress bar.
        callback: per-iteration callback (return ``True`` to stop).
        dtype: floating dtype (float64 by default).
        sqrt: use the square-root CKF.
        compile: compile the filter step.
        sides: which sides to calibrate.
        inflate_only: keep the variance scales at or above 1 (default): calibration then only adds
            uncertainty, never makes the filter more confident than its models. A measurement
            likelihood cannot see states that the measurements do not observe; shrinking their
            variance there would go unpunished by the fit and make the filter over-confident.
        gp: also refit the hyperparameters of the GP sides in ``sides``: ``"noise"`` (their
            likelihood noises) or ``"all"`` (noises, lengthscales and outputscales; the mean
            constants stay). The fit then runs through each GP's differentiable twin
            (:meth:`~torchfilt.models.gp.GPModel.twin`: the exact frozen predictor with the graph
            kept, rebuilt from the hyperparameters before every likelihood evaluation); the GPs
            are copied, and frozen again with their own options at the end. Independent exact
            GPs only. ``"none"`` (default): the GPs are left as they are.

    Returns:
        A :class:`CalibrationResult`.

    Raises:
        InputError: an invalid argument (an unknown side, ``gp`` value or fixed name, or ``u``
            given with a ``Sequences`` or recordings).
        ShapeError: ``x0`` or ``P0`` does not match the model's state dimension.
    """
    _check_options(model, sides, gp)
    check_compute_dtype(dtype)  # before the model is converted to it
    data = as_sequences(y, u, x0=x0, P0=P0)
    y, u = data.y, data.u
    x0 = torch.as_tensor(data.x0, dtype=dtype)
    P0 = torch.as_tensor(data.P0, dtype=dtype)
    # the calibrated wrapper no longer says what the model takes
    check_model_input(model, u if u is None or isinstance(u, Tensor) else next(iter(u), None))
    n = model.state_dim
    if x0.dim() < 1 or x0.shape[-1] != n:
        raise ShapeError(f"x0: expected shape (..., n) with n = {n}, got {tuple(x0.shape)}")
    if P0.dim() < 2 or P0.shape[-2:] != (n, n):
        raise ShapeError(f"P0: expected shape (..., n, n) with n = {n}, got {tuple(P0.shape)}")
    cal = _calibrated_model(
        model, u, x0, sides=sides, gp=gp, inflate_only=inflate_only, dtype=dtype
    )
    # the base models' own parameters (GP hyperparameters) stay fixed during the fit and get
    # their requires_grad flags back afterwards
    frozen = [
        p for p in cal.model.parameters() if p.requires_grad and not any(p is q for q in cal.params)
    ]
    for p in frozen:
        p.requires_grad_(False)
    wrapped = [side for side in cal.sides if isinstance(side, CalibratedModel)]

    user = hooks or FitHooks()

    def project() -> None:
        for side in wrapped:
            side.project_()
        if user.project is not None:
            user.project()

    def prepare() -> None:
        for g in cal.refit.values():
            g.predictor = g.twin()
        if user.prepare is not None:
            user.prepare()

    o = resolve_options(
        "calibrate", iterations=iterations, optimizer=optimizer, windows=windows,
        stopping=stopping, checkpoint=checkpoint,
        hooks=FitHooks(project, prepare if cal.refit or user.prepare else None, user.all_reduce),
    )  # fmt: skip
    default_subsets = DEFAULTS["calibrate"].windows.per_iteration
    if o.optimizer.optimizer == "lbfgs" and o.windows.per_iteration == default_subsets:
        # L-BFGS needs the full objective: the default subsets are Adam's (another explicit
        # per_iteration with L-BFGS is refused by the fit)
        o = o._replace(windows=replace(o.windows, per_iteration=None))
    try:
        fit = _fit_likelihood(
            cal.model, y, u, x0=x0, P0=P0, parameters=cal.params, fixed=fixed,
            validation=validation, options=o, progress=progress, callback=callback, dtype=dtype,
            sqrt=sqrt, rule=None, compile=compile,
        )  # fmt: skip
    finally:
        for p in frozen:
            p.requires_grad_(True)
        with torch.no_grad():
            for g in cal.refit.values():
                opts = g.freeze_options  # the fit swaps predictors, never the options
                if opts is None:
                    g.unfreeze()
                else:
                    g.freeze(**opts)
    return CalibrationResult(cal.model, fit, calibration_entry(cal.model), cal.refit)


def _check_options(model: StateSpaceModel, sides: Sequence[str], gp: str) -> None:
    """Refuse a model that is not a state-space model and unknown ``sides`` or ``gp``."""
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    bad = [s for s in sides if s not in ("transition", "measurement")]
    if bad or not sides:
        raise InputError(f"sides: expected 'transition' and/or 'measurement', got {list(sides)}")
    if gp not in ("none", "noise", "all"):
        raise InputError(f"gp: expected 'none', 'noise' or 'all', got {gp!r}")


class _Calibrated(NamedTuple):
    """The model whose calibration is fitted, its two sides, the GP copies refitted with it
    (by side name) and the parameters the fit moves."""

    model: StateSpaceModel
    sides: tuple[ConditionalModel, ConditionalModel]
    refit: dict[str, Any]
    params: list[nn.Parameter]


def _calibrated_model(
    model: StateSpaceModel,
    u: Any,
    x0: Tensor,
    *,
    sides: Sequence[str],
    gp: str,
    inflate_only: bool,
    dtype: torch.dtype,
) -> _Calibrated:
    """Wrap each side in ``sides`` in a :class:`CalibratedModel` (inside the drift wrappers of a
    :class:`DriftModel`), copying the GP sides to refit when ``gp`` asks, and list the
    parameters to fit."""
    base_f, base_h = model.transition.to(dtype), model.measurement.to(dtype)
    drift = model if isinstance(model, DriftModel) else None
    n = model.state_dim if drift is None else drift.base_state_dim
    m0 = x0.reshape(-1, model.state_dim)[:1, :n]  # the prior mean of the first recording, (1, n)
    u0 = None
    if u is not None:
        first_u = u.reshape(-1, u.shape[-2], u.shape[-1])[0] if isinstance(u, Tensor) else u[0]
        u0 = first_u[:1].to(dtype)

    refit: dict[str, Any] = {}

    def wrap(side: ConditionalModel, name: str, uu: Tensor | None) -> ConditionalModel:
        if name not in sides:
            return side
        if gp != "none":
            copied = _refit_copy(side, name)
            if copied is not None:
                side = refit[name] = copied
        var = _typical_variance(side, m0, uu)
        # with drift states the measurement's variance is split anew between the white noise and
        # the drift (its learned variance counted the drift as white noise): it may shrink
        inflate = inflate_only and not (drift is not None and name == "measurement")
        return CalibratedModel(
            side, floor=FLOOR_INIT * var, min_scale=1.0 if inflate else 0.0, dtype=dtype
        )

    if drift is not None:
        # calibrate the original sides inside the drift wrappers; the drift parameters are copied
        # and fitted with the scales and floors
        assert isinstance(base_f, DriftTransition) and isinstance(base_h, DriftMeasurement)
        f = wrap(base_f.base, "transition", u0)
        h = wrap(base_h.base, "measurement", None)
        calibrated: StateSpaceModel = DriftModel(
            StateSpaceModel(f, h),
            drift.channels,
            copy.deepcopy(base_f.tau),
            copy.deepcopy(base_f.sd),
            base_f.dt,
        )
    else:
        f = wrap(base_f, "transition", u0)
        h = wrap(base_h, "measurement", None)
        calibrated = StateSpaceModel(f, h)
    params = [
        p
        for side in (f, h)
        if isinstance(side, CalibratedModel)
        for p in (side.log_scale, side.log_floor)
    ]
    if isinstance(calibrated, DriftModel):
        params += calibrated.drift_parameters()
    if gp != "none" and not refit:
        raise InputError(
            f"gp: {gp!r} refits GP hyperparameters, but no side in {list(sides)} is a GP"
        )
    params += [p for g in refit.values() for p in g.hyperparameter_tensors(gp)]
    return _Calibrated(calibrated, (f, h), refit, params)


def calibration_entry(model: StateSpaceModel) -> dict[str, dict[str, Any]]:
    """The calibration parameters of a model's calibrated sides, as plain lists (for a bundle)."""
    out: dict[str, dict[str, Any]] = {}
    for name in ("transition", "measurement"):
        side = getattr(model, name)
        side = getattr(side, "base", side) if isinstance(model, DriftModel) else side
        if isinstance(side, CalibratedModel):
            out[name] = side.summary()
    if isinstance(model, DriftModel):
        out["drift"] = {
            "channels": model.channels,
            "time_constant": model.time_constant.detach().tolist(),
            "sd": model.drift_sd.detach().tolist(),
        }
    return out


@torch.no_grad()
def consistency(
    model: StateSpaceModel,
    recordings: Sequence[Recording],
    *,
    x0: Tensor,
    P0: Tensor,
    level: float = 0.95,
) -> dict[str, Any]:
    """Filter recordings and score the filter's honesty: NIS always, NEES and coverage where the
    recordings log the true states.

    Args:
        model: the model.
        recordings: recordings (row 0 is the prior's time).
        x0: prior mean ``(n,)``.
        P0: prior covariance ``(n, n)``.
        level: nominal probability of the coverage intervals.

    Returns:
        ``{"nis_mean", "nis_dof_mean", "nees_mean", "coverage95", "steps", "recordings"}``
        (NEES and coverage only where states are logged).

    Raises:
        InputError: no recordings given.
    """
    recs = list(recordings)
    if not recs:
        raise InputError("recordings: none given")
    filt = CKF(model)
    dtype = x0.dtype if x0.is_floating_point() else torch.float64
    nis_sum = dof_sum = 0.0
    nis_steps = 0
    nees_all: list[Tensor] = []
    truths: list[Tensor] = []
    means: list[Tensor] = []
    covs: list[Tensor] = []
    for r in recs:
        y = r.measurements[1:].to(dtype)
        u = None if r.inputs is None else r.inputs[:-1].to(dtype)
        res = filt.filter(y, u, x0=x0.to(dtype), P0=P0.to(dtype))
        value, dof = nis(res)
        ok = dof > 0
        nis_sum += float(value[ok].sum())
        dof_sum += float(dof[ok].double().sum())
        nis_steps += int(ok.sum())
        if r.states.shape[-1] == model.state_dim:
            truth = r.states[1:].to(dtype)
            good = torch.isfinite(truth).all(-1)
            if bool(good.any()):
                nees_all.append(nees(truth[good], res.mean[good], res.cov[good]))
                truths.append(truth[good])
                means.append(res.mean[good])
                covs.append(res.cov[good])
    out: dict[str, Any] = {
        "recordings": len(recs),
        "nis_mean": nis_sum / max(nis_steps, 1),
        "nis_dof_mean": dof_sum / max(nis_steps, 1),
        "steps": nis_steps,
    }
    if nees_all:
        ne = torch.cat(nees_all)
        out["nees_mean"] = float(ne.mean()) if bool(torch.isfinite(ne).all()) else math.inf
        out["coverage95"] = coverage(
            torch.cat(truths), torch.cat(means), torch.cat(covs), level
        ).tolist()
    return out
