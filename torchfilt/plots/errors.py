"""Monte Carlo error curves: absolute error over time per filter, one panel per state."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from torch import Tensor

from torchfilt.exceptions import ShapeError
from torchfilt.plots._util import label, names, to_numpy
from torchfilt.plots.style import PALETTE, style

__all__ = ["plot_errors"]


def plot_errors(
    errors: Mapping[str, Tensor | np.ndarray],
    *,
    times: Tensor | np.ndarray | None = None,
    state_names: Sequence[str] | None = None,
    units: Sequence[str | None] | None = None,
    time_unit: str | None = "s",
    log: bool = True,
    title: str | None = None,
) -> Figure:
    """Absolute estimation error over time, like the figures of filter papers.

    Each entry is one filter's signed or absolute errors ``(runs, T, n)`` (or ``(T, n)``); the
    curve is the root-mean-square over runs at each time, and the shaded band spans the 25th to
    75th percentile of the absolute error over runs. A run that fails (non-finite estimate) counts
    up to the step where it fails; the legend reports how many runs failed, and a curve ends
    where no run is left.

    Args:
        errors: ``{filter name: errors}``, each of shape ``(runs, T, n)`` or ``(T, n)``.
        times: sample times ``(T,)``.
        state_names: names of the states.
        units: units per state.
        time_unit: unit of ``times``.
        log: logarithmic error axis.
        title: figure title.

    Returns:
        The figure.

    Raises:
        ShapeError: error arrays of different ``(T, n)``, or ``state_names`` not ``n`` names.
    """
    arrays = {k: np.abs(to_numpy(v)) for k, v in errors.items()}
    arrays = {k: (v[None] if v.ndim == 2 else v) for k, v in arrays.items()}
    shapes = {v.shape[1:] for v in arrays.values()}
    if len(shapes) != 1:
        raise ShapeError(f"errors: all error arrays must share (T, n); got {shapes}")
    T, n = next(iter(shapes))
    t = np.arange(T, dtype=float) if times is None else to_numpy(times)
    sn = names("x", n, state_names, "state_names")
    un = list(units) if units is not None else [None] * n
    with style():
        fig = Figure(figsize=(8.0, 2.2 * n + 0.5))
        axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
        for j, (name, e) in enumerate(arrays.items()):
            alive = np.isfinite(e).all(axis=2)  # (runs, T)
            c = PALETTE[j % len(PALETTE)]
            failed = int((~alive.all(axis=1)).sum())
            tag = f"{name}" + (f" ({failed}/{alive.shape[0]} runs failed)" if failed else "")
            good = np.where(alive[..., None], e, np.nan)
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN time steps
                rms = np.sqrt(np.nanmean(good**2, axis=0))
                q25, q75 = np.nanpercentile(good, [25, 75], axis=0)
            for i, ax in enumerate(axes):
                ax.plot(t, rms[:, i], color=c, label=tag if i == 0 else None)
                if e.shape[0] > 1:
                    ax.fill_between(t, q25[:, i], q75[:, i], color=c, alpha=0.15, linewidth=0)
        for i, ax in enumerate(axes):
            ax.set_ylabel(label(f"|error| {sn[i]}", un[i]))
            if log:
                ax.set_yscale("log")
            ax.margins(x=0)
        axes[0].legend(loc="best")
        axes[-1].set_xlabel(label("time", time_unit))
        if title:
            fig.suptitle(title)
    return fig
