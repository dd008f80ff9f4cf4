"""Rauch-Tung-Striebel smoothing of a Gaussian filter's output.

Cubature RTS smoother (Särkkä & Svensson 2023, ch. 14; Arasaratnam & Haykin 2011): with the filter's
predicted moments ``m^-_{t+1}, P^-_{t+1}`` and the cross-covariance
``C_{t+1} = Cov(x_t, x_{t+1} | y_{1:t})`` computed from the same cubature points,

    G_t   = C_{t+1} (P^-_{t+1})^{-1}
    m^s_t = m_t + G_t (m^s_{t+1} - m^-_{t+1})
    P^s_t = P_t + G_t (P^s_{t+1} - P^-_{t+1}) G_t^T
"""

from __future__ import annotations

import torch

from torchfilt.exceptions import InputError
from torchfilt.filters.results import FilterResult, SmootherResult
from torchfilt.numerics import psd_solve, symmetrize

__all__ = ["rts_smooth"]


def rts_smooth(result: FilterResult) -> SmootherResult:
    """Backward RTS pass over a :class:`FilterResult` (any batch shape).

    The cross-covariances come from the filter's own prediction step, so no model evaluations are
    repeated: this is exactly the cubature (or unscented, ...) RTS smoother of the rule the filter
    used.

    Args:
        result: forward pass with ``mean (..., T, n)``, ``cov (..., T, n, n)`` and the predicted
            moments and cross-covariances.

    Returns:
        A :class:`SmootherResult` with ``mean (..., T, n)``, ``cov (..., T, n, n)`` and gains
        ``(..., T-1, n, n)``.

    Raises:
        InputError: ``result`` is not a :class:`FilterResult`.
    """
    if not isinstance(result, FilterResult):
        raise InputError(
            f"result: expected a FilterResult (from a filter's filter()), got {type(result).__name__}"
        )
    T = result.mean.shape[-2]
    n = result.mean.shape[-1]
    if T < 2:
        gain = result.cov.new_zeros(*result.cov.shape[:-3], 0, n, n)
        return SmootherResult(result.mean.clone(), result.cov.clone(), gain, result)
    # the gains do not depend on the backward recursion: one batched solve over all steps
    P_pred = result.predicted_cov[..., 1:, :, :]
    G_all = psd_solve(P_pred, result.cross_cov[..., 1:, :, :].mT, name="predicted covariance").mT
    GT_all = G_all.mT
    dm_pred = result.predicted_mean[..., 1:, :]
    m_s = result.mean[..., T - 1, :]
    P_s = result.cov[..., T - 1, :, :]
    means, covs = [m_s], [P_s]
    for t in range(T - 2, -1, -1):
        G = G_all[..., t, :, :]
        m_s = result.mean[..., t, :] + (G @ (m_s - dm_pred[..., t, :]).unsqueeze(-1)).squeeze(-1)
        P_s = symmetrize(
            result.cov[..., t, :, :] + G @ (P_s - P_pred[..., t, :, :]) @ GT_all[..., t, :, :]
        )
        means.append(m_s)
        covs.append(P_s)
    means.reverse()
    covs.reverse()
    return SmootherResult(torch.stack(means, -2), torch.stack(covs, -3), G_all, result)
