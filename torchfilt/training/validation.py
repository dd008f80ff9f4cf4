"""One-step predictive validation of learned models on held-out recordings."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchfilt.io import Recording
from torchfilt.models import ConditionalModel

__all__ = ["one_step_metrics"]

#: two-sided 95% interval of a Gaussian
_Z95 = 1.959963984540054


def _predictive(side: ConditionalModel, x: Tensor, u: Tensor | None) -> tuple[Tensor, Tensor]:
    """Predictive mean and variance ``(N, d)`` at points ``(N, n)`` (model variance + noise)."""
    pred = side.predict(x.unsqueeze(-2), None if u is None else u.unsqueeze(-2))
    mean = pred.mean.squeeze(-2)
    var = torch.zeros_like(mean)
    if pred.var is not None:
        var = var + pred.var.squeeze(-2)
    if pred.cov is not None:
        var = var + pred.cov.squeeze(-3).diagonal(dim1=-2, dim2=-1)
    noise = side.noise_cov(0) if side.time_varying_noise else side.noise_cov()
    if noise is not None:
        var = var + noise.to(mean).diagonal(dim1=-2, dim2=-1)
    return mean, var


def _score(mean: Tensor, var: Tensor, target: Tensor) -> dict[str, Any]:
    ok = torch.isfinite(target)
    e = torch.where(ok, target - mean, torch.zeros_like(mean))
    v = torch.where(ok, var.clamp_min(torch.finfo(var.dtype).tiny), torch.ones_like(var))
    n = ok.sum(0).clamp_min(1)
    nlpd = torch.where(ok, 0.5 * (math.log(2 * math.pi) + v.log() + e * e / v), torch.zeros_like(v))
    inside = ok & (e.abs() <= _Z95 * v.sqrt())
    return {
        "rmse": ((e * e).sum(0) / n).sqrt().tolist(),
        "nlpd": (nlpd.sum(0) / n).tolist(),
        "coverage95": (inside.sum(0) / n).tolist(),
        "points": ok.sum(0).tolist(),
    }


@torch.no_grad()
def one_step_metrics(
    transition: ConditionalModel, measurement: ConditionalModel, recordings: Sequence[Recording]
) -> dict[str, Any]:
    """One-step prediction RMSE, negative log predictive density and 95% coverage per output.

    The transition predicts ``x_{k+1}`` from the logged ``(x_k, u_k)``; the measurement model
    predicts the observed ``y_k`` from the logged ``x_k``. The predictive variance includes the
    model's per-point variance and its additive noise.

    Args:
        transition: the transition model.
        measurement: the measurement model.
        recordings: held-out recordings with states (ground truth).

    Returns:
        ``{"transition": {...}, "measurement": {...}}`` with lists per output.
    """
    if not recordings:
        return {}
    dtype = torch.float64
    xs, us, xn, ys = [], [], [], []
    for r in recordings:
        x = r.states.to(dtype)
        xs.append(x[:-1])
        xn.append(x[1:])
        u = r.inputs
        us.append(None if u is None else u[:-1].to(dtype))
        ys.append(r.measurements.to(dtype))
    X, Xn = torch.cat(xs), torch.cat(xn)
    U = None if us[0] is None else torch.cat(us)  # type: ignore[arg-type]
    f_mean, f_var = _predictive(transition, X, U)
    Xall = torch.cat([r.states.to(dtype) for r in recordings])
    Uall = None if us[0] is None else torch.cat([r.inputs.to(dtype) for r in recordings])  # type: ignore[union-attr]
    h_mean, h_var = _predictive(measurement, Xall, Uall)
    return {
        "transition": _score(f_mean, f_var, Xn),
        "measurement": _score(h_mean, h_var, torch.cat(ys)),
        "recordings": [r.name for r in recordings],
    }
