"""Compare estimate files with the truth logged in their recordings: RMSE, NEES, coverage."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from torchfilt.exceptions import InputError
from torchfilt.filters import coverage, nees
from torchfilt.io import Channel, DataError, atomic_write_text, read_recording
from torchfilt.io.atomic import check_new_outputs
from torchfilt.io.estimates import read_estimates

__all__ = ["evaluate_outputs"]


def evaluate_outputs(
    out: str | Path, *, which: str = "filtered", level: float = 0.95, force: bool = False
) -> dict[str, Any]:
    """Evaluate the estimates in a ``torchfilt filter`` output folder against logged truth.

    Reads ``filter_summary.json``, the estimate files and the recordings they came from, and
    computes per recording and pooled over recordings: RMSE per state, mean NEES, and the coverage
    of the ``level`` intervals per state. The prior row (row 0) is excluded.

    Args:
        out: the output folder of :func:`~torchfilt.pipeline.filter_recordings`.
        which: ``"filtered"`` or ``"smoothed"``.
        level: interval probability for the coverage.
        force: overwrite an existing ``evaluation_{which}.json``.

    Returns:
        The evaluation (also written to ``evaluation_{which}.json`` in ``out``).

    Raises:
        InputError: ``which`` is neither ``"filtered"`` nor ``"smoothed"``, or ``level`` is not
            in ``(0, 1)``.
        DataError: ``out`` is not a filter output folder, or its files are invalid.
        OutputError: the evaluation file exists (without ``force``).
    """
    out = Path(out)
    if which not in ("filtered", "smoothed"):
        raise InputError(f"which must be 'filtered' or 'smoothed', got {which!r}")
    if not 0.0 < level < 1.0:
        raise InputError(f"level must be in (0, 1), got {level}")
    index = out / "filter_summary.json"
    if not index.is_file():
        raise DataError(
            "not a torchfilt filter output folder (filter_summary.json missing)", path=out
        )
    target = out / f"evaluation_{which}.json"
    check_new_outputs([target], force=force)
    not_summary = "not a filter summary written by torchfilt filter"
    try:
        summary = json.loads(index.read_text(encoding="utf-8"))
        entries = list(summary["recordings"])
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        raise DataError(not_summary, path=index) from None
    if not all(isinstance(e, dict) and "recording" in e for e in entries):
        raise DataError(not_summary, path=index)
    per, errs, nees_all, inside = [], [], [], []
    names: list[str] = []
    for entry in entries:
        if which not in entry:
            raise DataError(
                f"has no {which} estimates (run torchfilt filter with --smooth)", path=index
            )
        est = read_estimates(out / entry[which])
        names = est.state_names
        rec = read_recording(
            entry["recording"],
            [Channel(n, "state") for n in names],
            time_column=str(entry.get("time_column", "time")),
            optional=("state",),
        )
        x = torch.as_tensor(rec.data[1:])
        m, P = (t[1:] for t in est.tensors())
        ok = torch.isfinite(x).all(-1) & torch.isfinite(m).all(-1)
        if not bool(ok.any()):
            continue
        e = (m - x)[ok]
        ne = nees(x[ok], m[ok], P[ok])
        cv = coverage(x[ok], m[ok], P[ok], level=level)
        errs.append(e)
        nees_all.append(ne)
        inside.append(cv * ok.sum())
        per.append(
            {
                "recording": entry["recording"],
                "rmse": e.pow(2).mean(0).sqrt().tolist(),
                "nees": float(ne.mean()),
                f"coverage{int(level * 100)}": cv.tolist(),
                "steps": int(ok.sum()),
            }
        )
    if not per:
        raise DataError("no recording has logged truth to evaluate against", path=out)
    E = torch.cat(errs)
    steps = sum(p["steps"] for p in per)
    result = {
        "which": which,
        "states": names,
        "recordings": per,
        "pooled": {
            "rmse": E.pow(2).mean(0).sqrt().tolist(),
            "nees": float(torch.cat(nees_all).mean()),
            "nees_expected": len(names),
            f"coverage{int(level * 100)}": (torch.stack(inside).sum(0) / steps).tolist(),
            "steps": steps,
        },
    }
    atomic_write_text(target, json.dumps(result, indent=2, default=float) + "\n")
    return result
