"""Estimate files: per-step mean, standard deviation, correlations and NIS, as CSV.

Columns: ``time``; for each state ``{name}_mean`` and ``{name}_sd``; for each pair of states
``corr_{a}_{b}`` (so the full covariance can be rebuilt); then ``nis`` and ``nis_dof`` when the
file holds filter (not smoother) output.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchfilt.io.atomic import atomic_write_text
from torchfilt.io.errors import DataError

__all__ = ["Estimates", "read_estimates", "write_estimates"]


@dataclass
class Estimates:
    """Estimates of one recording.

    Attributes:
        time: ``(T,)``.
        mean: ``(T, n)``.
        cov: ``(T, n, n)``.
        state_names: the ``n`` state names.
        nis: ``(T,)`` normalised innovation squared, or ``None``.
        nis_dof: ``(T,)`` degrees of freedom of the NIS, or ``None``.
    """

    time: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    state_names: list[str]
    nis: np.ndarray | None = None
    nis_dof: np.ndarray | None = None

    def tensors(self, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """``(mean (T, n), cov (T, n, n))`` as tensors."""
        return torch.as_tensor(self.mean, dtype=dtype), torch.as_tensor(self.cov, dtype=dtype)


def _columns(names: Sequence[str], with_nis: bool) -> list[str]:
    cols = ["time"]
    for s in names:
        cols += [f"{s}_mean", f"{s}_sd"]
    n = len(names)
    cols += [f"corr_{names[i]}_{names[j]}" for i in range(n) for j in range(i + 1, n)]
    if with_nis:
        cols += ["nis", "nis_dof"]
    return cols


def write_estimates(path: str | Path, est: Estimates) -> Path:
    """Write estimates as CSV, atomically (17 significant digits)."""
    T, n = est.mean.shape
    sd = np.sqrt(np.clip(np.diagonal(est.cov, axis1=-2, axis2=-1), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = est.cov / (sd[:, :, None] * sd[:, None, :])
    corr = np.where(np.isfinite(corr), corr, 0.0)  # undefined where a standard deviation is 0
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    with_nis = est.nis is not None
    w.writerow(_columns(est.state_names, with_nis))
    iu = np.triu_indices(n, 1)

    def fmt(v: float) -> str:
        return "nan" if not math.isfinite(v) else f"{v:.17g}"

    for t in range(T):
        row = [est.time[t]]
        for i in range(n):
            row += [est.mean[t, i], sd[t, i]]
        row += list(corr[t][iu])
        if with_nis:
            assert est.nis is not None and est.nis_dof is not None
            row += [est.nis[t], est.nis_dof[t]]
        w.writerow([fmt(float(v)) for v in row])
    return atomic_write_text(path, buf.getvalue())


def read_estimates(path: str | Path) -> Estimates:
    """Read an estimates CSV written by :func:`write_estimates` (or ``torchfilt filter``)."""
    path = Path(path)
    if not path.is_file():
        raise DataError("estimates file not found", path=path)
    try:
        rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))
    except UnicodeDecodeError:
        raise DataError("is not a CSV estimates file", path=path) from None
    if not rows or not rows[0] or rows[0][0] != "time":
        raise DataError("is not an estimates file (first column must be 'time')", path=path, line=1)
    header = rows[0]
    names = [h[: -len("_mean")] for h in header if h.endswith("_mean")]
    with_nis = "nis" in header
    want = _columns(names, with_nis)
    if header != want:
        raise DataError(f"unexpected columns {header}; expected {want}", path=path, line=1)
    try:
        data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=np.float64).reshape(
            -1, len(header)
        )
    except ValueError as e:
        raise DataError(f"unreadable value ({e})", path=path) from None
    n = len(names)
    T = data.shape[0]
    mean = data[:, 1 : 1 + 2 * n : 2]
    sd = data[:, 2 : 2 + 2 * n : 2]
    corr = np.repeat(np.eye(n)[None], T, axis=0)
    iu = np.triu_indices(n, 1)
    k = 1 + 2 * n
    for c, (i, j) in enumerate(zip(*iu, strict=True)):
        corr[:, i, j] = corr[:, j, i] = data[:, k + c]
    cov = corr * sd[:, :, None] * sd[:, None, :]
    nis = data[:, -2] if with_nis else None
    dof = data[:, -1] if with_nis else None
    return Estimates(data[:, 0], mean, cov, names, nis, dof)
