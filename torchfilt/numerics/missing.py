"""The missing-data rule, shared by every estimator that takes measurements.

**A measurement component that is not finite (NaN, +inf or -inf) is missing**: it is not used,
neither in the update nor in the likelihood, and the step is a prediction for that component.
The CKF (:class:`~torchfilt.CKF`), the constrained CKF and the DMC predictor
(:class:`~torchfilt.dmc.OpenLoopPredictor`) all apply this rule, so one ``inf`` never turns the
estimates non-finite. Their innovations are NaN where a component was missing.

Inputs (``u``, ``du``, ``dv``), states and prior means cannot be missing: a non-finite value there
is an :class:`~torchfilt.exceptions.InputError`. (A file reader may be stricter: see
``data/FORMAT.md`` for what a CSV cell may contain.)
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["observed"]


def observed(y: Tensor) -> Tensor:
    """Which measurement components are observed under the missing-data rule: the finite ones.

    Args:
        y: measurements, shape ``(..., m)``.

    Returns:
        Bool tensor of ``y``'s shape ``(..., m)``, ``True`` where the component is used.
    """
    return torch.isfinite(y)
