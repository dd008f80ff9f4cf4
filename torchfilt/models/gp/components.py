"""GPyTorch building blocks shared by the exact, multitask and sparse GP modules."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.models.gp.kernels import KERNELS

__all__ = ["base_kernel", "bound_arg", "gaussian_likelihood", "lengthscale_of"]

#: Initial ARD lengthscale in standardised input units.
INIT_LENGTHSCALE = 1.0


def base_kernel(
    kind: str, dims: int, batch_shape: torch.Size | None = None
) -> gpytorch.kernels.Kernel:
    """A unit-variance ARD kernel (``RBFKernel`` or ``MaternKernel``) over ``dims`` inputs.

    Args:
        kind: one of :data:`~torchfilt.models.gp.kernels.KERNELS`.
        dims: number of inputs (one lengthscale each).
        batch_shape: GPyTorch batch shape (one kernel per output).

    Returns:
        The kernel, lengthscales initialised to :data:`INIT_LENGTHSCALE`.
    """
    if kind not in KERNELS:
        raise InputError(f"kernel must be one of {sorted(KERNELS)}, got {kind!r}")
    nu = KERNELS[kind]
    batch_shape = torch.Size() if batch_shape is None else batch_shape
    batch_shape = torch.Size() if batch_shape is None else batch_shape
    if nu is None:
        k: gpytorch.kernels.Kernel = gpytorch.kernels.RBFKernel(
            ard_num_dims=dims, batch_shape=batch_shape
        )
    else:
        k = gpytorch.kernels.MaternKernel(nu=nu, ard_num_dims=dims, batch_shape=batch_shape)
    k.lengthscale = torch.full_like(k.lengthscale, INIT_LENGTHSCALE)
    return k


def lengthscale_of(kernel: gpytorch.kernels.Kernel) -> Tensor:
    """ARD lengthscales of a base kernel, shape ``(*batch, D)``."""
    return kernel.lengthscale.squeeze(-2)


def bound_arg(bound: Tensor) -> Tensor | float:
    """GPyTorch's constraint ``repr`` formats a one-element bound as a scalar; give it one."""
    return float(bound.reshape(())) if bound.numel() == 1 else bound


def gaussian_likelihood(
    floor: Tensor, init: Tensor, fixed: bool
) -> gpytorch.likelihoods.GaussianLikelihood:
    """A batch ``GaussianLikelihood`` with a per-output noise floor.

    Args:
        floor: lower bound of each output's noise variance, shape ``(g,)`` (standardised units).
        init: initial (or fixed) noise variance, shape ``(g,)``.
        fixed: hold the noise at ``init`` instead of learning it.

    Returns:
        The likelihood, batch shape ``(g,)``.
    """
    g = floor.shape[0]
    bound = torch.zeros_like(floor) if fixed else floor
    lik = gpytorch.likelihoods.GaussianLikelihood(
        batch_shape=torch.Size([g]),
        noise_constraint=gpytorch.constraints.GreaterThan(bound_arg(bound.unsqueeze(-1))),
    ).to(floor.dtype)
    # GPyTorch stores bounds in the default dtype; copy the exact value in the model's dtype.
    low = lik.noise_covar.raw_noise_constraint.lower_bound
    low.copy_(bound.unsqueeze(-1).reshape(low.shape))
    start = init if fixed else torch.maximum(init, 2.0 * floor)
    lik.noise = start.unsqueeze(-1).to(floor.dtype)
    if fixed:
        lik.raw_noise.requires_grad_(False)
    return lik
