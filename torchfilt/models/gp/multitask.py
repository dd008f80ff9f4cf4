"""Correlated outputs: an exact GP with a linear model of coregionalisation (LMC)."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from torchfilt.models.gp.components import base_kernel, bound_arg

__all__ = ["ExactMultitaskGP", "multitask_likelihood"]

#: Initial scale of the coregionalisation factors (small: the outputs start nearly independent).
INIT_TASK_FACTOR = 0.1


class ExactMultitaskGP(gpytorch.models.ExactGP):
    """``d`` correlated outputs: ``K((x, i), (x', j)) = sum_q B_q[i, j] k_q(x, x')``.

    Each ``B_q = W_q W_q^T + diag(v_q)`` (rank ``task_rank``), each ``k_q`` a unit-variance ARD
    kernel; ``num_latents = 1`` is the intrinsic coregionalisation model. Noise is independent per
    output.

    Args:
        train_x: standardised inputs, shape ``(S, D)``.
        train_y: standardised targets, shape ``(S, d)``.
        likelihood: from :func:`multitask_likelihood`.
        kernel: kernel name.
        num_latents: number of latent kernels ``Q``.
        task_rank: rank of each ``W_q``.
        generator: seeds the coregionalisation factors.
    """

    def __init__(
        self,
        train_x: Tensor,
        train_y: Tensor,
        likelihood: gpytorch.likelihoods.MultitaskGaussianLikelihood,
        kernel: str,
        num_latents: int,
        task_rank: int,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(train_x, train_y, likelihood)
        d, D = train_y.shape[-1], train_x.shape[-1]
        self.num_tasks = d
        self.mean_module = gpytorch.means.MultitaskMean(gpytorch.means.ConstantMean(), num_tasks=d)
        kernels = [base_kernel(kernel, D) for _ in range(num_latents)]
        for q, k in enumerate(kernels):  # distinct starting lengthscales break the symmetry
            k.lengthscale = k.lengthscale * (2.0**q)
        self.covar_module = gpytorch.kernels.LCMKernel(kernels, num_tasks=d, rank=task_rank)
        for q, mk in enumerate(self.covar_module.covar_module_list):
            idx = mk.task_covar_module
            w = torch.randn(idx.covar_factor.shape, generator=generator)
            idx.covar_factor.data.copy_(INIT_TASK_FACTOR * w / (q + 1))
            idx.var = torch.full_like(idx.var, 1.0 / num_latents)
        self.to(train_y.dtype)

    def forward(self, x: Tensor) -> gpytorch.distributions.MultitaskMultivariateNormal:
        return gpytorch.distributions.MultitaskMultivariateNormal(
            self.mean_module(x), self.covar_module(x)
        )


def multitask_likelihood(
    floor: Tensor, init: Tensor, fixed: bool
) -> gpytorch.likelihoods.MultitaskGaussianLikelihood:
    """Independent per-output noise for a multitask GP (no shared global noise).

    Args:
        floor: noise-variance lower bound per output, shape ``(d,)``.
        init: initial (or fixed) noise per output, shape ``(d,)``.
        fixed: hold the noise fixed.
    """
    d = floor.shape[0]
    bound = torch.zeros_like(floor) if fixed else floor
    lik = gpytorch.likelihoods.MultitaskGaussianLikelihood(
        num_tasks=d,
        rank=0,
        has_global_noise=False,
        noise_constraint=gpytorch.constraints.GreaterThan(bound_arg(bound)),
    ).to(floor.dtype)
    low = lik.raw_task_noises_constraint.lower_bound
    low.copy_(bound.reshape(low.shape))
    lik.task_noises = (init if fixed else torch.maximum(init, 2.0 * floor)).to(floor.dtype)
    if fixed:
        lik.raw_task_noises.requires_grad_(False)
    return lik
