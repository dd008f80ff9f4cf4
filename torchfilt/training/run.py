"""Running a recipe: train the models, log everything, checkpoint, validate, write the bundle.

A run directory holds:

- ``config.json``: the resolved recipe, its digest, library versions;
- ``dataset.json``: the dataset log (per-file SHA-256, row counts, channel statistics, the split);
- ``metrics.jsonl``: one line per iteration (stage, iteration, loss, hyperparameters, time);
- ``checkpoint.pt``: the latest checkpoint (written atomically every ``checkpoint_every``
  iterations), and ``{transition,measurement}.pt`` once a stage is done;
- ``train.log``: plain progress lines;
- ``validation.json``: one-step RMSE, NLPD and 95% coverage on the validation recordings;
- ``model.pt``: the final model bundle.

A run killed at any moment resumes from its last checkpoint with ``resume=True`` (``torchfilt train
... --resume``) and reaches the same model as an uninterrupted run with the same seed.
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import sys
from pathlib import Path
from typing import Any, TextIO

import torch
from torch import Tensor

from torchfilt._version import __version__
from torchfilt.exceptions import RunError
from torchfilt.io import Dataset, atomic_write, atomic_write_text, load_dataset
from torchfilt.io.recording import Recording
from torchfilt.systems import get_system
from torchfilt.training.bundle import BUNDLE_SCHEMA, build_side, nominal_model, save_bundle
from torchfilt.training.progress import ProgressBar
from torchfilt.training.recipe import Recipe, load_recipe
from torchfilt.training.validation import one_step_metrics

__all__ = ["RunError", "train_recipe"]

STAGES = ("transition", "measurement")


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _tensor_list(v: Tensor) -> Any:
    v = v.detach().cpu()
    return v.item() if v.numel() == 1 else v.tolist()


class _Log:
    """Plain lines to ``train.log`` (always) and to the console when progress is off."""

    def __init__(self, path: Path, echo: TextIO | None) -> None:
        self.fh = open(path, "a", encoding="utf-8")
        self.echo = echo

    def __call__(self, msg: str) -> None:
        line = f"{_now()} {msg}\n"
        self.fh.write(line)
        self.fh.flush()
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
                raise ValueError(
                    f"[{where}] inputs: index {v} out of range for features {features}"
                )
            return v
        if v not in features:
            raise ValueError(f"[{where}] inputs: unknown channel {v!r}; features are {features}")
        return features.index(v)

    if names and isinstance(names[0], list):
        return [[one(v) for v in per] for per in names]
    return [one(v) for v in names]


def _prior(recipe: Recipe, train: list[Recording], n: int) -> tuple[Tensor, Tensor, str]:
    """The bundle's default filter prior: from the data's initial states, a system, or explicit."""
    f = recipe.filter
    if "mean" in f or "cov_diag" in f:
        if "mean" not in f or "cov_diag" not in f:
            raise ValueError("[filter] give both mean and cov_diag")
        m = torch.tensor(f["mean"], dtype=torch.float64)
        c = torch.diag(torch.tensor(f["cov_diag"], dtype=torch.float64))
        if m.shape != (n,) or c.shape != (n, n):
            raise ValueError(f"[filter] mean and cov_diag must have {n} entries")
        return m, c, "recipe"
    prior = str(f.get("prior", "data"))
    if prior.startswith("system:"):
        s = get_system(prior.split(":", 1)[1])
        return s.prior_mean(), s.prior_cov(), prior
    if prior != "data":
        raise ValueError(
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
    progress: bool = True,
    stream: TextIO | None = None,
) -> Path:
    """Train the models a recipe describes and write a run directory (see the module docstring).

    Args:
        recipe: a recipe file (``trainers/*.toml``) or a :class:`Recipe`.
        out: run directory.
        resume: continue the run in ``out`` from its last checkpoint.
        progress: show a progress bar (on a terminal; plain lines otherwise).
        stream: where progress goes (default ``sys.stderr``).

    Returns:
        Path of the model bundle ``out/model.pt``.

    Raises:
        RunError: ``out`` already holds a run (without ``resume``), or has none to resume, or the
            recipe or dataset changed since the run started.
        RecipeError, DataError: invalid recipe or dataset.
    """
    r = recipe if isinstance(recipe, Recipe) else load_recipe(recipe)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stream = stream if stream is not None else sys.stderr
    cfg_path = out / "config.json"
    if resume:
        if not cfg_path.is_file():
            raise RunError(f"{out}: no run to resume (config.json missing)")
        old = json.loads(cfg_path.read_text())
        if old.get("digest") != r.digest():
            raise RunError(f"{out}: the recipe changed since this run started; start a new run")
    else:
        if any((out / f).exists() for f in ("config.json", "checkpoint.pt", "model.pt")):
            raise RunError(
                f"{out}: already holds a run; pass --resume to continue it, or choose another --out"
            )
        config = {
            "recipe": r.resolved(),
            "digest": r.digest(),
            "recipe_file": None if r.path is None else str(r.path),
            "created": _now(),
            "versions": {
                "torchfilt": __version__,
                "torch": str(torch.__version__),
                "python": platform.python_version(),
            },
        }
        atomic_write_text(cfg_path, json.dumps(config, indent=2) + "\n")
    log = _Log(out / "train.log", None if progress else stream)
    try:
        return _run(r, out, resume, progress, stream, log)
    finally:
        log.close()


def _run(r: Recipe, out: Path, resume: bool, progress: bool, stream: TextIO, log: _Log) -> Path:
    """Run the recipe with its thread count, restoring the caller's afterwards."""
    threads = torch.get_num_threads()
    if r.threads is not None:
        torch.set_num_threads(r.threads)
    try:
        return _run_recipe(r, out, resume, progress, stream, log)
    finally:
        torch.set_num_threads(threads)


def _run_recipe(
    r: Recipe, out: Path, resume: bool, progress: bool, stream: TextIO, log: _Log
) -> Path:
    dtype = torch.float64 if r.dtype == "float64" else torch.float32
    ds: Dataset = load_dataset(r.dataset)
    dlog = ds.log()
    ds_path = out / "dataset.json"
    if resume and ds_path.is_file():
        old = json.loads(ds_path.read_text())
        if old["fingerprint"]["dataset_sha256"] != dlog["fingerprint"]["dataset_sha256"]:
            raise RunError(
                f"{out}: the dataset changed since this run started (fingerprint differs)"
            )
    atomic_write_text(ds_path, json.dumps(dlog, indent=2, default=float) + "\n")
    train, val = ds.split("train"), ds.split("validation")
    if not train:
        raise ValueError(f"{ds.manifest_path}: the dataset has no training recordings")
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

    entries: dict[str, dict[str, Any]] = {}
    for stage in STAGES:
        opts = dict(getattr(r, stage))
        done = out / f"{stage}.pt"
        if "model" in opts:
            entries[stage] = {"kind": "system", "system": str(opts["model"]).split(":", 1)[1]}
            log(f"{stage}: built-in model {opts['model']}")
            continue
        if resume and done.is_file():
            entries[stage] = torch.load(done, weights_only=True)
            log(f"{stage}: already trained (resumed)")
            continue
        entries[stage] = _fit_stage(
            r, stage, opts, train, states, inputs, dtype, out, ckpt, progress, stream, log
        )
        _save(done, entries[stage])

    f = build_side(entries["transition"], "transition")
    h = build_side(entries["measurement"], "measurement")
    validation = one_step_metrics(f, h, val) if val else {}
    atomic_write_text(
        out / "validation.json", json.dumps(validation, indent=2, default=float) + "\n"
    )
    if validation:
        log(
            f"validation one-step RMSE: transition {_fmt(validation['transition']['rmse'])}, "
            f"measurement {_fmt(validation['measurement']['rmse'])}; 95% coverage: transition "
            f"{_fmt(validation['transition']['coverage95'])}, measurement {_fmt(validation['measurement']['coverage95'])}"
        )
    m0, P0, how = _prior(r, train, len(states))
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
        "time_unit": ds.manifest.time_unit,
        "prior": {"mean": m0, "cov": P0, "source": how},
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


def _save(path: Path, obj: dict[str, Any]) -> None:
    """``torch.save`` atomically (temporary file + rename)."""

    def write(fh: Any) -> None:
        torch.save(obj, fh)

    atomic_write(path, write)


def _fmt(v: list[float]) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def _trim_metrics(path: Path, ckpt: dict[str, Any] | None, fresh: bool) -> None:
    """Drop metric lines logged after the checkpoint a run resumes from (they will be redone)."""
    if fresh or not path.is_file():
        if fresh and path.exists():
            path.unlink()
        return
    keep = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
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
    metrics = open(out / "metrics.jsonl", "a", encoding="utf-8")
    every = r.checkpoint_every
    ckpt_path = out / "checkpoint.pt"

    def callback(state: Any) -> None:
        hyper = {k: _tensor_list(v) for k, v in state.hyperparameters().items()}
        metrics.write(
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
