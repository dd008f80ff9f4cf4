"""The noisy pendulum of Särkkä & Svensson, "Bayesian Filtering and Smoothing" (2nd ed.), ex. 5.1.

x_k = [x1 + dt x2,  x2 - g dt sin(x1)] + q,   Q = qc [[dt^3/3, dt^2/2], [dt^2/2, dt]]
y_k = sin(x1_k) + r,                          r ~ N(0, R)
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchfilt.models import StateSpaceModel

__all__ = ["model"]


def model(
    dt: float = 0.01,
    g: float = 9.81,
    qc: float = 0.01,
    R: float = 0.1,
    dtype: torch.dtype = torch.float64,
) -> StateSpaceModel:
    """Pendulum state-space model with the book's constants by default."""

    def f(x: Tensor) -> Tensor:
        return torch.stack(
            [x[..., 0] + dt * x[..., 1], x[..., 1] - g * dt * torch.sin(x[..., 0])], -1
        )

    def h(x: Tensor) -> Tensor:
        return torch.sin(x[..., :1])

    Q = qc * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=dtype)
    return StateSpaceModel(f, h, Q=Q, R=torch.tensor([[R]], dtype=dtype))
