"""Setting the likelihood-noise floor from the data.

GPyTorch's ``GaussianLikelihood`` bounds the noise variance below by 1e-4 in whatever units the
targets are in. On standardised targets that is a relative bound of 1 % in standard deviation: a
radar range standardised by ~4e4 ft then cannot have less than ~400 ft of noise, whatever its true
100 ft. The floor here is set per output from the data instead:

1. **Nearest-neighbour noise estimate** (:func:`neighbour_noise`). For each of up to
   ``NN_QUERIES`` training inputs, find its nearest other training input (standardised, selected
   features) and take ``d_i = (y_i - y_nn(i))^2 / 2``. For pure noise of variance ``s^2``,
   ``median(d) = 0.455 s^2`` (the median of ``chi^2_1``), so ``median(d) / 0.455`` estimates
   ``s^2``; where the function varies between neighbours it over-estimates, so it is an upper bound
   on the noise the data can resolve.
2. **Floor** (:func:`noise_floor`) = ``FLOOR_FRACTION`` x that estimate (a noise standard deviation
   ``sqrt(FLOOR_FRACTION)`` = 10 % of the neighbour scatter), clipped to
   ``[NUMERICAL_FLOOR[dtype], GPYTORCH_FLOOR]``: never above GPyTorch's default, never below what
   the Cholesky factorisation of ``K + s^2 I`` needs in that precision (float64: 1e-8, float32:
   1e-4, relative to the unit target variance).

The estimate also initialises the noise before training. A user who knows the noise passes it
(``noise=``, held fixed) or sets ``noise_floor=`` explicitly.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["FLOOR_FRACTION", "GPYTORCH_FLOOR", "NUMERICAL_FLOOR", "neighbour_noise", "noise_floor"]

#: Floor as a fraction of the nearest-neighbour noise estimate (variance).
FLOOR_FRACTION = 1e-2
#: GPyTorch's default noise lower bound; the automatic floor never exceeds it.
GPYTORCH_FLOOR = 1e-4
#: Smallest floor per dtype (standardised units) that keeps ``K + s^2 I`` factorable.
NUMERICAL_FLOOR = {torch.float64: 1e-8, torch.float32: 1e-4}
#: Number of query points of the nearest-neighbour estimate.
NN_QUERIES = 2000
#: Median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = 0.45493642311957283
#: Query rows per chunk of the distance computation.
_CHUNK = 256


def neighbour_noise(z: Tensor, y: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Nearest-neighbour estimate of the noise variance of each target column.

    Args:
        z: standardised inputs, shape ``(S, D)``.
        y: targets, shape ``(S, g)`` (columns share the inputs).
        generator: random generator for choosing the query points when ``S > NN_QUERIES``.

    Returns:
        Estimated noise variance per column, shape ``(g,)``, in the units of ``y`` squared.
    """
    S = z.shape[0]
    if S < 2:
        return torch.full((y.shape[1],), float("nan"), dtype=y.dtype)
    if S > NN_QUERIES:
        q = torch.randperm(S, generator=generator, device="cpu")[:NN_QUERIES].to(z.device)
    else:
        q = torch.arange(S, device=z.device)
    nn = torch.empty_like(q)
    z_sq = z.pow(2).sum(-1)
    for start in range(0, q.shape[0], _CHUNK):
        idx = q[start : start + _CHUNK]
        d2 = z_sq[idx, None] + z_sq[None, :] - 2.0 * z[idx] @ z.T
        d2[torch.arange(idx.shape[0], device=z.device), idx] = float("inf")
        nn[start : start + _CHUNK] = d2.argmin(-1)
    diff = 0.5 * (y[q] - y[nn]) ** 2
    return diff.median(0).values / _CHI2_1_MEDIAN


def noise_floor(estimate: Tensor, dtype: torch.dtype) -> Tensor:
    """The automatic floor from a noise estimate, both in standardised units.

    Args:
        estimate: noise-variance estimate per output, shape ``(g,)``.
        dtype: training dtype (sets the numerical floor).

    Returns:
        Floor per output, shape ``(g,)``.
    """
    low = NUMERICAL_FLOOR.get(dtype, NUMERICAL_FLOOR[torch.float32])
    est = torch.nan_to_num(estimate, nan=GPYTORCH_FLOOR / FLOOR_FRACTION)
    return (FLOOR_FRACTION * est).clamp(min=low, max=max(low, GPYTORCH_FLOOR))
