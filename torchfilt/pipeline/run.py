"""Running a recipe: train the models, log everything, checkpoint, validate, write the bundle.

A run directory holds:

- ``config.json``: the resolved recipe, its digest, library versions;
- ``dataset.json``: the dataset log (per-file SHA-256, row counts, channel statistics, the split);
- ``metrics.jsonl``: one line per iteration (stage, iteration, loss, hyperparameters, time);
- ``checkpoint.pt``: the latest checkpoint (written atomically every ``checkpoint_every``
  iterations), and ``{transition,measurement}.pt`` once a stage is done;
- ``train.log``: plain progress lines;
- ``calibration.pt`` once the calibration stage is done (``calibrate.ckpt`` while it runs): the
  variance scales and noise floors fitted by the filter likelihood (``[calibrate]`` in the recipe);
- ``validation.json``: one-step RMSE, NLPD and 95% coverage on the validation recordings (where
  they log states), and the filter's consistency there (NIS; NEES and 95% coverage where states
  are logged) before and after calibration;
- ``model.pt``: the final model bundle.

The recipe, the dataset and the recipe's channel names are checked before anything is written,
and a run that fails on an invalid option before any stage is trained removes the files it wrote,
so the next attempt is not blocked. ``force=True`` (``--force``) discards a run already in the
directory (its files above, nothing else) and starts afresh.

With ``states = "none"`` (learning from measurements alone) the ``transition`` stage builds an
:class:`~torchfilt.models.InducingTransition` (its inducing inputs spread over the states a pilot
CKF with the nominal or random-walk model estimates on the training recordings) and fits it with
:func:`~torchfilt.training.fit_measurement_only` on the training measurements and inputs, the
known ``[measurement]`` system being the gauge; the fit checkpoints into ``transition.ckpt``.
The state columns of the training recordings are never read.

A run killed at any moment resumes from its last checkpoint with ``resume=True`` (``torchfilt train
... --resume``) and reaches the same model as an uninterrupted run with the same seed.

**Who fits the likelihood stages.** The calibration stage and the ``states = "none"`` transition
stage call :func:`~torchfilt.training.calibrate` and
:func:`~torchfilt.training.fit_measurement_only` in this process, unless ``train_recipe`` is given
other :class:`StageFitters` (callables with the same arguments): the data-parallel ones of
:func:`torchfilt.pipeline.distributed.train_recipe_data_parallel` (``torchfilt train --ray
--data-parallel N``) run the same fits on Ray actors, each stage's checkpoint then a folder of one
file per actor. ``config.json`` records fitters other than the local ones (``"stage_fitters"``),
and a run resumes only with the fitters it started with (else a :class:`RunError`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import sys
from pathlib import Path
from typing import Any, TextIO

import torch
from torch import Tensor

from torchfilt._version import __version__
from torchfilt.exceptions import InputError, RecipeError, RunError
from torchfilt.io import Dataset, atomic_write_text, load_dataset
from torchfilt.io.atomic import output_dir
from torchfilt.io.lock import DirectoryLock
from torchfilt.io.recording import Recording
from torchfilt.models import StateSpaceModel
from torchfilt.pipeline.bundle import BUNDLE_SCHEMA, apply_calibration, build_side, save_bundle
from torchfilt.pipeline.entry_point import (
    entry_point_digest,
    entry_point_entry,
    is_entry_point,
    load_entry_point,
)
from torchfilt.pipeline.recipe import Recipe, check_calibrate, check_states, load_recipe
from torchfilt.pipeline.run_checks import STAGES, _check_against_dataset
from torchfilt.pipeline.run_files import (
    _checkpoint_iteration,
    _fmt,
    _load_checkpoint,
    _load_stage,
    _Log,
    _now,
    _remove,
    _save,
)
from torchfilt.pipeline.run_stages import (
    CALIBRATE_CHECKPOINT,
    LOCAL_FITTERS,
    MEASUREMENT_ONLY_CHECKPOINT,
    StageFitters,
    _calibrate_stage,
    _fit_measurement_only_stage,
    _fit_stage,
    _transition_checkpoints,
    _transition_iterations,
)
from torchfilt.training.calibrate import consistency
from torchfilt.training.validation import one_step_metrics

__all__ = [
    "CALIBRATE_CHECKPOINT",
    "LOCAL_FITTERS",
    "MEASUREMENT_ONLY_CHECKPOINT",
    "RUN_FILES",
    "STAGES",
    "RunError",
    "StageFitters",
    "train_recipe",
]

#: The files a run writes into its directory (``force`` removes these, and only these).
RUN_FILES = (
    "config.json",
    "dataset.json",
    "metrics.jsonl",
    "checkpoint.pt",
    "transition.pt",
    "measurement.pt",
    "train.log",
    "validation.json",
    "model.pt",
    "calibration.pt",
    CALIBRATE_CHECKPOINT,
    MEASUREMENT_ONLY_CHECKPOINT,
)
#: A directory holding any of these holds a run (``resume`` continues it, ``force`` discards it).
_RUN_MARKERS = (
    "config.json",
    "checkpoint.pt",
    "transition.pt",
    "measurement.pt",
    "calibration.pt",
    CALIBRATE_CHECKPOINT,
    MEASUREMENT_ONLY_CHECKPOINT,
    "model.pt",
)


def train_recipe(
    recipe: str | Path | Recipe,
    out: str | Path,
    *,
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    stream: TextIO | None = None,
    fitters: StageFitters = LOCAL_FITTERS,
) -> Path:
    """Train the models a recipe describes and write a run directory (see the module docstring).

    Args:
        recipe: a recipe file (``trainers/*.toml``) or a :class:`Recipe`.
        out: run directory.
        resume: continue the run in ``out`` from its last checkpoint.
        force: discard a run already in ``out`` (the files of :data:`RUN_FILES`) and start afresh.
        progress: show a progress bar (on a terminal; plain lines otherwise).
        stream: where progress goes (default ``sys.stderr``).
        fitters: who fits the calibration and ``states = "none"`` transition stages (default:
            the local functions; see :class:`StageFitters`).

    Returns:
        Path of the model bundle ``out/model.pt``.

    Raises:
        RunError: another live process is writing ``out`` (the message names its pid), or
            ``out`` already holds a run (without ``resume`` or ``force``), or has none to
            resume, or the recipe or dataset changed since the run started, or the run started
            with other ``fitters`` (``StageFitters.name``).
        InputError: both ``resume`` and ``force``, or ``fitters`` dealing the recordings to
            more processes than the training split has.
        RecipeError: an invalid recipe (raised before anything is written).
        DataError: an invalid dataset (raised before anything is written).
        OutputError: ``out`` is a file, is read-only, or the disk is full.
    """
    if resume and force:
        raise InputError("--resume continues the run in --out and --force discards it: pick one")
    r = recipe if isinstance(recipe, Recipe) else load_recipe(recipe)
    try:
        check_states(r)  # again for a Recipe built in code
        check_calibrate(r)
    except RecipeError as e:
        raise RecipeError(str(e) if r.path is None else f"{r.path}: {e}") from None
    # states = "none": the state columns are never read for training (absent or NaN is fine)
    if r.states == "none":
        ds: Dataset = load_dataset(r.dataset, require_finite=("input",), optional=("state",))
    else:
        ds = load_dataset(r.dataset)
    prior = _check_against_dataset(r, ds)
    n_train = len(ds.split("train"))
    if fitters.shards > n_train:
        raise InputError(
            f"{fitters.name}: the fits deal the training recordings to {fitters.shards} "
            f"processes, but the dataset has {n_train}; use at most {n_train}"
        )
    out = Path(out)
    stream = stream if stream is not None else sys.stderr
    cfg_path = out / "config.json"
    if resume and not cfg_path.is_file():
        raise RunError(f"{out}: no run to resume (config.json missing)")
    created_dir = not out.exists()
    output_dir(out)
    lock = DirectoryLock(out).acquire()  # a live run in out: RunError naming its pid
    try:
        _check_run_dir(out, r, fitters, resume, force)
    except BaseException:
        lock.release()
        raise
    before = {f for f in RUN_FILES if (out / f).exists()}
    log: _Log | None = None
    try:
        if not resume:
            atomic_write_text(cfg_path, json.dumps(_config(r, fitters), indent=2) + "\n")
        log = _Log(out / "train.log", None if progress else stream)
        return _run(r, ds, prior, out, resume, progress, stream, log, fitters)
    except Exception:
        if not resume and not any((out / f).exists() for f in _RUN_MARKERS[1:]):
            # nothing trained yet (an invalid option, a full disk): remove what this attempt
            # wrote, so it blocks no other. A kill (no exception) leaves the run to --resume.
            if log is not None:
                log.close()
            for f in RUN_FILES:
                if f not in before and (out / f).is_file():
                    (out / f).unlink()
            lock.release()
            if created_dir and not any(out.iterdir()):
                out.rmdir()
        raise
    finally:
        if log is not None:
            log.close()
        lock.release()


def _check_run_dir(out: Path, r: Recipe, fitters: StageFitters, resume: bool, force: bool) -> None:
    """A run to resume must have started with this recipe and these fitters; a new run needs a
    directory without one (``force`` removes it)."""
    cfg_path = out / "config.json"
    if resume:
        try:
            old = json.loads(cfg_path.read_text(encoding="utf-8"))
            old_digest = old.get("digest") if isinstance(old, dict) else None
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise RunError(f"{cfg_path}: unreadable run configuration (not JSON)") from None
        if old_digest != r.digest():
            raise RunError(
                f"{out}: the recipe changed since this run started; start a new run "
                "(another --out, or --force to discard this one)"
            )
        if old.get("sensors", {}) != _sensor_digests(r):
            raise RunError(
                f"{out}: the sensor module of [measurement] model = "
                f'"{r.measurement.get("model")}" changed since this run started (its file\'s '
                "SHA-256 differs); restore it, or start a new run (another --out, or --force)"
            )
        old_fitters = old.get("stage_fitters", LOCAL_FITTERS.name)
        if old_fitters != fitters.name:
            raise RunError(
                f"{out}: this run fits its likelihood stages {_fitters_text(old_fitters)}; "
                f"resume it the same way, not {_fitters_text(fitters.name)} (or --force to "
                "start afresh)"
            )
    else:
        if force:
            for f in RUN_FILES:
                _remove(out / f)
        elif any((out / f).exists() for f in _RUN_MARKERS):
            raise RunError(
                f"{out}: already holds a run; pass --resume to continue it, --force to discard "
                "it, or choose another --out"
            )


def _fitters_text(name: Any) -> str:
    return "locally" if name == LOCAL_FITTERS.name else str(name)


def _config(r: Recipe, fitters: StageFitters = LOCAL_FITTERS) -> dict[str, Any]:
    """``config.json`` of a new run: the resolved recipe, its digest, library versions (and the
    stage fitters, when they are not the local ones)."""
    extra: dict[str, Any] = (
        {} if fitters.name == LOCAL_FITTERS.name else {"stage_fitters": fitters.name}
    )
    sensors = _sensor_digests(r)
    if sensors:
        extra["sensors"] = sensors
    return {
        "recipe": r.resolved(),
        "digest": r.digest(),
        "recipe_file": None if r.path is None else str(r.path),
        "created": _now(),
        "versions": {
            "torchfilt": __version__,
            "torch": str(torch.__version__),
            "python": platform.python_version(),
        },
        **extra,
    }


def _run(
    r: Recipe,
    ds: Dataset,
    prior: tuple[Tensor, Tensor, str],
    out: Path,
    resume: bool,
    progress: bool,
    stream: TextIO,
    log: _Log,
    fitters: StageFitters,
) -> Path:
    """Run the recipe with its thread count, restoring the caller's afterwards."""
    threads = torch.get_num_threads()
    if r.threads is not None:
        torch.set_num_threads(r.threads)
    try:
        return _run_recipe(r, ds, prior, out, resume, progress, stream, log, fitters)
    finally:
        torch.set_num_threads(threads)


def _run_recipe(
    r: Recipe,
    ds: Dataset,
    prior: tuple[Tensor, Tensor, str],
    out: Path,
    resume: bool,
    progress: bool,
    stream: TextIO,
    log: _Log,
    fitters: StageFitters,
) -> Path:
    dtype = torch.float64 if r.dtype == "float64" else torch.float32
    dlog = _dataset_log(r, ds, out, resume, log)
    train, val = _split(r, ds, log)
    ckpt_path = out / "checkpoint.pt"
    ckpt = _load_checkpoint(ckpt_path) if resume and ckpt_path.is_file() else None
    _trim_metrics(out / "metrics.jsonl", ckpt if resume else None, fresh=not resume)
    m0, P0, how = prior
    entries = _train_sides(
        r, ds, train, val, m0, P0, dtype, out, resume, ckpt, progress, stream, log, fitters
    )  # fmt: skip
    f = build_side(entries["transition"], "transition")
    h = build_side(entries["measurement"], "measurement")
    calibration = _calibrate_stage(
        r, entries, StateSpaceModel(f, h), train, val, m0, P0, dtype, out, resume, progress,
        stream, log, fitters,
    )  # fmt: skip
    uncal = StateSpaceModel(f, h)
    if calibration is not None and calibration.get("models"):
        # GPs refitted by the calibration: the bundle and the validation take them
        for stage, state in calibration.pop("models").items():
            entries[stage] = {**entries[stage], "state": state}
        f = build_side(entries["transition"], "transition")
        h = build_side(entries["measurement"], "measurement")
    validation = _validate(f, h, uncal, calibration, val, m0, P0, out, log)
    bundle = {
        "name": r.name,
        "transition": entries["transition"],
        "measurement": entries["measurement"],
        "channels": {
            "states": [[c.name, c.unit] for c in ds.manifest.channels if c.role == "state"],
            "inputs": [[c.name, c.unit] for c in ds.manifest.channels if c.role == "input"],
            "measurements": [
                [c.name, c.unit] for c in ds.manifest.channels if c.role == "measurement"
            ],
        },
        "sample_time": ds.manifest.sample_time,
        "time_column": ds.manifest.time_column,
        "time_unit": ds.manifest.time_unit,
        "prior": {"mean": m0, "cov": P0, "source": how},
        "calibration": calibration,
        "dataset": dlog["fingerprint"],
        "recipe": r.resolved(),
        "validation": validation,
        "created": _now(),
        "versions": {"torchfilt": __version__, "torch": str(torch.__version__)},
    }
    path = save_bundle(out / "model.pt", bundle)
    if ckpt_path.exists():
        ckpt_path.unlink()
    log(f"wrote {path} ({BUNDLE_SCHEMA})")
    return path


def _dataset_log(r: Recipe, ds: Dataset, out: Path, resume: bool, log: _Log) -> dict[str, Any]:
    """Write the dataset log ``dataset.json`` (a resumed run first checks that the dataset is
    the one it started on) and log the run's first line; returns the log."""
    dlog = ds.log()
    ds_path = out / "dataset.json"
    if resume and ds_path.is_file():
        try:
            old_sha = json.loads(ds_path.read_text(encoding="utf-8"))["fingerprint"][
                "dataset_sha256"
            ]
        except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
            raise RunError(f"{ds_path}: unreadable dataset log") from None
        if old_sha != dlog["fingerprint"]["dataset_sha256"]:
            raise RunError(
                f"{out}: the dataset changed since this run started (fingerprint differs)"
            )
    atomic_write_text(ds_path, json.dumps(dlog, indent=2, default=float) + "\n")
    train, val = ds.split("train"), ds.split("validation")
    log(
        f"run {r.name}: dataset {ds.manifest.name} ({len(train)} train / {len(val)} validation recordings, "
        f"fingerprint {dlog['fingerprint']['dataset_sha256'][:12]})"
    )
    return dlog


def _split(r: Recipe, ds: Dataset, log: _Log) -> tuple[list[Recording], list[Recording]]:
    """The training and validation recordings: the dataset's split, or, when it has no
    validation recordings, a default hold-out of ``r.holdout`` (``[train] holdout``): the last
    ``ceil(holdout x N)`` of ``N >= 4`` training recordings, else the last part of each (its
    first part trains). The model is trained on the rest and not refit on the held-out data."""
    train, val = ds.split("train"), ds.split("validation")
    if val:
        return train, val
    if r.holdout <= 0:
        log(
            "no validation recordings ([train] holdout = 0 and none in the dataset): early "
            "stopping and model selection cannot act, validation.json is empty"
        )
        return train, val
    hint = "set [dataset] validation recordings in the manifest or [train] holdout = 0 to change"
    if len(train) >= 4:
        k = math.ceil(r.holdout * len(train))
        train, val = train[:-k], train[-k:]
        log(
            f"{len(train)} train / {len(val)} validation recordings (held out by default: the "
            f"last {k}; {hint})"
        )
        return train, val
    heads, tails = [], []
    for rec in train:
        cut = len(rec) - max(2, math.ceil(r.holdout * len(rec)))
        if cut < 2:
            heads.append(rec)
            continue
        heads.append(dataclasses.replace(rec, time=rec.time[:cut], data=rec.data[:cut]))
        tails.append(dataclasses.replace(rec, time=rec.time[cut:], data=rec.data[cut:]))
    log(
        f"{len(train)} train recordings, their last {r.holdout:.0%} held out for validation "
        f"(held out by default: fewer than 4 recordings; {hint})"
    )
    return heads, tails


def _train_sides(
    r: Recipe,
    ds: Dataset,
    train: list[Recording],
    val: list[Recording],
    m0: Tensor,
    P0: Tensor,
    dtype: torch.dtype,
    out: Path,
    resume: bool,
    ckpt: dict[str, Any] | None,
    progress: bool,
    stream: TextIO,
    log: _Log,
    fitters: StageFitters,
) -> dict[str, dict[str, Any]]:
    """The bundle entry of each side: a built-in model, a stage trained before (resumed), or
    the side trained now (a GP, or the ``states = "none"`` transition) and saved."""
    states = ds.manifest.names("state")
    inputs = ds.manifest.names("input")
    entries: dict[str, dict[str, Any]] = {}
    for stage in STAGES:
        opts = dict(getattr(r, stage))
        done = out / f"{stage}.pt"
        if stage == "transition" and r.states == "none":
            if resume and done.is_file():
                entries[stage] = _load_stage(done)
                log(f"{stage}: already trained (resumed)")
                continue
            h0 = _sensor(r, ds)
            entries[stage] = _fit_measurement_only_stage(
                r, ds, h0, train, val, m0, P0, dtype, out, resume, progress, stream, log,
                fitters,
            )  # fmt: skip
            _save(done, entries[stage])
            for ck in _transition_checkpoints(out).values():
                _remove(ck)
            continue
        if "model" in opts:
            learned = (entries.get("transition") or {}).get("fit", {}).get("measurement_R")
            R = learned if stage == "measurement" else None
            entries[stage] = _known_entry(r, ds, stage, R)
            what = "built-in" if entries[stage]["kind"] == "system" else "known (entry point)"
            log(
                f"{stage}: {what} model {opts['model']}"
                + ("" if R is None else f", its noise R learned with the transition: {R}")
            )
            continue
        if resume and done.is_file():
            entries[stage] = _load_stage(done)
            log(f"{stage}: already trained (resumed)")
            continue
        entries[stage] = _fit_stage(
            r, stage, opts, train, states, inputs, dtype, out, ckpt, progress, stream, log
        )
        _save(done, entries[stage])
    return entries


def _known_entry(r: Recipe, ds: Dataset, stage: str, R: Any = None) -> dict[str, Any]:
    """The bundle entry of a side with a known ``model``: a built-in system, or an entry point
    (with its ``R``, or the learned ``R`` given, and its module file's SHA-256)."""
    opts = getattr(r, stage)
    spec = str(opts["model"])
    if stage == "measurement" and is_entry_point(spec):
        return entry_point_entry(
            spec, opts.get("R") if R is None else R, role=stage, state_dim=ds.state_dim,
            obs_dim=ds.obs_dim, input_dim=ds.input_dim,
        )  # fmt: skip
    return {"kind": "system", "system": spec.split(":", 1)[1]}


def _sensor(r: Recipe, ds: Dataset) -> Any:
    """The known measurement side of a ``states = "none"`` fit: frozen, or with its noise
    learnable from the recipe's ``R`` (``[measurement_only] learn_measurement_noise``)."""
    if not r.measurement_only.get("learn_measurement_noise"):
        return build_side(_known_entry(r, ds, "measurement"), "measurement")
    return load_entry_point(
        str(r.measurement["model"]), r.measurement["R"], role="measurement",
        state_dim=ds.state_dim, obs_dim=ds.obs_dim, input_dim=ds.input_dim, learn_R=True,
    )[0]  # fmt: skip


def _sensor_digests(r: Recipe) -> dict[str, Any]:
    """The SHA-256 of the module file of each entry-point side (what ``config.json`` records, so
    that ``--resume`` refuses a changed sensor)."""
    out: dict[str, Any] = {}
    spec = r.measurement.get("model")
    if is_entry_point(spec):
        out["measurement"] = entry_point_digest(str(spec), "measurement")
    return out


def _validate(
    f: Any,
    h: Any,
    uncal: StateSpaceModel,
    calibration: dict[str, Any] | None,
    val: list[Recording],
    m0: Tensor,
    P0: Tensor,
    out: Path,
    log: _Log,
) -> dict[str, Any]:
    """``validation.json``: one-step metrics of the sides ``f``, ``h`` and the filter's
    consistency before (``uncal``) and after calibration, on the validation recordings."""
    # one-step metrics need logged states: computed where every validation recording has them
    # (with states = "none" they are evaluation only, in the learned state coordinates)
    with_states = bool(val) and all(bool(torch.isfinite(rec.states).all()) for rec in val)
    validation = one_step_metrics(f, h, val) if with_states else {}
    if val and not with_states:
        validation["one_step"] = "skipped: the validation recordings do not all log the states"
    if val:
        validation["filter"] = {"uncalibrated": consistency(uncal, val, x0=m0, P0=P0)}
        if calibration is not None:
            fc = apply_calibration(f, calibration.get("transition"))
            hc = apply_calibration(h, calibration.get("measurement"))
            validation["filter"]["calibrated"] = consistency(
                StateSpaceModel(fc, hc), val, x0=m0, P0=P0
            )
        for k, v in validation["filter"].items():
            nees_txt = f", NEES {v['nees_mean']:.3g}" if "nees_mean" in v else ""
            log(
                f"validation filter ({k}): NIS {v['nis_mean']:.3g} per {v['nis_dof_mean']:.3g} dof{nees_txt}"
            )
    atomic_write_text(
        out / "validation.json", json.dumps(validation, indent=2, default=float) + "\n"
    )
    if "transition" in validation:
        log(
            f"validation one-step RMSE: transition {_fmt(validation['transition']['rmse'])}, "
            f"measurement {_fmt(validation['measurement']['rmse'])}; 95% coverage: transition "
            f"{_fmt(validation['transition']['coverage95'])}, measurement {_fmt(validation['measurement']['coverage95'])}"
        )
    return validation


def _trim_metrics(path: Path, ckpt: dict[str, Any] | None, fresh: bool) -> None:
    """Drop metric lines logged after the checkpoint a run resumes from (they will be redone)."""
    if fresh or not path.is_file():
        if fresh and path.exists():
            path.unlink()
        return
    keep = []
    cal_done = (path.parent / "calibration.pt").is_file()
    cal_ckpt = path.parent / CALIBRATE_CHECKPOINT
    cal_it = _checkpoint_iteration(cal_ckpt) if cal_ckpt.exists() else 0
    # a states = "none" transition fit keeps its own checkpoint (fit_measurement_only's; one
    # per method under method = "auto" or "both", whose metrics lines name their method)
    mo_open = not (path.parent / "transition.pt").is_file()
    mo_its = _transition_iterations(path.parent)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    for i, line in enumerate(lines):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            rec = None
        if not isinstance(rec, dict) or not {"stage", "iteration"} <= rec.keys():
            if i == len(lines) - 1:  # torn by a kill mid-write: that iteration is redone
                continue
            raise RunError(
                f"{path}: line {i + 1} is not a metrics record; delete the file to resume "
                "without the earlier metrics"
            ) from None
        if rec.get("stage") == "calibrate":
            if cal_done or rec["iteration"] <= cal_it:
                keep.append(line)
            continue
        if mo_open and rec.get("stage") == "transition" and any(mo_its.values()):
            if rec["iteration"] <= mo_its.get(str(rec.get("method", "")), 0):
                keep.append(line)
            continue
        if ckpt is None:
            # no checkpoint: only completed stages survive (their stage files exist)
            if (path.parent / f"{rec['stage']}.pt").is_file():
                keep.append(line)
            continue
        st = ckpt["stage"]
        if rec["stage"] != st and (path.parent / f"{rec['stage']}.pt").is_file():
            keep.append(line)
        elif rec["stage"] == st and rec["iteration"] <= ckpt["fit"]["iteration"]:
            keep.append(line)
    atomic_write_text(path, "".join(k + "\n" for k in keep))
