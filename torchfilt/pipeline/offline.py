"""Filtering (and smoothing) recordings offline, batched on a device."""

from __future__ import annotations

import io
import json
import os
import warnings
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchfilt.exceptions import InputError, NumericsWarning, OutputError
from torchfilt.filters import CKF, coverage, nees, nis, rmse
from torchfilt.io import DataError, Recording, atomic_write_bytes, atomic_write_text, read_recording
from torchfilt.io.atomic import check_new_outputs, output_dir
from torchfilt.io.estimates import Estimates, write_estimates
from torchfilt.io.recording import SUFFIXES
from torchfilt.pipeline.bundle import ModelSpec, load_model_spec

__all__ = [
    "INDEX_NAME",
    "ModelSpec",
    "check_device",
    "check_recording_files",
    "filter_batch",
    "filter_recordings",
    "output_names",
    "recording_outputs",
    "resolve_model",
    "shard_plan",
]

#: Summary file that ``filter_recordings`` writes into its output folder (read by evaluate).
INDEX_NAME = "filter_summary.json"


def resolve_model(spec: str | Path | ModelSpec) -> ModelSpec:
    """A model from ``system:NAME`` (a built-in analytic model) or a model bundle file."""
    if isinstance(spec, ModelSpec):
        return spec
    s = str(spec)
    if s.startswith("system:"):
        return ModelSpec.from_system(s.split(":", 1)[1])
    return load_model_spec(s)


def check_device(device: str | torch.device) -> torch.device:
    """Parse and check a torch device before anything is loaded onto it.

    Raises:
        InputError: not a device name, or a device this torch build or machine does not have
            (``cuda`` on a CPU-only build or without a visible GPU, ``cuda:3`` with two GPUs).
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise InputError(
            f"--device {device!r}: not a torch device (use cpu, cuda, cuda:N or mps)"
        ) from None
    if dev.type == "cuda":
        if torch.version.cuda is None and getattr(torch.version, "hip", None) is None:
            raise InputError(f"--device {device!r}: this torch build has no CUDA support")
        if not torch.cuda.is_available():
            raise InputError(f"--device {device!r}: no CUDA device is visible")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InputError(
                f"--device {device!r}: only {torch.cuda.device_count()} CUDA device(s) visible"
            )
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise InputError(f"--device {device!r}: MPS is not available on this machine")
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise InputError(f"--device {device!r}: unsupported device type {dev.type!r}")
    return dev


def output_names(recordings: Sequence[str | Path]) -> list[str]:
    """Unique output base names for recordings, relative to the output folder.

    The file stem (``a/rec.csv`` -> ``rec``) when the stems are unique; otherwise the path relative
    to the recordings' common folder without its suffix (``a/rec.csv``, ``b/rec.csv`` -> ``a/rec``,
    ``b/rec``), so no output overwrites another.

    Raises:
        InputError: a recording is given twice, or two differ only by their suffix.
    """
    paths = [Path(os.path.abspath(p)) for p in recordings]
    seen: dict[Path, int] = {}
    for i, p in enumerate(paths):
        if p in seen:
            raise InputError(f"{recordings[i]}: recording given twice (as argument {seen[p] + 1})")
        seen[p] = i + 1
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    root = Path(os.path.commonpath([str(p.parent) for p in paths]))
    names = [p.relative_to(root).with_suffix("").as_posix() for p in paths]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise InputError(
            f"recordings {dup!r} with different suffixes would write the same estimate files; "
            "filter them into different --out folders"
        )
    return names


def check_recording_files(recordings: Sequence[str | Path]) -> None:
    """Check that recordings were given, exist and have a readable suffix.

    Raises:
        InputError: no recordings.
        DataError: a recording is missing or of an unsupported file type.
    """
    if not recordings:
        raise InputError("no recordings given")
    for p in recordings:
        if not Path(p).is_file():
            raise DataError("recording not found", path=p)
        if Path(p).suffix.lower() not in SUFFIXES:
            raise DataError(
                f"unsupported file type {Path(p).suffix!r}; use one of {SUFFIXES}", path=p
            )


def recording_outputs(name: str, *, smooth: bool, plot: bool) -> list[str]:
    """The files ``filter_recordings`` writes for the recording with output name ``name``,
    relative to the output folder, in the order written (the filtered estimates last)."""
    files = []
    if smooth:
        files.append(f"{name}.smoothed.csv")
    if plot:
        files.append(f"{name}.png")
    files.append(f"{name}.filtered.csv")
    return files


def _metrics(truth: Tensor, mean: Tensor, cov: Tensor) -> dict[str, Any]:
    ok = torch.isfinite(truth).all(-1)
    if not bool(ok.any()):
        return {}
    x, m, P = truth[ok], mean[ok], cov[ok]
    return {
        "rmse": rmse(x, m).tolist(),
        "nees": float(nees(x, m, P).mean()),
        "coverage95": coverage(x, m, P).tolist(),
        "steps_with_truth": int(ok.sum()),
    }


def filter_recordings(
    model: str | Path | ModelSpec,
    recordings: Sequence[str | Path],
    out: str | Path,
    *,
    smooth: bool = False,
    plot: bool = False,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    sqrt: bool = False,
    x0: Tensor | None = None,
    P0: Tensor | None = None,
    force: bool = False,
    batch_size: int | None = None,
) -> dict[str, Any]:
    """Filter (and optionally smooth) recordings with a model; write estimates, plots and a summary.

    The prior ``N(x0, P0)`` (default: the model's) is the state at each recording's first row; the
    filter then predicts and updates on rows ``1..T-1`` (input row ``k`` drives the step from row
    ``k`` to ``k + 1``). Recordings of equal length are filtered as one batch on ``device`` (batches
    of at most ``batch_size``, see :func:`shard_plan`);
    :func:`~torchfilt.pipeline.distributed.filter_recordings_ray` does the same on a Ray cluster.

    Writes into ``out``: ``{name}.filtered.csv`` (mean, sd, correlations and NIS per step),
    ``{name}.smoothed.csv`` with ``smooth``, ``{name}.png`` with ``plot``, and
    ``filter_summary.json`` (inputs, outputs, and RMSE/NEES/coverage where the log has truth).
    ``name`` is the recording's file stem, or its path relative to the recordings' common folder
    when two recordings share a stem (:func:`output_names`). An existing output file is an error
    unless ``force``; the device, the recording files and the outputs are checked before the
    model is loaded.

    Args:
        model: ``system:NAME``, a model bundle path, or a :class:`ModelSpec`.
        recordings: recording files (CSV or NPZ) with the model's measurement and input channels;
            state channels, when present, are used as truth.
        out: output folder.
        smooth: also run the RTS smoother.
        plot: write a report figure per recording.
        device: torch device for the batch.
        dtype: floating dtype.
        sqrt: use the square-root filter.
        x0: prior mean override ``(n,)``.
        P0: prior covariance override ``(n, n)``.
        force: overwrite existing output files.
        batch_size: most recordings per batch (default: all recordings of one length).

    Returns:
        The summary (also written to ``filter_summary.json``).

    Raises:
        InputError: no recordings, a recording given twice, a bad device.
        DataError: a recording is missing or invalid.
        OutputError: an output exists (without ``force``), or ``out`` cannot be written.
    """
    dev = check_device(device)
    shard_plan([], batch_size)  # check the option before anything is read
    check_recording_files(recordings)
    out = Path(out)
    names = output_names(recordings)
    planned = [out / INDEX_NAME]
    for n in names:
        planned.extend(out / f for f in recording_outputs(n, smooth=smooth, plot=plot))
    check_new_outputs(planned, force=force)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: the output folder is a file; choose a folder")
    spec = resolve_model(model)
    recs = _read_recordings(spec, recordings)
    output_dir(out)
    filt = CKF(spec.model.to(device=dev, dtype=dtype), sqrt=sqrt)
    m0 = (spec.prior_mean if x0 is None else torch.as_tensor(x0)).to(dev, dtype)
    C0 = (spec.prior_cov if P0 is None else torch.as_tensor(P0)).to(dev, dtype)
    summary: dict[str, Any] = {"model": spec.source, "smooth": smooth, "recordings": []}
    entries: dict[int, dict[str, Any]] = {}
    for idx in shard_plan([len(r) for r in recs], batch_size):
        if recs[idx[0]].measurements[0].isfinite().any():
            warnings.warn(
                "the first row of a recording is the prior's time; its measurements are not used",
                stacklevel=2,
            )
        for i, entry in filter_batch(
            spec,
            filt,
            [recs[i] for i in idx],
            [names[i] for i in idx],
            m0,
            C0,
            out,
            smooth=smooth,
            plot=plot,
        ):
            entries[idx[i]] = entry
    summary["recordings"] = [entries[i] for i in range(len(recs))]
    atomic_write_text(out / INDEX_NAME, json.dumps(summary, indent=2, default=float) + "\n")
    return summary


def _read_recordings(spec: ModelSpec, recordings: Sequence[str | Path]) -> list[Recording]:
    """Read and validate every recording with the model's channels (at least 2 rows each)."""
    recs: list[Recording] = []
    for p in recordings:
        recs.append(
            read_recording(
                p,
                spec.channels,
                time_column=spec.time_column,
                sample_time=spec.sample_time,
                optional=("state",),
            )
        )
        if len(recs[-1]) < 2:
            raise DataError("needs at least 2 rows (the first row is the prior's time)", path=p)
    return recs


def shard_plan(lengths: Sequence[int], batch_size: int | None = None) -> list[list[int]]:
    """How recordings are batched: the indices of each batch, in order.

    Recordings of equal length form a group (groups in order of first appearance, members in input
    order); a group is split into consecutive batches of at most ``batch_size`` (one batch per group
    when ``None``). Batched linear algebra can round differently for different batch shapes, so an
    estimate's last bits depend on the batch it was filtered in: the local and the distributed
    paths both follow this plan, and give byte-identical files for the same ``batch_size``.

    Raises:
        InputError: ``batch_size`` is not a positive integer.
    """
    if batch_size is not None and (
        isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1
    ):
        raise InputError(
            f"batch_size (--batch-size) must be a positive integer, got {batch_size!r}"
        )
    groups: dict[int, list[int]] = defaultdict(list)
    for i, n in enumerate(lengths):
        groups[n].append(i)
    plan: list[list[int]] = []
    for idx in groups.values():
        step = len(idx) if batch_size is None else batch_size
        plan.extend(idx[k : k + step] for k in range(0, len(idx), step))
    return plan


def filter_batch(
    spec: ModelSpec,
    filt: CKF,
    recs: Sequence[Recording],
    names: Sequence[str],
    m0: Tensor,
    C0: Tensor,
    out: Path,
    *,
    smooth: bool,
    plot: bool,
    write: Sequence[bool] | None = None,
) -> list[tuple[int, dict[str, Any]]]:
    """Filter recordings of equal length as one batch and write their outputs into ``out``.

    Each recording's files are written atomically, the filtered estimates last (after the smoothed
    estimates and the plot). ``write[b]`` false skips writing recording ``b`` (it is still part of
    the batch, so the others' numbers do not change). Returns ``(b, summary entry)`` for each
    recording written.
    """
    dev, dtype = m0.device, m0.dtype
    y = torch.stack([r.measurements[1:] for r in recs]).to(dev, dtype)
    u = None
    if spec.inputs:
        u = torch.stack([r.inputs[:-1] for r in recs]).to(dev, dtype)  # type: ignore[index]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NumericsWarning)
        if smooth:
            sm = filt.smooth(y, u, x0=m0, P0=C0)
            res = sm.filtered
        else:
            sm, res = None, filt.filter(y, u, x0=m0, P0=C0)
    value, dof = nis(res)
    done: list[tuple[int, dict[str, Any]]] = []
    for b, rec in enumerate(recs):
        if write is not None and not write[b]:
            continue
        entry = _write_one(
            rec, names[b], spec, res, sm, b, value[b], dof[b], m0, C0, out, plot, len(caught)
        )
        done.append((b, entry))
    return done


def _with_prior(mean: Tensor, cov: Tensor, m0: Tensor, C0: Tensor) -> tuple[np.ndarray, np.ndarray]:
    M = torch.cat([m0[None], mean]).detach().cpu().numpy()
    P = torch.cat([C0[None], cov]).detach().cpu().numpy()
    return M, P


def _write_one(
    rec: Recording,
    name: str,
    spec: ModelSpec,
    res: Any,
    sm: Any,
    b: int,
    value: Tensor,
    dof: Tensor,
    m0: Tensor,
    C0: Tensor,
    out: Path,
    plot: bool,
    warned: int,
) -> dict[str, Any]:
    names = [n for n, _ in spec.states]
    M, P = _with_prior(res.mean[b], res.cov[b], m0, C0)
    nis_v = np.concatenate([[np.nan], value.detach().cpu().numpy()])
    nis_k = np.concatenate([[0.0], dof.detach().cpu().numpy()])
    entry: dict[str, Any] = {
        "recording": str(rec.path),
        "rows": len(rec),
        "filtered": f"{name}.filtered.csv",
        "time_column": rec.time_column,
        "numerics_warnings": warned,
        "finite": bool(np.isfinite(M).all()),
    }
    truth = rec.states
    entry["filtered_metrics"] = _metrics(
        truth[1:], res.mean[b].cpu().double(), res.cov[b].cpu().double()
    )
    obs = dof > 0
    entry["mean_nis"] = float(value[obs].mean()) if bool(obs.any()) else None
    entry["mean_nis_dof"] = float(dof[obs].double().mean()) if bool(obs.any()) else None
    if sm is not None:
        Ms, Ps = _with_prior(sm.mean[b], sm.cov[b], m0, C0)
        spath = out / f"{name}.smoothed.csv"
        write_estimates(spath, Estimates(rec.time, Ms, Ps, names))
        entry["smoothed"] = f"{name}.smoothed.csv"
        entry["smoothed_metrics"] = _metrics(
            truth[1:], sm.mean[b].cpu().double(), sm.cov[b].cpu().double()
        )
    if plot:
        import matplotlib  # here, not at the top: the pipeline imports without matplotlib

        from torchfilt.plots import plot_recording

        matplotlib.use("Agg", force=False)
        one = type(res)(*(f[b] if isinstance(f, torch.Tensor) else f for f in res))
        one_sm = None
        if sm is not None:
            one_sm = type(sm)(sm.mean[b], sm.cov[b], sm.gain[b], one)
        fig = plot_recording(
            one,
            smoothed=one_sm,
            times=torch.as_tensor(rec.time[1:]),
            truth=truth[1:],
            measurements=rec.measurements[1:],
            state_names=names,
            state_units=[u for _, u in spec.states],
            measurement_names=[n for n, _ in spec.measurements],
            measurement_units=[u for _, u in spec.measurements],
            title=f"{rec.name}: {spec.source}",
        )
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        atomic_write_bytes(out / f"{name}.png", buf.getvalue())
        entry["plot"] = f"{name}.png"
    # the filtered estimates last: once they exist, so do the recording's other outputs
    write_estimates(out / f"{name}.filtered.csv", Estimates(rec.time, M, P, names, nis_v, nis_k))
    return entry
