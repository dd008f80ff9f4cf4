"""What :func:`~torchfilt.training.fit_measurement_only` does around one method's fit: the
process noise scaled on held-out data (``noise_scale``), and ``method="auto"``: both methods,
the better kept by held-out likelihood.

**Why both.** Neither method is the better one on every problem (measured with
``scripts/reproduce_measurement_only.py``, and in ``scripts/results/cpu-2026-12-05-em-then-
likelihood/``):

* EM's steps are cheap and monotone, but where the process noise is small against the
  smoothed uncertainty its steps shrink (a slow tail), and a cubature E-step may stop it at
  "no improvement" far from the optimum: the re-entry radar case (``torchfilt.systems.reentry``,
  8 runs) stops after 2 iterations at 10 times the state-trained model's RMSE, where the
  likelihood method ends at 1.0 times;
* the likelihood method climbs the filter's likelihood itself, but on a flexible GP residual
  (the 2A -> B reaction from total pressure) it found a worse held-out fit than EM.

A user without the states cannot tell by RMSE which fit is right; held-out measurements can.
``"both"`` fits both from the same start (each from its own copy of the model), on the same
kept data, scores each by the innovation log-likelihood of the same held-out steps
(:func:`~torchfilt.training.noise_scale.held_out_noise_scale` at scale 1) and keeps the
higher. The held-out part is ``validation`` when given (both fit all the data), else that of
the noise scale (:func:`~torchfilt.training.noise_scale.split_held_out`): the last ``holdout``
of the recordings (whole ones when there are at least 5, else the tail of each) when that
leaves at least :data:`~torchfilt.training.noise_scale.AUTO_MIN_HELD_OUT` steps. With
``noise_scale="none"`` and no ``validation``, or without enough held-out steps, both fit all
the data and the training log-likelihood decides (both maximise it, EM through its E-step's
approximation). A method whose fit fails
(a :class:`~torchfilt.exceptions.FitError`) is recorded and the other kept; when both fail the
error names both. A method that cannot fit the model is skipped and recorded (the likelihood
method needs a parameter with ``requires_grad``: a linear-Gaussian model of plain tensors is
EM's alone). It costs the two fits together, and the likelihood method is the slow one: on the
Van der Pol case (one 300-step recording) 369 s against EM's 9 s, on the DaISy robot arm 780 s
against 35 s, and EM was the one kept in both (``scripts/results/cpu-2026-12-05-method-auto/``).

``"auto"`` (the default of :func:`~torchfilt.training.fit_measurement_only`) pays for the
comparison only where EM is in doubt: it fits EM, and the likelihood method too when EM
stopped with ``"no improvement"`` (:data:`STALLED`: no step of its approximate E-step raised the
filter likelihood, so it may sit far from the maximum, as on re-entry) or failed; an EM that
converged, or was still climbing at its budget, is kept, the likelihood method recorded as
skipped. On the five cases measured it kept the same fit as ``"both"``.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar, Literal, Protocol, TypeVar

import torch
from torch import Tensor

from torchfilt.cubature import CubatureRule
from torchfilt.exceptions import FitError, InputError
from torchfilt.models import StateSpaceModel
from torchfilt.optim import CheckpointOptions, free_parameters
from torchfilt.training.data import FitData, Sequences, as_sequences
from torchfilt.training.noise_scale import (
    INFLATE_SCALES,
    enough_held_out,
    held_out_noise_scale,
    scales_by_default,
    split_held_out,
    with_process_noise_scale,
)

__all__ = ["METHODS", "STALLED", "fit_both_methods", "held_out_scaled", "method_checkpoint"]


class _Fit(Protocol):
    """What this module reads of a :class:`~torchfilt.training.MeasurementOnlyFit` (a
    dataclass; defined beside the fits, which call this module)."""

    __dataclass_fields__: ClassVar[dict[str, Any]]
    model: StateSpaceModel
    log_likelihood: float
    iterations: int
    stopped: str
    elapsed: float


_R = TypeVar("_R", bound=_Fit)

#: The methods ``"both"`` (and ``"auto"``) compare, in the order they run (on equal scores the
#: first is kept).
METHODS: tuple[Literal["em", "likelihood"], ...] = ("em", "likelihood")

#: How an EM fit ends when its approximate E-step can no longer raise the filter likelihood:
#: ``"auto"`` then fits the likelihood method too.
STALLED = ("no improvement",)


def method_checkpoint(options: CheckpointOptions, method: str) -> CheckpointOptions:
    """The checkpoint of one method's fit under ``method="auto"``: ``run.pt`` becomes
    ``run.em.pt`` and ``run.likelihood.pt`` (each resumes on its own).

    Args:
        options: the fit's checkpoint options.
        method: ``"em"`` or ``"likelihood"``.

    Returns:
        The options with the method's file (unchanged without a file).
    """
    if options.path is None:
        return options
    path = Path(options.path)
    return replace(options, path=path.with_name(f"{path.stem}.{method}{path.suffix}"))


def _not_applicable(method: str, model: StateSpaceModel, fixed: tuple[str, ...]) -> str | None:
    """Why ``method`` cannot fit ``model`` (``None``: it can). The likelihood method steps the
    parameters with ``requires_grad``, less ``fixed``: a linear-Gaussian model of plain tensors
    (EM's closed form needs no ``nn.Parameter``), or one whose every parameter is fixed, has
    none."""
    if method != "likelihood":
        return None
    try:
        free_parameters(model, None, fixed, what="model")
    except InputError as e:
        return str(e)
    return None


def _validation(data: Sequences, validation: FitData, n: int) -> Sequences:
    """``validation`` as recordings with the fit's prior."""
    x0, P0 = data.x0, data.P0
    assert x0 is not None and P0 is not None  # as_sequences with the fit's prior
    return as_sequences(
        validation, x0=x0.reshape(-1, n)[0], P0=P0.reshape(-1, n, n)[0], name="validation"
    )


def held_out_scaled(
    fit: Callable[[FitData], _R],
    model: StateSpaceModel,
    data: Sequences,
    validation: FitData | None,
    holdout: float,
    *,
    dtype: torch.dtype,
    rule: CubatureRule | None,
    all_reduce: Callable[[Tensor], None] | None,
) -> _R:
    """``fit`` on the kept part of ``data`` (:func:`split_held_out`: whole recordings or the
    heads; all of it, with ``validation``), its process noise then scaled by the held-out part
    (or ``validation``), from :data:`INFLATE_SCALES`. A data-parallel fit sums the held-out
    scores over its processes (each splits its own recordings); ``validation`` is every
    process's own copy of the same data (as for the likelihood fit's early stopping), scored
    without a sum."""
    if validation is None:
        kept, scored, starts = split_held_out(model, data, holdout, dtype=dtype)
        return _noise_scaled(
            fit(kept), scored, starts, dtype=dtype, rule=rule, all_reduce=all_reduce
        )
    val = _validation(data, validation, model.state_dim)
    return _noise_scaled(fit(data), val, None, dtype=dtype, rule=rule, all_reduce=None)


def _noise_scaled(
    result: _R,
    scored: Sequences,
    starts: list[int] | None,
    *,
    dtype: torch.dtype,
    rule: CubatureRule | None,
    all_reduce: Callable[[Tensor], None] | None,
) -> _R:
    """``result`` with its model's process noise scaled by the held-out steps of ``scored``
    (from ``starts``; ``None``: every step), chosen from :data:`INFLATE_SCALES`, and the choice
    recorded as its ``noise_scale``."""
    choice = held_out_noise_scale(
        result.model, scored, starts, dtype=dtype, rule=rule, all_reduce=all_reduce,
        scales=INFLATE_SCALES,
    )  # fmt: skip
    scaled = with_process_noise_scale(result.model, choice.scale, dtype=dtype)
    return replace(result, model=scaled, noise_scale=choice)


def fit_both_methods(
    fit: Callable[[str, StateSpaceModel, FitData], _R],
    model: StateSpaceModel,
    data: Sequences,
    validation: FitData | None,
    holdout: float,
    noise_scale: str,
    *,
    always: bool = True,
    fixed: tuple[str, ...],
    dtype: torch.dtype,
    rule: CubatureRule | None,
    all_reduce: Callable[[Tensor], None] | None,
) -> _R:
    """``method="both"`` and ``"auto"`` (see the module docstring): ``fit(method, copy, data)``
    for each of :data:`METHODS` (a fit of one method with ``noise_scale="none"``; with
    ``always=False`` the likelihood method only after an EM that stalled or failed), the better
    kept by the innovation log-likelihood of the held-out steps, then its process noise scaled
    as ``noise_scale`` says.

    Args:
        fit: one method's fit of a model on recordings.
        model: the start (left as given: each method fits its own copy).
        data: the recordings, with their prior.
        validation: held-out recordings given by the user, or ``None``.
        holdout: the fraction held out without ``validation``.
        noise_scale: ``"auto"``, ``"none"`` or ``"held-out"``.
        always: fit both methods (``method="both"``); ``False`` (``"auto"``): the likelihood
            method only after an EM that ended :data:`STALLED` or failed.
        fixed: the parameters held fixed.
        dtype: floating dtype.
        rule: cubature rule of the filter.
        all_reduce: sums a flat tensor across the processes of a data-parallel fit.

    Returns:
        The kept method's :class:`~torchfilt.training.MeasurementOnlyFit`, its ``elapsed``
        the whole comparison's, its ``compared`` one record per method.

    Raises:
        FitError: no method fitted (the message names each failure, or why it was skipped).
    """
    t0 = time.perf_counter()
    kept, scored, starts = data, data, None
    basis = "training"
    if validation is not None:
        scored, basis = _validation(data, validation, model.state_dim), "validation"
    elif noise_scale == "held-out" or (
        noise_scale == "auto" and enough_held_out(data, holdout, all_reduce=all_reduce)
    ):
        kept, scored, starts = split_held_out(model, data, holdout, dtype=dtype)
        basis = "held-out"
    results: dict[str, _R] = {}
    scores: dict[str, float] = {}
    records: list[dict[str, Any]] = []
    for method in METHODS:
        record: dict[str, Any] = {"method": method, "basis": basis}
        skip = _not_applicable(method, model, fixed)
        ended = results["em"].stopped if "em" in results else None
        if skip is None and method == "likelihood" and not always and ended not in (None, *STALLED):
            skip = (
                f"EM ended {ended!r}, not stalled: the likelihood method runs after an EM "
                f"that stops with {' or '.join(map(repr, STALLED))} or fails (method='both': "
                "always)"
            )
        if skip is not None:
            records.append({**record, "score": -math.inf, "skipped": skip})
            continue
        try:
            res = fit(method, copy.deepcopy(model), kept)
            score = held_out_noise_scale(
                res.model, scored, starts, dtype=dtype, rule=rule, scales=(1.0,), margin=0.0,
                all_reduce=None if basis == "validation" else all_reduce,
            ).log_likelihood  # fmt: skip
        except FitError as e:
            records.append({**record, "score": -math.inf, "error": str(e)})
            continue
        results[method], scores[method] = res, score
        records.append(
            {
                **record, "score": score, "log_likelihood": res.log_likelihood,
                "iterations": res.iterations, "stopped": res.stopped, "elapsed": res.elapsed,
            }
        )  # fmt: skip
    if not results:
        name = f'fit_measurement_only(method="{"both" if always else "auto"}")'
        raise FitError(
            f"{name}: no method fitted: "
            + "; ".join(f"{r['method']}: {r.get('error', r.get('skipped'))}" for r in records),
            fit=name,
            step="both methods",
        )
    best = max(results, key=scores.__getitem__)
    for r in records:
        r["kept"] = r["method"] == best
    chosen = results[best]
    out = replace(chosen, compared=records, elapsed=time.perf_counter() - t0)
    scale = noise_scale == "held-out" or scales_by_default(
        model, data, holdout, validation=validation is not None, fixed=fixed,
        all_reduce=all_reduce,
    )  # fmt: skip
    if noise_scale == "none" or basis == "training" or not scale:
        return out
    return _noise_scaled(
        out, scored, starts, dtype=dtype, rule=rule,
        all_reduce=None if basis == "validation" else all_reduce,
    )  # fmt: skip
