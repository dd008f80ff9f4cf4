"""The exact Kalman filter's check of its own results in the working precision.

The closed-form recursion never fails loudly in float32: a covariance that loses definiteness by
rounding still yields finite (over-confident) estimates, and means whose magnitude dwarfs their
standard deviation are rounded by more than the filter's own uncertainty. :func:`warn_precision`
looks for both once a run is over, vectorised over the batch and time (one host synchronisation
for the whole run, none per step), and emits a :class:`~torchfilt.exceptions.PrecisionWarning`
that says how to fix it.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from torchfilt.exceptions import PrecisionWarning
from torchfilt.filters.results import FilterResult
from torchfilt.numerics import no_host_sync

__all__ = ["precision_problems", "warn_precision"]

#: a covariance counts as indefinite when it does not factor even after adding this many ulps of
#: its largest variance (times the state dimension) to its diagonal: rounding-level singularity
#: of a covariance that is exactly singular (a noiseless state) does not count
_DEFINITE_ULPS = 16.0
#: the means count as unresolved where the rounding of a mean, one ulp of its magnitude, exceeds
#: this fraction of its standard deviation (rounding errors then add up to a sizeable part of it)
_RESOLUTION = 0.25


def _distinct(x: Tensor, tail: int) -> Tensor:
    """``x`` with the leading dimensions it is only expanded along (stride 0) cut to size 1."""
    lead = x.dim() - tail
    return x[tuple(slice(0, 1) if st == 0 else slice(None) for st in x.stride()[:lead])]


def precision_problems(res: FilterResult) -> tuple[float, float]:
    """The share of filtered covariances that are indefinite (beyond rounding), and the largest
    rounding of a mean in units of its standard deviation (``eps |m_i| / sqrt(P_ii)``; 0 where
    the covariance or the means were not kept). Finite entries only."""
    cov = res.cov if res.cov.numel() else res.predicted_cov
    if not cov.numel():
        return 0.0, 0.0
    with torch.no_grad():
        C = _distinct(cov.detach(), 3)
        n, eps = C.shape[-1], torch.finfo(C.dtype).eps
        var = C.diagonal(dim1=-2, dim2=-1)
        finite = torch.isfinite(C).flatten(-2).all(-1)
        C = torch.where(finite[..., None, None], C, torch.eye(n, dtype=C.dtype, device=C.device))
        var = torch.where(finite[..., None], var, torch.ones_like(var))
        scale = var.abs().amax(-1)  # (..., T)
        floor = _DEFINITE_ULPS * n * eps * scale
        eye = torch.eye(n, dtype=C.dtype, device=C.device)
        info = torch.linalg.cholesky_ex(C + floor[..., None, None] * eye).info
        indefinite = (info > 0).to(C.dtype).mean()
        resolution = torch.zeros((), dtype=C.dtype, device=C.device)
        mean = res.mean.detach() if cov is res.cov else res.predicted_mean.detach()
        if mean.numel():
            # a variance at the covariance's rounding level has no meaningful standard deviation
            sd = torch.where(var > eps * scale[..., None], var, torch.inf).sqrt()
            ratio = eps * mean.abs() / sd
            resolution = torch.where(torch.isfinite(ratio), ratio, 0.0).amax()
        shares = torch.stack([indefinite, resolution]).tolist()  # the one host synchronisation
    return float(shares[0]), float(shares[1])


def warn_precision(
    res: FilterResult,
    *,
    sqrt: bool,
    stacklevel: int,
    problems: tuple[float, float] | None = None,
) -> None:
    """Emit a :class:`~torchfilt.exceptions.PrecisionWarning` if the results of the exact filter
    ``res`` are over-confident because of the working precision (see
    :func:`precision_problems`; ``problems``: its result, where the caller has it already);
    nothing where a host synchronisation is not allowed.

    ``stacklevel`` counts from this function (as in :func:`warnings.warn`)."""
    if no_host_sync():
        return
    indefinite, resolution = precision_problems(res) if problems is None else problems
    dt = res.mean.dtype
    dtype, digits = str(dt).replace("torch.", ""), round(-math.log10(torch.finfo(dt).eps))
    # in float64 already, there is no wider dtype to advise
    wider = "" if dt == torch.float64 else "Run in float64 (the model and the data .double()), or "
    if indefinite > 0:
        form = (
            "the square-root form (sqrt=True) only helps where the factor stays definite"
            if sqrt
            else "use the square-root form (sqrt=True), which keeps the covariance definite"
        )
        fixes = (
            f"{wider}{form}, or put a jitter floor on Q (Q + eps I with eps about 1e-6 of its "
            "scale)"
        )
        warnings.warn(
            f"the exact Kalman filter in {dtype}: the filtered covariance lost positive "
            f"definiteness at {indefinite:.1%} of the steps, so the estimates are over-confident. "
            + fixes[0].upper()
            + fixes[1:],
            PrecisionWarning,
            stacklevel=stacklevel + 1,
        )
    if resolution > _RESOLUTION:
        fixes = (
            f"{wider}re-centre or rescale the state so that its magnitude is closer to its "
            "uncertainty"
        )
        if dt == torch.float64:
            fixes += " (means this far beyond it often come from a transition that diverges)"
        warnings.warn(
            f"the exact Kalman filter in {dtype}: the means are rounded by up to "
            f"{resolution:.3g} of their standard deviation ({dtype} keeps about {digits} "
            "significant digits), so the estimates are over-confident; the square-root form does "
            "not help. " + fixes[0].upper() + fixes[1:],
            PrecisionWarning,
            stacklevel=stacklevel + 1,
        )
