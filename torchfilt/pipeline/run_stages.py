"""The stages of a run (see :mod:`torchfilt.pipeline.run`): the GP fits, the ``states = "none"``
transition fit, the calibration; their checkpoints, metrics lines and log, and the fitters
(:class:`StageFitters`) that run the likelihood stages."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, Protocol, TextIO

import torch
from torch import Tensor

from torchfilt.exceptions import RunError
from torchfilt.filters import CKF
from torchfilt.io import Dataset
from torchfilt.io.atomic import output_error
from torchfilt.io.progress import ProgressBar
from torchfilt.io.recording import Recording
from torchfilt.models import CholeskyCovariance, InducingTransition, StateSpaceModel
from torchfilt.optim import CheckpointOptions, OptimizerOptions, StoppingOptions, WindowOptions
from torchfilt.pipeline.bundle import inducing_state, nominal_model
from torchfilt.pipeline.entry_point import learned_noise
from torchfilt.pipeline.linear_start import linear_em_start
from torchfilt.pipeline.recipe import OPTION_KEYS, Recipe, fit_options
from torchfilt.pipeline.recipe_options import option_default
from torchfilt.pipeline.run_checks import STAGES, _feature_indices, _known_channels
from torchfilt.pipeline.run_files import (
    _checkpoint_iteration,
    _ended,
    _fmt,
    _Log,
    _remove,
    _save,
    _StageClock,
    _tensor_list,
)
from torchfilt.training.calibrate import CalibrationResult, calibrate
from torchfilt.training.data import FitData
from torchfilt.training.likelihood import LikelihoodState
from torchfilt.training.measurement_only import EMState, MeasurementOnlyFit, fit_measurement_only
from torchfilt.training.method_choice import method_checkpoint

__all__ = [
    "CALIBRATE_CHECKPOINT",
    "LOCAL_FITTERS",
    "MEASUREMENT_ONLY_CHECKPOINT",
    "PILOT_NOISE_SCALES",
    "StageFitters",
]

#: Scales of the default initial process noise (1e-2 x the prior variances) that a
#: ``states = "none"`` fit without ``process_noise`` tries as starts (the best is fitted).
PILOT_NOISE_SCALES = (0.1, 1.0, 10.0)
#: The calibration stage's checkpoint in a run directory.
CALIBRATE_CHECKPOINT = "calibrate.ckpt"
#: The checkpoint of a ``states = "none"`` transition fit (``fit_measurement_only``'s own).
MEASUREMENT_ONLY_CHECKPOINT = "transition.ckpt"


class CalibrateFitter(Protocol):
    """What a calibration stage calls: :func:`~torchfilt.training.calibrate`'s contract.

    The stage passes the model and the training recordings (a list of
    :class:`~torchfilt.io.recording.Recording`) positionally and the rest by keyword; a fitter
    must keep their meaning (``x0`` ``(n,)``, ``P0`` ``(n, n)``, ``validation`` the validation
    recordings or ``None``) and may take more keywords with defaults. mypy holds every fitter
    handed to :class:`StageFitters` to this signature.
    """

    def __call__(
        self,
        model: StateSpaceModel,
        y: FitData,
        /,
        *,
        x0: Tensor,
        P0: Tensor,
        validation: FitData | None,
        sides: Sequence[Literal["transition", "measurement"]],
        inflate_only: bool,
        gp: Literal["none", "noise", "all"],
        callback: Callable[[LikelihoodState], bool | None] | None,
        checkpoint: CheckpointOptions,
        dtype: torch.dtype,
        iterations: int | None = ...,
        optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = ...,
        windows: WindowOptions | None = ...,
        stopping: StoppingOptions | None = ...,
    ) -> CalibrationResult: ...


class MeasurementOnlyFitter(Protocol):
    """What a ``states = "none"`` transition stage calls:
    :func:`~torchfilt.training.fit_measurement_only`'s contract.

    The stage passes the model, the measurements (a list of ``(T_i, m)``) and the inputs (a list
    of ``(T_i, nu)`` or ``None``) positionally and the rest by keyword; a fitter must keep their
    meaning and may take more keywords with defaults.
    """

    def __call__(
        self,
        model: StateSpaceModel,
        y: FitData,
        u: Tensor | Sequence[Tensor] | None,
        /,
        *,
        x0: Tensor,
        P0: Tensor,
        known_channels: Sequence[int] | None,
        method: Literal["auto", "both", "em", "likelihood"],
        learn_measurement_noise: bool,
        m_step_iterations: int,
        compile: bool,
        noise_scale: Literal["auto", "none", "held-out"],
        callback: Callable[[EMState | LikelihoodState], bool | None] | None,
        progress: bool,
        dtype: torch.dtype,
        checkpoint: CheckpointOptions,
        iterations: int | None = ...,
        optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = ...,
        windows: WindowOptions | None = ...,
        stopping: StoppingOptions | None = ...,
        accelerate: bool | None = ...,
        validation: FitData | None = ...,
    ) -> MeasurementOnlyFit: ...


@dataclass(frozen=True)
class StageFitters:
    """The fits behind a run's two likelihood stages (see :mod:`torchfilt.pipeline.run`).

    Each stage calls its fitter exactly as it calls the local function, and a replacement must
    accept those arguments and keep their meaning: :class:`CalibrateFitter` and
    :class:`MeasurementOnlyFitter` state them as types.

    ``callback`` must be called in the calling process, once per iteration in order and before
    that iteration's checkpoint (the stage writes ``metrics.jsonl`` and the progress bar from
    it; ``stopping`` is passed only where the recipe set ``patience``). ``checkpoint`` is a
    :class:`~torchfilt.optim.CheckpointOptions` whose path in the run directory the fitter owns:
    one checkpoint file,
    or a folder of files (one per process of a data-parallel fit), each a dictionary whose
    ``"iteration"`` says how far it got (a folder resumes from the lowest); the stage removes it
    when the stage is done.

    Attributes:
        calibrate: the calibration fit (a :class:`CalibrateFitter`); ``None``:
            :func:`~torchfilt.training.calibrate`.
        measurement_only: the ``states = "none"`` transition fit (a
            :class:`MeasurementOnlyFitter`); ``None``:
            :func:`~torchfilt.training.fit_measurement_only`.
        name: how ``config.json`` records these fitters (``"stage_fitters"``, omitted for
            ``"local"``); a run resumes only with fitters of the same name.
        shards: processes the fitters deal the training recordings to: a dataset with fewer
            training recordings is refused before anything is written.
    """

    calibrate: CalibrateFitter | None = None
    measurement_only: MeasurementOnlyFitter | None = None
    name: str = "local"
    shards: int = 1


#: The fitters of a plain run: the local functions, in this process.
LOCAL_FITTERS = StageFitters()
# the local functions keep the contracts (checked by mypy; the stages look them up when they run)
_LOCAL_CONTRACTS: tuple[CalibrateFitter, MeasurementOnlyFitter] = (calibrate, fit_measurement_only)


def _given(r: Recipe, section: str) -> frozenset[str] | None:
    """The keys section ``section`` of the recipe file wrote (``None``: a recipe built in code)."""
    return None if r.given is None else r.given.get(section, frozenset())


def _fit_stage(
    r: Recipe,
    stage: str,
    opts: dict[str, Any],
    train: list[Recording],
    states: list[str],
    inputs: list[str],
    dtype: torch.dtype,
    out: Path,
    ckpt: dict[str, Any] | None,
    progress: bool,
    stream: TextIO,
    log: _Log,
) -> dict[str, Any]:
    from torchfilt.models.gp import GPMeasurement, GPTransition  # heavy import (gpytorch)

    features = states + inputs if stage == "transition" else states
    pm = opts.get("prior_mean")
    if pm is not None:
        opts["prior_mean"] = nominal_model(pm)
    if "inputs" in opts:
        opts["inputs"] = _feature_indices(opts["inputs"], features, stage)
    iterations = int(opts.get("iterations", option_default("gp", "iterations")))
    bar = ProgressBar(f"train {stage}", iterations, stream, enabled=progress)
    try:
        metrics = open(out / "metrics.jsonl", "a", encoding="utf-8")
    except OSError as e:
        raise output_error(out / "metrics.jsonl", e) from None
    every = r.checkpoint_every
    ckpt_path = out / "checkpoint.pt"

    clock = _StageClock(stage, iterations, log)

    def callback(state: Any) -> None:
        hyper = {k: _tensor_list(v) for k, v in state.hyperparameters().items()}
        metrics.write(  # append-only log; a torn last line is dropped on resume
            json.dumps(
                {
                    "stage": stage,
                    "iteration": state.iteration,
                    "loss": state.loss,
                    "elapsed": state.elapsed,
                    "hyperparameters": hyper,
                }
            )
            + "\n"
        )
        metrics.flush()
        bar.update(state.iteration, f"loss {state.loss:.4g}")
        clock.tick(state.iteration, state.elapsed)
        if state.iteration % every == 0 or state.iteration == state.iterations:
            _save(ckpt_path, {"stage": stage, "fit": state.checkpoint()})
            log(
                f"{stage}: iteration {state.iteration}/{state.iterations} loss {state.loss:.6g} (checkpoint)"
            )

    resume_from = ckpt["fit"] if ckpt is not None and ckpt.get("stage") == stage else None
    if resume_from is not None:
        log(f"{stage}: resuming from iteration {resume_from['iteration']}")
    fit_opts = {  # the keys of the recipe schema (RECIPE_SCHEMA): the fit's keywords, but lr
        **{k: v for k, v in opts.items() if k not in OPTION_KEYS},
        **fit_options(opts, "gp"),  # iterations, and optimizer= with the recipe's lr
        "seed": r.seed,
        "dtype": dtype,
        "progress": False,
        "callback": callback,
        "resume": resume_from,
    }
    try:
        if stage == "transition":
            xs = [rec.states.to(dtype) for rec in train]
            us = [rec.inputs[:-1].to(dtype) for rec in train] if inputs else None  # type: ignore[index]
            model: Any = GPTransition.fit(xs, us, **fit_opts)
        else:
            model = GPMeasurement.fit(
                [rec.states.to(dtype) for rec in train],
                [rec.measurements.to(dtype) for rec in train],
                **fit_opts,
            )
    finally:
        metrics.close()
    log(f"{stage}: trained ({type(model).__name__})")
    return {"kind": "gp", "state": model.to_state(), "prior_mean": pm}


def _measurement_only_model(
    r: Recipe,
    h: Any,
    train: list[Recording],
    n: int,
    nu: int,
    m0: Tensor,
    P0: Tensor,
    dtype: torch.dtype,
    scale: float = 1.0,
) -> StateSpaceModel:
    """The initial model of a ``states = "none"`` fit: an :class:`InducingTransition` on the
    nominal model (or a random walk), its inducing inputs spread over the filtered states of a
    pilot CKF with that model on the training recordings, its lengthscales their spread; a
    learnable process noise ``Q`` (``process_noise``, default ``scale`` x 1e-2 x the prior
    variances)."""
    o = r.measurement_only
    g = None if o["nominal"] is None else nominal_model(o["nominal"])
    pn = o["process_noise"]
    if pn is None:
        q0 = scale * 1e-2 * P0.diagonal().to(dtype)
    else:
        q0 = torch.as_tensor(pn, dtype=dtype).expand(n).clone()
    pilot = StateSpaceModel(
        InducingTransition(n, 0, input_dim=nu, nominal=g, dtype=dtype), h, Q=torch.diag(q0)
    )
    xs, us = [], []
    with torch.no_grad():
        for rec in train:
            y = rec.measurements[1:].to(dtype)
            u = None if not nu else rec.inputs[:-1].to(dtype)  # type: ignore[index]
            res = CKF(pilot).filter(y, u, x0=m0.to(dtype), P0=P0.to(dtype))
            xs.append(res.mean)
            us.append(u)
    X = torch.cat(xs)
    U = torch.cat(us) if nu else None  # type: ignore[arg-type]
    ok = torch.isfinite(X).all(-1)
    X, U = X[ok], None if U is None else U[ok]
    cloud = X if U is None else torch.cat([X, U], -1)
    M = int(o["inducing"])
    if cloud.shape[0] < max(M, 2):
        raise RunError(
            f"[measurement_only] inducing = {M}: the pilot filter estimated only "
            f"{cloud.shape[0]} finite states on the training recordings; use fewer inducing "
            "points, more data, or a [filter] prior and nominal model closer to the data"
        )
    spread = cloud.std(0)
    ls = torch.where(spread > 1e-6, spread, torch.ones_like(spread))
    f = InducingTransition(
        n, M, input_dim=nu, nominal=g, lengthscale=ls, outputscale=q0, dtype=dtype
    )
    f.init_inducing(X, U)
    return StateSpaceModel(f, h, Q=CholeskyCovariance(torch.diag(q0)))


def _score(
    model: StateSpaceModel, recs: list[Recording], nu: int, m0: Tensor, P0: Tensor, dtype: Any
) -> float:
    """The CKF log-likelihood of ``model`` on recordings (``-inf`` where not finite)."""
    total = 0.0
    with torch.no_grad():
        for rec in recs:
            y = rec.measurements[1:].to(dtype)
            u = None if not nu else rec.inputs[:-1].to(dtype)  # type: ignore[index]
            res = CKF(model).filter(y, u, x0=m0.to(dtype), P0=P0.to(dtype))
            total += float(res.log_likelihood.sum())
    return total if math.isfinite(total) else -math.inf


def _start(
    r: Recipe,
    h: Any,
    train: list[Recording],
    val: list[Recording],
    n: int,
    nu: int,
    m0: Tensor,
    P0: Tensor,
    dtype: torch.dtype,
    log: _Log,
    known: list[int] | None = None,
) -> tuple[StateSpaceModel, list[dict[str, Any]]]:
    """The start of a ``states = "none"`` fit. With ``process_noise`` given: that model. Without:
    one pilot start per scale of :data:`PILOT_NOISE_SCALES` on the default process noise and,
    without a nominal model, the linear-EM start (``linear_em_start``: N4SID, a short linear
    EM, a GP transition starting exactly at it), each
    scored by its filter log-likelihood on the validation recordings (the training ones where
    there are none), the best kept; each candidate is logged and returned as a record. Every
    candidate is deterministic, so a resumed run picks the same one."""
    if r.measurement_only["process_noise"] is not None:
        return _measurement_only_model(r, h, train, n, nu, m0, P0, dtype), []
    recs, where = (val, "held-out") if val else (train, "training")
    models, records, scores = [], [], []
    for k, sc in enumerate(PILOT_NOISE_SCALES, 1):
        model = _measurement_only_model(r, h, train, n, nu, m0, P0, dtype, sc)
        ll = _score(model, recs, nu, m0, P0, dtype)
        models.append(model)
        scores.append(ll)
        records.append(
            {"candidate": k, "start": "pilot", "process_noise_scale": sc, "score": ll, "on": where}
        )
        log(
            f"transition: candidate start {k}: process noise {sc:g} x 1e-2 x the prior "
            f"variances, {where} log-likelihood {ll:.6g}"
        )
    k = len(models) + 1
    if r.measurement_only["nominal"] is not None:
        log(f"transition: no linear-EM candidate {k} (a nominal model is set: it is the start)")
    else:
        lin = linear_em_start(
            h, train, n=n, nu=nu, m0=m0, P0=P0, q0=1e-2 * P0.diagonal().to(dtype),
            inducing=int(r.measurement_only["inducing"]),
            known=list(range(h.out_dim)) if known is None else known, dtype=dtype,
            stable=bool(r.measurement_only["stable"]),
        )  # fmt: skip
        if lin is None:
            log(f"transition: no linear-EM candidate {k} (the sensor or the fit did not allow it)")
        else:
            ll = _score(lin.model, recs, nu, m0, P0, dtype)
            models.append(lin.model)
            scores.append(ll)
            records.append({"candidate": k, **lin.record, "score": ll, "on": where})
            log(
                f"transition: linear-EM candidate {k}: {lin.record['em_iterations']} EM "
                f"iterations from {_linear_source(lin.record)}, {where} log-likelihood {ll:.6g}"
            )
    best = max(range(len(scores)), key=lambda i: scores[i])
    for i, rec in enumerate(records):
        rec["chosen"] = i == best
    log(f"transition: starting from candidate {best + 1} (the best {where} log-likelihood)")
    return models[best], records


def _linear_source(record: dict[str, Any]) -> str:
    """Where the linear-EM candidate started, in words: ``random walk``, or ``N4SID (10 block
    rows, stabilised; after the EM from 10: -99.26, 10 stabilised: 403.3, 20: 285.1)`` (the
    kept start, and each tried with its training log-likelihood after the EM; ``kept as
    started`` where ``stable`` kept a start whose EM left the unit circle)."""
    if "block_rows" not in record:
        return str(record["from"])

    def name(t: dict[str, Any]) -> str:
        return f"{t['block_rows']}" + (" stabilised" if t.get("stabilised") else "")

    def kept(t: dict[str, Any]) -> str:
        if "unstable_after_em" not in t:
            return ""
        return f" (kept as started: the EM's spectral radius {t['unstable_after_em']:.4g})"

    tried = ", ".join(
        f"{name(t)}: {t['log_likelihood']:.6g}{kept(t)}" for t in record["block_rows_tried"]
    )
    rows = f"{record['block_rows']} block rows" + (
        ", stabilised" if record.get("stabilised") else ""
    )
    return f"{record['from']} ({rows}; after the EM from {tried})"


def _transition_iterations(out: Path) -> dict[str, int]:
    """The iterations the ``states = "none"`` transition fit's checkpoints in run directory
    ``out`` resume from, by method as :func:`_transition_checkpoints` names them (0: none); a
    data-parallel fit's are in the folder ``transition.ckpt``, one file per process (and per
    method: ``rank{r}.{method}.ckpt``)."""
    folder = out / MEASUREMENT_ONLY_CHECKPOINT
    return {
        m: _checkpoint_iteration(folder, m)
        if folder.is_dir()
        else (_checkpoint_iteration(ck) if ck.exists() else 0)
        for m, ck in _transition_checkpoints(out).items()
    }


def _transition_checkpoints(out: Path) -> dict[str, Path]:
    """The ``states = "none"`` transition fit's checkpoints in run directory ``out``, by the
    method the metrics lines name (``""``: one method; ``"em"``, ``"likelihood"``: those of
    ``method = "auto"`` or ``"both"``,
    :func:`~torchfilt.training.method_choice.method_checkpoint`)."""
    ckpt = out / MEASUREMENT_ONLY_CHECKPOINT
    files = {"": ckpt}
    for m in ("em", "likelihood"):
        files[m] = Path(str(method_checkpoint(CheckpointOptions(ckpt), m).path))
    return files


class _TransitionLog:
    """The ``states = "none"`` transition fit's callback: a ``metrics.jsonl`` line, the progress
    bar, the estimated time and a log line at every checkpoint, per iteration; under
    ``method = "auto"`` or ``"both"`` each labelled with the method that runs (each has its own
    iterations, estimate and checkpoint)."""

    def __init__(
        self, out: Path, counted: int, iterations: int, every: int, auto: bool,
        progress: bool, stream: TextIO, log: _Log,
    ) -> None:  # fmt: skip
        self.counted, self.iterations, self.every, self.auto = counted, iterations, every, auto
        self.log = log
        self.clocks: dict[str, _StageClock] = {}
        self.bar = ProgressBar("train transition", iterations, stream, enabled=progress)
        try:
            self.metrics = open(out / "metrics.jsonl", "a", encoding="utf-8")
        except OSError as e:
            raise output_error(out / "metrics.jsonl", e) from None

    def __call__(self, state: Any) -> None:
        ll = float(state.log_likelihood)
        loss = float(getattr(state, "loss", -ll / self.counted))
        rec = {
            "stage": "transition",
            "iteration": state.iteration,
            "loss": loss,
            "log_likelihood": ll,
            "elapsed": state.elapsed,
        }
        method = "em" if isinstance(state, EMState) else "likelihood"
        label = f"transition ({method})" if self.auto else "transition"
        if self.auto:
            rec["method"] = method
        self.metrics.write(json.dumps(rec) + "\n")
        self.metrics.flush()
        self.bar.update(state.iteration, f"loss {loss:.4g}")
        clock = self.clocks.setdefault(label, _StageClock(label, self.iterations, self.log))
        clock.tick(state.iteration, state.elapsed)
        if state.iteration % self.every == 0 or state.iteration == state.iterations:
            self.log(
                f"{label}: iteration {state.iteration}/{state.iterations} loss {loss:.6g} (checkpoint)"
            )

    def close(self) -> None:
        self.metrics.close()


def _fit_measurement_only_stage(
    r: Recipe,
    ds: Dataset,
    h: Any,
    train: list[Recording],
    val: list[Recording],
    m0: Tensor,
    P0: Tensor,
    dtype: torch.dtype,
    out: Path,
    resume: bool,
    progress: bool,
    stream: TextIO,
    log: _Log,
    fitters: StageFitters = LOCAL_FITTERS,
) -> dict[str, Any]:
    """The ``states = "none"`` transition stage: :func:`fit_measurement_only` (or
    ``fitters.measurement_only``) on the training recordings' measurements and inputs; returns
    the ``"inducing"`` bundle entry."""
    o = r.measurement_only
    n, nu = ds.state_dim, ds.input_dim
    known = _known_channels(r, ds)
    model, candidates = _start(r, h, train, val, n, nu, m0, P0, dtype, log, known)
    ys = [rec.measurements[1:].to(dtype) for rec in train]
    us = [rec.inputs[:-1].to(dtype) for rec in train] if nu else None  # type: ignore[index]
    counted = max(1, sum(int(torch.isfinite(y).sum()) for y in ys))
    options = fit_options(o, "measurement_only", _given(r, "measurement_only"))
    iterations = int(options["iterations"])
    if o.get("accelerate"):  # passed only when set: a fitter of before need not know it
        options["accelerate"] = True
    ckpt = out / MEASUREMENT_ONLY_CHECKPOINT
    method = o["method"]
    auto = method in ("auto", "both")
    done = _transition_iterations(out)
    for m in ("em", "likelihood") if auto else ("",):
        if resume and done[m]:
            label = f" ({m})" if m else ""
            log(f"transition{label}: resuming from iteration {done[m]}")
    log(
        f"transition: learning from measurements alone ({method}, {model.transition.base.num_inducing} "  # type: ignore[union-attr]
        f"inducing points, known channels {[ds.manifest.names('measurement')[i] for i in known]}"
        + (", and the sensor's noise R" if o["learn_measurement_noise"] else "")
        + ")"
    )
    if auto:  # the methods are compared on the validation recordings (the training ones without)
        options["validation"] = val or None
        when = "" if method == "both" else ' if EM stops with "no improvement"'
        log(
            f"transition: method {method}: EM, then the likelihood method{when}, from the "
            f"same start; the better {'validation' if val else 'training'} log-likelihood is kept"
        )
    every = r.checkpoint_every
    callback = _TransitionLog(out, counted, iterations, every, auto, progress, stream, log)
    learn_R = any(p.requires_grad for p in model.measurement.parameters())
    fitter = fitters.measurement_only or fit_measurement_only  # looked up now: patchable
    try:
        fit = fitter(
            model,
            ys,
            us,
            x0=m0.to(dtype),
            P0=P0.to(dtype),
            known_channels=known,
            method=method,
            learn_measurement_noise=learn_R,
            m_step_iterations=int(o["m_step_iterations"]),
            compile=bool(o["compile"]),
            # the pipeline scales the transition's variance in its calibration stage (on by
            # default, inflate_only): a CalibratedModel the bundle keeps and verifies. A
            # second scale here would hold recordings out of the fit for nothing
            noise_scale="none",
            callback=callback,
            progress=False,
            dtype=dtype,
            checkpoint=CheckpointOptions(ckpt, every=every, resume=resume),
            **options,
        )
    finally:
        callback.close()
    if auto:
        for rec in fit.compared:
            what = (
                f"{rec['basis']} log-likelihood {rec['score']:.6g}"
                if "error" not in rec and "skipped" not in rec
                else f"not fitted: {rec.get('error', rec.get('skipped'))}"
            )
            log(
                f"transition: method {method}: {rec['method']}: {what}"
                + (", kept" if rec["kept"] else "")
            )
    entry = _measurement_only_entry(fit, o, ds.manifest.names("measurement"))
    if candidates:
        entry["fit"]["candidates"] = candidates
    R = learned_noise(fit.model.measurement) if o["learn_measurement_noise"] else None
    if R is not None:  # the bundle's measurement entry takes it (run._train_sides)
        entry["fit"]["measurement_R"] = R.tolist()
    log(
        f"transition: {_ended(fit.stopped, fit.iterations, 'measurement_only')}; log-likelihood "
        f"{entry['fit']['initial_log_likelihood']:.6g} -> {fit.log_likelihood:.6g}"
    )
    return entry


def _measurement_only_entry(
    fit: MeasurementOnlyFit, o: dict[str, Any], names: list[str]
) -> dict[str, Any]:
    """The ``"inducing"`` bundle entry of a ``states = "none"`` fit: the learned transition and
    the fit's record and options ``o`` (``names``: the measurement channels)."""
    info = {
        "method": fit.method,
        "known_channels": [names[i] for i in fit.known_channels],
        "iterations": fit.iterations,
        "stopped": fit.stopped,
        "log_likelihood": fit.log_likelihood,
        "initial_log_likelihood": fit.detail.initial_log_likelihood,
        "per_measurement": fit.per_measurement,
        "options": dict(o),
    }
    if fit.compared:  # method = "auto" or "both": both methods' records (a score of -inf: None; no
        # seconds: a resumed run writes the identical record)
        info["compared"] = [
            {
                k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in c.items()
                if k != "elapsed"
            }
            for c in fit.compared
        ]
    return {
        "kind": "inducing",
        "nominal": o["nominal"],
        "state": inducing_state(fit.model.transition),
        "fit": info,
    }


def _calibrate_stage(
    r: Recipe,
    entries: dict[str, dict[str, Any]],
    model: StateSpaceModel,
    train: list[Recording],
    val: list[Recording],
    m0: Tensor,
    P0: Tensor,
    dtype: torch.dtype,
    out: Path,
    resume: bool,
    progress: bool,
    stream: TextIO,
    log: _Log,
    fitters: StageFitters = LOCAL_FITTERS,
) -> dict[str, Any] | None:
    """Fit variance scales and floors by the filter likelihood on the training recordings
    (:func:`calibrate`, or ``fitters.calibrate``)."""
    c = r.calibrate
    if not c["enabled"]:
        log("calibrate: off ([calibrate] enabled = false)")
        return None
    learned = [s for s in STAGES if entries[s].get("kind") in ("gp", "inducing")]
    sides = learned if c["sides"] == "learned" else list(c["sides"])
    if not sides:
        log("calibrate: no learned side to calibrate; skipped")
        return None
    done = out / "calibration.pt"
    if resume and done.is_file():
        log("calibrate: already done (resumed)")
        return dict(torch.load(done, weights_only=True))
    ckpt = out / CALIBRATE_CHECKPOINT
    if resume and ckpt.exists():
        log(f"calibrate: resuming from iteration {_checkpoint_iteration(ckpt)}")
    options = fit_options(c, "calibrate", _given(r, "calibrate"))
    iterations = int(options["iterations"])
    # short recordings: the burn-in may take at most half of the shortest one
    shortest = min(len(rec) - 1 for rec in train)
    burn_in = min(int(c["burn_in"]), shortest // 2)
    options["windows"] = replace(options["windows"], burn_in=burn_in)
    if burn_in < int(c["burn_in"]):
        log(
            f"calibrate: burn_in {c['burn_in']} -> {burn_in} (shortest recording: {shortest} steps)"
        )
    bar = ProgressBar("calibrate", iterations, stream, enabled=progress)
    every = r.checkpoint_every
    with open(out / "metrics.jsonl", "a", encoding="utf-8") as metrics:
        clock = _StageClock("calibrate", iterations, log)

        def callback(state: Any) -> None:
            rec = {
                "stage": "calibrate",
                "iteration": state.iteration,
                "loss": state.loss,
                "validation": state.validation,
                "elapsed": state.elapsed,
            }
            metrics.write(json.dumps(rec) + "\n")
            metrics.flush()
            bar.update(state.iteration, f"-loglik/meas {state.loss:.4g}")
            clock.tick(state.iteration, state.elapsed)
            if state.iteration % every == 0:
                log(f"calibrate: iteration {state.iteration}/{iterations} loss {state.loss:.6g}")

        fitter = fitters.calibrate or calibrate  # looked up now: patchable
        res = fitter(
            model,
            train,
            x0=m0,
            P0=P0,
            validation=val or None,
            sides=sides,  # type: ignore[arg-type]
            inflate_only=bool(c["inflate_only"]),
            gp=c.get("gp", "none"),
            callback=callback,
            checkpoint=CheckpointOptions(ckpt, every=every, resume=resume),
            dtype=dtype,
            **options,
        )
    fit = res.fit
    entry = _calibration_entry(res, c)
    _save(done, entry)
    _remove(ckpt)
    log(
        f"calibrate: {_ended(fit.stopped, fit.iterations, 'calibrate')}; log-likelihood "
        f"{fit.initial_log_likelihood:.6g} -> {fit.log_likelihood:.6g}; "
        + "; ".join(
            f"{k} scale {_fmt(v['scale'])} floor {_fmt(v['floor'])}"
            for k, v in res.parameters.items()
        )
    )
    return entry


def _calibration_entry(res: CalibrationResult, c: dict[str, Any]) -> dict[str, Any]:
    """The bundle's ``calibration`` entry: the scales and floors, the fit's record and options
    ``c``, and the GPs the calibration refitted (with their hyperparameters), if any."""
    fit = res.fit
    entry: dict[str, Any] = {
        **res.parameters,
        "fit": {
            "stopped": fit.stopped,
            "iterations": fit.iterations,
            "best_iteration": fit.best_iteration,
            "log_likelihood": fit.log_likelihood,
            "initial_log_likelihood": fit.initial_log_likelihood,
            "validation_per_measurement": fit.validation,
            "measurements": fit.measurements,
            "windows": fit.windows,
            "options": dict(c),
        },
    }
    if res.refit:
        # the refitted GPs replace the stage's models in the bundle; their hyperparameters are
        # logged beside the scales
        entry["models"] = {name: g.to_state() for name, g in res.refit.items()}
        entry["gp_hyperparameters"] = {
            name: {k: v.tolist() for k, v in g.hyperparameters().items()}
            for name, g in res.refit.items()
        }
    return entry
