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
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError
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
    "TrainingRecord",
    "drift",
    "measurement",
    "model",
    "prior_cov",
    "record_training_data",
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
    gamma: float | Tensor = GAMMA,
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


#: Largest velocity (ft/s) a recorded state may have: 2.5x the entry speed. Beyond it the state is
#: in the runaway of a negative ballistic coefficient (the dynamics blow up in finite time).
MAX_VELOCITY = 5e4
#: Sub-steps of the reference integration that checks each recorded step.
CHECK_SUBSTEPS = 40
#: A step is rejected when the 10- and 40-sub-step RK4 results differ by more than this fraction of
#: the step's increment (altitude and velocity): the 1 s step is not resolved there (stiff drag).
CHECK_RTOL = 1e-2


class TrainingRecord(NamedTuple):
    """Logged re-entry data for learning ``f`` and ``h``.

    Attributes:
        states: recordings ``x_0..x_{T_i}``, a list of ``(T_i + 1, 3)`` tensors (true states).
        measurements: noisy radar range at each recorded state, a list of ``(T_i + 1, 1)``.
        initial: the initial states drawn, ``(R, 3)`` (including recordings that produced no
            transition).
        rejected: number of recordings cut short, by reason: ``"non-finite"``, ``"ground"``
            (altitude below 0), ``"velocity"`` (negative, or above :data:`MAX_VELOCITY`),
            ``"integrator"`` (see :data:`CHECK_RTOL`).
    """

    states: list[Tensor]
    measurements: list[Tensor]
    initial: Tensor
    rejected: dict[str, int]

    @property
    def pairs(self) -> int:
        """Number of transition pairs ``(x_k, x_{k+1})``."""
        return sum(int(s.shape[0]) - 1 for s in self.states)


def record_training_data(
    samples: int = 5000,
    seed: int = 0,
    *,
    horizon: int = STEPS,
    batch: int = 64,
    x0_mean: Tensor | None = None,
    x0_cov: Tensor | None = None,
    M: float = RADAR_M,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> TrainingRecord:
    """Record physically plausible re-entry trajectories that cover where the filter looks.

    Sampling: initial states are drawn from the filter's prior ``N(PRIOR_MEAN, diag(1e6, 4e6,
    1e-4))`` (so the ballistic coefficient spreads with sd 0.01 around 3e-5, about half of the draws
    negative), and each is propagated with the true dynamics (:func:`transition`) for up to
    ``horizon`` steps. The trajectories therefore fan out over the region the filter's cubature
    points visit, rather than filling a box (a box puts stiff, unphysical combinations of low
    altitude, high speed and large drag into the data, where the integrator returns garbage).

    Every step is checked before it is recorded; the recording stops at the first step that fails
    (the rest of that trajectory is discarded and counted in ``rejected``):

    * the next state is finite;
    * altitude stays >= 0 (the vehicle reached the ground);
    * velocity stays in ``[0, MAX_VELOCITY]`` (a negative ballistic coefficient accelerates the
      vehicle until the dynamics blow up: those targets are absurd);
    * the 1 s step is resolved: RK4 with 10 and with 40 sub-steps agree to ``CHECK_RTOL`` of the
      step's increment.

    Recordings are drawn in batches until ``samples`` transition pairs are collected; the last
    recording is shortened so that the total is exactly ``samples``. Each recorded state gets a
    radar range ``sqrt(M^2 + (x1 - H)^2) + v``, ``v ~ N(0, R_VAR)``.

    Args:
        samples: number of transition pairs to record.
        seed: seeds the initial states and the measurement noise.
        horizon: longest recording, in steps.
        batch: trajectories simulated together.
        x0_mean: mean of the initial states (default :data:`PRIOR_MEAN`).
        x0_cov: covariance of the initial states (default :func:`prior_cov`).
        M: radar horizontal offset of the recorded measurements.
        dtype: floating dtype.
        device: simulate on this device (e.g. ``"cuda"`` for millions of samples); random draws
            and the returned tensors stay on the CPU, so the record does not depend on it beyond
            rounding.

    Returns:
        A :class:`TrainingRecord` with ``samples`` pairs.
    """
    if samples < 1 or horizon < 1 or batch < 1:
        raise InputError("samples, horizon and batch must be positive")
    gen = torch.Generator().manual_seed(seed)
    mean = torch.tensor(PRIOR_MEAN, dtype=dtype) if x0_mean is None else x0_mean.to(dtype)
    cov = prior_cov(dtype) if x0_cov is None else x0_cov.to(dtype)
    L = torch.linalg.cholesky(cov)
    states: list[Tensor] = []
    meas: list[Tensor] = []
    initial: list[Tensor] = []
    rejected = {"non-finite": 0, "ground": 0, "velocity": 0, "integrator": 0}
    total = 0
    while total < samples:
        x = mean + torch.randn(batch, 3, generator=gen, dtype=dtype) @ L.T
        initial.append(x)
        x = x.to(device) if device is not None else x
        traj = [x]
        alive = torch.ones(batch, dtype=torch.bool, device=x.device)
        length = torch.zeros(batch, dtype=torch.long, device=x.device)
        for _ in range(horizon):
            with torch.no_grad():
                nxt = transition(x)
                ref = transition(x, substeps=CHECK_SUBSTEPS)
            finite = torch.isfinite(nxt).all(-1) & torch.isfinite(ref).all(-1)
            ground = nxt[:, 0] < 0
            speed = (nxt[:, 1] < 0) | (nxt[:, 1] > MAX_VELOCITY)
            err = ((nxt - ref).abs() / ((ref - x).abs() + 1e-12))[:, :2].amax(-1)
            integ = ~(err <= CHECK_RTOL)
            for name, flag in (
                ("non-finite", ~finite),
                ("ground", finite & ground),
                ("velocity", finite & ~ground & speed),
                ("integrator", finite & ~ground & ~speed & integ),
            ):
                rejected[name] += int((alive & flag).sum())
            alive = alive & finite & ~ground & ~speed & ~integ
            length = length + alive.long()
            x = torch.where(alive.unsqueeze(-1), nxt, x)
            traj.append(x)
            if not bool(alive.any()):
                break
        stacked = torch.stack(traj, 1).cpu()  # (batch, steps + 1, 3)
        length = length.cpu()
        for i in range(batch):
            steps = int(length[i])
            if steps < 1 or total >= samples:
                continue
            steps = min(steps, samples - total)
            rec = stacked[i, : steps + 1]
            noise = torch.randn(steps + 1, 1, generator=gen, dtype=dtype) * R_VAR**0.5
            states.append(rec)
            meas.append(measurement(rec, M=M) + noise)
            total += steps
    return TrainingRecord(states, meas, torch.cat(initial), rejected)
