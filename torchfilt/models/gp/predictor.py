"""The frozen predictor: a GP's posterior with every training-set solve cached, in plain torch.

After training, ``alpha = (K + s^2 I)^{-1} (y - c)`` and a root ``R`` of ``(K + s^2 I)^{-1}`` (see
:mod:`~torchfilt.models.gp.root`) do not change. A prediction at ``N`` points then costs kernel
evaluations against the ``S`` training (or ``M`` inducing) inputs and two matrix products:

    mean = c + k*^T alpha
    var  = s_f^2 - |k*^T R|^2 + s^2                    (exact GP; exact or low-rank R)
    var  = s_f^2 + j + k*^T W k* + s^2                  (SVGP: W = L^{-T} (S_u - I) L^{-1},
                                                         L L^T = K_uu + j I, j GPyTorch's jitter)

No GPyTorch call, no solve per step, differentiable in the points (autograd). Large batches are
processed in chunks of ``chunk_size`` points (one ``(N, S)`` kernel matrix for a huge ``N`` is slower
than several small ones). Inputs are standardised and outputs de-standardised inside.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.models.gp.kernels import correlation, scaled_sq_dist
from torchfilt.models.gp.root import exact_root, lowrank_root

__all__ = ["FrozenGP", "FrozenOutput", "VarianceMode"]

VarianceMode = Literal["exact", "lowrank", "sparse"]

#: Default number of points per kernel chunk.
CHUNK_SIZE = 128


class FrozenOutput(NamedTuple):
    """Predictive moments in target units (before adding any prior mean).

    Attributes:
        mean: ``(N, d)``.
        var: latent variance + noise, ``(N, d)``.
        cov: ``(N, d, d)`` for correlated outputs, else ``None``.
    """

    mean: Tensor
    var: Tensor
    cov: Tensor | None


class _Block(nn.Module):
    """Frozen state of one output group (non-persistent buffers: recomputed, never saved)."""

    outputs: Tensor
    features: Tensor
    in_shift: Tensor
    scale: Tensor
    points: Tensor
    points_sq: Tensor
    alpha: Tensor
    const: Tensor
    noise: Tensor
    out_shift: Tensor
    out_scale: Tensor

    def _buf(self, name: str, value: Tensor | None) -> None:
        self.register_buffer(
            name, None if value is None else value.detach().clone(), persistent=False
        )

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:  # pragma: no cover
        raise NotImplementedError


class _IndependentBlock(_Block):
    """``g`` independent outputs: exact GP (exact or low-rank root) or SVGP (middle matrix)."""

    outputscale: Tensor
    prior_var: Tensor
    root: Tensor | None
    middle: Tensor | None

    def __init__(
        self,
        *,
        kernel: str,
        outputs: Tensor,
        features: Tensor,
        in_shift: Tensor,
        in_scale: Tensor,
        lengthscale: Tensor,
        points: Tensor,
        alpha: Tensor,
        const: Tensor,
        outputscale: Tensor,
        noise: Tensor,
        extra_diag: Tensor,
        out_shift: Tensor,
        out_scale: Tensor,
        root: Tensor | None = None,
        middle: Tensor | None = None,
    ) -> None:
        super().__init__()
        self.kernel = kernel
        scale = in_scale.unsqueeze(0) * lengthscale  # (g, D)
        pts = points / lengthscale.unsqueeze(-2)  # points: (g, S, D) standardised
        self._buf("outputs", outputs)
        self._buf("features", features)
        self._buf("in_shift", in_shift)
        self._buf("scale", scale)
        self._buf("points", pts)  # (g, S, D), inputs / lengthscale
        self._buf("points_sq", pts.pow(2).sum(-1))
        self._buf("alpha", alpha.unsqueeze(-1))  # (g, S, 1)
        self._buf("const", const)
        self._buf("outputscale", outputscale)
        self._buf("prior_var", outputscale + extra_diag)
        self._buf("noise", noise)
        self._buf("out_shift", out_shift)
        self._buf("out_scale", out_scale)
        self._buf("root", root)
        self._buf("middle", middle)

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        zs = (z[:, self.features] - self.in_shift).unsqueeze(0) / self.scale.unsqueeze(-2)
        d2 = scaled_sq_dist(zs, self.points, self.points_sq)  # (g, N, S)
        K = self.outputscale[:, None, None] * correlation(d2, self.kernel)
        mean = self.const.unsqueeze(-1) + (K @ self.alpha).squeeze(-1)  # (g, N)
        if self.root is not None:
            var = self.prior_var.unsqueeze(-1) - (K @ self.root).pow(2).sum(-1)
        else:
            assert self.middle is not None
            var = self.prior_var.unsqueeze(-1) + ((K @ self.middle) * K).sum(-1)
        var = var.clamp_min(0.0) + self.noise.unsqueeze(-1)
        return (
            (mean * self.out_scale.unsqueeze(-1) + self.out_shift.unsqueeze(-1)).T,
            (var * self.out_scale.pow(2).unsqueeze(-1)).T,
            None,
        )


class _MultitaskBlock(_Block):
    """Correlated outputs (LMC): ``K = sum_q k_q (x) B_q`` in data-major order ``i * d + t``."""

    task_covar: Tensor
    root: Tensor

    def __init__(
        self,
        *,
        kernel: str,
        outputs: Tensor,
        features: Tensor,
        in_shift: Tensor,
        in_scale: Tensor,
        lengthscale: Tensor,
        points: Tensor,
        task_covar: Tensor,
        alpha: Tensor,
        const: Tensor,
        noise: Tensor,
        out_shift: Tensor,
        out_scale: Tensor,
        root: Tensor,
    ) -> None:
        super().__init__()
        self.kernel = kernel
        scale = in_scale.unsqueeze(0) * lengthscale  # (Q, D)
        pts = points.unsqueeze(0) / lengthscale.unsqueeze(-2)  # (Q, S, D)
        self._buf("outputs", outputs)
        self._buf("features", features)
        self._buf("in_shift", in_shift)
        self._buf("scale", scale)
        self._buf("points", pts)
        self._buf("points_sq", pts.pow(2).sum(-1))
        self._buf("task_covar", task_covar)  # (Q, d, d)
        self._buf("alpha", alpha.reshape(-1, 1))  # (S d, 1)
        self._buf("const", const)
        self._buf("noise", noise)
        self._buf("out_shift", out_shift)
        self._buf("out_scale", out_scale)
        self._buf("root", root)  # (S d, r)

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        zs = (z[:, self.features] - self.in_shift).unsqueeze(0) / self.scale.unsqueeze(-2)
        d2 = scaled_sq_dist(zs, self.points, self.points_sq)  # (Q, N, S)
        k = correlation(d2, self.kernel)
        N, S = k.shape[1], k.shape[2]
        d = self.task_covar.shape[-1]
        Kfull = torch.einsum("qns,qtu->ntsu", k, self.task_covar).reshape(N, d, S * d)
        mean = self.const + (Kfull @ self.alpha).squeeze(-1)  # (N, d)
        A = Kfull @ self.root  # (N, d, r)
        cov = self.task_covar.sum(0) - A @ A.mT + torch.diag_embed(self.noise)
        cov = 0.5 * (cov + cov.mT)
        s = self.out_scale
        cov = cov * (s.unsqueeze(-1) * s.unsqueeze(-2))
        return mean * s + self.out_shift, cov.diagonal(dim1=-2, dim2=-1), cov


class FrozenGP(nn.Module):
    """A trained GP model's posterior with all training-set solves cached.

    Build it with :meth:`GPModel.freeze() <torchfilt.models.gp.GPModel.freeze>`; call it on raw
    (unstandardised) features ``[x, u]``.

    Args:
        blocks: one frozen block per output group.
        out_dim: number of outputs ``d``.
        variance: the variance mode the blocks were built with.
        rank: the low-rank root's rank (``variance="lowrank"``).
        chunk_size: points per kernel chunk.
    """

    def __init__(
        self,
        blocks: Sequence[nn.Module],
        out_dim: int,
        variance: VarianceMode,
        rank: int | None,
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(blocks)
        self.out_dim = int(out_dim)
        self.variance = variance
        self.rank = rank
        self.chunk_size = int(chunk_size)
        self.correlated = any(isinstance(b, _MultitaskBlock) for b in blocks)

    def _dtype(self) -> torch.dtype:
        blk = self.blocks[0]
        assert isinstance(blk, _Block)
        return blk.alpha.dtype

    def forward(self, z: Tensor) -> FrozenOutput:
        """Predictive moments at features ``z`` ``(..., F)``; returns ``(..., d)`` tensors."""
        lead = z.shape[:-1]
        flat = z.reshape(-1, z.shape[-1]).to(self._dtype())
        means, vars_, covs = [], [], []
        for start in range(0, max(flat.shape[0], 1), self.chunk_size):
            m, v, c = self._chunk(flat[start : start + self.chunk_size])
            means.append(m)
            vars_.append(v)
            if c is not None:
                covs.append(c)
        d = self.out_dim
        mean = torch.cat(means).reshape(*lead, d).to(z.dtype)
        var = torch.cat(vars_).reshape(*lead, d).to(z.dtype)
        cov = torch.cat(covs).reshape(*lead, d, d).to(z.dtype) if covs else None
        return FrozenOutput(mean, var, cov)

    def _chunk(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        N, d = z.shape[0], self.out_dim
        if len(self.blocks) == 1:
            m, v, c = self.blocks[0](z)
            b = self.blocks[0]
            assert isinstance(b, _Block)
            if torch.equal(b.outputs, torch.arange(d, device=b.outputs.device)):
                return m, v, c
        mean = z.new_zeros(N, d)
        var = z.new_zeros(N, d)
        cov = z.new_zeros(N, d, d) if self.correlated else None
        for blk in self.blocks:
            assert isinstance(blk, _Block)
            m, v, c = blk(z)
            idx = blk.outputs
            mean = mean.index_copy(1, idx, m)
            var = var.index_copy(1, idx, v)
            if cov is not None:
                block = c if c is not None else torch.diag_embed(v)
                rows = cov.index_select(1, idx).index_copy(2, idx, block)
                cov = cov.index_copy(1, idx, rows)
        return mean, var, cov


def independent_block(
    *,
    kernel: str,
    outputs: Tensor,
    features: Tensor,
    in_shift: Tensor,
    in_scale: Tensor,
    train_x: Tensor,
    train_y: Tensor,
    hyper: dict[str, Tensor],
    out_shift: Tensor,
    out_scale: Tensor,
    variance: Literal["exact", "lowrank"],
    rank: int | None,
) -> _IndependentBlock:
    """Freeze an exact independent group: Cholesky of ``K + s^2 I``, ``alpha`` and a root.

    Args:
        kernel: kernel name.
        outputs: output indices ``(g,)``.
        features: feature indices ``(D,)``.
        in_shift: input standardisation shift of the selected features ``(D,)``.
        in_scale: input standardisation scale ``(D,)``.
        train_x: standardised training inputs ``(S, D)``.
        train_y: standardised targets ``(g, S)``.
        hyper: the group's hyperparameters (``lengthscale (g, D)``, ``outputscale``, ``noise``,
            ``constant``, all ``(g,)``).
        out_shift: target shift of the outputs ``(g,)``.
        out_scale: target scale ``(g,)``.
        variance: ``"exact"`` or ``"lowrank"``.
        rank: rank of the low-rank root.
    """
    ls, os_, noise, c = (
        hyper["lengthscale"],
        hyper["outputscale"],
        hyper["noise"],
        hyper["constant"],
    )
    pts = train_x.unsqueeze(0) / ls.unsqueeze(-2)  # (g, S, D)
    K = os_[:, None, None] * correlation(scaled_sq_dist(pts, pts), kernel)
    S = train_x.shape[0]
    Khat = K + noise[:, None, None] * torch.eye(S, dtype=K.dtype, device=K.device)
    L, info = torch.linalg.cholesky_ex(Khat)
    if bool((info > 0).any()):
        raise torch.linalg.LinAlgError(
            "K + noise I is not positive definite in the frozen predictor; the noise floor is "
            "too low for this dtype (train in float64 or raise noise_floor)"
        )
    alpha = torch.cholesky_solve((train_y - c.unsqueeze(-1)).unsqueeze(-1), L).squeeze(-1)
    root = exact_root(L) if variance == "exact" else lowrank_root(Khat, int(rank or 0))
    return _IndependentBlock(
        kernel=kernel,
        outputs=outputs,
        features=features,
        in_shift=in_shift,
        in_scale=in_scale,
        lengthscale=ls,
        points=train_x.unsqueeze(0).expand(ls.shape[0], -1, -1),
        alpha=alpha,
        const=c,
        outputscale=os_,
        noise=noise,
        extra_diag=torch.zeros_like(os_),
        out_shift=out_shift,
        out_scale=out_scale,
        root=root,
    )


def sparse_block(
    *,
    kernel: str,
    outputs: Tensor,
    features: Tensor,
    in_shift: Tensor,
    in_scale: Tensor,
    inducing: Tensor,
    var_mean: Tensor,
    var_chol: Tensor,
    jitter: float,
    hyper: dict[str, Tensor],
    out_shift: Tensor,
    out_scale: Tensor,
) -> _IndependentBlock:
    """Freeze an SVGP group (whitened): ``alpha = L^{-T} m``, ``W = L^{-T} (C C^T - I) L^{-1}``.

    Args:
        inducing: inducing inputs (standardised) ``(g, M, D)``.
        var_mean: whitened variational mean ``m`` ``(g, M)``.
        var_chol: lower Cholesky factor ``C`` of the whitened variational covariance ``(g, M, M)``.
        jitter: the diagonal jitter GPyTorch adds to ``K_uu`` and to the predictive covariance.
        Other arguments as in :func:`independent_block`.
    """
    ls, os_, noise, c = (
        hyper["lengthscale"],
        hyper["outputscale"],
        hyper["noise"],
        hyper["constant"],
    )
    pts = inducing / ls.unsqueeze(-2)
    M = inducing.shape[-2]
    eye = torch.eye(M, dtype=inducing.dtype, device=inducing.device)
    Kuu = os_[:, None, None] * correlation(scaled_sq_dist(pts, pts), kernel) + jitter * eye
    L = torch.linalg.cholesky(Kuu)
    Linv = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
    C = var_chol.tril()
    middle = Linv.mT @ (C @ C.mT - eye) @ Linv
    alpha = (Linv.mT @ var_mean.unsqueeze(-1)).squeeze(-1)
    return _IndependentBlock(
        kernel=kernel,
        outputs=outputs,
        features=features,
        in_shift=in_shift,
        in_scale=in_scale,
        lengthscale=ls,
        points=inducing,
        alpha=alpha,
        const=c,
        outputscale=os_,
        noise=noise,
        extra_diag=torch.full_like(os_, jitter),
        out_shift=out_shift,
        out_scale=out_scale,
        middle=0.5 * (middle + middle.mT),
    )


def multitask_block(
    *,
    kernel: str,
    outputs: Tensor,
    features: Tensor,
    in_shift: Tensor,
    in_scale: Tensor,
    train_x: Tensor,
    train_y: Tensor,
    hyper: dict[str, Tensor],
    out_shift: Tensor,
    out_scale: Tensor,
    variance: Literal["exact", "lowrank"],
    rank: int | None,
) -> _MultitaskBlock:
    """Freeze an LMC group: the ``(S d) x (S d)`` system in data-major order.

    Args:
        train_y: standardised targets ``(d, S)``.
        hyper: ``lengthscale (Q, D)``, ``task_covar (Q, d, d)``, ``constant (d,)``, ``noise (d,)``.
        Other arguments as in :func:`independent_block`.
    """
    ls, B, c, noise = hyper["lengthscale"], hyper["task_covar"], hyper["constant"], hyper["noise"]
    S, d = train_x.shape[0], B.shape[-1]
    pts = train_x.unsqueeze(0) / ls.unsqueeze(-2)
    k = correlation(scaled_sq_dist(pts, pts), kernel)  # (Q, S, S)
    K = torch.einsum("qij,qtu->itju", k, B).reshape(S * d, S * d)
    Khat = K + torch.diag(noise.repeat(S))
    L = torch.linalg.cholesky(Khat)
    resid = (train_y.T - c).reshape(-1, 1)  # data-major: row i * d + t
    alpha = torch.cholesky_solve(resid, L).squeeze(-1)
    root = exact_root(L) if variance == "exact" else lowrank_root(Khat, int(rank or 0))
    return _MultitaskBlock(
        kernel=kernel,
        outputs=outputs,
        features=features,
        in_shift=in_shift,
        in_scale=in_scale,
        lengthscale=ls,
        points=train_x,
        task_covar=B,
        alpha=alpha,
        const=c,
        noise=noise,
        out_shift=out_shift,
        out_scale=out_scale,
        root=root,
    )
