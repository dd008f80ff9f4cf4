"""Box-constrained cubature points and weights (Liu, Zhang & Chu 2018, section 3; spec ``cckf.md`` s.2).

From a mean ``x`` (inside the box) and ``S`` with ``S S^T = P``, the third-degree rule's ``2n``
directions are ``dx_i = S xi_i`` (``xi_i = +-sqrt(n) e_i``). Each point is pulled back inside the box
along its direction and re-weighted by how much probability lies on its side:

    theta_i = min_j { (b_j - x_j) / dx_{i,j} : dx_{i,j} != 0 },  b_j = upper_j if dx_{i,j} > 0
                                                                  else lower_j   (+inf if none)
    lambda_i = min(1, theta_i),      X_i = x + lambda_i dx_i
    F(t) = Phi(t) - 1/2,             w_i = F(theta_i) / (F(theta_i) + F(theta_{i+n}))
    omega_i = w_i / n                                            (pairs i, i+n; sum omega = 1)

With no bound in reach of any direction (every ``theta_i = inf``) all ``omega_i = 1/(2n)``: the CKF.
A finite bound, even one the points never reach, tilts the weights of its pair towards the side with
more room.
The paper measures ``theta`` in units of the cubature step, which is ``sqrt(n)`` standard deviations
long (``theta="paper"``); ``theta="std"`` evaluates ``F(sqrt(n) theta_i)``, i.e. ``theta`` in
standard deviations along the direction.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchfilt.cubature.rules import SphericalRadialRule
from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics import Box

__all__ = ["ConstrainedPoints", "ThetaReading", "constrained_points"]

ThetaReading = Literal["paper", "std"]

_RULE = SphericalRadialRule(3)


class ConstrainedPoints(NamedTuple):
    """Constrained cubature points of one Gaussian per batch element.

    Attributes:
        points: ``X_i``, shape ``(..., 2n, n)``, every one inside the box.
        weights: ``omega_i``, shape ``(..., 2n)``, non-negative, summing to 1.
        theta: step fraction to the boundary along each direction (``inf`` if none), ``(..., 2n)``.
        lam: ``min(1, theta)``, the fraction of the step kept, ``(..., 2n)``.
    """

    points: Tensor
    weights: Tensor
    theta: Tensor
    lam: Tensor


def constrained_points(
    mean: Tensor, sqrt: Tensor, box: Box, *, theta: ThetaReading = "paper"
) -> ConstrainedPoints:
    """Third-degree cubature points pulled inside a box, with the paper's probability weights.

    Equations in the module docstring (Liu, Zhang & Chu 2018, eqs. (19)-(21) and the weight rule of
    their section 3, restated in spec ``cckf.md`` section 2). When both directions of a pair meet
    the boundary at once (``F(theta_i) + F(theta_{i+n}) = 0``: both points sit on the mean) the
    pair's weights are 1/2 each.

    Args:
        mean: means, shape ``(..., n)``; projected onto the box first (a no-op inside it).
        sqrt: square roots ``S`` of the covariances (``S S^T = P``), shape ``(..., n, n)``.
        box: the bounds, ``(..., n)``; infinite entries allowed.
        theta: ``"paper"`` (``F(theta)``, theta in cubature steps) or ``"std"``
            (``F(sqrt(n) theta)``, theta in standard deviations).

    Returns:
        :class:`ConstrainedPoints` with points ``(..., 2n, n)`` and weights ``(..., 2n)``.

    Raises:
        InputError: ``theta`` is neither ``"paper"`` nor ``"std"``.
        ShapeError: ``sqrt`` is not ``(..., n, n)`` or the box's dimension is not ``n``.
    """
    if theta not in ("paper", "std"):
        raise InputError(f"theta must be 'paper' or 'std', got {theta!r}")
    n = mean.shape[-1]
    if sqrt.shape[-2:] != (n, n):
        raise ShapeError(f"sqrt: expected shape (..., {n}, {n}), got {tuple(sqrt.shape)}")
    if box.dim != n:
        raise ShapeError(f"box: dimension {box.dim} does not match the mean's n = {n}")
    mean = box.project(mean)
    xi = _RULE.unit_points(n, dtype=mean.dtype, device=mean.device)[0]  # (2n, n)
    dx = xi @ sqrt.mT  # (..., 2n, n): rows sqrt(n) S e_i, then -sqrt(n) S e_i
    lo = box.lower.to(mean).unsqueeze(-2)
    hi = box.upper.to(mean).unsqueeze(-2)
    x = mean.unsqueeze(-2)
    pos, neg = dx > 0, dx < 0
    bound = torch.where(pos, hi, lo)
    hit = (pos | neg) & torch.isfinite(bound)
    # double-where keeps the gradient finite where the ratio is not used (inf bounds, dx = 0)
    gap = torch.where(hit, bound - x, torch.ones_like(dx))
    step = torch.where(hit, dx, torch.ones_like(dx))
    ratio = torch.where(hit, (gap / step).clamp_min(0.0), torch.full_like(dx, math.inf))
    th = ratio.amin(-1)  # (..., 2n)
    lam = th.clamp(max=1.0)
    points = torch.clamp(x + lam.unsqueeze(-1) * dx, lo, hi)  # removes round-off only
    arg = th * math.sqrt(n) if theta == "std" else th
    Fv = torch.special.ndtr(arg) - 0.5
    Fa, Fb = Fv[..., :n], Fv[..., n:]
    tot = Fa + Fb
    degenerate = tot <= 0
    safe = torch.where(degenerate, torch.ones_like(tot), tot)
    half = torch.full_like(tot, 0.5)
    wa = torch.where(degenerate, half, Fa / safe)
    wb = torch.where(degenerate, half, Fb / safe)
    weights = torch.cat([wa, wb], dim=-1) / n
    return ConstrainedPoints(points, weights, th, lam)
