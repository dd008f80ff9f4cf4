"""Plots: filter estimates with credible bands, NIS consistency, and Monte Carlo error curves.

All functions return a matplotlib ``Figure`` and draw with :func:`style`, a light, readable house
style (colour-blind-safe palette, light grid, no top/right spines).
"""

from torchfilt.plots.errors import plot_errors
from torchfilt.plots.estimates import plot_estimates, plot_nis
from torchfilt.plots.report import plot_recording
from torchfilt.plots.style import PALETTE, style

__all__ = ["PALETTE", "plot_errors", "plot_estimates", "plot_nis", "plot_recording", "style"]
