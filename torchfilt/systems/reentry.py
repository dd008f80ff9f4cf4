"""Re-entry vehicle tracking by a radar (Athans, Wishner & Bertolini 1968; Wei & Song 2013, sec. 3).

State ``x = [altitude (ft), velocity (ft/s), ballistic coefficient]``:

    dx1/dt = -x2
    dx2/dt = -exp(-gamma x1) x2^2 x3,   gamma = 5e-5
    dx3/dt = 0

sampled every ``DT = 1`` s with RK4 and ``SUBSTEPS = 10`` sub-steps; no process noise in the truth.
Radar range ``z = sqrt(M^2 + (x1 - H)^2) + v``, ``var(v) = 1e4``, ``M = H = 1e5`` ft.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from torchfilt.models import StateSpaceModel
from torchfilt.systems.simulate import Simulation, simulate

__all__ = [
    "DT",
    "GAMMA",
    "PRIOR_COV_DIAG",
    "PRIOR_MEAN",
    "RADAR_H",
    "RADAR_M",
    "RADAR_M_WRONG",
    "R_VAR",
    "STEPS",
    "SUBSTEPS",
    "X0_TRUE",
    "drift",
    "measurement",
    "model",
    "prior_cov",
    "simulate_truth",
    "transition",
]

GAMMA = 5e-5
RADAR_M = 1e5
RADAR_H = 1e5
RADAR_M_WRONG = 3e5
R_VAR = 1e4
DT = 1.0
SUBSTEPS = 10
STEPS = 60
X0_TRUE = (3e5, 2e4, 1e-3)
PRIOR_MEAN = (3e5, 2e4, 3e-5)
PRIOR_COV_DIAG = (1e6, 4e6, 1e-4)


def prior_cov(dtype: torch.dtype = torch.float64) -> Tensor:
    """The filter's prior covariance ``diag(1e6, 4e6, 1e-4)``."""
    return torch.diag(torch.tensor(PRIOR_COV_DIAG, dtype=dtype))


def drift(x: Tensor, u: Tensor | None = None, *, gamma: float = GAMMA) -> Tensor:
    """Continuous dynamics ``dx/dt``, ``(..., 3) -> (..., 3)`` (``gamma``: air-density decay)."""
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    return torch.stack([-x2, -torch.exp(-gamma * x1) * x2 * x2 * x3, torch.zeros_like(x3)], -1)


def transition(
    x: Tensor,
    u: Tensor | None = None,
    *,
    dt: float = DT,
    substeps: int = SUBSTEPS,
    gamma: float = GAMMA,
) -> Tensor:
    """One sampling period of the dynamics (RK4), ``(..., 3) -> (..., 3)``.

    Equal to ``rk4(drift, x, None, dt, substeps)`` (a nominal model may change ``gamma``),
    written out on the components: ``x3`` is
    constant, so only ``(x1, x2)`` are integrated (the same RK4 arithmetic with half the work).
    """
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    h = dt / substeps

    def acc(a: Tensor, v: Tensor) -> Tensor:  # dx2/dt at altitude a, velocity v
        return -torch.exp(-gamma * a) * v * v * x3

    for _ in range(substeps):
        k1a, k1v = -x2, acc(x1, x2)
        a2, v2 = x1 + 0.5 * h * k1a, x2 + 0.5 * h * k1v
        k2a, k2v = -v2, acc(a2, v2)
        a3, v3 = x1 + 0.5 * h * k2a, x2 + 0.5 * h * k2v
        k3a, k3v = -v3, acc(a3, v3)
        a4, v4 = x1 + h * k3a, x2 + h * k3v
        k4a, k4v = -v4, acc(a4, v4)
        x1 = x1 + (h / 6.0) * (k1a + 2.0 * k2a + 2.0 * k3a + k4a)
        x2 = x2 + (h / 6.0) * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return torch.stack([x1, x2, x3], dim=-1)


def measurement(
    x: Tensor, u: Tensor | None = None, *, M: float = RADAR_M, H: float = RADAR_H
) -> Tensor:
    """Radar range ``sqrt(M^2 + (x1 - H)^2)``, ``(..., 3) -> (..., 1)``."""
    return torch.sqrt(M * M + (x[..., :1] - H) ** 2)


def model(
    M: float = RADAR_M, *, Q: Tensor | None = None, dtype: torch.dtype = torch.float64
) -> StateSpaceModel:
    """The re-entry state-space model with radar offset ``M``.

    ``model()`` is CKF1's (true) model, ``model(RADAR_M_WRONG)`` CKF2's. ``Q`` defaults to zero
    (the truth has no process noise).
    """
    Q = torch.zeros(3, 3, dtype=dtype) if Q is None else Q
    R = torch.tensor([[R_VAR]], dtype=dtype)
    return StateSpaceModel(transition, functools.partial(measurement, M=M), Q=Q, R=R)


def simulate_truth(
    runs: int, *, steps: int = STEPS, seed: int = 0, dtype: torch.dtype = torch.float64
) -> Simulation:
    """Truth and radar measurements for ``runs`` Monte Carlo runs (same trajectory, new noise)."""
    gen = torch.Generator().manual_seed(seed)
    return simulate(
        model(dtype=dtype),
        steps,
        torch.tensor(X0_TRUE, dtype=dtype),
        batch_shape=(runs,),
        generator=gen,
    )
