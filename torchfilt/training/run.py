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

import datetime as _dt
import io
import json
import platform
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import torch
from torch import Tensor

from torchfilt._version import __version__
from torchfilt.exceptions import DataError, InputError, RecipeError, RunError
from torchfilt.filters import CKF
from torchfilt.io import Dataset, atomic_write_bytes, atomic_write_text, load_dataset
from torchfilt.io.atomic import output_dir, output_error
from torchfilt.io.recording import Recording
from torchfilt.models import CholeskyCovariance, InducingTransition, StateSpaceModel
from torchfilt.systems import get_system
from torchfilt.training.bundle import (
    BUNDLE_SCHEMA,
    apply_calibration,
    build_side,
    inducing_state,
    nominal_model,
    save_bundle,
)
from torchfilt.training.calibrate import CalibrationResult, calibrate, consistency
from torchfilt.training.measurement_only import MeasurementOnlyFit, fit_measurement_only
from torchfilt.training.progress import ProgressBar
from torchfilt.training.recipe import Recipe, check_calibrate, check_states, load_recipe
from torchfilt.training.validation import one_step_metrics

__all__ = ["LOCAL_FITTERS", "RunError", "StageFitters", "train_recipe"]

STAGES = ("transition", "measurement")
#: The calibration stage's checkpoint in a run directory.
CALIBRATE_CHECKPOINT = "calibrate.ckpt"
#: The checkpoint of a ``states = "none"`` transition fit (``fit_measurement_only``'s own).
MEASUREMENT_ONLY_CHECKPOINT = "transition.ckpt"
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


@dataclass(frozen=True)
class StageFitters:
    """The fits behind a run's two likelihood stages (see the module docstring).

    Each stage calls its fitter exactly as it calls the local function, and a replacement must
    accept those arguments and keep their meaning:

    - ``calibrate(model, train, *, x0, P0, validation, sides, window, burn_in, iterations, lr,
      optimizer, patience, inflate_only, gp, callback, checkpoint, resume, checkpoint_every,
      dtype)`` -> :class:`~torchfilt.training.calibrate.CalibrationResult`, as
      :func:`~torchfilt.training.calibrate` (``train`` the training recordings, ``x0`` ``(n,)``,
      ``P0`` ``(n, n)``, ``validation`` the validation recordings or ``None``);
    - ``measurement_only(model, ys, us, *, x0, P0, known_channels, method, iterations, window,
      burn_in, optimizer, lr, learn_measurement_noise, m_step_iterations, callback, progress,
      dtype, checkpoint, checkpoint_every, resume)`` ->
      :class:`~torchfilt.training.measurement_only.MeasurementOnlyFit`, as
      :func:`~torchfilt.training.fit_measurement_only` (``ys`` a list of ``(T_i, m)``, ``us`` a
      list of ``(T_i, nu)`` or ``None``).

    ``callback`` must be called in the calling process, once per iteration in order and before
    that iteration's checkpoint (the stage writes ``metrics.jsonl`` and the progress bar from
    it). ``checkpoint`` is a path in the run directory that the fitter owns: one checkpoint file,
    or a folder of files (one per process of a data-parallel fit), each a dictionary whose
    ``"iteration"`` says how far it got (a folder resumes from the lowest); the stage removes it
    when the stage is done.

    Attributes:
        calibrate: the calibration fit; ``None``: :func:`~torchfilt.training.calibrate`.
        measurement_only: the ``states = "none"`` transition fit; ``None``:
            :func:`~torchfilt.training.fit_measurement_only`.
        name: how ``config.json`` records these fitters (``"stage_fitters"``, omitted for
            ``"local"``); a run resumes only with fitters of the same name.
        shards: processes the fitters deal the training recordings to: a dataset with fewer
            training recordings is refused before anything is written.
    """

    calibrate: Callable[..., CalibrationResult] | None = None
    measurement_only: Callable[..., MeasurementOnlyFit] | None = None
    name: str = "local"
    shards: int = 1


#: The fitters of a plain run: the local functions, in this process.
LOCAL_FITTERS = StageFitters()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _tensor_list(v: Tensor) -> Any:
    v = v.detach().cpu()
    return v.item() if v.numel() == 1 else v.tolist()


class _Log:
    """Plain lines to ``train.log`` (always) and to the console when progress is off."""

    def __init__(self, path: Path, echo: TextIO | None) -> None:
        self.path = path
        try:
            self.fh = open(path, "a", encoding="utf-8")
        except OSError as e:
            raise output_error(path, e) from None
        self.echo = echo

    def __call__(self, msg: str) -> None:
        line = f"{_now()} {msg}\n"
        try:
            self.fh.write(line)
            self.fh.flush()
        except OSError as e:
            raise output_error(self.path, e) from None
        if self.echo is not None:
            self.echo.write(msg + "\n")
            self.echo.flush()

    def close(self) -> None:
        self.fh.close()


def _feature_indices(names: list[Any] | None, features: list[str], where: str) -> list[Any] | None:
    """Translate input selection by channel name into feature indices."""
    if names is None:
        return None

    def one(v: Any) -> int:
        if isinstance(v, int):
            if not 0 <= v < len(features):
                raise RecipeError(
                    f"[{where}] inputs: index {v} out of range for features {features}"
                )
            return v
        if not isinstance(v, str) or v not in features:
            raise RecipeError(
                f"[{where}] inputs: unknown channel {v!r}; the channels are {features}"
            )
        return features.index(v)

    if names and isinstance(names[0], list):
        return [[one(v) for v in per] for per in names]
    return [one(v) for v in names]


def _prior(recipe: Recipe, train: list[Recording], n: int) -> tuple[Tensor, Tensor, str]:
    """The bundle's default filter prior: from the data's initial states, a system, or explicit."""
    f = recipe.filter
    if "mean" in f or "cov_diag" in f:
        if "mean" not in f or "cov_diag" not in f:
            raise RecipeError("[filter] give both mean and cov_diag")
        try:
            m = torch.tensor(f["mean"], dtype=torch.float64)
            c = torch.diag(torch.tensor(f["cov_diag"], dtype=torch.float64))
        except (TypeError, ValueError, RuntimeError):
            raise RecipeError("[filter] mean and cov_diag must be lists of numbers") from None
        if m.shape != (n,) or c.shape != (n, n):
            raise RecipeError(f"[filter] mean and cov_diag must have {n} entries (the states)")
        if not bool(torch.isfinite(m).all()) or not bool((c.diagonal() > 0).all()):
            raise RecipeError("[filter] mean must be finite and cov_diag positive")
        return m, c, "recipe"
    prior = str(f.get("prior", "data"))
    if prior.startswith("system:"):
        s = get_system(prior.split(":", 1)[1])
        return s.prior_mean(), s.prior_cov(), prior
    if prior != "data":
        raise RecipeError(
            f"[filter] prior must be 'data', 'system:NAME' or mean/cov_diag, got {prior!r}"
        )
    x0 = torch.stack([r.states[0].to(torch.float64) for r in train])
    m = x0.mean(0)
    if x0.shape[0] > n:
        c = torch.cov(x0.T).reshape(n, n)
    else:
        allx = torch.cat([r.states.to(torch.float64) for r in train])
        c = torch.diag(allx.var(0))
    c = 0.5 * (c + c.T) + torch.diag(c.diagonal().abs() * 1e-9 + torch.finfo(torch.float64).tiny)
    return m, c, "data: mean and covariance of the training recordings' initial states"


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
        RunError: ``out`` already holds a run (without ``resume`` or ``force``), or has none to
            resume, or the recipe or dataset changed since the run started, or the run started
            with other ``fitters`` (``StageFitters.name``).
        RecipeError, DataError: invalid recipe or dataset (raised before anything is written).
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
            if created_dir and not any(out.iterdir()):
                out.rmdir()
        raise
    finally:
        if log is not None:
            log.close()


def _fitters_text(name: Any) -> str:
    return "locally" if name == LOCAL_FITTERS.name else str(name)


def _remove(path: Path) -> None:
    """Remove a run file, or a stage checkpoint folder (of a data-parallel fit), if present."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.is_file():
        path.unlink()


def _config(r: Recipe, fitters: StageFitters = LOCAL_FITTERS) -> dict[str, Any]:
    """``config.json`` of a new run: the resolved recipe, its digest, library versions (and the
    stage fitters, when they are not the local ones)."""
    extra = {} if fitters.name == LOCAL_FITTERS.name else {"stage_fitters": fitters.name}
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


def _check_against_dataset(r: Recipe, ds: Dataset) -> tuple[Tensor, Tensor, str]:
    """Check the recipe against the dataset before any training: training recordings exist, the
    ``inputs`` of each GP side name channels, a ``prior_mean`` system exists, the ``[filter]``
    prior fits. Returns the bundle's default filter prior. Errors name the recipe file."""
    try:
        return _check_channels(r, ds)
    except RecipeError as e:
        if r.path is None:
            raise
        raise RecipeError(f"{r.path}: {e}") from None


def _check_channels(r: Recipe, ds: Dataset) -> tuple[Tensor, Tensor, str]:
    train = ds.split("train")
    if not train:
        raise DataError("the dataset has no training recordings", path=ds.manifest_path)
    states, inputs = ds.manifest.names("state"), ds.manifest.names("input")
    if r.states == "none":
        _check_measurement_only(r, ds)
        return _prior(r, train, len(states))
    for stage in STAGES:
        opts = getattr(r, stage)
        if "model" in opts:
            get_system(str(opts["model"]).split(":", 1)[1])
            continue
        features = states + inputs if stage == "transition" else states
        if "inputs" in opts:
            sel = opts["inputs"]
            if not isinstance(sel, list):
                raise RecipeError(f"[{stage}] inputs must be a list of channel names")
            _feature_indices(sel, features, stage)
        if opts.get("prior_mean") is not None:
            nominal_model(opts["prior_mean"])
    return _prior(r, train, len(states))


def _known_channels(r: Recipe, ds: Dataset) -> list[int]:
    """``[measurement_only] known_channels`` as measurement indices (default: all)."""
    names = ds.manifest.names("measurement")
    kc = r.measurement_only.get("known_channels")
    if kc is None:
        return list(range(len(names)))
    unknown = [c for c in kc if c not in names]
    if unknown:
        raise RecipeError(
            f"[measurement_only] known_channels: unknown measurement channel(s) {unknown}; the "
            f"measurement channels are {names}"
        )
    return [names.index(c) for c in kc]


def _check_measurement_only(r: Recipe, ds: Dataset) -> None:
    """``states = "none"`` against the dataset: the measurement system fits its channels, the
    known channels exist, the nominal model maps the states, ``process_noise`` has one value per
    state."""
    n, nu, m = ds.state_dim, ds.input_dim, ds.obs_dim
    name = str(r.measurement["model"]).split(":", 1)[1]
    try:
        spec = get_system(name)
    except InputError as e:
        raise RecipeError(f"[measurement] model: {e}") from None
    if len(spec.states) != n or len(spec.measurements) != m:
        raise RecipeError(
            f'[measurement] model = "system:{name}" maps {len(spec.states)} states to '
            f"{len(spec.measurements)} measurements, but the dataset declares {n} state and {m} "
            "measurement channels"
        )
    _known_channels(r, ds)
    o = r.measurement_only
    if o["nominal"] is not None:
        try:
            g = nominal_model(o["nominal"])
        except (InputError, TypeError, ValueError) as e:
            raise RecipeError(f"[measurement_only] nominal: {e}") from None
        u = torch.zeros(1, nu, dtype=torch.float64) if nu else None
        try:
            out = g(torch.zeros(1, n, dtype=torch.float64), u)
        except Exception as e:
            raise RecipeError(
                f"[measurement_only] nominal {o['nominal']!r} does not map the dataset's {n} "
                f"states ({type(e).__name__}: {e})"
            ) from None
        if tuple(out.shape) != (1, n):
            raise RecipeError(
                f"[measurement_only] nominal {o['nominal']!r} maps {n} states to shape "
                f"{tuple(out.shape)[1:]}, expected ({n},)"
            )
    pn = o["process_noise"]
    if isinstance(pn, list) and len(pn) not in (1, n):
        raise RecipeError(
            f"[measurement_only] process_noise: {len(pn)} values for {n} states {ds.manifest.names('state')}"
        )


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
    states = ds.manifest.names("state")
    inputs = ds.manifest.names("input")
    log(
        f"run {r.name}: dataset {ds.manifest.name} ({len(train)} train / {len(val)} validation recordings, "
        f"fingerprint {dlog['fingerprint']['dataset_sha256'][:12]})"
    )

    ckpt_path = out / "checkpoint.pt"
    ckpt = _load_checkpoint(ckpt_path) if resume and ckpt_path.is_file() else None
    metrics_path = out / "metrics.jsonl"
    _trim_metrics(metrics_path, ckpt if resume else None, fresh=not resume)

    m0, P0, how = prior
    entries: dict[str, dict[str, Any]] = {}
    for stage in STAGES:
        opts = dict(getattr(r, stage))
        done = out / f"{stage}.pt"
        if stage == "transition" and r.states == "none":
            if resume and done.is_file():
                entries[stage] = _load_stage(done)
                log(f"{stage}: already trained (resumed)")
                continue
            h0 = build_side(
                {"kind": "system", "system": str(r.measurement["model"]).split(":", 1)[1]},
                "measurement",
            )
            entries[stage] = _fit_measurement_only_stage(
                r, ds, h0, train, m0, P0, dtype, out, resume, progress, stream, log, fitters
            )
            _save(done, entries[stage])
            _remove(out / MEASUREMENT_ONLY_CHECKPOINT)
            continue
        if "model" in opts:
            entries[stage] = {"kind": "system", "system": str(opts["model"]).split(":", 1)[1]}
            log(f"{stage}: built-in model {opts['model']}")
            continue
        if resume and done.is_file():
            entries[stage] = _load_stage(done)
            log(f"{stage}: already trained (resumed)")
            continue
        entries[stage] = _fit_stage(
            r, stage, opts, train, states, inputs, dtype, out, ckpt, progress, stream, log
        )
        _save(done, entries[stage])

    f = build_side(entries["transition"], "transition")
    h = build_side(entries["measurement"], "measurement")
    calibration = _calibrate_stage(
        r,
        entries,
        StateSpaceModel(f, h),
        train,
        val,
        m0,
        P0,
        dtype,
        out,
        resume,
        progress,
        stream,
        log,
        fitters,
    )
    uncal = StateSpaceModel(f, h)
    if calibration is not None and calibration.get("models"):
        # GPs refitted by the calibration: the bundle and the validation take them
        for stage, state in calibration.pop("models").items():
            entries[stage] = {**entries[stage], "state": state}
        f = build_side(entries["transition"], "transition")
        h = build_side(entries["measurement"], "measurement")
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


def _load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by this module (plain data only), with a clear error if unusable."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise RunError(
            f"{path}: unreadable checkpoint ({type(e).__name__}); delete it to restart the stage "
            "it belongs to"
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("stage") not in STAGES or "fit" not in ckpt:
        raise RunError(
            f"{path}: not a torchfilt training checkpoint; delete it to restart the stage"
        )
    return ckpt


def _load_stage(path: Path) -> dict[str, Any]:
    """A finished stage's entry (plain data only), with a clear error if unusable."""
    try:
        entry = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise RunError(
            f"{path}: unreadable stage file ({type(e).__name__}); delete it to retrain the stage"
        ) from None
    if not isinstance(entry, dict) or "kind" not in entry:
        raise RunError(f"{path}: not a torchfilt stage file; delete it to retrain the stage")
    return entry


def _save(path: Path, obj: dict[str, Any]) -> None:
    """``torch.save`` into memory, then one atomic write (temporary file + rename)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def _fmt(v: list[float]) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


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
    # a states = "none" transition fit keeps its own checkpoint (fit_measurement_only's)
    mo_ckpt = path.parent / MEASUREMENT_ONLY_CHECKPOINT
    mo_open = mo_ckpt.exists() and not (path.parent / "transition.pt").is_file()
    mo_it = _checkpoint_iteration(mo_ckpt) if mo_open else 0
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    for i, line in enumerate(lines):
        try:
            rec = json.loads(line)
            if not isinstance(rec, dict) or not {"stage", "iteration"} <= rec.keys():
                raise TypeError
        except (json.JSONDecodeError, KeyError, TypeError):
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
        if mo_open and rec.get("stage") == "transition":
            if rec["iteration"] <= mo_it:
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
    iterations = int(opts.get("iterations", 200))
    bar = ProgressBar(f"train {stage}", iterations, stream, enabled=progress)
    try:
        metrics = open(out / "metrics.jsonl", "a", encoding="utf-8")
    except OSError as e:
        raise output_error(out / "metrics.jsonl", e) from None
    every = r.checkpoint_every
    ckpt_path = out / "checkpoint.pt"

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
        if state.iteration % every == 0 or state.iteration == state.iterations:
            _save(ckpt_path, {"stage": stage, "fit": state.checkpoint()})
            log(
                f"{stage}: iteration {state.iteration}/{state.iterations} loss {state.loss:.6g} (checkpoint)"
            )

    resume_from = ckpt["fit"] if ckpt is not None and ckpt.get("stage") == stage else None
    if resume_from is not None:
        log(f"{stage}: resuming from iteration {resume_from['iteration']}")
    fit_opts = {
        **opts,
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
) -> StateSpaceModel:
    """The initial model of a ``states = "none"`` fit: an :class:`InducingTransition` on the
    nominal model (or a random walk), its inducing inputs spread over the filtered states of a
    pilot CKF with that model on the training recordings, its lengthscales their spread; a
    learnable process noise ``Q`` (``process_noise``, default 1e-2 x the prior variances)."""
    o = r.measurement_only
    g = None if o["nominal"] is None else nominal_model(o["nominal"])
    pn = o["process_noise"]
    if pn is None:
        q0 = 1e-2 * P0.diagonal().to(dtype)
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


def _fit_measurement_only_stage(
    r: Recipe,
    ds: Dataset,
    h: Any,
    train: list[Recording],
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
    model = _measurement_only_model(r, h, train, n, nu, m0, P0, dtype)
    ys = [rec.measurements[1:].to(dtype) for rec in train]
    us = [rec.inputs[:-1].to(dtype) for rec in train] if nu else None  # type: ignore[index]
    counted = max(1, sum(int(torch.isfinite(y).sum()) for y in ys))
    iterations = int(o["iterations"])
    ckpt = out / MEASUREMENT_ONLY_CHECKPOINT
    if resume and ckpt.exists():
        log(f"transition: resuming from iteration {_checkpoint_iteration(ckpt)}")
    log(
        f"transition: learning from measurements alone ({o['method']}, {model.transition.base.num_inducing} "  # type: ignore[union-attr]
        f"inducing points, known channels {[ds.manifest.names('measurement')[i] for i in known]})"
    )
    bar = ProgressBar("train transition", iterations, stream, enabled=progress)
    every = r.checkpoint_every
    try:
        metrics = open(out / "metrics.jsonl", "a", encoding="utf-8")
    except OSError as e:
        raise output_error(out / "metrics.jsonl", e) from None

    def callback(state: Any) -> None:
        ll = float(state.log_likelihood)
        loss = float(getattr(state, "loss", -ll / counted))
        metrics.write(
            json.dumps(
                {
                    "stage": "transition",
                    "iteration": state.iteration,
                    "loss": loss,
                    "log_likelihood": ll,
                    "elapsed": state.elapsed,
                }
            )
            + "\n"
        )
        metrics.flush()
        bar.update(state.iteration, f"loss {loss:.4g}")
        if state.iteration % every == 0 or state.iteration == state.iterations:
            log(
                f"transition: iteration {state.iteration}/{state.iterations} loss {loss:.6g} (checkpoint)"
            )

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
            method=o["method"],
            iterations=iterations,
            window=o["window"],
            burn_in=int(o["burn_in"]),
            optimizer=o["optimizer"],
            lr=o["lr"],
            learn_measurement_noise=learn_R,
            m_step_iterations=int(o["m_step_iterations"]),
            callback=callback,
            progress=False,
            dtype=dtype,
            checkpoint=ckpt,
            checkpoint_every=every,
            resume=resume,
        )
    finally:
        metrics.close()
    names = ds.manifest.names("measurement")
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
    log(
        f"transition: {fit.stopped} after {fit.iterations} iterations; log-likelihood "
        f"{info['initial_log_likelihood']:.6g} -> {fit.log_likelihood:.6g}"
    )
    return {
        "kind": "inducing",
        "nominal": o["nominal"],
        "state": inducing_state(fit.model.transition),
        "fit": info,
    }


def _checkpoint_iteration(path: Path) -> int:
    """The iteration a stage checkpoint resumes from: that of its file, or the lowest of the files
    in its folder (a data-parallel fit's processes agree on the latest iteration all of them
    saved); 0 where unreadable."""
    if path.is_dir():
        its = [_checkpoint_iteration(p) for p in sorted(path.glob("*.ckpt"))]
        return min(its, default=0)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        return int(ck["iteration"])
    except Exception:
        return 0


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
    iterations = int(c["iterations"])
    # short recordings: the burn-in may take at most half of the shortest one
    shortest = min(len(rec) - 1 for rec in train)
    burn_in = min(int(c["burn_in"]), shortest // 2)
    if burn_in < int(c["burn_in"]):
        log(
            f"calibrate: burn_in {c['burn_in']} -> {burn_in} (shortest recording: {shortest} steps)"
        )
    bar = ProgressBar("calibrate", iterations, stream, enabled=progress)
    every = r.checkpoint_every
    with open(out / "metrics.jsonl", "a", encoding="utf-8") as metrics:

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
            window=int(c["window"]),
            burn_in=burn_in,
            iterations=iterations,
            lr=float(c["lr"]),
            optimizer=c["optimizer"],
            patience=int(c["patience"]),
            inflate_only=bool(c["inflate_only"]),
            gp=c.get("gp", "none"),
            callback=callback,
            checkpoint=ckpt,
            resume=resume,
            checkpoint_every=every,
            dtype=dtype,
        )
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
    _save(done, entry)
    _remove(ckpt)
    log(
        f"calibrate: {fit.stopped} after {fit.iterations} iterations; log-likelihood "
        f"{fit.initial_log_likelihood:.6g} -> {fit.log_likelihood:.6g}; "
        + "; ".join(
            f"{k} scale {_fmt(v['scale'])} floor {_fmt(v['floor'])}"
            for k, v in res.parameters.items()
        )
    )
    return entry
