"""Gas-phase reaction 2A -> B in a constant-volume reactor (Haseltine & Rawlings 2005; Liu et al. 2018).

    dPA/dt = -2 k1 PA^2,   dPB/dt = k1 PA^2,   k1 = 0.16

State ``x = [PA, PB]`` (partial pressures), sampled every ``DT = 0.1`` s with one Euler step:

    x_k = [PA - 2 k1 PA^2 DT,  PB + k1 PA^2 DT] + w,   w ~ N(0, diag(0.01^2, 0.01^2))
    z_k = PA + PB + v,                                 v ~ N(0, 0.01)      (total pressure)

(Liu, Zhang & Chu print ``- 2 k1`` in the second row of their eq. (31); that contradicts the ODE and
is a typo, spec ``cckf.md`` s.4.) Bounds ``0 <= x <= 100``. Two starts:

* ``"paper"``: truth ``x0 = [10, 1]``, filter prior ``N([5, 5], 36 I)`` (Liu et al., section 4);
* ``"hr"``: truth ``x0 = [3, 1]``, filter prior ``N([0.1, 4.5], 36 I)`` (Haseltine & Rawlings, Ind.
  Eng. Chem. Res. 44(8), 2005), where unconstrained filters are known to settle on a negative PA.

Pressures are in the papers' (unstated) pressure units, time in seconds.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.models import StateSpaceModel
from torchfilt.systems.simulate import Simulation, simulate

__all__ = [
    "DT",
    "K1",
    "LOWER",
    "PRIOR_COV_DIAG",
    "Q_DIAG",
    "R_VAR",
    "STARTS",
    "STEPS",
    "UPPER",
    "Start",
    "measurement",
    "model",
    "prior_cov",
    "prior_mean",
    "simulate_truth",
    "transition",
    "true_x0",
]

K1 = 0.16
DT = 0.1
STEPS = 100
Q_DIAG = (0.01**2, 0.01**2)
R_VAR = 0.01
PRIOR_COV_DIAG = (36.0, 36.0)
LOWER = (0.0, 0.0)
UPPER = (100.0, 100.0)

Start = Literal["paper", "hr"]
#: ``start -> (true x0, filter prior mean)``.
STARTS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "paper": ((10.0, 1.0), (5.0, 5.0)),
    "hr": ((3.0, 1.0), (0.1, 4.5)),
}


def _start(start: str) -> tuple[tuple[float, float], tuple[float, float]]:
    if start not in STARTS:
        raise InputError(f"start must be one of {sorted(STARTS)}, got {start!r}")
    return STARTS[start]


def transition(
    x: Tensor, u: Tensor | None = None, *, k1: float | Tensor = K1, dt: float = DT
) -> Tensor:
    """One Euler step of the reaction, ``(..., 2) -> (..., 2)``."""
    pa, pb = x[..., 0], x[..., 1]
    rate = k1 * pa * pa * dt
    return torch.stack([pa - 2.0 * rate, pb + rate], dim=-1)


def measurement(x: Tensor, u: Tensor | None = None) -> Tensor:
    """Total pressure ``PA + PB``, ``(..., 2) -> (..., 1)``."""
    return x.sum(-1, keepdim=True)


def model(dtype: torch.dtype = torch.float64) -> StateSpaceModel:
    """The 2A -> B state-space model with the papers' noise levels."""
    Q = torch.diag(torch.tensor(Q_DIAG, dtype=dtype))
    R = torch.tensor([[R_VAR]], dtype=dtype)
    return StateSpaceModel(transition, measurement, Q=Q, R=R)


def prior_mean(start: Start = "paper", dtype: torch.dtype = torch.float64) -> Tensor:
    """The filter's initial mean for ``start``."""
    return torch.tensor(_start(start)[1], dtype=dtype)


def true_x0(start: Start = "paper", dtype: torch.dtype = torch.float64) -> Tensor:
    """The true initial state for ``start``."""
    return torch.tensor(_start(start)[0], dtype=dtype)


def prior_cov(dtype: torch.dtype = torch.float64) -> Tensor:
    """The filter's initial covariance ``diag(36, 36)``."""
    return torch.diag(torch.tensor(PRIOR_COV_DIAG, dtype=dtype))


def simulate_truth(
    runs: int,
    *,
    start: Start = "paper",
    steps: int = STEPS,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> Simulation:
    """Monte Carlo truth and measurements: ``runs`` independent noise draws from the fixed ``x0``.

    Returns:
        A :class:`~torchfilt.systems.Simulation` with ``states (runs, steps, 2)`` and
        ``measurements (runs, steps, 1)``.
    """
    gen = torch.Generator().manual_seed(seed)
    return simulate(model(dtype), steps, true_x0(start, dtype), batch_shape=(runs,), generator=gen)
