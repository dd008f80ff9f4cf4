"""The exact E-step of a linear-Gaussian model in :func:`~torchfilt.training.fit_em`: the
closed-form Kalman filter and RTS smoother, in the square-root form where the standard one fails.

The standard (covariance) form is the fast one, and the one EM uses. With a nearly singular
``Q`` and a mode of ``A`` outside the unit circle, its rounding errors can make the filtered
covariance indefinite and then grow without bound: on the robot-arm log of
``scripts/bench_real_logs.py`` (4 states, ``Q`` eigenvalues from 1e-8, a pole at 1.27, 546
steps) the smallest eigenvalue of the filtered covariance reached -6e50, the log-likelihood read
-12555 where the square-root form gives 42.4, and the smoothed moments were NaN. The next
M-step then produced a non-finite ``A``. The filter says so with a
:class:`~torchfilt.exceptions.PrecisionWarning`; :func:`exact_smoother` makes the same check
(:func:`~torchfilt.filters.kalman_checks.precision_problems`) and, where the covariance lost
definiteness or the result is not finite, runs the square-root form (``sqrt=True``), which keeps
the covariance definite, and returns that. Where the standard form is sound nothing else runs (its
definiteness is checked again: one batched Cholesky over the steps).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from torchfilt.exceptions import PrecisionWarning
from torchfilt.filters import SmootherResult, kalman_smoother
from torchfilt.filters.kalman_checks import precision_problems, warn_precision
from torchfilt.models import StateSpaceModel

__all__ = ["exact_smoother"]


@torch.no_grad()
def exact_smoother(
    model: StateSpaceModel, y: Tensor, u: Tensor | None, x0: Tensor, P0: Tensor
) -> SmootherResult:
    """The Kalman filter and RTS smoother of ``model``: the standard form, or the square-root
    form where the standard one warned of lost definiteness or ended non-finite.

    Args:
        model: a linear-Gaussian model (one :func:`~torchfilt.filters.kalman_filter` takes).
        y: measurements ``(..., T, m)`` (NaN: missing).
        u: inputs ``(..., T, nu)`` or ``None``.
        x0: prior means ``(..., n)``.
        P0: prior covariances ``(..., n, n)``.

    Returns:
        The :class:`~torchfilt.filters.SmootherResult` (means ``(..., T, n)``, covariances
        ``(..., T, n, n)``). The standard form's other warnings pass as they come; its
        ``PrecisionWarning`` only where it is kept (the means' rounding, which the square-root
        form does not help).
    """
    with warnings.catch_warnings():  # its definiteness is checked below; the rest passes
        warnings.filterwarnings("ignore", category=PrecisionWarning)
        sm = kalman_smoother(model, y, u, x0=x0, P0=P0)
    finite = bool(torch.isfinite(sm.filtered.log_likelihood).all() & torch.isfinite(sm.mean).all())
    problems = precision_problems(sm.filtered)
    if finite and problems[0] == 0.0:  # the means' rounding, if any, is still said
        warn_precision(sm.filtered, sqrt=False, stacklevel=2, problems=problems)
        return sm
    return kalman_smoother(model, y, u, x0=x0, P0=P0, sqrt=True)
