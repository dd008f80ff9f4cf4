"""Batch-independent exact GPs: ``g`` outputs that share inputs, one GPyTorch batch GP."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from torchfilt.models.gp.components import base_kernel

__all__ = ["ExactIndependentGP"]


class ExactIndependentGP(gpytorch.models.ExactGP):
    """``g`` independent GPs with constant means and ARD kernels, as one batch of shape ``(g,)``.

    ``f_j ~ GP(c_j, s_j^2 k(x, x'; l_j))``, ``y_j = f_j(x) + e_j``, ``e_j ~ N(0, noise_j)``.

    Args:
        train_x: standardised inputs, shape ``(S, D)``.
        train_y: standardised targets, shape ``(g, S)``.
        likelihood: a ``GaussianLikelihood`` of batch shape ``(g,)``.
        kernel: kernel name.
    """

    def __init__(
        self,
        train_x: Tensor,
        train_y: Tensor,
        likelihood: gpytorch.likelihoods.GaussianLikelihood,
        kernel: str,
    ) -> None:
        g, S = train_y.shape
        super().__init__(train_x.expand(g, S, train_x.shape[-1]), train_y, likelihood)
        batch = torch.Size([g])
        self.mean_module = gpytorch.means.ConstantMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            base_kernel(kernel, train_x.shape[-1], batch), batch_shape=batch
        )
        self.to(train_y.dtype)

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
