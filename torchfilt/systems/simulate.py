"""Drawing trajectories and measurements from any state-space model, in batch."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import ShapeError
from torchfilt.models import ConditionalModel, StateSpaceModel

__all__ = ["Simulation", "simulate"]


class Simulation(NamedTuple):
    """Simulated data.

    Attributes:
        initial: initial states ``x_0``, shape ``(..., n)``.
        states: states ``x_1..x_T``, shape ``(..., T, n)``.
        measurements: measurements ``y_1..y_T``, shape ``(..., T, m)``.
    """

    initial: Tensor
    states: Tensor
    measurements: Tensor


def _sample(
    side: ConditionalModel, x: Tensor, u: Tensor | None, step: int, gen: torch.Generator | None
) -> Tensor:
    pred = side.predict(x.unsqueeze(-2), None if u is None else u.unsqueeze(-2))
    mean = pred.mean.squeeze(-2)
    cov = side.noise_cov(step) if side.time_varying_noise else side.noise_cov()
    cov = None if cov is None else cov.to(mean)
    if pred.var is not None:
        v = torch.diag_embed(pred.var.squeeze(-2))
        cov = v if cov is None else cov + v
    if pred.cov is not None:
        c = pred.cov.squeeze(-3)
        cov = c if cov is None else cov + c
    if cov is None or not bool(cov.any()):
        return mean
    evals, evecs = torch.linalg.eigh(0.5 * (cov + cov.mT))
    root = evecs * evals.clamp_min(0).sqrt().unsqueeze(-2)
    z = torch.randn(mean.shape, generator=gen, dtype=mean.dtype, device=mean.device)
    return mean + (root @ z.unsqueeze(-1)).squeeze(-1)


@torch.no_grad()
def simulate(
    model: StateSpaceModel,
    steps: int,
    x0: Tensor,
    *,
    P0: Tensor | None = None,
    u: Tensor | None = None,
    batch_shape: tuple[int, ...] = (),
    generator: torch.Generator | None = None,
) -> Simulation:
    """Simulate ``x_t = f(x_{t-1}, u_t) + w``, ``y_t = h(x_t, u_t) + v`` for ``t = 0..T-1``.

    ``x_{-1}`` is the initial state and ``u_t`` the input row ``u[..., t, :]``: the input
    convention of :mod:`torchfilt.filters` (a filter started at ``initial`` with ``u`` runs the
    same steps). Noise comes from the model's additive covariances plus any
    per-point variance it reports (a GP model's predictive variance).

    Args:
        model: the model to simulate.
        steps: number of steps ``T``.
        x0: initial mean, shape ``(..., n)``.
        P0: if given, ``x_0 ~ N(x0, P0)`` (``(..., n, n)``); else ``x_0 = x0``.
        u: inputs, shape ``(..., T, nu)``.
        batch_shape: extra leading batch shape (Monte Carlo runs).
        generator: random generator, for reproducibility.

    Returns:
        A :class:`Simulation` with ``initial (..., n)``, ``states (..., T, n)`` and
        ``measurements (..., T, m)``.

    Raises:
        ShapeError: ``x0`` is not ``(..., n)``, or ``u`` has not ``T`` steps.
    """
    n = model.state_dim
    x0 = torch.as_tensor(x0)
    if x0.shape[-1] != n:
        raise ShapeError(f"x0: expected shape (..., {n}), got {tuple(x0.shape)}")
    if u is not None and u.shape[-2] != steps:
        raise ShapeError(f"u: expected shape (..., {steps}, nu), got {tuple(u.shape)}")
    batch = torch.broadcast_shapes(tuple(batch_shape) + x0.shape[:-1])
    x = x0.expand(*batch, n).clone()
    if P0 is not None:
        L = torch.linalg.cholesky(torch.as_tensor(P0, dtype=x.dtype, device=x.device))
        z = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        x = x + (L @ z.unsqueeze(-1)).squeeze(-1)
    initial = x
    xs, ys = [], []
    for t in range(steps):
        ut = None if u is None else u[..., t, :].to(x).expand(*batch, u.shape[-1])
        x = _sample(model.transition, x, ut, t, generator)
        ys.append(_sample(model.measurement, x, ut, t, generator))
        xs.append(x)
    return Simulation(initial, torch.stack(xs, -2), torch.stack(ys, -2))
