"""A learned model's process noise, scaled by held-out data.

A model learned from measurements alone fits its process noise ``Q`` to the recordings it was
trained on. A flexible transition (a GP) explains those recordings better than it will explain
new ones, so its ``Q`` comes out small and its filter is over-confident on new data. On the Van
der Pol case of ``scripts/_oscillator_case.py`` (one 300-step recording, EM with its defaults),
the held-out mean NEES was 6.6 (n = 2). The training likelihood was highest at the fitted
``Q``, but the held-out one was highest with ``Q`` 2 to 4 times larger, and there the NEES was
3.5 to 4.9.

:func:`held_out_noise_scale` chooses the scale ``s`` of the transition's variance from
:data:`NOISE_SCALES` (powers of ``sqrt(2)`` from 1/4 to 64). The criterion is the innovation
log-likelihood of held-out steps, filtered with the scaled model from each recording's prior.
The choice is the largest scale whose held-out log-likelihood is within ``margin`` = 1.92 nats
of the best: the upper end of the 95% likelihood-ratio interval of ``s`` (Wilks:
``2 (L_best - L) <= 3.84``, chi-square with one degree of freedom). A short held-out part
cannot tell neighbouring scales apart: on the Van der Pol case the last 60 steps scored 1.4,
2, 2.8 and 4 within 1.3 nats of each other, while 20 new recordings put the best at 2.8 and
gave the mean NEES 4.6, 3.8, 3.2 and 2.8 at them. Where the data cannot decide, the larger
scale errs on the side of a filter that knows it may be wrong; with much held-out data the
interval closes on the best scale. The held-out steps are:

* with at least :data:`WHOLE_RECORDINGS_MIN` recordings, the last ``holdout`` fraction of
  them, whole (:func:`split_held_out`): every step scored;
* with fewer, the last ``holdout`` fraction of each recording (:func:`split_tails`): the fit
  sees the heads only, and the filter runs through the head into the tail, whose steps alone
  are scored. A tail is not always like the rest of its recording (a process that settles
  has quiet tails), so whole recordings are preferred where there are enough;
* or held-out recordings given by the user (``validation=``), every step scored.

:func:`~torchfilt.training.fit_measurement_only` tries :data:`INFLATE_SCALES` (1 to 64)
only: it inflates a fitted noise, never shrinks it.

:func:`with_process_noise_scale` applies ``s``:

* a :class:`~torchfilt.models.LinearGaussianModel` gets ``s Q``;
* any other :class:`~torchfilt.models.StateSpaceModel` gets its transition wrapped in a
  :class:`~torchfilt.models.CalibratedModel` with the scale ``s``, fixed. The wrapper scales the
  whole transition variance, ``Q`` and a GP's per-point variance.

This is one scalar chosen from a grid, so a short held-out part can carry it (a few dozen steps).
Per-output scales and floors learned by gradient are :func:`~torchfilt.training.calibrate`'s
job.

:func:`scales_by_default` is the rule of ``noise_scale="auto"`` (the default of
:func:`~torchfilt.training.fit_measurement_only`): scale when there is held-out data to score
(``validation``, or at least :data:`AUTO_MIN_HELD_OUT` held-out steps in all), the model's
process noise can be scaled, and no transition parameter is held fixed.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Collection, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.cubature import CubatureRule
from torchfilt.exceptions import DivergenceWarning, FitError, InputError
from torchfilt.filters import CKF
from torchfilt.models import CalibratedModel, LinearGaussianModel, StateSpaceModel
from torchfilt.training.data import Sequences
from torchfilt.training.likelihood import _recordings, step_log_likelihood

__all__ = [
    "AUTO_MIN_HELD_OUT",
    "INFLATE_SCALES",
    "LR_MARGIN",
    "NOISE_SCALES",
    "WHOLE_RECORDINGS_MIN",
    "NoiseScale",
    "check_holdout",
    "held_out_noise_scale",
    "scalable",
    "scales_by_default",
    "split_held_out",
    "split_tails",
    "with_process_noise_scale",
]

#: Scales of the transition variance tried by :func:`held_out_noise_scale`: ``2^(i/2)``,
#: ``i = -4 .. 12`` (1/4 to 64).
NOISE_SCALES: tuple[float, ...] = tuple(2.0 ** (i / 2) for i in range(-4, 13))
#: The scales :func:`~torchfilt.training.fit_measurement_only` tries: :data:`NOISE_SCALES`
#: from 1 up. A fitted noise is biased small for new data, not large; a held-out part that
#: asks for less noise mostly predicts its measurements better by trusting the model more in
#: directions the measurements do not see (on 2A -> B, one measured sum of two states: the
#: held-out recordings chose 0.35, and the states' NEES rose from 15 to 34).
INFLATE_SCALES: tuple[float, ...] = tuple(s for s in NOISE_SCALES if s >= 1.0)
#: Default ``margin`` of :func:`held_out_noise_scale`: half the 95% point of chi-square(1).
LR_MARGIN = 1.92
#: Fewest recordings from which whole recordings, rather than tails, are held out.
WHOLE_RECORDINGS_MIN = 5
#: Fewest held-out steps (summed over the recordings, and over the processes of a
#: data-parallel fit) for which ``noise_scale="auto"`` scales.
AUTO_MIN_HELD_OUT = 30


class NoiseScale(NamedTuple):
    """The held-out choice of a process-noise scale.

    Attributes:
        scale: the chosen scale ``s`` of the transition variance.
        log_likelihood: the held-out innovation log-likelihood at ``s``.
        best: the scale with the best held-out log-likelihood (``scale`` is the largest within
            the margin of it).
        scores: ``(scale, held-out log-likelihood)`` for every scale tried (``-inf``: the
            filter failed on the held-out steps).
        held_out: counted held-out measurements (summed over the processes of a
            data-parallel fit).
    """

    scale: float
    log_likelihood: float
    best: float
    scores: list[tuple[float, float]]
    held_out: int


def with_process_noise_scale(
    model: StateSpaceModel, scale: float, *, dtype: torch.dtype = torch.float64
) -> StateSpaceModel:
    """``model`` with its transition variance multiplied by ``scale`` (``model`` itself at 1).

    Args:
        model: a :class:`~torchfilt.models.LinearGaussianModel` (its ``Q`` is scaled) or a
            plain :class:`~torchfilt.models.StateSpaceModel` (its transition is wrapped in a
            :class:`~torchfilt.models.CalibratedModel` whose scale is fixed: no parameter to
            learn).
        scale: the scale, finite and positive.
        dtype: dtype of the wrapper's parameters.

    Returns:
        A new model sharing the maps of ``model``.

    Raises:
        InputError: a scale that is not finite and positive, or a model of another class (a
            subclass of ``StateSpaceModel`` with its own structure, e.g. a drift model), or
            with a time-varying process noise.
    """
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"scale: expected a finite positive number, got {scale}")
    if scale == 1.0:
        return model
    if isinstance(model, LinearGaussianModel):
        Q, R = model.transition.noise_cov(), model.measurement.noise_cov()
        if Q is None or R is None or model.transition.time_varying_noise:
            raise InputError("model: a linear-Gaussian model with time-varying noise")
        return LinearGaussianModel(model.A, model.H, scale * Q, R, B=model.B, D=model.D)
    if type(model) is not StateSpaceModel:
        raise InputError(
            f"model: the process noise of a {type(model).__name__} cannot be scaled here; "
            "give a StateSpaceModel or a LinearGaussianModel"
        )
    tiny = torch.finfo(dtype).tiny  # CalibratedModel's floor must be positive: none, in effect
    side = CalibratedModel(model.transition, scale=scale, floor=tiny, dtype=dtype)
    base = {id(p) for p in model.transition.parameters()}
    for p in side.parameters():  # the wrapper's own: the model's stay as they are
        if id(p) not in base:
            p.requires_grad_(False)
    return StateSpaceModel(side, model.measurement)


def scalable(model: StateSpaceModel) -> bool:
    """Whether :func:`with_process_noise_scale` can scale ``model``'s process noise: a
    constant one (neither a time-varying ``Q`` nor the wrapper take it) of a
    ``LinearGaussianModel`` or a plain ``StateSpaceModel``."""
    if model.transition.time_varying_noise:
        return False
    if isinstance(model, LinearGaussianModel):
        return model.transition.noise_cov() is not None
    return type(model) is StateSpaceModel


def check_holdout(holdout: float) -> None:
    """Refuse a ``holdout`` that is not a fraction in ``(0, 1)`` (an ``InputError``)."""
    if isinstance(holdout, bool) or not isinstance(holdout, int | float) or not 0 < holdout < 1:
        raise InputError(f"holdout: expected a fraction in (0, 1), got {holdout!r}")


def _lengths(y: Tensor | Sequence[Tensor]) -> list[int]:
    """The recordings' lengths in ``y`` (none of what is malformed: the fit refuses it)."""
    if isinstance(y, Tensor):
        if y.dim() < 2:
            return []
        return [int(y.shape[-2])] * math.prod(y.shape[:-2])
    return [int(v.shape[0]) for v in y if isinstance(v, Tensor) and v.dim() >= 1]


def scales_by_default(
    model: StateSpaceModel,
    data: Sequences,
    holdout: float,
    *,
    validation: bool,
    fixed: Collection[str] = (),
    all_reduce: Callable[[Tensor], None] | None = None,
) -> bool:
    """Whether ``noise_scale="auto"`` scales the process noise of a fit of ``model``.

    Args:
        model: the model to fit.
        data: the training recordings.
        holdout: the fraction of each recording held out without ``validation``.
        validation: whether held-out recordings are given.
        fixed: the fit's fixed parameters: ``"Q"`` or any name under ``"transition."`` keeps
            the transition as the user set it.
        all_reduce: sums a flat tensor across the processes of a data-parallel fit (their
            held-out steps are counted together, so that every process decides alike).

    Returns:
        True when held-out data can be scored (``validation``, or at least
        :data:`AUTO_MIN_HELD_OUT` held-out steps), the model is scalable and no transition
        parameter is fixed.
    """
    if not scalable(model):
        return False
    if any(name == "Q" or name.startswith("transition.") for name in fixed):
        return False
    return validation or enough_held_out(data, holdout, all_reduce=all_reduce)


def enough_held_out(
    data: Sequences, holdout: float, *, all_reduce: Callable[[Tensor], None] | None = None
) -> bool:
    """Whether holding out ``holdout`` of ``data`` (:func:`split_held_out`) leaves at least
    :data:`AUTO_MIN_HELD_OUT` held-out steps in all (over the processes of a data-parallel fit,
    with ``all_reduce``).

    Args:
        data: the training recordings.
        holdout: the fraction held out.
        all_reduce: sums a flat tensor across the processes of a data-parallel fit.

    Returns:
        Whether the held-out part is long enough to score.
    """
    lengths = _lengths(data.y)
    k = _whole_held_out(len(lengths), holdout)
    steps = sum(lengths[-k:]) if k else sum(math.floor(holdout * T) for T in lengths)
    count = torch.tensor([float(steps)])
    if all_reduce is not None:
        all_reduce(count)
    return float(count) >= AUTO_MIN_HELD_OUT


def _whole_held_out(recordings: int, holdout: float) -> int:
    """How many whole recordings of ``recordings`` are held out (0: the tails instead)."""
    if recordings < WHOLE_RECORDINGS_MIN:
        return 0
    return max(1, min(recordings - 1, round(holdout * recordings)))


def split_held_out(
    model: StateSpaceModel, data: Sequences, holdout: float, *, dtype: torch.dtype
) -> tuple[Sequences, Sequences, list[int] | None]:
    """Hold out the last ``holdout`` fraction of the recordings, whole, when there are at
    least :data:`WHOLE_RECORDINGS_MIN` (at least one, and one kept), else the tail of each
    (:func:`split_tails`).

    Args:
        model: the model the data are for (their shapes are checked against it).
        data: the recordings, with their prior (``x0``, ``P0`` set).
        holdout: the fraction held out, in ``(0, 1)``.
        dtype: floating dtype of the returned tensors.

    Returns:
        ``(train, scored, starts)``: the recordings to fit, those to score (each as a
        :class:`~torchfilt.training.data.Sequences` of lists, one prior per recording), and
        the first scored step of each scored recording (``None``: every step, for whole
        recordings; see :func:`split_tails` for the tails).

    Raises:
        InputError: ``holdout`` not in ``(0, 1)``, or as :func:`split_tails`.
        ShapeError: data that do not fit the model.
    """
    check_holdout(holdout)
    recs = _recordings(model, data.y, data.u, data.x0, data.P0, dtype)
    k = _whole_held_out(len(recs.lengths), holdout)
    if k == 0:
        return split_tails(model, data, holdout, dtype=dtype)
    ys = [recs.y[r, :T] for r, T in enumerate(recs.lengths)]
    us = None if recs.u is None else [recs.u[r, :T] for r, T in enumerate(recs.lengths)]
    cut = len(ys) - k

    def part(sl: slice) -> Sequences:
        return Sequences(ys[sl], None if us is None else us[sl], recs.x0[sl], recs.P0[sl])

    return part(slice(0, cut)), part(slice(cut, None)), None


def split_tails(
    model: StateSpaceModel, data: Sequences, holdout: float, *, dtype: torch.dtype
) -> tuple[Sequences, Sequences, list[int]]:
    """Hold out the last ``holdout`` fraction of every recording.

    Args:
        model: the model the data are for (their shapes are checked against it).
        data: the recordings, with their prior (``x0``, ``P0`` set).
        holdout: the fraction held out, in ``(0, 1)``: ``floor(holdout T_i)`` steps of each
            recording of ``T_i`` steps.
        dtype: floating dtype of the returned tensors.

    Returns:
        ``(heads, whole, starts)``: the heads ``(T_i - k_i, m)`` each, the whole recordings,
        both as :class:`~torchfilt.training.data.Sequences` of lists with one prior per
        recording, and the first held-out step ``T_i - k_i`` of each.

    Raises:
        InputError: ``holdout`` not in ``(0, 1)``, or no recording long enough to hold out a
            step while keeping one.
        ShapeError: data that do not fit the model.
    """
    check_holdout(holdout)
    recs = _recordings(model, data.y, data.u, data.x0, data.P0, dtype)
    starts = [T - math.floor(holdout * T) for T in recs.lengths]
    if all(s == T for s, T in zip(starts, recs.lengths, strict=True)):
        raise InputError(
            f"holdout: {holdout} of recordings of {max(recs.lengths)} steps at most holds out "
            "no step; give a larger holdout, or held-out recordings (validation=)"
        )
    ys = [recs.y[r, :T] for r, T in enumerate(recs.lengths)]
    us = None if recs.u is None else [recs.u[r, :T] for r, T in enumerate(recs.lengths)]
    heads_u = None if us is None else [v[:s] for v, s in zip(us, starts, strict=True)]
    heads = Sequences([v[:s] for v, s in zip(ys, starts, strict=True)], heads_u, recs.x0, recs.P0)
    return heads, Sequences(ys, us, recs.x0, recs.P0), starts


@torch.no_grad()
def held_out_noise_scale(
    model: StateSpaceModel,
    data: Sequences,
    starts: Sequence[int] | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    rule: CubatureRule | None = None,
    all_reduce: Callable[[Tensor], None] | None = None,
    scales: Sequence[float] = NOISE_SCALES,
    margin: float = LR_MARGIN,
) -> NoiseScale:
    """The scale of ``model``'s transition variance with the best held-out likelihood.

    Args:
        model: the fitted model.
        data: recordings with their prior (``x0``, ``P0`` set), filtered whole by the CKF.
        starts: the first scored step of each recording (the held-out tails of
            :func:`split_tails`); ``None``: every step is scored (held-out recordings).
        dtype: floating dtype.
        rule: cubature rule of the filter.
        all_reduce: sums a flat tensor in place across the processes of a data-parallel fit,
            each with its own recordings, so that every process chooses the same scale.
        scales: the scales tried, increasing (default :data:`NOISE_SCALES`).
        margin: nats below the best held-out log-likelihood within which the largest scale is
            chosen (default :data:`LR_MARGIN`, the 95% likelihood-ratio interval; 0: the best).

    Returns:
        A :class:`NoiseScale`. Among equal best scores the scale nearest 1 is the best.

    Raises:
        InputError: ``starts`` of the wrong length, scales not increasing and positive, a
            negative ``margin``, or no held-out measurement is observed.
        FitError: the filter fails on the held-out steps at every scale.
    """
    if not (math.isfinite(margin) and margin >= 0):
        raise InputError(f"margin: expected a finite number >= 0, got {margin}")
    if not scales or any(not (b > a >= 0) for a, b in zip([0.0, *scales], scales, strict=False)):
        raise InputError(f"scales: expected increasing positive numbers, got {list(scales)}")
    recs = _recordings(model, data.y, data.u, data.x0, data.P0, dtype)
    R, T = int(recs.y.shape[0]), int(recs.y.shape[1])
    first = torch.zeros(R, dtype=torch.long) if starts is None else torch.tensor(list(starts))
    if first.shape != (R,):
        raise InputError(f"starts: expected one start per recording ({R}), got {len(first)}")
    scored = torch.arange(T).unsqueeze(0) >= first.unsqueeze(-1)  # (R, T)
    counted = int((torch.isfinite(recs.y) & scored.unsqueeze(-1)).sum())
    totals = []
    for s in scales:
        scaled = with_process_noise_scale(model, float(s), dtype=dtype)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DivergenceWarning)  # a scale may not fit: -inf
            res = CKF(scaled, rule=rule).filter(recs.y, recs.u, x0=recs.x0, P0=recs.P0)
            ll = step_log_likelihood(res).to(torch.float64)
        total = float((ll * scored.to(ll.dtype)).sum())
        totals.append(total if math.isfinite(total) else -math.inf)
    flat = torch.tensor([*totals, float(counted)], dtype=torch.float64)
    if all_reduce is not None:  # a sum of finite values and -inf: -inf where any process failed
        all_reduce(flat)
    held_out = int(flat[-1])
    if held_out == 0:
        raise InputError("no held-out measurement is observed: nothing to choose a scale by")
    values = flat[:-1].tolist()
    order = sorted(range(len(scales)), key=lambda i: abs(math.log(scales[i])))
    best = max(order, key=lambda i: values[i])
    if not math.isfinite(values[best]):
        raise FitError(
            "the held-out noise scale: the filter fails on the held-out steps at every scale "
            f"({scales[0]:.3g} to {scales[-1]:.3g})",
            fit="held_out_noise_scale",
            step="the held-out filter",
        )
    scores = [(float(s), v) for s, v in zip(scales, values, strict=True)]
    chosen = max(i for i, v in enumerate(values) if v >= values[best] - margin)
    return NoiseScale(float(scales[chosen]), values[chosen], float(scales[best]), scores, held_out)
