"""Small helpers shared by the plotting functions."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from torchfilt.exceptions import ShapeError


def to_numpy(x: Tensor | np.ndarray | Sequence[float]) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=float)


def label(name: str, unit: str | None) -> str:
    return f"{name} [{unit}]" if unit else name


def names(prefix: str, n: int, given: Sequence[str] | None, arg: str) -> list[str]:
    """``given`` (checked to hold ``n`` names; ``arg`` names the argument) or ``prefix1..n``."""
    if given is None:
        return [f"{prefix}{i + 1}" for i in range(n)]
    if len(given) != n:
        raise ShapeError(f"{arg}: expected {n} names, got {len(given)}: {list(given)}")
    return list(given)
