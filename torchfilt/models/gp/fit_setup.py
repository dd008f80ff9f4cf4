"""The set-up of a GP fit from training pairs: the noise levels to start from and the groups.

Used by :meth:`torchfilt.models.gp.GPModel._from_pairs`; not part of the public API.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.gp.config import GPConfig, GroupSpec
from torchfilt.models.gp.data import MIN_POINTS
from torchfilt.models.gp.group import GPGroup
from torchfilt.models.gp.noise import neighbour_noise
from torchfilt.models.gp.noise import noise_floor as auto_floor
from torchfilt.models.gp.standardize import Standardizer

__all__ = ["INIT_NOISE_MAX", "make_groups", "noise_levels"]

#: The initial noise (standardised) is the neighbour estimate, capped at this value.
INIT_NOISE_MAX = 0.1


def _per_output(value: Any, d: int, name: str, dtype: torch.dtype) -> Tensor:
    t = torch.as_tensor(value, dtype=dtype).reshape(-1)
    if t.numel() == 1:
        t = t.expand(d).clone()
    if t.numel() != d:
        raise ShapeError(
            f"{name}: expected a scalar or {d} values (one per output), got {t.numel()}"
        )
    if not bool(torch.isfinite(t).all()) or not bool((t > 0).all()):
        raise InputError(f"{name}: variances must be positive and finite, got {t.tolist()}")
    return t


def noise_levels(
    specs: list[GroupSpec],
    valid: Tensor,
    z_all: Tensor,
    y_all: Tensor,
    target_std: Standardizer,
    noise: Any,
    noise_floor: Any,
    gen: torch.Generator,
    d: int,
    dtype: torch.dtype,
) -> tuple[bool, Tensor, Tensor]:
    """``(fixed, floor, init)``: is the noise fixed, its floor and initial value ``(d,)``, scaled."""
    scale2 = target_std.scale.pow(2)
    est = torch.zeros(d, dtype=dtype)
    for spec in specs:
        rows = valid[:, list(spec.outputs)].all(-1)
        z, outs = z_all[rows][:, list(spec.features)], list(spec.outputs)
        est[outs] = neighbour_noise(z, y_all[rows][:, outs], gen)
    fixed = noise is not None
    if fixed:
        init = _per_output(noise, d, "noise", dtype) / scale2
        floor = torch.zeros(d, dtype=dtype)
    else:
        if isinstance(noise_floor, str):
            if noise_floor != "auto":
                raise InputError(f"noise_floor must be 'auto' or a variance, got {noise_floor!r}")
            floor = auto_floor(est, dtype)
        else:
            floor = _per_output(noise_floor, d, "noise_floor", dtype) / scale2
        init = torch.minimum(est, torch.full_like(est, INIT_NOISE_MAX)).clamp_min(0.0)
        init = torch.maximum(torch.nan_to_num(init, nan=INIT_NOISE_MAX), floor)
    return fixed, floor.masked_fill(target_std.constant, 0.0), init


def make_groups(
    config: GPConfig,
    valid: Tensor,
    z_all: Tensor,
    y_all: Tensor,
    floor: Tensor,
    init: Tensor,
    gen: torch.Generator,
) -> list[GPGroup]:
    """One :class:`GPGroup` per group of ``config``, on the rows observing all its outputs."""
    target_name, groups = "x_next" if config.role == "transition" else "y", []
    for spec in config.groups:
        outs = list(spec.outputs)
        rows = valid[:, outs].all(-1)
        if int(rows.sum()) < MIN_POINTS:  # a multitask GP needs every output at a row
            raise InputError(
                f"{target_name}: only {int(rows.sum())} rows observe all of outputs {outs}; "
                f"a multitask GP needs at least {MIN_POINTS}"
            )
        groups.append(
            GPGroup(
                config.structure,
                z_all[rows][:, list(spec.features)].contiguous(),
                y_all[rows][:, outs].T.contiguous(),
                kernel=config.kernel,
                floor=floor[outs],
                noise_init=init[outs],
                noise_fixed=config.noise_fixed,
                num_latents=config.num_latents,
                task_rank=config.task_rank,
                num_inducing=config.num_inducing,
                generator=gen,
            )
        )
    return groups
