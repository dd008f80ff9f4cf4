"""Filtering many recordings as Ray tasks, one batch per task, resumable
(``torchfilt filter ... --ray``; see :mod:`torchfilt.pipeline.distributed`)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import torch

from torchfilt.exceptions import InputError, OutputError, RunError
from torchfilt.filters import CKF
from torchfilt.io import DataError, atomic_write_text, read_recording
from torchfilt.io.atomic import check_new_outputs, output_dir
from torchfilt.pipeline.distributed.jobs import (
    _JOB_SCHEMA,
    JOB_FILE,
    _complete_entry,
    _job_identity,
    _marker,
    _read_job,
)
from torchfilt.pipeline.distributed.session import _one_line, import_ray, ray_session
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

__all__ = ["filter_recordings_ray"]


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
    out, names = _check_arguments(recordings, out, device, batch_size, max_retries, dtype)
    spec = resolve_model(model)
    opts = {
        "smooth": bool(smooth), "plot": bool(plot), "dtype": str(dtype).removeprefix("torch."),
        "sqrt": bool(sqrt), "batch_size": batch_size, "device": device,
        "x0": None if x0 is None else torch.as_tensor(x0, dtype=torch.float64).tolist(),
        "P0": None if P0 is None else torch.as_tensor(P0, dtype=torch.float64).tolist(),
    }  # fmt: skip
    job, identity, lengths, fresh = _prepare_job(spec, model, recordings, names, out, opts, force)
    pending, found = _pending_shards(job, out, shard_plan(lengths, batch_size), fresh)
    stats: dict[str, Any] = {"filtered": 0, "complete_before": found, "tasks": len(pending)}
    stats["prepare_s"] = time.perf_counter() - t_start
    failures: list[str] = []
    task_times: list[dict[str, float]] = []  # per task: size, compute_s, wall_s
    with contextlib.ExitStack() as stack:
        # Ray first: an unreachable cluster is reported before anything is written
        ray = stack.enter_context(ray_session(address, workers=workers)) if pending else None
        output_dir(out)
        if fresh:
            _start_job(out, identity, job["paths"], lengths)
        if ray is not None:
            show = _Progress(progress, stream if stream is not None else sys.stderr, len(names))
            task_times = _run_shards(
                ray, job, spec, pending, found, show, stats, failures,
                gpus_per_task=gpus_per_task, max_retries=max_retries,
            )  # fmt: skip
    stats["task_times"] = task_times
    stats["failed_tasks"] = len(failures)
    summary = _summary(out, spec, smooth, job["names"], failures, len(pending))
    stats["total_s"] = time.perf_counter() - t_start
    return {**summary, "distributed": stats}


def _check_arguments(
    recordings: Sequence[str | Path],
    out: str | Path,
    device: str,
    batch_size: int,
    max_retries: int,
    dtype: torch.dtype,
) -> tuple[Path, list[str]]:
    """The options, then the recording files and the output folder, checked before anything is
    read; ``out`` as a path and the recordings' output names."""
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
    return out, output_names(recordings)


def _prepare_job(
    spec: ModelSpec,
    model: str | Path | ModelSpec,
    recordings: Sequence[str | Path],
    names: list[str],
    out: Path,
    opts: dict[str, Any],
    force: bool,
) -> tuple[dict[str, Any], dict[str, Any], list[int], bool]:
    """The job to run in ``out`` (its recordings in the first run's order), its identity, the
    recordings' lengths, and whether it is a new job. A new job checks that it overwrites
    nothing and validates every recording before anything is written; a job resumed in ``out``
    takes the order and lengths of its job file."""
    given = [str(Path(p)) for p in recordings]
    paths = [os.path.abspath(p) for p in recordings]
    identity = _job_identity(spec, model, sorted(paths), opts)
    old = _read_job(out / JOB_FILE)
    if old is not None and not force and old.get("identity") != identity:
        raise OutputError(
            f"{out}: holds the outputs of another filter job (other recordings, model or "
            "options); pass --force (force=True) to replace them, or choose another --out"
        )
    if old is not None and not force:
        # resuming: the first run's order fixes the plan and the summary's order
        order = {p: i for i, p in enumerate(paths)}
        perm = [order[p] for p in old["paths"]]
        lengths = list(old["lengths"])
    else:
        perm = list(range(len(paths)))
        planned = [out / INDEX_NAME]
        for nm in names:
            planned.extend(
                out / f for f in recording_outputs(nm, smooth=opts["smooth"], plot=opts["plot"])
            )
        check_new_outputs(planned, force=force)
        lengths = _recording_lengths(spec, recordings)
    job: dict[str, Any] = {
        "out": os.path.abspath(out),
        "recordings": [given[i] for i in perm],
        "names": [names[i] for i in perm],
        "paths": [paths[i] for i in perm],
        **{k: opts[k] for k in ("smooth", "plot", "dtype", "sqrt", "device", "x0", "P0")},
    }
    # a new job: its markers (if any, of a forced one) go
    return job, identity, lengths, old is None or force


def _recording_lengths(spec: ModelSpec, recordings: Sequence[str | Path]) -> list[int]:
    """Validate every recording (before anything is written); their lengths."""
    lengths = []
    first_row_seen = False
    for p in recordings:
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
            stacklevel=4,  # the caller of filter_recordings_ray
        )
    return lengths


def _pending_shards(
    job: dict[str, Any], out: Path, plan: list[list[int]], fresh: bool
) -> tuple[list[list[int]], int]:
    """The batches with an incomplete recording (every batch of a new job), and the number of
    recordings found complete."""

    def incomplete(i: int) -> bool:
        return fresh or _complete_entry(out, job["names"][i]) is None

    pending = [sh for sh in plan if any(incomplete(i) for i in sh)]
    found = len(job["names"]) - sum(incomplete(i) for sh in pending for i in sh)
    return pending, found


def _start_job(out: Path, identity: dict[str, Any], paths: list[str], lengths: list[int]) -> None:
    """Write a new job's file (removing the bookkeeping of a job it replaces)."""
    if (out / ".torchfilt").is_dir():
        shutil.rmtree(out / ".torchfilt")
    atomic_write_text(
        out / JOB_FILE,
        json.dumps(
            {"schema": _JOB_SCHEMA, "identity": identity, "paths": paths, "lengths": lengths},
            indent=1,
        )
        + "\n",
    )


def _run_shards(
    ray: Any,
    job: dict[str, Any],
    spec: ModelSpec,
    pending: list[list[int]],
    found: int,
    show: _Progress,
    stats: dict[str, Any],
    failures: list[str],
    *,
    gpus_per_task: float | None,
    max_retries: int,
) -> list[dict[str, float]]:
    """One task per pending batch; wait for them in the order they finish, counting what each
    wrote into ``stats`` and each failure's line into ``failures``. Returns the tasks' times."""
    gpus = gpus_per_task
    if gpus is None:
        gpus = 1.0 if job["device"] != "cpu" and ray.cluster_resources().get("GPU", 0) > 0 else 0.0
    remote = ray.remote(_filter_shard).options(num_cpus=1, num_gpus=gpus, max_retries=max_retries)
    task_times: list[dict[str, float]] = []
    job_ref, spec_ref = ray.put(job), ray.put(spec)
    started: dict[Any, tuple[float, int]] = {}
    for s in pending:
        started[remote.remote(job_ref, spec_ref, s)] = (time.perf_counter(), len(s))
    done_count = found
    left = list(started)
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
            {"size": size, "compute_s": res["compute_s"], "wall_s": time.perf_counter() - t_sub}
        )
        done_count += size
        show(done_count)
    return task_times


def _summary(
    out: Path, spec: ModelSpec, smooth: bool, names: list[str], failures: list[str], tasks: int
) -> dict[str, Any]:
    """The job's summary, written to ``filter_summary.json`` once every recording is complete."""
    if failures and any(_complete_entry(out, nm) is None for nm in names):
        raise RunError(
            f"{len(failures)} of {tasks} filter tasks failed (first: {failures[0]}); the "
            "recordings finished are kept in "
            f"{out}: run the same command again to do the rest"
        )
    entries = []
    for name in names:
        entry = _complete_entry(out, name)
        if entry is None:  # pragma: no cover - every task returned without error
            raise RunError(f"{out}: {name} has no complete output after the job; run it again")
        entries.append(entry)
    summary: dict[str, Any] = {"model": spec.source, "smooth": smooth, "recordings": entries}
    atomic_write_text(out / INDEX_NAME, json.dumps(summary, indent=2, default=float) + "\n")
    return summary


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
