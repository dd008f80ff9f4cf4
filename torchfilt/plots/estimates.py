"""Estimates with 95% bands, truth and measurements; NIS against its chi-square band."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from torch import Tensor

from torchfilt.exceptions import ShapeError
from torchfilt.filters import FilterResult, SmootherResult, nis
from torchfilt.numerics import chi2_quantile
from torchfilt.plots._util import label, names, to_numpy
from torchfilt.plots.style import MEASUREMENT_COLOR, PALETTE, TRUTH_COLOR, style

__all__ = ["nis_panel", "plot_estimates", "plot_nis"]

#: two-sided 95% band of a Gaussian
Z95 = 1.959963984540054


def plot_estimates(
    result: FilterResult | SmootherResult,
    *,
    times: Tensor | np.ndarray | None = None,
    truth: Tensor | np.ndarray | None = None,
    measurements: Tensor | np.ndarray | None = None,
    measured_states: dict[int, int] | None = None,
    state_names: Sequence[str] | None = None,
    units: Sequence[str | None] | None = None,
    time_unit: str | None = "s",
    title: str | None = None,
    filtered_too: bool = True,
) -> Figure:
    """One row per state: estimate, 95% band, truth and measurements; with truth, its errors.

    With ``truth`` a second column shows the error ``estimate - truth`` against the 95% band of
    the estimate, and the legend gives the fraction of steps inside the band.

    Args:
        result: a single sequence's filter or smoother result (``mean (T, n)``, ``cov (T, n, n)``).
        times: sample times ``(T,)``; default ``0..T-1``.
        truth: true states ``(T, n)``, drawn dashed when given.
        measurements: measurements ``(T, m)``, drawn as dots on the panels of the states they
            measure directly (see ``measured_states``).
        measured_states: ``{measurement index: state index}`` for measurements that observe a
            state directly.
        state_names: names of the states (default ``x1..xn``).
        units: units per state, for axis labels.
        time_unit: unit of ``times``.
        title: figure title.
        filtered_too: for a smoother result, also draw the filtered mean (thin line).

    Returns:
        The figure.

    Raises:
        ShapeError: a result of more than one sequence, or ``state_names`` not ``n`` names.
    """
    smoothed = isinstance(result, SmootherResult)
    mean = to_numpy(result.mean)
    cov = to_numpy(result.cov)
    if mean.ndim != 2:
        raise ShapeError(f"result: plot_estimates takes one sequence (T, n), got {mean.shape}")
    T, n = mean.shape
    t = np.arange(T, dtype=float) if times is None else to_numpy(times)
    sd = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))
    sn = names("x", n, state_names, "state_names")
    un = list(units) if units is not None else [None] * n
    x_true = None if truth is None else to_numpy(truth)
    y = None if measurements is None else to_numpy(measurements)
    with style():
        cols = 2 if x_true is not None else 1
        fig = Figure(figsize=(6.0 + 4.0 * (cols - 1), 2.1 * n + 0.5))
        axes = fig.subplots(n, cols, sharex=True, squeeze=False)
        what = "smoothed" if smoothed else "filtered"
        band = Z95 * sd
        for i in range(n):
            ax = axes[i, 0]
            c = PALETTE[0]
            ax.fill_between(
                t,
                mean[:, i] - band[:, i],
                mean[:, i] + band[:, i],
                color=c,
                alpha=0.18,
                linewidth=0,
                label="95% band",
            )
            ax.plot(t, mean[:, i], color=c, label=f"{what} mean")
            if smoothed and filtered_too:
                fm = to_numpy(result.filtered.mean)  # type: ignore[union-attr]
                ax.plot(
                    t, fm[:, i], color=PALETTE[1], linewidth=0.9, alpha=0.9, label="filtered mean"
                )
            if x_true is not None:
                ax.plot(
                    t, x_true[:, i], color=TRUTH_COLOR, linestyle="--", linewidth=1.1, label="truth"
                )
            if y is not None and measured_states:
                for j, s in measured_states.items():
                    if s == i:
                        ax.plot(
                            t,
                            y[:, j],
                            ".",
                            color=MEASUREMENT_COLOR,
                            markersize=3,
                            label="measurement",
                        )
            ax.set_ylabel(label(sn[i], un[i]))
            ax.margins(x=0)
            if x_true is not None:
                ax = axes[i, 1]
                err = mean[:, i] - x_true[:, i]
                inside = float(np.mean(np.abs(err) <= band[:, i]))
                ax.fill_between(
                    t, -band[:, i], band[:, i], color=c, alpha=0.18, linewidth=0, label="95% band"
                )
                ax.axhline(0.0, color=TRUTH_COLOR, linewidth=0.8)
                ax.plot(t, err, color=c, label=f"error ({inside:.0%} inside band)")
                ax.set_ylabel(label(f"error {sn[i]}", un[i]))
                ax.margins(x=0)
                ax.legend(loc="upper right")
        axes[0, 0].legend(loc="best", ncols=2)
        for ax in axes[-1]:
            ax.set_xlabel(label("time", time_unit))
        if x_true is not None:
            axes[0, 0].set_title("estimate")
            axes[0, 1].set_title("estimate - truth")
        if title:
            fig.suptitle(title)
    return fig


def nis_panel(ax: Axes, result: FilterResult, t: np.ndarray, level: float = 0.95) -> float:
    """Draw NIS points and the chi-square band on ``ax``; return the fraction inside the band."""
    value, dof = nis(result)
    v, k = to_numpy(value), to_numpy(dof)
    if v.ndim != 1:
        raise ShapeError(f"result: plot_nis takes one sequence, got NIS of shape {v.shape}")
    seen = k > 0
    lo = np.full_like(v, np.nan)
    hi = np.full_like(v, np.nan)
    if seen.any():
        a = (1.0 - level) / 2.0
        lo[seen] = to_numpy(chi2_quantile(a, torch.as_tensor(k[seen])))
        hi[seen] = to_numpy(chi2_quantile(1.0 - a, torch.as_tensor(k[seen])))
    inside = (
        float(np.mean((v[seen] >= lo[seen]) & (v[seen] <= hi[seen])))
        if seen.any()
        else float("nan")
    )
    ax.fill_between(
        t,
        lo,
        hi,
        step="mid",
        color=PALETTE[2],
        alpha=0.18,
        linewidth=0,
        label=f"{level:.0%} chi-square band",
    )
    ax.plot(
        t[seen], v[seen], ".", color=PALETTE[0], markersize=4, label=f"NIS ({inside:.0%} inside)"
    )
    ax.set_yscale("log")
    ax.set_ylabel("NIS")
    ax.margins(x=0)
    return inside


def plot_nis(
    result: FilterResult,
    *,
    times: Tensor | np.ndarray | None = None,
    level: float = 0.95,
    time_unit: str | None = "s",
    title: str | None = "Normalised innovation squared",
) -> Figure:
    """NIS per step against the chi-square band of the given level (per-step degrees of freedom).

    Args:
        result: a single sequence's filter result.
        times: sample times ``(T,)``.
        level: probability mass of the band (default 95%).
        time_unit: unit of ``times``.
        title: figure title.

    Returns:
        The figure; the legend reports the fraction of steps inside the band.

    Raises:
        ShapeError: a result of more than one sequence.
    """
    T = result.innovation.shape[-2]
    t = np.arange(T, dtype=float) if times is None else to_numpy(times)
    with style():
        fig = Figure(figsize=(8.0, 2.6))
        ax = fig.subplots()
        nis_panel(ax, result, t, level)
        ax.set_xlabel(label("time", time_unit))
        fig.legend(loc="outside upper right", ncols=2)
        if title:
            fig.suptitle(title, x=0.01, ha="left")
    return fig
