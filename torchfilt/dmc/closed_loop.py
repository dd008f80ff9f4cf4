"""Closed-loop simulation of DMC on a plant sampled exactly from its transfer functions.

The plant is the superposition of exactly sampled step responses (zero-order-hold inputs; fractional
dead times exact) over the whole simulation, with no truncation, so it differs from the controller's
step-response model (horizon ``N``) wherever the true response has not settled by ``N``:

    y(k) = c * ( sum_{i=1}^{k} S^u_i du(k-i) + sum_{i=1}^{k} S^v_i dv(k-i) ) + noise(k)

with the plant at rest before ``k = 0`` and ``c`` an output scale (the paper's model mismatch ``0.9``).

One closed-loop sample ``k``: measure ``y(k)`` and ``v(k)``; the predictor consumes ``y(k)``,
``du(k-1)``, ``dv(k)``; the target layer maps the steady-state prediction ``y^ol(k+N|k)`` and
``u(k-1)`` to ``(y_t, u_t)``; the controller returns ``du(k)``; ``u(k) = u(k-1) + du(k)`` is held over
``[k, k+1)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.dmc.controller import DMCController
from torchfilt.dmc.predictor import OpenLoopPredictor
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.dmc.target import SteadyStateTarget
from torchfilt.dmc.transfer import TransferEntry
from torchfilt.exceptions import InputError, ShapeError

__all__ = ["ClosedLoopResult", "SampledPlant", "run_closed_loop"]


class SampledPlant:
    """A plant given by transfer-function matrices, sampled exactly over ``steps`` samples.

    Args:
        Gu: MV channels (rows of :class:`FOPDT`/:class:`IPDT`/``None``).
        Gv: DV channels, or ``None``.
        dt: sampling period.
        steps: number of samples the plant will be simulated for.
        output_scale: factor on the output (model mismatch), default 1.
    """

    def __init__(
        self,
        Gu: Sequence[Sequence[TransferEntry | int | None]],
        Gv: Sequence[Sequence[TransferEntry | int | None]] | None = None,
        *,
        dt: float,
        steps: int,
        output_scale: float = 1.0,
    ) -> None:
        exact = StepResponseModel.from_transfer_functions(Gu, Gv, dt=dt, horizon=max(int(steps), 1))
        self.Su, self.Sv = exact.Su, exact.Sv  # S_1..S_{steps+1}, exact
        self.steps, self.scale = int(steps), float(output_scale)
        self.ny, self.nu, self.nv = exact.ny, exact.nu, exact.nv

    def output(self, k: int, du: Tensor, dv: Tensor | None = None) -> Tensor:
        """The plant's output ``y(k)`` after the moves up to sample ``k - 1``.

        Args:
            k: the sample.
            du: the MV moves ``du(0..k-1)``, shape ``(K, nu)`` with ``K >= k``.
            dv: the DV changes ``dv(0..k-1)``, shape ``(K, nv)`` with ``K >= k``, or ``None``.

        Returns:
            ``y(k)``, shape ``(ny,)``.
        """
        y = torch.einsum("iyu,iu->y", self.Su[:k], du[:k].flip(0)) if k > 0 else None
        out = torch.zeros(self.ny, dtype=self.Su.dtype) if y is None else y
        if dv is not None and self.nv and k > 0:
            out = out + torch.einsum("iyv,iv->y", self.Sv[:k], dv[:k].flip(0))
        return self.scale * out


class ClosedLoopResult(NamedTuple):
    """A closed-loop run of ``K`` samples.

    Attributes:
        y: measured CVs ``y(k)``, shape ``(K, ny)``.
        u: inputs ``u(k)`` (held over ``[k, k+1)``), shape ``(K, nu)``.
        du: moves ``du(k)``, shape ``(K, nu)``.
        y_target: CV targets, shape ``(K, ny)``.
        u_target: MV targets, shape ``(K, nu)``.
        y_ss: steady-state open-loop predictions ``y^ol(k+N|k)``, shape ``(K, ny)``.
    """

    y: Tensor
    u: Tensor
    du: Tensor
    y_target: Tensor
    u_target: Tensor
    y_ss: Tensor


def run_closed_loop(
    plant: SampledPlant,
    predictor: OpenLoopPredictor,
    controller: DMCController,
    target: SteadyStateTarget,
    v: Tensor | None = None,
    *,
    steps: int | None = None,
    noise: Tensor | None = None,
) -> ClosedLoopResult:
    """Simulate the double-layered DMC loop (see the module docstring).

    Args:
        plant: the simulated plant.
        predictor: the open-loop prediction module (reset to rest at 0 first).
        controller: the dynamic layer.
        target: the steady-state target layer.
        v: measured disturbances ``v(0..K-1)``, shape ``(K, nv)`` (``v(-1) = 0``), or ``None``.
        steps: number of samples ``K`` (default ``v``'s length, else ``plant.steps``).
        noise: measurement noise added to ``y``, shape ``(K, ny)``, or ``None``.

    Returns:
        The :class:`ClosedLoopResult`.

    Raises:
        ShapeError: a predictor model whose channels are not the plant's, or ``v`` or ``noise``
            of the wrong shape.
        InputError: more ``steps`` than the plant was built for.
    """
    dt = predictor.model.dtype
    nu, nv, ny = plant.nu, plant.nv, plant.ny
    if predictor.model.ny != ny or predictor.model.nu != nu or predictor.model.nv != nv:
        raise ShapeError(
            f"predictor model is {predictor.model.ny}x{predictor.model.nu} (+{predictor.model.nv} "
            f"DVs) but the plant is {ny}x{nu} (+{nv} DVs)"
        )
    K = steps if steps is not None else (v.shape[0] if v is not None else plant.steps)
    if K > plant.steps:
        raise InputError(f"steps = {K} exceeds the {plant.steps} samples the plant was built for")
    v_t = torch.zeros(K, nv, dtype=dt) if v is None else torch.as_tensor(v, dtype=dt)
    if v_t.shape != (K, nv):
        raise ShapeError(f"v: expected shape ({K}, {nv}), got {tuple(v_t.shape)}")
    dv = torch.diff(v_t, dim=0, prepend=torch.zeros(1, nv, dtype=dt))
    if noise is not None and tuple(noise.shape) != (K, ny):
        raise ShapeError(f"noise: expected shape ({K}, {ny}), got {tuple(noise.shape)}")
    predictor.reset()
    du = torch.zeros(K, nu, dtype=dt)
    u = torch.zeros(K, nu, dtype=dt)
    ys, yts, uts, yss = (torch.zeros(K, n, dtype=dt) for n in (ny, ny, nu, ny))
    u_prev = torch.zeros(nu, dtype=dt)
    du_prev = torch.zeros(nu, dtype=dt)
    for k in range(K):
        y = plant.output(k, du, dv)
        if noise is not None:
            y = y + noise[k]
        free = predictor.update(y, du_prev, dv[k])
        tgt = target(free[-1], u_prev)
        du_k = controller.move(free, u_prev, tgt.y, tgt.u)
        du[k] = du_k
        u[k] = u_prev + du_k
        ys[k], yts[k], uts[k], yss[k] = y, tgt.y, tgt.u, free[-1]
        u_prev, du_prev = u[k], du_k
    return ClosedLoopResult(ys, u, du, yts, uts, yss)
