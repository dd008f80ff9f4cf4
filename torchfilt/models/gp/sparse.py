"""Sparse variational GPs (SVGP, Hensman et al. 2015) for logs too large for an exact GP."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from torchfilt.models.gp.components import base_kernel

__all__ = ["SparseIndependentGP"]


class SparseIndependentGP(gpytorch.models.ApproximateGP):
    """``g`` independent SVGPs sharing inputs, batch shape ``(g,)``, whitened, learned inducing points.

    ``q(u_j) = N(m_j, S_j)`` over ``M`` inducing values per output (whitened, natural
    parameterisation), trained on the evidence lower bound with minibatches: natural-gradient steps
    for ``q(u)`` (Salimbeni, Eleftheriadis & Hensman 2018), Adam for the hyperparameters and the
    inducing inputs.

    Args:
        inducing: initial inducing inputs (standardised), shape ``(g, M, D)``.
        kernel: kernel name.
    """

    def __init__(self, inducing: Tensor, kernel: str) -> None:
        g, M, D = inducing.shape
        batch = torch.Size([g])
        q = gpytorch.variational.NaturalVariationalDistribution(M, batch_shape=batch)
        strategy = gpytorch.variational.VariationalStrategy(
            self, inducing, q, learn_inducing_locations=True
        )
        super().__init__(strategy)
        self.mean_module = gpytorch.means.ConstantMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            base_kernel(kernel, D, batch), batch_shape=batch
        )
        self.to(inducing.dtype)

    @torch.no_grad()
    def init_prior(self) -> None:
        """Start ``q(u)`` at the (whitened) prior ``N(0, I)``, deterministically (GPyTorch's own
        initialisation adds random noise from the global generator)."""
        strat = self.variational_strategy
        dist = strat._variational_distribution
        M = dist.natural_vec.shape[-1]
        eye = torch.eye(M, dtype=dist.natural_vec.dtype, device=dist.natural_vec.device)
        dist.natural_vec.zero_()
        dist.natural_mat.copy_(-0.5 * eye.expand_as(dist.natural_mat))
        strat.variational_params_initialized.fill_(1)

    def variational_moments(self) -> tuple[Tensor, Tensor]:
        """Whitened variational mean ``(g, M)`` and lower Cholesky factor of its covariance
        ``(g, M, M)``."""
        q = self.variational_strategy._variational_distribution()
        root = getattr(q.lazy_covariance_matrix, "root", None)
        chol = root.to_dense() if root is not None else torch.linalg.cholesky(q.covariance_matrix)
        return q.mean, chol

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
