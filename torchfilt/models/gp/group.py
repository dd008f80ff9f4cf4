"""One output group: the outputs that share a GPyTorch model (same inputs, same training rows)."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import gpytorch
import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError
from torchfilt.models.gp.components import gaussian_likelihood, lengthscale_of
from torchfilt.models.gp.exact import ExactIndependentGP
from torchfilt.models.gp.multitask import ExactMultitaskGP, multitask_likelihood
from torchfilt.models.gp.settings import exact_settings, gpytorch_default_settings
from torchfilt.models.gp.sparse import SparseIndependentGP

__all__ = ["GPGroup", "GroupPosterior"]


class GroupPosterior(NamedTuple):
    """Standardised predictive moments of a group at ``N`` points.

    Attributes:
        mean: ``(N, g)``.
        var: latent variance plus noise, ``(N, g)``.
        cov: ``(N, g, g)`` for a multitask group (else ``None``).
    """

    mean: Tensor
    var: Tensor
    cov: Tensor | None


class GPGroup(nn.Module):
    """A batch GP over ``g`` outputs that see the same input features and the same rows.

    The training data are buffers (standardised), so a state dict carries them.

    Args:
        structure: ``"independent"``, ``"multitask"`` or ``"sparse"``.
        train_x: standardised inputs, shape ``(S, D)``.
        train_y: standardised targets, shape ``(g, S)``.
        kernel: kernel name.
        floor: noise-variance floor per output (standardised), shape ``(g,)``.
        noise_init: initial or fixed noise per output, shape ``(g,)``.
        noise_fixed: hold the noise fixed.
        num_latents: LMC latents (multitask).
        task_rank: LMC rank (multitask).
        num_inducing: inducing points (sparse).
        generator: seeds random initialisation (inducing points, LMC factors).
    """

    train_x: Tensor
    train_y: Tensor

    def __init__(
        self,
        structure: str,
        train_x: Tensor,
        train_y: Tensor,
        *,
        kernel: str,
        floor: Tensor,
        noise_init: Tensor,
        noise_fixed: bool,
        num_latents: int = 1,
        task_rank: int = 1,
        num_inducing: int = 256,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.structure = structure
        self.register_buffer("train_x", train_x)
        self.register_buffer("train_y", train_y)
        g, S = train_y.shape
        self.kernel = kernel
        self._fit_rows: Tensor | None = None
        self._cache_mode: str | None = None
        if structure == "independent":
            self.likelihood = gaussian_likelihood(floor, noise_init, noise_fixed)
            self.gp: gpytorch.models.GP = ExactIndependentGP(
                train_x, train_y, self.likelihood, kernel
            )
        elif structure == "multitask":
            self.likelihood = multitask_likelihood(floor, noise_init, noise_fixed)
            self.gp = ExactMultitaskGP(
                train_x, train_y.T, self.likelihood, kernel, num_latents, task_rank, generator
            )
        elif structure == "sparse":
            M = min(num_inducing, S)
            rows = torch.stack([torch.randperm(S, generator=generator)[:M] for _ in range(g)]).to(
                train_x.device
            )
            inducing = train_x[rows].clone()  # (g, M, D)
            self.likelihood = gaussian_likelihood(floor, noise_init, noise_fixed)
            self.gp = SparseIndependentGP(inducing, kernel)
            self.gp.init_prior()
        else:
            raise InputError(f"unknown structure {structure!r}")

    # ------------------------------------------------------------------ sizes
    @property
    def num_outputs(self) -> int:
        return int(self.train_y.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.train_y.shape[1])

    # ------------------------------------------------------------------ training
    def variational_parameters(self) -> list[nn.Parameter]:
        """The natural parameters of ``q(u)`` (sparse groups; empty otherwise)."""
        if self.structure != "sparse":
            return []
        return list(self.gp.variational_strategy._variational_distribution.parameters())

    def use_rows(self, rows: Tensor | None) -> None:
        """Train an exact group's hyperparameters on a subset of its rows (``None``: all rows)."""
        if self.structure == "sparse":
            return
        x = self.train_x if rows is None else self.train_x[rows]
        y = self.train_y if rows is None else self.train_y[:, rows]
        if self.structure == "independent":
            self.gp.set_train_data(x.expand(y.shape[0], *x.shape), y, strict=False)
        else:
            self.gp.set_train_data(x, y.T, strict=False)
        self._fit_rows = rows
        self._cache_mode = None

    def loss(self, batch: Tensor | None = None) -> Tensor:
        """Negative log marginal likelihood (exact) or negative ELBO (sparse), per point, summed
        over the group's outputs. ``batch`` selects the minibatch rows of a sparse group."""
        self.gp.train()
        self.likelihood.train()
        with exact_settings():
            if self.structure == "sparse":
                rows = batch if batch is not None else torch.arange(self.num_points)
                x = self.train_x[rows]
                y = self.train_y[:, rows]
                out = self.gp(x.expand(y.shape[0], *x.shape))
                elbo = gpytorch.mlls.VariationalELBO(
                    self.likelihood, self.gp, num_data=self.num_points
                )
                return -elbo(out, y).sum()
            mll = gpytorch.mlls.ExactMarginalLogLikelihood(self.likelihood, self.gp)
            inputs = self.gp.train_inputs[0]
            out = self.gp(inputs)
            return -mll(out, self.gp.train_targets).sum()

    # ------------------------------------------------------------------ GPyTorch prediction
    def posterior(self, z: Tensor, *, fast_pred_var: bool = False) -> GroupPosterior:
        """GPyTorch's predictive moments (eval mode) at standardised points ``z`` ``(N, D)``.

        Args:
            z: points, shape ``(N, D)``.
            fast_pred_var: use GPyTorch's default numerics with LOVE
                (:func:`~torchfilt.models.gp.settings.gpytorch_default_settings`), for benchmarks;
                default: :func:`~torchfilt.models.gp.settings.exact_settings`.
        """
        mode = "fast" if fast_pred_var else "exact"
        if self._fit_rows is not None:
            self.use_rows(None)
        if self._cache_mode != mode and hasattr(self.gp, "prediction_strategy"):
            # The cached solves depend on the settings they were computed under.
            self.gp.prediction_strategy = None
        self._cache_mode = mode
        self.gp.eval()
        self.likelihood.eval()
        ctx = gpytorch_default_settings() if fast_pred_var else exact_settings()
        with ctx, warnings.catch_warnings():
            # Predicting at the training inputs in eval mode is intended here (not a forgotten
            # model.train()).
            warnings.simplefilter("ignore", gpytorch.utils.warnings.GPInputWarning)
            if self.structure == "multitask":
                out = self.likelihood(self.gp(z))
                mean = out.mean  # (N, d)
                N, d = mean.shape
                full = out.covariance_matrix  # interleaved: row i*d + t
                idx = torch.arange(N, device=z.device)
                blocks = full.reshape(N, d, N, d)[idx, :, idx, :]  # (N, d, d)
                return GroupPosterior(mean, blocks.diagonal(dim1=-2, dim2=-1), blocks)
            g = self.num_outputs
            out = self.likelihood(self.gp(z.expand(g, *z.shape)))
            return GroupPosterior(out.mean.T, out.variance.T, None)

    # ------------------------------------------------------------------ hyperparameters
    def noise(self) -> Tensor:
        """Likelihood noise variance per output (standardised), shape ``(g,)``."""
        if self.structure == "multitask":
            return self.likelihood.task_noises.reshape(-1)
        return self.likelihood.noise.reshape(-1)

    def hyperparameters(self, detach: bool = True) -> dict[str, Tensor]:
        """Current hyperparameters (standardised units), detached unless ``detach=False`` (then
        they carry the graph from the raw parameters)."""
        out: dict[str, Tensor] = {"noise": self.noise()}
        if self.structure == "multitask":
            kl = self.gp.covar_module.covar_module_list
            out["lengthscale"] = torch.stack([lengthscale_of(k.data_covar_module) for k in kl])
            out["task_covar"] = torch.stack(
                [k.task_covar_module.covar_matrix.to_dense() for k in kl]
            )
            out["constant"] = torch.stack(
                [m.constant.reshape(()) for m in self.gp.mean_module.base_means]
            )
        else:
            out["lengthscale"] = lengthscale_of(self.gp.covar_module.base_kernel)
            out["outputscale"] = self.gp.covar_module.outputscale.reshape(-1)
            out["constant"] = self.gp.mean_module.constant.reshape(-1)
        if not detach:
            return out
        return {k: v.detach().clone() for k, v in out.items()}
