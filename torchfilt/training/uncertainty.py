"""How well the training recordings determine a fitted model's parameters.

:func:`parameter_posterior` gives the Gaussian (Laplace) approximation of the parameters'
posterior at a maximum of the filter's innovation log-likelihood ``l(theta)`` (flat prior):

- ``covariance="hessian"``: ``C = H^{-1}`` with ``H = -d^2 l / d theta^2``, the observed
  information. Right when the model (prior ``N(x0, P0)`` included) is the data's distribution.
- ``covariance="sandwich"``: ``C = R / (R - p) H^{-1} J H^{-1}`` with ``J = sum_r g_r g_r^T``
  over the ``R`` recordings' scores ``g_r = d l_r / d theta`` (the robust Huber-White form, with
  the HC1 small-sample factor for ``p`` parameter values). It stays right when the model is
  misspecified, e.g. when every recording starts from the same state rather than from a draw of
  the prior; it needs more recordings than parameters (``R > p``).

``scripts/posterior_calibration.py`` checks both against the spread of the maximum-likelihood
estimates over independent training sets (re-entry radar).

:class:`~torchfilt.models.UncertainParameters` carries the result into a filter.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ModelError
from torchfilt.filters import CKF
from torchfilt.models import StateSpaceModel
from torchfilt.models.uncertain import (
    ParameterPosterior,
    map_parameters,
    noise_parameter_names,
)
from torchfilt.training.likelihood import _recordings

__all__ = ["parameter_posterior"]


class _NegativeLogLikelihood(torch.nn.Module):
    """``-log p(y_r)`` per recording ``(R,)`` by the CKF: a module, so that
    ``torch.func.functional_call`` can evaluate it at other parameter values."""

    def __init__(self, model: StateSpaceModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, y: Tensor, u: Tensor | None, x0: Tensor, P0: Tensor) -> Tensor:
        return -CKF(self.model).filter(y, u, x0=x0, P0=P0).log_likelihood


def parameter_posterior(
    model: StateSpaceModel,
    y: Tensor | Sequence[Tensor],
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    parameters: Sequence[str] | None = None,
    covariance: Literal["hessian", "sandwich"] = "hessian",
    dtype: torch.dtype = torch.float64,
) -> ParameterPosterior:
    """The Laplace approximation of a fitted model's parameter posterior from its training data.

    Call it on the recordings the model was fitted to, at the fit's maximum
    (:func:`~torchfilt.training.fit_likelihood`, :func:`~torchfilt.training.fit_measurement_only`);
    the noise covariances stay at their fitted values. Whole recordings are filtered, every step
    counted.

    Args:
        model: the fitted state-space model; converted to ``dtype`` in place, its values kept.
        y: measurements ``(..., T, m)`` or a list of ``(T_i, m)``; NaN is missing.
        u: inputs ``(..., T, nu)``, a list, or ``None``.
        x0: prior mean ``(n,)`` or one per recording ``(..., n)``.
        P0: prior covariance ``(n, n)`` or ``(..., n, n)``.
        parameters: names as in ``model.named_parameters()`` (default: every parameter of the
            maps with ``requires_grad``, the noises' excluded).
        covariance: ``"hessian"`` or ``"sandwich"`` (see the module docstring).
        dtype: floating dtype (float64 by default).

    Returns:
        A :class:`~torchfilt.models.ParameterPosterior` ``(names, mean (p,), cov (p, p))``.

    Raises:
        InputError: an unknown or noise parameter, no parameter, a ``"sandwich"`` with no more
            recordings than parameter values, or an unknown ``covariance``.
        ModelError: the log-likelihood is not at a maximum in some direction (not fitted, or a
            combination of parameters the data cannot tell apart); the message names the
            parameters of that direction.
    """
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    if covariance not in ("hessian", "sandwich"):
        raise InputError(f"covariance must be 'hessian' or 'sandwich', got {covariance!r}")
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    model.to(dtype)
    if parameters is None:
        noise = noise_parameter_names(model)
        names = [
            k
            for k, v in model.named_parameters()
            if v.requires_grad
            and k not in noise
            and k.split(".")[0] in ("transition", "measurement")
        ]
        if not names:
            raise InputError("parameters: the model's maps have no parameter with requires_grad")
    else:
        names = [str(k) for k in parameters]
    named = map_parameters(model, names, "parameters")
    recs = _recordings(model, y, u, x0, P0, dtype)
    R = int(recs.y.shape[0])
    shapes = [named[k].shape for k in names]
    sizes = [s.numel() for s in shapes]
    p = sum(sizes)
    if covariance == "sandwich" and R <= p:
        raise InputError(
            f"covariance='sandwich' needs more recordings than parameter values ({p}); got {R} "
            "(use 'hessian')"
        )
    theta = torch.cat([named[k].detach().reshape(-1) for k in names]).clone().requires_grad_(True)
    wrapped = _NegativeLogLikelihood(model)

    def per_recording_nll(t: Tensor) -> Tensor:
        values = {
            f"model.{k}": c.reshape(s)
            for k, c, s in zip(names, t.split(sizes), shapes, strict=True)
        }
        out: Tensor = torch.func.functional_call(
            wrapped, values, (recs.y, recs.u, recs.x0, recs.P0)
        )
        return out

    nll = per_recording_nll(theta)
    if not bool(torch.isfinite(nll).all()):
        raise ModelError("parameter_posterior: the filter's log-likelihood is not finite")
    (grad,) = torch.autograd.grad(nll.sum(), theta, create_graph=True)
    rows = [torch.autograd.grad(grad[i], theta, retain_graph=True)[0] for i in range(p)]
    H = torch.stack(rows)
    H = 0.5 * (H + H.mT)
    flat_names = [
        k if s == 1 else f"{k}[{j}]" for k, s in zip(names, sizes, strict=True) for j in range(s)
    ]
    Hd = H.detach()
    diag = Hd.diagonal()
    if not bool((diag > 0).all()):
        i = int(torch.argmin(diag))
        raise ModelError(
            f"parameter_posterior: the log-likelihood is not at a maximum in {flat_names[i]!r} "
            f"(curvature {float(diag[i]):.3g}): fit the model first"
        )
    # scale-free test: the correlation form of H must be positive definite
    scale = diag.rsqrt()
    evals, evecs = torch.linalg.eigh(scale[:, None] * Hd * scale[None, :])
    if not bool(evals[0] > 1e-10):
        v = evecs[:, 0].abs()
        top = [flat_names[int(i)] for i in torch.argsort(v, descending=True)[:3] if v[i] > 0.1]
        raise ModelError(
            "parameter_posterior: the log-likelihood is not at a maximum along a combination of "
            f"{top} (relative curvature {float(evals[0]):.3g}): fit the model first, or leave "
            "out parameters the data cannot tell apart"
        )
    Hinv = torch.linalg.inv(H.detach())
    if covariance == "hessian":
        cov = Hinv
    else:
        scores = torch.stack(
            [torch.autograd.grad(nll[r], theta, retain_graph=True)[0] for r in range(R)]
        )
        # HC1: the degrees-of-freedom correction R / (R - p) of the small-sample sandwich
        cov = (R / (R - p)) * (Hinv @ (scores.mT @ scores) @ Hinv)
    cov = 0.5 * (cov + cov.mT)
    return ParameterPosterior(tuple(names), theta.detach().clone(), cov.detach())
