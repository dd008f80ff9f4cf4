"""The gauge of a measurement-only fit: which measurement channels have a known map.

A state-space model learned from measurements alone is defined only up to a change of state
coordinates; :func:`check_gauge` refuses a model whose known channels do not pin them (see
:mod:`torchfilt.training.measurement_only`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import Tensor, nn

from torchfilt.exceptions import GaugeError, InputError
from torchfilt.models import CovarianceParameter, StateSpaceModel
from torchfilt.models.sensor import AffineSensor

__all__ = ["check_gauge"]


def check_gauge(
    model: StateSpaceModel,
    known_channels: Sequence[int] | None,
    params: Iterable[nn.Parameter] | None = None,
) -> list[int]:
    """Check that a model to be learned from measurements alone has a fixed gauge.

    Args:
        model: the state-space model.
        known_channels: indices of the measurement channels whose map ``h_j`` is known (not
            learned); at least one.
        params: the parameters that will be learned (default: every parameter of ``model`` with
            ``requires_grad``).

    Returns:
        The sorted known channels.

    Raises:
        GaugeError: no known channel, or a known channel's map depends on a learned parameter.
        InputError: a channel index out of range or repeated.
    """
    m = model.obs_dim
    if known_channels is None or len(list(known_channels)) == 0:
        raise GaugeError(
            "known_channels: learning from measurements alone needs a fixed gauge (the state "
            "coordinates are otherwise free: x -> T x fits equally well); give the measurement "
            f"channels (of 0..{m - 1}) whose measurement map h is known and not learned, e.g. "
            "known_channels=[0] for a datasheet sensor model"
        )
    ch = [int(c) for c in known_channels]
    if len(set(ch)) != len(ch) or any(not 0 <= c < m for c in ch):
        raise InputError(f"known_channels: expected distinct indices in 0..{m - 1}, got {ch}")
    learned = [p for p in (model.parameters() if params is None else params) if p.requires_grad]
    noise_ids = {
        id(p)
        for mod in model.measurement.modules()
        if isinstance(mod, CovarianceParameter)
        for p in mod.parameters()
    }
    map_params = {
        id(p): name for name, p in model.measurement.named_parameters() if id(p) not in noise_ids
    }
    suspects = [p for p in learned if id(p) in map_params]
    calibrations = [mod for mod in model.measurement.modules() if isinstance(mod, AffineSensor)]
    cal_ids = {id(p) for mod in calibrations for p in (mod.log_scale, mod.bias)}
    if any(id(p) in cal_ids for p in suspects):
        for mod in calibrations:
            if any(p.requires_grad for p in (mod.log_scale, mod.bias)):
                _check_nonlinear(mod, sorted(set(mod.channels) & set(ch)), model.state_dim)
        suspects = [p for p in suspects if id(p) not in cal_ids]
    if suspects:
        x, u, _ = _probe_points(model.measurement, model.state_dim, suspects[0].dtype, seed=0)
        out = model.measurement.predict(x, u).mean[..., ch].sum()
        grads = torch.autograd.grad(out, suspects, allow_unused=True)
        for p, g in zip(suspects, grads, strict=True):
            if g is not None and bool((g != 0).any()):
                raise GaugeError(
                    f"known_channels {ch}: the measurement map of these channels depends on the "
                    f"learned parameter measurement.{map_params[id(p)]}; freeze it "
                    "(requires_grad_(False)) or leave those channels out of known_channels: a "
                    "known channel must not be learned"
                )
    return sorted(ch)


def _probe_points(
    side: nn.Module, n: int, dtype: torch.dtype, *, seed: int
) -> tuple[Tensor, Tensor | None, torch.Generator]:
    """Seeded random states ``(1, 4, n)`` and, for a side with inputs, inputs ``(1, 4, nu)`` at
    which the gauge checks probe a measurement map; the generator, for further draws."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(1, 4, n, generator=gen, dtype=dtype)
    u = None
    nu = getattr(side, "input_dim", None)
    if isinstance(nu, int) and nu > 0:
        u = torch.randn(1, 4, nu, generator=gen, dtype=dtype)
    return x, u, gen


def _check_nonlinear(sensor: AffineSensor, channels: list[int], n: int) -> None:
    """Refuse a learned gain and offset on a known channel whose map is affine in the state
    (its Hessian-vector products are zero at random points): ``x -> a x + c`` would absorb them."""
    if not channels:
        return
    dtype = sensor.log_scale.dtype
    x, u, gen = _probe_points(sensor.base, n, dtype, seed=1)
    x.requires_grad_(True)
    v = torch.randn(1, 4, n, generator=gen, dtype=dtype)
    with torch.enable_grad():
        out = sensor.base.predict(x, u).mean
        for j in channels:
            (g,) = torch.autograd.grad(out[..., j].sum(), x, create_graph=True, retain_graph=True)
            hv = None
            if g.requires_grad:
                (hv,) = torch.autograd.grad((g * v).sum(), x, retain_graph=True, allow_unused=True)
            if hv is None or not bool((hv != 0).any()):
                raise GaugeError(
                    f"known_channels: channel {j} has a learned gain and offset (AffineSensor) "
                    "on a map that is affine in the state, so x -> a x + c absorbs them and the "
                    "gauge is not fixed; freeze its scale and bias, or know the gain and "
                    "offset of another channel"
                )


# ----------------------------------------------------------------------------------- results
