"""The bookkeeping of a filter job in its output folder (see :mod:`torchfilt.pipeline.distributed`):
the job file, the completion markers, and what makes two jobs the same (so a re-run resumes)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from torchfilt.exceptions import OutputError
from torchfilt.io import sha256_file
from torchfilt.pipeline.offline import ModelSpec

__all__ = ["DONE_DIR", "JOB_FILE"]

#: The job description in an output folder of :func:`filter_recordings_ray`.
JOB_FILE = ".torchfilt/job.json"
#: Completion markers, one per recording: ``{DONE_DIR}/{name}.json``.
DONE_DIR = ".torchfilt/done"
_JOB_SCHEMA = "torchfilt-ray-filter/1"


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
