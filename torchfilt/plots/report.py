"""One figure per recording: states with bands and truth, measurements against their prediction, NIS."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from torch import Tensor

from torchfilt.exceptions import ShapeError
from torchfilt.filters import FilterResult, SmootherResult
from torchfilt.plots._util import label, names, to_numpy
from torchfilt.plots.estimates import Z95, nis_panel
from torchfilt.plots.style import MEASUREMENT_COLOR, PALETTE, TRUTH_COLOR, style

__all__ = ["plot_recording"]


def plot_recording(
    filtered: FilterResult,
    *,
    smoothed: SmootherResult | None = None,
    times: Tensor | np.ndarray | None = None,
    truth: Tensor | np.ndarray | None = None,
    measurements: Tensor | np.ndarray | None = None,
    state_names: Sequence[str] | None = None,
    state_units: Sequence[str | None] | None = None,
    measurement_names: Sequence[str] | None = None,
    measurement_units: Sequence[str | None] | None = None,
    time_unit: str | None = "s",
    title: str | None = None,
) -> Figure:
    """A report figure for one filtered (and optionally smoothed) recording.

    Rows: each state (filtered mean with its 95% band, the smoothed mean and band if given, truth
    dashed if known); each measurement channel (the readings as dots, the predicted measurement
    with the 95% band of the innovation covariance); the NIS against its 95% chi-square band.

    Args:
        filtered: the filter result of one sequence (``mean (T, n)``).
        smoothed: the smoother result of the same sequence, if any.
        times: times of the ``T`` steps, shape ``(T,)``; default ``0..T-1``.
        truth: true states ``(T, n)``; rows that are all NaN are not drawn.
        measurements: the measurements ``(T, m)`` (NaN where missing).
        state_names: names of the states (default ``x1..xn``).
        state_units: units per state, for axis labels.
        measurement_names: names of the measurement channels (default ``y1..ym``).
        measurement_units: units per measurement channel.
        time_unit: unit of ``times``.
        title: figure title.

    Returns:
        The figure.

    Raises:
        ShapeError: a result of more than one sequence, or names that are not one per state or
            measurement channel.
    """
    mean = to_numpy(filtered.mean)
    if mean.ndim != 2:
        raise ShapeError(
            f"filtered: plot_recording takes one sequence, mean (T, n); got {mean.shape}"
        )
    T, n = mean.shape
    m = filtered.innovation.shape[-1]
    t = np.arange(T, dtype=float) if times is None else to_numpy(times)
    sn, mn = (
        names("x", n, state_names, "state_names"),
        names("y", m, measurement_names, "measurement_names"),
    )
    su = list(state_units) if state_units is not None else [None] * n
    mu = list(measurement_units) if measurement_units is not None else [None] * m
    x_true = None if truth is None else to_numpy(truth)
    if x_true is not None and not np.isfinite(x_true).any():
        x_true = None
    with style():
        fig = Figure(figsize=(8.5, 1.9 * (n + m + 1) + 0.6))
        axes = list(fig.subplots(n + m + 1, 1, sharex=True, squeeze=False)[:, 0])
        sd = _sd(filtered.cov)
        sm = None if smoothed is None else (to_numpy(smoothed.mean), _sd(smoothed.cov))
        for i in range(n):
            ax = axes[i]
            _band(ax, t, mean[:, i], sd[:, i], PALETTE[0], 0.15, "filter")
            if sm is not None:
                _band(ax, t, sm[0][:, i], sm[1][:, i], PALETTE[1], 0.18, "smoother")
            if x_true is not None:
                ax.plot(
                    t, x_true[:, i], color=TRUTH_COLOR, linestyle="--", linewidth=1.1, label="truth"
                )
            ax.set_ylabel(label(sn[i], su[i]))
            ax.margins(x=0)
        ym, ysd = to_numpy(filtered.measurement_mean), _sd(filtered.innovation_cov)
        y = None if measurements is None else to_numpy(measurements)
        for j in range(m):
            ax = axes[n + j]
            _band(ax, t, ym[:, j], ysd[:, j], PALETTE[2], 0.18, "predicted")
            if y is not None:
                ax.plot(t, y[:, j], ".", color=MEASUREMENT_COLOR, markersize=3.5, label="measured")
            ax.set_ylabel(label(mn[j], mu[j]))
            ax.margins(x=0)
        nis_panel(axes[-1], filtered, t)
        axes[-1].legend(loc="upper right", ncols=2)
        axes[0].legend(loc="best", ncols=3)
        if m:
            axes[n].legend(loc="best", ncols=3)
        axes[-1].set_xlabel(label("time", time_unit))
        if title:
            fig.suptitle(title)
    return fig


def _sd(cov: Tensor) -> np.ndarray:
    """Standard deviations ``(T, d)`` from covariances ``(T, d, d)`` (negative rounding clipped)."""
    return np.sqrt(np.clip(np.diagonal(to_numpy(cov), axis1=-2, axis2=-1), 0, None))


def _band(
    ax: Axes, t: np.ndarray, mean: np.ndarray, sd: np.ndarray, color: str, alpha: float, name: str
) -> None:
    """A mean line with its 95% band, labelled ``name`` and ``name 95%``."""
    ax.fill_between(
        t,
        mean - Z95 * sd,
        mean + Z95 * sd,
        color=color,
        alpha=alpha,
        linewidth=0,
        label=f"{name} 95%",
    )
    ax.plot(t, mean, color=color, label=name)
