"""Filtering many recordings, and training several models, as parallel tasks on Ray.

Ray is an optional dependency (``pip install 'torchfilt[distributed]'``); it is imported only when
one of these functions runs, never by ``import torchfilt``.

**Filtering.** :func:`filter_recordings_ray` shards the recordings into batches with the plan of
:func:`~torchfilt.pipeline.offline.shard_plan` (recordings of equal length, at most
``batch_size`` per batch) and filters each batch as one Ray task on its worker's device (the GPU
where the task was given one, else the CPU). Each task writes its recordings' files straight into
the output folder, each file atomically (:mod:`torchfilt.io.atomic`), then one *completion marker*
per recording, ``.torchfilt/done/{name}.json``, holding the recording's summary entry (renamed
into place like every output, but not flushed to disk first: a marker lost or emptied by a system
crash only makes its recording be filtered again, while the estimates it vouches for were flushed
before it was written).

A recording is **complete** when its marker exists and so do the files the marker lists. The
marker is written last, after the recording's estimates (themselves written smoothed, plot, then
filtered), so a worker killed at any moment leaves each recording either complete or not: a file
of an incomplete recording is whole (atomic rename) and is rewritten, with the same bytes, by the
next attempt. A complete recording is never written again: a retried task and a re-run check the
markers first. The job's options and recordings are kept in ``.torchfilt/job.json``; running the
same job again into the same folder (the same recordings, in any order, and the same options)
does only the incomplete recordings, and a different job there is an error unless ``force``.
When every recording is complete, ``filter_summary.json`` is written as the local path writes it.

Because a batch's estimates can differ in their last bits with the batch's shape (batched
linear algebra), both the local path (:func:`~torchfilt.pipeline.offline.filter_recordings` with
the same ``batch_size``) and this one follow the same plan over the whole job, and a re-run
filters a batch with incomplete members whole (writing only those members): the files are
byte-identical to a local run's on the same kind of device.

The output folder and the recordings must be visible under the same paths on every worker (one
machine, or a shared filesystem).

**Training.** :func:`train_recipes_ray` trains several recipes, or one recipe over several
datasets, as parallel Ray tasks, each :func:`~torchfilt.training.train_recipe` with its own run
directory (and so its own checkpoints and ``--resume``).

**Data-parallel fits.** :func:`calibrate_ray` and :func:`fit_measurement_only_ray` (likelihood or
EM) deal the recordings to Ray actors in one ``torch.distributed`` ``gloo`` group that sums what
the fit needs at every step, so the result is that of one process on all recordings. A lost
actor (killed, or past ``timeout`` at a collective) stops the group with a
:class:`~torchfilt.exceptions.WorkerError` naming its rank; ``resume=True`` continues from the
actors' checkpoints. With ``callback_on="driver"`` the per-iteration callback runs in the calling
process (rank 0's state, rank 0 waiting for it), so it need not pickle and may write local files.

**One recipe, data-parallel.** :func:`train_recipe_data_parallel` (``torchfilt train RECIPE
--ray --data-parallel N``) is :func:`~torchfilt.training.train_recipe` whose calibration stage and
``states = "none"`` transition stage are these data-parallel fits on ``N`` actors (the other
stages run in this process): the same run directory, dataset log and bundle as a local run (the
calibrated and learned parameters equal up to the order of the sums), each stage's checkpoint a
folder of per-actor files, ``resume`` as for a local run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
import socket
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from functools import partial
from pathlib import Path
from typing import Any, Literal, TextIO

import torch

from torchfilt.exceptions import (
    InputError,
    MissingDependencyError,
    OutputError,
    RunError,
    TorchfiltError,
    WorkerError,
)
from torchfilt.filters import CKF
from torchfilt.io import DataError, atomic_write_text, read_recording, sha256_file
from torchfilt.io.atomic import check_new_outputs, output_dir
from torchfilt.pipeline.offline import (
    INDEX_NAME,
    ModelSpec,
    check_device,
    check_recording_files,
    filter_batch,
    output_names,
    recording_outputs,
    resolve_model,
    shard_plan,
)
from torchfilt.settings import RAY_BATCH_SIZE
from torchfilt.training.recipe import Recipe, load_recipe
from torchfilt.training.run import StageFitters

__all__ = [
    "DONE_DIR",
    "INSTALL_HINT",
    "JOB_FILE",
    "calibrate_ray",
    "filter_recordings_ray",
    "fit_measurement_only_ray",
    "import_ray",
    "ray_session",
    "train_recipe_data_parallel",
    "train_recipes_ray",
]

#: How to install the optional dependency.
INSTALL_HINT = "pip install 'torchfilt[distributed]'"
#: The job description in an output folder of :func:`filter_recordings_ray`.
JOB_FILE = ".torchfilt/job.json"
#: Completion markers, one per recording: ``{DONE_DIR}/{name}.json``.
DONE_DIR = ".torchfilt/done"
_JOB_SCHEMA = "torchfilt-ray-filter/1"


def import_ray() -> Any:
    """The ``ray`` module.

    Raises:
        MissingDependencyError: Ray is not installed (the message says how to install it).
    """
    try:
        import ray
    except ImportError:
        raise MissingDependencyError(
            f"--ray: Ray is not installed; install it with {INSTALL_HINT}"
        ) from None
    return ray


@contextlib.contextmanager
def ray_session(address: str | None = None, *, workers: int | None = None) -> Iterator[Any]:
    """Use Ray inside this block: the session already open in this process if there is one, else
    a new local instance (``address`` ``None`` or ``"local"``, with ``workers`` CPUs: default all)
    or the cluster at ``address`` (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``). A session
    this block opened is shut down at its end.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` is not a positive integer, ``workers`` with a cluster address, or
            the cluster at ``address`` cannot be reached.
    """
    ray = import_ray()
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)):
        raise InputError(f"--workers must be a positive integer, got {workers!r}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be a positive integer, got {workers}")
    if ray.is_initialized():
        yield ray
        return
    local = address in (None, "local")
    if not local and workers is not None:
        raise InputError(
            "--workers sets the CPUs of a local Ray instance; a cluster at --ray ADDRESS has its own"
        )
    if not local:
        _check_reachable(str(address))
    try:
        if local:
            ray.init(
                address="local",
                num_cpus=workers,
                include_dashboard=False,
                logging_level="warning",
                log_to_driver=False,
            )
        else:
            ray.init(address=address, logging_level="warning", log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as e:
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({e})") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str) -> None:
    """A ``host:port`` address must accept a connection within a few seconds (Ray itself keeps
    retrying an unreachable one for minutes)."""
    m = re.fullmatch(r"([\w.\-]+):(\d+)", address)
    if m is None:
        return  # "auto", "ray://...": Ray reports these quickly itself
    try:
        with socket.create_connection((m.group(1), int(m.group(2))), timeout=5.0):
            pass
    except OSError as e:
        raise InputError(
            f"--ray {address}: no Ray cluster answers there ({e.strerror or e}); start one with "
            "`ray start --head` or check the address"
        ) from None


# ------------------------------------------------------------------------------------- filtering


def _marker(out: Path, name: str) -> Path:
    return out / DONE_DIR / f"{name}.json"


def _complete_entry(out: Path, name: str) -> dict[str, Any] | None:
    """The summary entry of a complete recording (marker and listed files present), else None."""
    try:
        entry = json.loads(_marker(out, name).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(entry, dict):
        return None
    files = [entry.get(k) for k in ("filtered", "smoothed", "plot") if k in entry]
    if not files or not all(isinstance(f, str) and (out / f).is_file() for f in files):
        return None
    return entry


def _worker_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return check_device(device)


def _filter_shard(job: dict[str, Any], spec: ModelSpec, shard: list[int]) -> dict[str, Any]:
    """One Ray task: filter the batch ``shard`` (indices into the job's recordings) and write the
    outputs and markers of its incomplete recordings."""
    t0 = time.perf_counter()
    out = Path(job["out"])
    names = [job["names"][i] for i in shard]
    todo = [_complete_entry(out, n) is None for n in names]
    if not any(todo):
        return {"written": 0, "compute_s": time.perf_counter() - t0, "device": None}
    dev = _worker_device(job["device"])
    dtype = getattr(torch, job["dtype"])
    recs = [
        read_recording(
            job["paths"][i],
            spec.channels,
            time_column=spec.time_column,
            sample_time=spec.sample_time,
            optional=("state",),
        )
        for i in shard
    ]
    filt = CKF(spec.model.to(device=dev, dtype=dtype), sqrt=job["sqrt"])
    x0, P0 = job["x0"], job["P0"]
    m0 = (spec.prior_mean if x0 is None else torch.tensor(x0, dtype=torch.float64)).to(dev, dtype)
    C0 = (spec.prior_cov if P0 is None else torch.tensor(P0, dtype=torch.float64)).to(dev, dtype)
    written = filter_batch(
        spec, filt, recs, names, m0, C0, out, smooth=job["smooth"], plot=job["plot"], write=todo
    )
    for b, entry in written:
        entry["recording"] = job["recordings"][shard[b]]  # as the user named it
        # no fsync: the estimates it vouches for are on disk already, and a marker lost or
        # emptied by a system crash only makes its recording be filtered again
        atomic_write_text(
            _marker(out, names[b]), json.dumps(entry, default=float) + "\n", fsync=False
        )
    return {"written": len(written), "compute_s": time.perf_counter() - t0, "device": str(dev)}


def _job_identity(
    spec: ModelSpec,
    model: str | Path | ModelSpec,
    paths: list[str],
    opts: dict[str, Any],
) -> dict[str, Any]:
    """What makes two jobs the same: the model, the options, and each recording's file."""
    digest = None
    if not isinstance(model, ModelSpec) and not str(model).startswith("system:"):
        digest = sha256_file(model)
    files = {}
    for p in paths:
        st = os.stat(p)
        files[p] = [st.st_size, st.st_mtime_ns]
    return {"model": spec.source, "model_sha256": digest, **opts, "files": files}


def filter_recordings_ray(
    model: str | Path | ModelSpec,
    recordings: Sequence[str | Path],
    out: str | Path,
    *,
    address: str | None = None,
    workers: int | None = None,
    batch_size: int = RAY_BATCH_SIZE,
    smooth: bool = False,
    plot: bool = False,
    device: str = "auto",
    gpus_per_task: float | None = None,
    dtype: torch.dtype = torch.float64,
    sqrt: bool = False,
    x0: torch.Tensor | None = None,
    P0: torch.Tensor | None = None,
    force: bool = False,
    max_retries: int = 3,
    progress: bool = True,
    stream: TextIO | None = None,
) -> dict[str, Any]:
    """:func:`~torchfilt.pipeline.filter_recordings` as Ray tasks, one batch per task, resumable.

    Writes the same files as the local path (with the same ``batch_size``, the same bytes), plus
    the job file and completion markers under ``out/.torchfilt/`` (see the module docstring).
    Recordings already complete in ``out`` from an earlier run of the same job are not filtered
    again.

    Args:
        model: ``system:NAME``, a model bundle path, or a :class:`ModelSpec` (sent to the workers).
        recordings: recording files (CSV or NPZ), on a filesystem the workers see.
        out: output folder (idem).
        address: Ray cluster to join (``"auto"``, ``"host:6379"``, ``"ray://host:10001"``); ``None``
            or ``"local"`` starts a local instance. An instance already open in this process is
            used as it is.
        workers: CPUs of a new local instance (default: all).
        batch_size: most recordings per task (:func:`~torchfilt.pipeline.offline.shard_plan`).
        smooth: also run the RTS smoother.
        plot: write a report figure per recording.
        device: ``"auto"`` (each task: CUDA if it was given a GPU, else CPU), or a torch device
            every worker has.
        gpus_per_task: GPUs Ray reserves per task (default: 1 if the cluster has GPUs, else 0).
        dtype: floating dtype.
        sqrt: use the square-root filter.
        x0: prior mean override ``(n,)``.
        P0: prior covariance override ``(n, n)``.
        force: discard an earlier job in ``out`` and overwrite its files (and any others).
        max_retries: times Ray reruns a task whose worker died.
        progress: show the number of recordings done.
        stream: where progress goes (default ``sys.stderr``).

    Returns:
        The summary (as written to ``filter_summary.json``), plus ``"distributed"``: recordings
        filtered by this call (``filtered``), recordings found complete (``complete_before``),
        tasks run and failed, the seconds spent checking the recordings before the first task
        (``prepare_s``) and in all (``total_s``), and per task the seconds spent in the task
        (``compute_s``) and from submission to result (``wall_s``).

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: no recordings, a recording given twice, a bad option, an unreachable cluster.
        DataError: a recording is missing or invalid.
        OutputError: ``out`` holds outputs of another job or run (without ``force``), or cannot
            be written.
        RunError: some tasks failed; the recordings finished are kept, and running the same call
            again does the rest.
    """
    import_ray()  # fail fast, before any file is read
    t_start = time.perf_counter()
    if device != "auto":
        check_device(device)
    shard_plan([], batch_size)
    if isinstance(max_retries, bool) or not isinstance(max_retries, int) or max_retries < 0:
        raise InputError(f"max_retries must be a non-negative integer, got {max_retries!r}")
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    check_recording_files(recordings)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: the output folder is a file; choose a folder")
    stream = stream if stream is not None else sys.stderr
    given = [str(Path(p)) for p in recordings]
    names_given = output_names(recordings)
    paths_given = [os.path.abspath(p) for p in recordings]
    spec = resolve_model(model)
    opts = {
        "smooth": bool(smooth),
        "plot": bool(plot),
        "dtype": str(dtype).removeprefix("torch."),
        "sqrt": bool(sqrt),
        "batch_size": batch_size,
        "device": device,
        "x0": None if x0 is None else torch.as_tensor(x0, dtype=torch.float64).tolist(),
        "P0": None if P0 is None else torch.as_tensor(P0, dtype=torch.float64).tolist(),
    }
    identity = _job_identity(spec, model, sorted(paths_given), opts)
    job_path = out / JOB_FILE
    old = _read_job(job_path)
    if old is not None and not force and old.get("identity") != identity:
        raise OutputError(
            f"{out}: holds the outputs of another filter job (other recordings, model or "
            "options); pass --force (force=True) to replace them, or choose another --out"
        )
    if old is not None and not force:
        # resuming: the first run's order fixes the plan and the summary's order
        order = {p: i for i, p in enumerate(paths_given)}
        perm = [order[p] for p in old["paths"]]
        lengths = list(old["lengths"])
    else:
        perm = list(range(len(paths_given)))
        planned = [out / INDEX_NAME]
        for nm in names_given:
            planned.extend(out / f for f in recording_outputs(nm, smooth=smooth, plot=plot))
        check_new_outputs(planned, force=force)
        lengths = []
        first_row_seen = False
        for p in recordings:  # validate every recording before anything is written
            rec = read_recording(
                p,
                spec.channels,
                time_column=spec.time_column,
                sample_time=spec.sample_time,
                optional=("state",),
            )
            if len(rec) < 2:
                raise DataError("needs at least 2 rows (the first row is the prior's time)", path=p)
            lengths.append(len(rec))
            first_row_seen = first_row_seen or bool(rec.measurements[0].isfinite().any())
        if first_row_seen:
            warnings.warn(
                "the first row of a recording is the prior's time; its measurements are not used",
                stacklevel=2,
            )
    job: dict[str, Any] = {
        "out": os.path.abspath(out),
        "recordings": [given[i] for i in perm],
        "names": [names_given[i] for i in perm],
        "paths": [paths_given[i] for i in perm],
        **{k: opts[k] for k in ("smooth", "plot", "dtype", "sqrt", "device", "x0", "P0")},
    }
    plan = shard_plan(lengths, batch_size)
    total = len(job["names"])
    fresh = old is None or force  # a new job: its markers (if any, of a forced one) go

    def incomplete(i: int) -> bool:
        return fresh or _complete_entry(out, job["names"][i]) is None

    pending = [sh for sh in plan if any(incomplete(i) for i in sh)]
    found = total - sum(incomplete(i) for sh in pending for i in sh)
    stats: dict[str, Any] = {"filtered": 0, "complete_before": found, "tasks": len(pending)}
    stats["prepare_s"] = time.perf_counter() - t_start
    failures: list[str] = []
    task_times: list[dict[str, float]] = []
    with contextlib.ExitStack() as stack:
        # Ray first: an unreachable cluster is reported before anything is written
        ray = stack.enter_context(ray_session(address, workers=workers)) if pending else None
        output_dir(out)
        if fresh:
            if (out / ".torchfilt").is_dir():
                shutil.rmtree(out / ".torchfilt")
            atomic_write_text(
                job_path,
                json.dumps(
                    {
                        "schema": _JOB_SCHEMA,
                        "identity": identity,
                        "paths": job["paths"],
                        "lengths": lengths,
                    },
                    indent=1,
                )
                + "\n",
            )
        if ray is not None:
            gpus = gpus_per_task
            if gpus is None:
                gpus = 1.0 if device != "cpu" and ray.cluster_resources().get("GPU", 0) > 0 else 0.0
            remote = ray.remote(_filter_shard).options(
                num_cpus=1, num_gpus=gpus, max_retries=max_retries
            )
            job_ref, spec_ref = ray.put(job), ray.put(spec)
            started: dict[Any, tuple[float, int]] = {}
            for s in pending:
                started[remote.remote(job_ref, spec_ref, s)] = (time.perf_counter(), len(s))
            done_count = found
            left = list(started)
            show = _Progress(progress, stream, total)
            show(done_count)
            while left:
                ready, left = ray.wait(left, num_returns=1)
                ref = ready[0]
                t_sub, size = started[ref]
                try:
                    res = ray.get(ref)
                except Exception as e:  # a task error or a worker lost for good
                    failures.append(_one_line(e))
                    continue
                stats["filtered"] += res["written"]
                task_times.append(
                    {
                        "size": size,
                        "compute_s": res["compute_s"],
                        "wall_s": time.perf_counter() - t_sub,
                    }
                )
                done_count += size
                show(done_count)
    stats["task_times"] = task_times
    stats["failed_tasks"] = len(failures)
    if failures and any(_complete_entry(out, nm) is None for nm in job["names"]):
        raise RunError(
            f"{len(failures)} of {len(pending)} filter tasks failed (first: {failures[0]}); the "
            "recordings finished are kept in "
            f"{out}: run the same command again to do the rest"
        )
    entries = []
    for name in job["names"]:
        entry = _complete_entry(out, name)
        if entry is None:  # pragma: no cover - every task returned without error
            raise RunError(f"{out}: {name} has no complete output after the job; run it again")
        entries.append(entry)
    summary: dict[str, Any] = {"model": spec.source, "smooth": smooth, "recordings": entries}
    atomic_write_text(out / INDEX_NAME, json.dumps(summary, indent=2, default=float) + "\n")
    stats["total_s"] = time.perf_counter() - t_start
    return {**summary, "distributed": stats}


def _read_job(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        job = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise OutputError(
            f"{path}: unreadable job file; pass --force (force=True) to start the job afresh"
        ) from None
    if not isinstance(job, dict) or job.get("schema") != _JOB_SCHEMA:
        raise OutputError(
            f"{path}: not a torchfilt filter job file; pass --force (force=True) to start afresh"
        )
    return job


class _Progress:
    """``filter: k/N recordings done`` lines: at the start, at every further percent, at the end."""

    def __init__(self, enabled: bool, stream: TextIO, total: int) -> None:
        self.enabled, self.stream, self.total = enabled, stream, total
        self.last = -1

    def __call__(self, done: int) -> None:
        pct = 100 * done // max(self.total, 1)
        if not self.enabled or (pct == self.last and done < self.total):
            return
        self.last = pct
        self.stream.write(f"filter: {done}/{self.total} recordings done\n")
        self.stream.flush()


def _one_line(e: BaseException) -> str:
    """A task's failure in one line: a TorchfiltError raised in the task by its own message
    (Ray wraps it, with the worker's traceback), anything else by its type and message."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, TorchfiltError):
        return " ".join(str(cause).split())
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:300]}"


# -------------------------------------------------------------------------------------- training


def _train_one(recipe: Recipe, out: str, resume: bool, force: bool) -> dict[str, Any]:
    from torchfilt.training import train_recipe

    t0 = time.perf_counter()
    bundle = train_recipe(recipe, out, resume=resume, force=force, progress=False)
    return {"bundle": str(bundle), "seconds": time.perf_counter() - t0}


def train_recipes_ray(
    recipes: Sequence[str | Path | Recipe],
    out: str | Path,
    *,
    datasets: Sequence[str | Path] | None = None,
    address: str | None = None,
    workers: int | None = None,
    resume: bool = False,
    force: bool = False,
    max_retries: int = 0,
    stream: TextIO | None = None,
) -> dict[str, Path]:
    """Train several models as parallel Ray tasks, one run directory each under ``out``.

    Either several recipes (run directory ``out/{recipe name}``), or one recipe over several
    ``datasets`` (one model per unit: ``out/{dataset folder name}``, the recipe with its
    ``[dataset] path`` replaced). Each task is :func:`~torchfilt.training.train_recipe`, so each
    run has its own checkpoints; ``resume`` continues every run from its checkpoint (a run
    already finished is not retrained).

    Args:
        recipes: recipe files or :class:`Recipe` objects.
        out: parent folder of the run directories.
        datasets: with one recipe, the datasets to train it on.
        address: Ray cluster (see :func:`ray_session`).
        workers: CPUs of a new local instance.
        resume: continue the runs in the run directories.
        force: discard runs already in the run directories.
        max_retries: times Ray reruns a task whose worker died (a rerun resumes from the
            checkpoint).
        stream: where progress lines go (default ``sys.stderr``).

    Returns:
        The model bundle of each unit, by run name.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: no recipes, ``datasets`` with several recipes, a dataset that does not exist,
            two units with one run name.
        RecipeError: an invalid recipe (checked here, before any task starts).
        RunError: some runs failed, including on an invalid dataset or a run directory that
            already holds a run (each task checks its own before it trains, as
            :func:`~torchfilt.training.train_recipe` does); the message gives the first failure's
            own message. The other runs are kept; ``resume`` continues them.
    """
    import_ray()
    if not recipes:
        raise InputError("no recipes given")
    if resume and force:
        raise InputError("--resume continues the runs and --force discards them: pick one")
    stream = stream if stream is not None else sys.stderr
    rs = [r if isinstance(r, Recipe) else load_recipe(r) for r in recipes]
    units: list[tuple[str, Recipe]] = []
    if datasets:
        if len(rs) != 1:
            raise InputError("--dataset trains one recipe over several datasets: give one recipe")
        for d in datasets:
            p = Path(d).resolve()
            if not p.exists():
                raise InputError(f"--dataset {d}: not found")
            name = (p.parent if p.is_file() else p).name
            units.append((name, dataclasses.replace(rs[0], dataset=p)))
    else:
        units = [(r.name, r) for r in rs]
    seen: dict[str, int] = {}
    for i, (name, _) in enumerate(units):
        if name in seen:
            raise InputError(
                f"two units would share the run directory {Path(out) / name} "
                f"(units {seen[name] + 1} and {i + 1}); give them distinct names"
            )
        seen[name] = i
    results: dict[str, Path] = {}
    failures: list[str] = []
    with ray_session(address, workers=workers) as ray:
        output_dir(out)  # after Ray is reached: an unreachable cluster leaves nothing behind
        remote = ray.remote(_train_one).options(num_cpus=1, max_retries=max_retries)
        refs = {
            remote.remote(r, os.path.abspath(Path(out) / name), resume, force): name
            for name, r in units
        }
        left = list(refs)
        while left:
            ready, left = ray.wait(left, num_returns=1)
            name = refs[ready[0]]
            try:
                res = ray.get(ready[0])
            except Exception as e:
                failures.append(f"{name}: {_one_line(e)}")
                stream.write(f"train {name}: failed\n")
                continue
            results[name] = Path(res["bundle"])
            stream.write(f"train {name}: done in {res['seconds']:.1f} s -> {res['bundle']}\n")
            stream.flush()
    if failures:
        raise RunError(
            f"{len(failures)} of {len(units)} training runs failed (first: {failures[0]}); "
            "the finished runs are kept: pass --resume to continue the others"
        )
    return {name: results[name] for name, _ in units}


def _shard_sequences(data: Any, rank: int, world: int) -> Any:
    """Recordings ``rank::world`` of a list of recordings or a :class:`Sequences`."""
    from torchfilt.training.likelihood import Sequences

    if isinstance(data, Sequences):

        def part(v: Any) -> Any:
            return None if v is None else v[rank::world]

        return Sequences(part(data.y), part(data.u), data.x0, data.P0)
    return list(data)[rank::world]


def _free_address() -> str:
    """``tcp://{this node}:{a free port}``: the rendezvous of a ``gloo`` process group."""
    ray = import_ray()
    with socket.socket() as s:
        s.bind(("", 0))
        port = s.getsockname()[1]
    return f"tcp://{ray.util.get_node_ip_address()}:{port}"


#: Seconds a collective of a data-parallel fit waits for the other actors by default.
GROUP_TIMEOUT = 1800.0
#: Seconds the driver waits, after a first actor failed, for the others to report theirs.
_FAILURE_GRACE = 10.0


def _fit_rank(rank: int, world: int, init: str, job: dict[str, Any]) -> dict[str, Any]:
    """One process of a data-parallel fit (``job["kind"]``): its shard, sums over ``gloo``."""
    import datetime

    import torch.distributed as dist

    from torchfilt.training.calibrate import calibrate
    from torchfilt.training.measurement_only import fit_measurement_only

    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo",
        init_method=init,
        rank=rank,
        world_size=world,
        timeout=datetime.timedelta(seconds=float(job["timeout"])),
    )
    try:
        ckpt = job["checkpoint"]
        path = None if ckpt is None else Path(ckpt) / f"rank{rank}.ckpt"
        data = _shard_sequences(job["recordings"], rank, world)
        if job["kind"] == "calibrate":
            res: Any = calibrate(
                job["model"], data, all_reduce=dist.all_reduce, checkpoint=path, **job["options"]
            )
        else:
            res = fit_measurement_only(
                job["model"],
                data.y,
                data.u,
                all_reduce=dist.all_reduce,
                checkpoint=path,
                **job["options"],
            )
    finally:
        dist.destroy_process_group()
    return {"result": res if rank == 0 else None}


def _check_timeout(timeout: float) -> float:
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)):
        raise InputError(f"timeout must be a number of seconds, got {timeout!r}")
    if not (timeout > 0 and timeout < float("inf")):
        raise InputError(f"timeout must be a positive finite number of seconds, got {timeout}")
    return float(timeout)


def calibrate_ray(
    model: Any,
    recordings: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    workers: int = 2,
    address: str | None = None,
    validation: Any = None,
    sides: Sequence[str] = ("transition", "measurement"),
    window: int | None = 100,
    burn_in: int = 20,
    iterations: int = 150,
    lr: float = 0.1,
    optimizer: str = "adam",
    patience: int = 15,
    inflate_only: bool = True,
    gp: str = "none",
    dtype: torch.dtype = torch.float64,
    callback: Callable[[Any], bool | None] | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    checkpoint_every: int = 10,
    timeout: float = GROUP_TIMEOUT,
    callback_on: Literal["actors", "driver"] = "actors",
) -> Any:
    """:func:`~torchfilt.training.calibrate` as a data-parallel job on Ray.

    The recordings are dealt to ``workers`` Ray actors (recording ``i`` to actor ``i % workers``),
    which form a ``torch.distributed`` ``gloo`` group: each filters its own windows and the
    log-likelihood, the measurement count and the gradient are summed over the group at every
    evaluation, so all take the steps of one calibration on all recordings (equal to it up to the
    order of the sums; tested). Each actor checkpoints into ``checkpoint/rank{r}.ckpt``.

    **A lost worker.** A collective cannot lose a member: when an actor dies (its process killed,
    out of memory) or does not reach a collective within ``timeout`` seconds, the others fail in
    their next collective, every actor is stopped, and a :class:`~torchfilt.exceptions.WorkerError`
    names the rank. Run the same call again with ``resume=True`` to continue from the checkpoints:
    the actors agree on the latest iteration all of them saved (each checkpoint also keeps the
    one before it), and the result equals an uninterrupted fit (tested).

    Args:
        model, recordings, x0, P0, validation, sides, window, burn_in, iterations, lr,
        optimizer, patience, inflate_only, gp, dtype, checkpoint_every: as in
            :func:`~torchfilt.training.calibrate` (``recordings`` a list of recordings or a
            :class:`~torchfilt.training.likelihood.Sequences` whose ``x0``/``P0`` are shared).
        workers: Ray actors, one CPU each; the cluster must have that many free at once.
        address: Ray cluster (see :func:`ray_session`).
        callback: called in every actor's process after each iteration (its rank is
            ``torch.distributed.get_rank()``); one returning ``True`` stops all. Sent to the
            actors, so it must pickle. With ``callback_on="driver"``: see there.
        checkpoint: folder of the actors' checkpoints (``None``: no checkpoints, and a lost
            worker means starting again).
        resume: continue from the checkpoints in ``checkpoint``.
        timeout: seconds a collective waits for the other actors before it fails (the longest
            one actor may compute between two collectives, e.g. filter its shard, must stay
            below it).
        callback_on: ``"actors"`` (above), or ``"driver"``: ``callback`` is called in this
            process with rank 0's state after each iteration, in order, while rank 0 waits for
            it (before that iteration's checkpoint); its ``True`` stops all, and an exception it
            raises stops the actors (their checkpoints kept: ``resume=True`` continues) and is
            raised here. It need not pickle.

    Returns:
        The :class:`~torchfilt.training.calibrate.CalibrationResult` of actor 0.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` below 1 or more than the recordings or the cluster's CPUs, or a
            bad ``timeout``.
        WorkerError: an actor was lost (see above).
    """
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "validation": validation,
        "sides": tuple(sides),
        "window": window,
        "burn_in": burn_in,
        "iterations": iterations,
        "lr": lr,
        "optimizer": optimizer,
        "patience": patience,
        "inflate_only": inflate_only,
        "gp": gp,
        "dtype": dtype,
        "callback": callback,
        "resume": resume,
        "checkpoint_every": checkpoint_every,
    }
    return _run_group(
        "calibrate_ray", "calibrate", model, recordings, options, workers, address, checkpoint,
        timeout, callback_on,
    )  # fmt: skip


def _run_group(
    caller: str,
    kind: str,
    model: Any,
    recordings: Any,
    options: dict[str, Any],
    workers: int,
    address: str | None,
    checkpoint: str | Path | None,
    timeout: float,
    callback_on: str = "actors",
) -> Any:
    """Run a data-parallel fit on ``workers`` Ray actors in one ``gloo`` group; actor 0's result.

    The driver waits for the actors one at a time: at the first failure it gives the others a
    few seconds to report theirs (an actor whose peer died fails in its next collective, or after
    ``timeout``), stops them all, and raises: an actor's own
    :class:`~torchfilt.exceptions.TorchfiltError` if one raised one (a bad argument, a
    checkpoint of another fit), else a :class:`~torchfilt.exceptions.WorkerError` naming the
    rank that died, or the one still running when the others had given up waiting for it.

    With ``callback_on="driver"`` the driver also serves rank 0's callback states (a
    :class:`_Relay` actor passes them) by calling ``options["callback"]`` here."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if callback_on not in ("actors", "driver"):
        raise InputError(f"callback_on must be 'actors' or 'driver', got {callback_on!r}")
    timeout = _check_timeout(timeout)
    on_driver = options["callback"] if callback_on == "driver" else None
    count = len(recordings.y) if hasattr(recordings, "y") else len(list(recordings))
    if workers > count:
        raise InputError(f"workers: {workers} workers for {count} recordings; use at most {count}")
    if checkpoint is not None:
        Path(checkpoint).mkdir(parents=True, exist_ok=True)
    job = {
        "kind": kind,
        "model": model,
        "recordings": recordings,
        "options": options,
        "checkpoint": None if checkpoint is None else str(Path(checkpoint).resolve()),
        "timeout": timeout,
    }
    with ray_session(address) as ray:
        total = int(ray.cluster_resources().get("CPU", 0))
        if total < workers:
            raise InputError(
                f"workers: {workers} actors must run at once, but the Ray cluster has {total} CPUs"
            )
        actor = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(_Rank)
        ranks = [actor.remote() for _ in range(workers)]
        relay = None
        if on_driver is not None:
            # no CPU of its own: it only passes states, and the actors may take every CPU
            relay = ray.remote(num_cpus=0, max_concurrency=4, max_restarts=0)(_Relay).remote()
            job["options"] = {**options, "callback": _DriverCallback(relay)}
        try:
            init = ray.get(ranks[0].address.remote())
            ref = ray.put(job)
            refs = [a.run.remote(r, workers, init, ref) for r, a in enumerate(ranks)]
            rank_of = {r: i for i, r in enumerate(refs)}
            outs: dict[int, Any] = {}
            errors: dict[int, BaseException] = {}
            pending = list(refs)
            take = None if relay is None else relay.take.remote()
            while pending and not errors:
                ready, _ = ray.wait(pending if take is None else [*pending, take], num_returns=1)
                if take is not None and ready[0] == take:
                    seq, state = ray.get(take)
                    stop = on_driver(state)  # type: ignore[misc]  # an exception stops all
                    relay.answer.remote(seq, bool(stop))  # type: ignore[union-attr]
                    take = relay.take.remote()  # type: ignore[union-attr]
                    continue
                pending = [p for p in pending if p != ready[0]]
                _collect(ray, ready, rank_of, outs, errors)
            if errors and pending:
                ready, pending = ray.wait(
                    pending, num_returns=len(pending), timeout=min(_FAILURE_GRACE, timeout)
                )
                _collect(ray, ready, rank_of, outs, errors)
        finally:
            for a in [*ranks, *([] if relay is None else [relay])]:
                ray.kill(a)
    if errors:
        stuck = sorted(rank_of[r] for r in pending)
        raise _group_error(ray, caller, errors, stuck, workers, job["checkpoint"], timeout)
    return outs[0]["result"]


def _collect(
    ray: Any,
    ready: list[Any],
    rank_of: dict[Any, int],
    outs: dict[int, Any],
    errors: dict[int, BaseException],
) -> None:
    for r in ready:
        try:
            outs[rank_of[r]] = ray.get(r)
        except Exception as e:
            errors[rank_of[r]] = e


def _group_error(
    ray: Any,
    caller: str,
    errors: dict[int, BaseException],
    stuck: list[int],
    world: int,
    checkpoint: str | None,
    timeout: float,
) -> TorchfiltError:
    """The error a failed data-parallel job raises (see :func:`_run_group`): a rank's own
    TorchfiltError, else a WorkerError naming the rank that died, else the one still running
    when the others had failed (it did not reach a collective in time), else the one that
    failed."""
    causes = [getattr(errors[r], "cause", None) for r in sorted(errors)]
    own = [c for c in causes if isinstance(c, TorchfiltError)]
    # a rank's own error before one that only says another rank failed (``peer``)
    own.sort(key=lambda c: bool(getattr(c, "peer", False)))
    if own:
        return own[0]
    died = [r for r in sorted(errors) if isinstance(errors[r], ray.exceptions.RayActorError)]
    if died:
        what = f"rank {died[0]} of {world} was lost (its Ray actor died: process killed or exited)"
    elif stuck:
        first = min(errors)
        what = (
            f"rank {stuck[0]} of {world} did not reach a collective within timeout={timeout:g} s "
            f"(rank {first} stopped waiting: {_cause_line(errors[first])})"
        )
    else:
        rank = min(errors)
        what = f"rank {rank} of {world} failed ({_cause_line(errors[rank])})"
    if checkpoint is None:
        hint = (
            "no checkpoints were kept, so the fit must start again; pass checkpoint=DIR to be "
            "able to resume after a lost worker"
        )
    else:
        hint = (
            f"run the same call again with resume=True to continue from the checkpoints in "
            f"{checkpoint} (every rank restarts from the latest iteration all of them saved)"
        )
    return WorkerError(f"{caller}: {what}; the other ranks were stopped; {hint}")


def _cause_line(e: BaseException) -> str:
    """An actor's exception in one short line: the original one Ray wraps, if any."""
    cause = getattr(e, "cause", None)
    err = cause if isinstance(cause, BaseException) else e
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text[:200]}"


def fit_measurement_only_ray(
    model: Any,
    recordings: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    known_channels: Sequence[int] | None,
    method: str = "likelihood",
    workers: int = 2,
    address: str | None = None,
    iterations: int = 100,
    window: int | None = None,
    burn_in: int = 0,
    validation: Any = None,
    optimizer: str = "lbfgs",
    lr: float | None = None,
    tol: float | None = None,
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    dtype: torch.dtype = torch.float64,
    callback: Callable[[Any], bool | None] | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    checkpoint_every: int = 1,
    timeout: float = GROUP_TIMEOUT,
    callback_on: Literal["actors", "driver"] = "actors",
) -> Any:
    """:func:`~torchfilt.training.fit_measurement_only` as a data-parallel job on Ray: the same
    group of actors as :func:`calibrate_ray` (recordings dealt round-robin, one checkpoint per
    actor, ``resume``, a :class:`~torchfilt.exceptions.WorkerError` for a lost worker). With
    ``method="likelihood"`` the gradients are summed over ``gloo`` at every L-BFGS evaluation;
    with ``method="em"`` each actor runs the E-step on its recordings and the M-step sums the
    expected sufficient statistics (linear model) or the expected complete-data log-likelihood
    and its gradient (any other), see :func:`~torchfilt.training.fit_em`.

    Args:
        model, x0, P0, known_channels, method, iterations, window, burn_in, validation,
        optimizer, lr, tol, learn_measurement_noise, m_step_iterations, dtype,
        checkpoint_every: as in :func:`~torchfilt.training.fit_measurement_only`.
        recordings: a :class:`~torchfilt.training.likelihood.Sequences` (``y``, ``u``; shared
            ``x0``/``P0``).
        workers, address, callback, checkpoint, resume, timeout, callback_on: as in
            :func:`calibrate_ray`.

    Returns:
        Actor 0's :class:`~torchfilt.training.measurement_only.MeasurementOnlyFit`.

    Raises:
        InputError: ``method`` not ``"em"`` or ``"likelihood"``; see :func:`calibrate_ray`.
        WorkerError: an actor was lost.
    """
    if method not in ("em", "likelihood"):
        raise InputError(f"method must be 'em' or 'likelihood', got {method!r}")
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "known_channels": known_channels,
        "method": method,
        "iterations": iterations,
        "window": window,
        "burn_in": burn_in,
        "validation": validation,
        "optimizer": optimizer,
        "lr": lr,
        "tol": tol,
        "learn_measurement_noise": learn_measurement_noise,
        "m_step_iterations": m_step_iterations,
        "dtype": dtype,
        "callback": callback,
        "resume": resume,
        "checkpoint_every": checkpoint_every,
    }
    return _run_group(
        "fit_measurement_only_ray", "measurement_only", model, recordings, options, workers,
        address, checkpoint, timeout, callback_on,
    )  # fmt: skip


class _Rank:
    """A Ray actor of :func:`calibrate_ray` and :func:`fit_measurement_only_ray`."""

    def address(self) -> str:
        return _free_address()

    def run(self, rank: int, world: int, init: str, job: dict[str, Any]) -> dict[str, Any]:
        return _fit_rank(rank, world, init, job)


class _Relay:
    """A Ray actor (threaded) that passes rank 0's callback states to the driver and the
    driver's answers back (``callback_on="driver"``): rank 0 calls :meth:`put`, which returns
    the driver's answer; the driver calls :meth:`take`, then :meth:`answer`."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._seq = 0
        self._waiting: tuple[int, Any] | None = None
        self._answers: dict[int, bool] = {}

    def put(self, state: Any) -> bool:
        with self._cv:
            self._seq += 1
            seq = self._seq
            self._waiting = (seq, state)
            self._cv.notify_all()
            self._cv.wait_for(lambda: seq in self._answers)
            return self._answers.pop(seq)

    def take(self) -> tuple[int, Any]:
        with self._cv:
            self._cv.wait_for(lambda: self._waiting is not None)
            item, self._waiting = self._waiting, None
            assert item is not None
            return item

    def answer(self, seq: int, stop: bool) -> None:
        with self._cv:
            self._answers[seq] = stop
            self._cv.notify_all()


class _DriverCallback:
    """The callback the actors get with ``callback_on="driver"``: rank 0 sends its state to the
    driver (through the :class:`_Relay`) and returns the driver's answer; the others do
    nothing (rank 0's ``True`` stops them all)."""

    def __init__(self, relay: Any) -> None:
        self.relay = relay

    def __call__(self, state: Any) -> bool | None:
        import torch.distributed as dist

        if dist.get_rank() != 0:
            return None
        return bool(import_ray().get(self.relay.put.remote(state)))


# ------------------------------------------------------------------ one recipe, data-parallel


def _measurement_only_stage_ray(
    model: Any,
    y: Any,
    u: Any = None,
    *,
    workers: int,
    timeout: float,
    x0: torch.Tensor,
    P0: torch.Tensor,
    known_channels: Sequence[int] | None,
    method: Literal["em", "likelihood"] = "em",
    iterations: int = 100,
    window: int | None = None,
    burn_in: int = 0,
    optimizer: str = "lbfgs",
    lr: float | None = None,
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    callback: Callable[[Any], bool | None] | None = None,
    progress: bool = False,
    dtype: torch.dtype = torch.float64,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 1,
    resume: bool = False,
) -> Any:
    """:func:`fit_measurement_only_ray` called as :func:`~torchfilt.training.fit_measurement_only`
    (``y`` and ``u`` lists of ``(T_i, m)`` / ``(T_i, nu)``), the callback on the driver:
    the ``measurement_only`` fitter of :func:`train_recipe_data_parallel`. ``progress`` is
    ignored (the stage draws its own from the callback)."""
    from torchfilt.training.likelihood import Sequences

    return fit_measurement_only_ray(
        model,
        Sequences(y, u),
        x0=x0,
        P0=P0,
        known_channels=known_channels,
        method=method,
        workers=workers,
        iterations=iterations,
        window=window,
        burn_in=burn_in,
        optimizer=optimizer,
        lr=lr,
        learn_measurement_noise=learn_measurement_noise,
        m_step_iterations=m_step_iterations,
        dtype=dtype,
        callback=callback,
        checkpoint=checkpoint,
        resume=resume,
        checkpoint_every=checkpoint_every,
        timeout=timeout,
        callback_on="driver",
    )


def data_parallel_fitters(workers: int, *, timeout: float = GROUP_TIMEOUT) -> StageFitters:
    """The :class:`~torchfilt.training.run.StageFitters` of :func:`train_recipe_data_parallel`:
    :func:`calibrate_ray` and :func:`fit_measurement_only_ray` on ``workers`` actors of the Ray
    session open when a stage runs, the stage's callback on the driver, the stage's checkpoint
    path the folder of the actors' checkpoints.

    Raises:
        InputError: ``workers`` is not a positive integer, or a bad ``timeout``.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"--data-parallel must be a positive integer, got {workers!r}")
    timeout = _check_timeout(timeout)
    return StageFitters(
        calibrate=partial(calibrate_ray, workers=workers, timeout=timeout, callback_on="driver"),
        measurement_only=partial(_measurement_only_stage_ray, workers=workers, timeout=timeout),
        name=f"data-parallel on {workers} Ray actors (--data-parallel {workers})",
        shards=workers,
    )


def train_recipe_data_parallel(
    recipe: str | Path | Recipe,
    out: str | Path,
    *,
    workers: int,
    address: str | None = None,
    cpus: int | None = None,
    resume: bool = False,
    force: bool = False,
    timeout: float = GROUP_TIMEOUT,
    progress: bool = True,
    stream: TextIO | None = None,
) -> Path:
    """:func:`~torchfilt.training.train_recipe` with its likelihood stages data-parallel on Ray.

    The calibration stage runs :func:`calibrate_ray` and a ``states = "none"`` recipe's
    transition stage :func:`fit_measurement_only_ray`, each on ``workers`` actors (one CPU each)
    with the training recordings dealt round-robin (recording ``i`` to actor ``i % workers``);
    the GP stages, the validation and the bundle run in this process, as in a local run. The run
    directory, dataset log and bundle are those of a local run: the calibrated scales and floors
    and the learned transition equal the local ones up to the order of the sums (float64: to
    ~1e-9, tested), and ``metrics.jsonl``, ``train.log`` and the progress bar are written here
    from rank 0's per-iteration states. Each stage checkpoints into a folder in the run
    directory (``calibrate.ckpt/rank{r}.ckpt``, ``transition.ckpt/rank{r}.ckpt``), removed when
    the stage is done.

    ``config.json`` records the fitters (``"stage_fitters"``), and the run resumes only as it
    started: ``resume=True`` with the same ``workers`` continues it from its checkpoints to the
    bundle of an uninterrupted run (a lost actor is a
    :class:`~torchfilt.exceptions.WorkerError`, and resuming continues from the checkpoints all
    actors saved); :func:`~torchfilt.training.train_recipe` (local) or other ``workers`` refuse
    it with a :class:`~torchfilt.exceptions.RunError`.

    Args:
        recipe: a recipe file or a :class:`~torchfilt.training.Recipe`.
        out: run directory (visible under the same path to every actor: one machine or a shared
            filesystem).
        workers: Ray actors per data-parallel stage (``--data-parallel N``); at most the training
            recordings and the cluster's CPUs.
        address: Ray cluster (see :func:`ray_session`; ``None``: a new local instance, unless one
            is open in this process).
        cpus: CPUs of a new local instance (default: all; ``--workers``).
        resume: continue the run in ``out``.
        force: discard a run already in ``out``.
        timeout: seconds a collective waits for the other actors (see :func:`calibrate_ray`).
        progress: show progress bars (on a terminal; plain lines otherwise).
        stream: where progress goes (default ``sys.stderr``).

    Returns:
        Path of the model bundle ``out/model.pt``.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` not a positive integer or more than the training recordings or
            the cluster's CPUs, ``resume`` with ``force``, an unreachable cluster.
        RecipeError, DataError: as :func:`~torchfilt.training.train_recipe` (before Ray starts).
        RunError: as :func:`~torchfilt.training.train_recipe`, and a run started with other
            fitters.
        WorkerError: an actor was lost; ``resume=True`` continues.
    """
    from torchfilt.training import train_recipe

    import_ray()
    fitters = data_parallel_fitters(workers, timeout=timeout)
    if resume and force:
        raise InputError("--resume continues the run in --out and --force discards it: pick one")
    r = recipe if isinstance(recipe, Recipe) else load_recipe(recipe)  # errors before Ray starts
    with ray_session(address, workers=cpus) as ray:
        total = int(ray.cluster_resources().get("CPU", 0))
        if total < workers:
            raise InputError(
                f"--data-parallel {workers}: {workers} actors must run at once, but the Ray "
                f"cluster has {total} CPUs"
            )
        try:
            return train_recipe(
                r, out, resume=resume, force=force, progress=progress, stream=stream,
                fitters=fitters,
            )  # fmt: skip
        except WorkerError as e:
            raise WorkerError(
                f"{e}. For this run: resume it with --resume (resume=True) and the same "
                f"--ray --data-parallel {workers}"
            ) from None
