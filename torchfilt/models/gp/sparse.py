"""Sparse variational GPs (SVGP, Hensman et al. 2015) for logs too large for an exact GP."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from torchfilt.models.gp.components import base_kernel

__all__ = ["SparseIndependentGP"]


class SparseIndependentGP(gpytorch.models.ApproximateGP):
    """``g`` independent SVGPs sharing inputs, batch shape ``(g,)``, whitened, learned inducing points.

    ``q(u_j) = N(m_j, S_j)`` over ``M`` inducing values per output (whitened), trained on the
    evidence lower bound with minibatches.

    Args:
        inducing: initial inducing inputs (standardised), shape ``(g, M, D)``.
        kernel: kernel name.
    """

    def __init__(self, inducing: Tensor, kernel: str) -> None:
        g, M, D = inducing.shape
        batch = torch.Size([g])
        q = gpytorch.variational.CholeskyVariationalDistribution(M, batch_shape=batch)
        strategy = gpytorch.variational.VariationalStrategy(
            self, inducing, q, learn_inducing_locations=True
        )
        super().__init__(strategy)
        self.mean_module = gpytorch.means.ConstantMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            base_kernel(kernel, D, batch), batch_shape=batch
        )
        self.to(inducing.dtype)

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
