"""Shared helpers for the GP tests: small seeded data sets and a one-thread fixture.

The GP tests run many tiny tensor operations; on a 2-core machine shared with other processes,
OpenMP's second thread makes those ~10x slower, so each GP test runs single-threaded (restored
afterwards).
"""

from __future__ import annotations

import pytest
import torch

DT = torch.float64


@pytest.fixture()
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def smooth_data(
    S: int = 80, noise_sd: float = 0.05, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``x (S, 2)``, ``y (S, 2)``: two smooth functions of two inputs plus Gaussian noise."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(S, 2, generator=g, dtype=DT)
    f = torch.stack([torch.sin(x[:, 0]) + 0.5 * x[:, 1], x[:, 0] * x[:, 1]], -1)
    return x, f + noise_sd * torch.randn(S, 2, generator=g, dtype=DT)


def query_points(P: int = 9, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 1.5 * torch.randn(P, 2, generator=g, dtype=DT)
