"""The frozen blocks of :class:`~torchfilt.models.gp.predictor.FrozenGP`: one output group each
(independent outputs of an exact GP or an SVGP, or correlated LMC outputs), every training-set
solve cached; and the kernel matrices and factors they are built from.
"""

from __future__ import annotations

from abc import abstractmethod

import torch
from torch import Tensor, nn

from torchfilt.models.gp.kernels import correlation, scaled_sq_dist

__all__ = ["independent_khat", "multitask_khat", "stack_key"]


class _Block(nn.Module):
    """Frozen state of one output group (non-persistent buffers: recomputed, never saved).

    Attributes:
        form: ``"exact"``, ``"lowrank"`` or ``"sparse"``.
        rank: rank of a low-rank form.
    """

    outputs: Tensor
    features: Tensor
    points: Tensor
    points_sq: Tensor
    alpha: Tensor
    noise: Tensor
    factor: Tensor

    cache_args: dict[str, Tensor]

    def __init__(
        self, kernel: str, form: str, rank: int | None, differentiable: bool = False
    ) -> None:
        super().__init__()
        self.kernel = kernel
        self.form = form
        self.rank = rank
        self.differentiable = differentiable

    def _buf(self, name: str, value: Tensor | None) -> None:
        # a differentiable twin keeps the graph from the hyperparameters to its caches
        if value is not None and not self.differentiable:
            value = value.detach().clone()
        self.register_buffer(name, value, persistent=False)

    @abstractmethod
    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """Mean ``(N, g)``, variance ``(N, g)`` and, for correlated outputs, covariance
        ``(N, g, g)`` at features ``z`` ``(N, F)``."""

    @abstractmethod
    def mean(self, z: Tensor) -> Tensor:
        """The predictive mean alone, ``(N, F) -> (N, g)`` (the same arithmetic as ``forward``)."""


class _IndependentBlock(_Block):
    """``g`` independent outputs sharing inputs (exact GP or SVGP).

    Everything affine is folded into cached tensors: the points are mapped to
    ``(z - shift) / (scale * lengthscale)`` by one ``addcmul``, the outputscale and the output
    de-standardisation are folded into ``alpha``, the variance factor and the noise, so a call is
    about a dozen tensor operations.
    """

    in_weight: Tensor
    in_bias: Tensor
    mean0: Tensor
    var0: Tensor
    qscale: Tensor

    def __init__(
        self,
        *,
        kernel: str,
        form: str,
        rank: int | None,
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
        factor: Tensor,
        differentiable: bool = False,
    ) -> None:
        super().__init__(kernel, form, rank, differentiable)
        self.cache_args = _cache_args(
            form,
            outputs=outputs,
            features=features,
            in_shift=in_shift,
            in_scale=in_scale,
            lengthscale=lengthscale,
            points=points,
            alpha=alpha,
            const=const,
            outputscale=outputscale,
            noise=noise,
            extra_diag=extra_diag,
            out_shift=out_shift,
            out_scale=out_scale,
            factor=factor,
        )
        pts = points / lengthscale.unsqueeze(-2)  # points: (g, S, D) standardised
        weight = 1.0 / (in_scale.unsqueeze(0) * lengthscale)  # (g, D)
        amp = outputscale * out_scale  # (g,): kernel amplitude in target units
        # features 0..D-1 of a D-column input need no gather
        self.prefix = bool(torch.equal(features.cpu(), torch.arange(features.shape[0])))
        self.num_selected = int(features.shape[0])
        self._buf("outputs", outputs)
        self._buf("features", features)
        self._buf("in_weight", weight.unsqueeze(-2))  # (g, 1, D)
        self._buf("in_bias", (-in_shift * weight).unsqueeze(-2))
        self._buf("points", pts)
        self._buf("points_sq", pts.pow(2).sum(-1))
        self._buf("alpha", (alpha * amp.unsqueeze(-1)).unsqueeze(-1))  # (g, S, 1)
        self._buf("mean0", (out_shift + out_scale * const).unsqueeze(-1))  # (g, 1)
        self._buf("var0", ((outputscale + extra_diag) * out_scale.pow(2)).unsqueeze(-1))
        self._buf("noise", (noise * out_scale.pow(2)).unsqueeze(-1))
        if form == "lowrank":
            factor = factor * amp[:, None, None]
        elif form == "sparse":
            factor = factor * amp.pow(2)[:, None, None]
        self._buf("qscale", amp.pow(2).unsqueeze(-1))  # exact form: |L^-1 c|^2 * amp^2
        self._buf("factor", factor)

    @classmethod
    def stacked(cls, blocks: list[_IndependentBlock]) -> _IndependentBlock:
        """One block computing the outputs of ``blocks`` at once: each one's training (or
        inducing) points padded to the largest count with zeros, whose ``alpha`` and variance
        factor rows are zero, so the padding adds nothing to the mean or the variance.

        Only frozen low-rank blocks of one kernel, one rank and the same input features, or
        sparse ones of one kernel, one inducing count and the same features (no padding then),
        stack (an exact block's triangular solve would count the padding); the caller checks
        (:func:`stack_key`). For the outputs of a GP whose outputs were fitted on
        different rows (missing measurements), which become one block per output.
        """
        first = blocks[0]
        out = cls.__new__(cls)
        _Block.__init__(out, first.kernel, first.form, first.rank, False)
        out.cache_args = {}  # a stacked block is built from cached blocks, never cached itself
        out.prefix, out.num_selected = first.prefix, first.num_selected
        S = max(int(b.points.shape[1]) for b in blocks)

        def padded(name: str) -> Tensor:
            parts = []
            for b in blocks:
                t = getattr(b, name)
                if t.shape[1] < S:
                    fill = t.new_zeros((t.shape[0], S - t.shape[1], *t.shape[2:]))
                    t = torch.cat([t, fill], 1)
                parts.append(t)
            return torch.cat(parts, 0)

        for name in ("points", "points_sq", "alpha", "factor"):
            out._buf(name, padded(name))
        for name in ("outputs", "in_weight", "in_bias", "mean0", "var0", "noise", "qscale"):
            out._buf(name, torch.cat([getattr(b, name) for b in blocks], 0))
        out._buf("features", first.features)
        return out

    def correlation_rows(self, z: Tensor) -> Tensor:
        """Unit-variance ``k(z, X)`` for every output, ``(N, F)`` -> ``(g, N, S)``."""
        whole = self.prefix and z.shape[-1] == self.num_selected
        zf = z if whole else z[:, self.features]
        zs = torch.addcmul(self.in_bias, zf.unsqueeze(0), self.in_weight)  # (g, N, D)
        return correlation(scaled_sq_dist(zs, self.points, self.points_sq), self.kernel)

    def mean(self, z: Tensor) -> Tensor:
        c = self.correlation_rows(z)
        return torch.baddbmm(self.mean0.unsqueeze(-1), c, self.alpha).squeeze(-1).T

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        c = self.correlation_rows(z)  # (g, N, S)
        mean = torch.baddbmm(self.mean0.unsqueeze(-1), c, self.alpha).squeeze(-1)  # (g, N)
        if self.form == "exact":
            w = torch.linalg.solve_triangular(self.factor, c.mT, upper=False)
            var = self.var0 - self.qscale * w.pow(2).sum(-2)
        elif self.form == "lowrank":
            var = self.var0 - (c @ self.factor).pow(2).sum(-1)
        else:
            var = self.var0 + ((c @ self.factor) * c).sum(-1)
        var = var.clamp_min(0.0) + self.noise
        return mean.T, var.T, None


class _MultitaskBlock(_Block):
    """Correlated outputs (LMC): ``K = sum_q k_q (x) B_q`` in data-major order ``i * d + t``."""

    task_covar: Tensor
    in_shift: Tensor
    scale: Tensor
    const: Tensor
    out_shift: Tensor
    out_scale: Tensor

    def __init__(
        self,
        *,
        kernel: str,
        form: str,
        rank: int | None,
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
        factor: Tensor,
    ) -> None:
        super().__init__(kernel, form, rank)
        self.cache_args = _cache_args(
            form,
            outputs=outputs,
            features=features,
            in_shift=in_shift,
            in_scale=in_scale,
            lengthscale=lengthscale,
            points=points,
            task_covar=task_covar,
            alpha=alpha,
            const=const,
            noise=noise,
            out_shift=out_shift,
            out_scale=out_scale,
            factor=factor,
        )
        pts = points.unsqueeze(0) / lengthscale.unsqueeze(-2)  # (Q, S, D)
        self._buf("outputs", outputs)
        self._buf("features", features)
        self._buf("in_shift", in_shift)
        self._buf("scale", in_scale.unsqueeze(0) * lengthscale)  # (Q, D)
        self._buf("points", pts)
        self._buf("points_sq", pts.pow(2).sum(-1))
        self._buf("task_covar", task_covar)  # (Q, d, d)
        self._buf("alpha", alpha.reshape(-1, 1))  # (S d, 1)
        self._buf("const", const)
        self._buf("noise", noise)
        self._buf("out_shift", out_shift)
        self._buf("out_scale", out_scale)
        self._buf("factor", factor)

    def kernel_rows(self, z: Tensor) -> Tensor:
        """Cross-covariances of the ``d`` outputs at ``z`` with the training system,
        ``(N, F)`` -> ``(N, d, S d)``."""
        zs = (z[:, self.features] - self.in_shift).unsqueeze(0) / self.scale.unsqueeze(-2)
        k = correlation(scaled_sq_dist(zs, self.points, self.points_sq), self.kernel)
        N, S, d = k.shape[1], k.shape[2], self.task_covar.shape[-1]
        return torch.einsum("qns,qtu->ntsu", k, self.task_covar).reshape(N, d, S * d)

    def mean(self, z: Tensor) -> Tensor:
        c = self.kernel_rows(z)
        mean = self.const + (c @ self.alpha).squeeze(-1)
        return mean * self.out_scale + self.out_shift

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        c = self.kernel_rows(z)  # (N, d, S d)
        mean = self.const + (c @ self.alpha).squeeze(-1)  # (N, d)
        if self.form == "exact":
            A = torch.linalg.solve_triangular(self.factor, c.mT, upper=False).mT
        else:
            A = c @ self.factor  # (N, d, r)
        cov = self.task_covar.sum(0) - A @ A.mT + torch.diag_embed(self.noise)
        cov = 0.5 * (cov + cov.mT)
        s = self.out_scale
        cov = cov * (s.unsqueeze(-1) * s.unsqueeze(-2))
        return mean * s + self.out_shift, cov.diagonal(dim1=-2, dim2=-1), cov


def stack_key(block: nn.Module) -> tuple[object, ...] | None:
    """What blocks must share to be :meth:`_IndependentBlock.stacked` together (``None``: this
    one does not stack): kernel, form, input features and the factor's last size (a low-rank
    block's rank; a sparse block's inducing count, so sparse blocks never need padding)."""
    if type(block) is not _IndependentBlock or block.differentiable:
        return None
    if block.form not in ("lowrank", "sparse"):
        return None
    features = tuple(int(i) for i in block.features.tolist())
    return (block.kernel, block.form, int(block.factor.shape[-1]), features)


def _cache_args(form: str, **args: Tensor) -> dict[str, Tensor]:
    """A block's constructor arguments, less an exact form's factor (recomputed from the rest)."""
    return {k: v.detach() for k, v in args.items() if not (k == "factor" and form == "exact")}


def independent_khat(
    kernel: str, points: Tensor, lengthscale: Tensor, outputscale: Tensor, noise: Tensor
) -> tuple[Tensor, Tensor]:
    """``K`` and ``K + s^2 I`` of an independent group, ``(g, S, S)`` each.

    Args:
        kernel: kernel name.
        points: standardised training inputs ``(g, S, D)`` (or ``(S, D)``).
        lengthscale: ``(g, D)``; outputscale, noise: ``(g,)``.
    """
    K = _independent_k(kernel, points, lengthscale, outputscale)
    Khat = K.clone()
    Khat.diagonal(dim1=-2, dim2=-1).add_(noise.unsqueeze(-1))
    return K, Khat


def _independent_k(kernel: str, points: Tensor, lengthscale: Tensor, outputscale: Tensor) -> Tensor:
    """``K = s_f^2 k(X, X)`` of an independent group, ``(g, S, S)``, in one fresh buffer."""
    pts = points / lengthscale.unsqueeze(-2)  # (g, S, D)
    k = correlation(scaled_sq_dist(pts, pts), kernel)
    if k.requires_grad or outputscale.requires_grad:  # a differentiable twin: out of place
        return k * outputscale[:, None, None]
    return k.mul_(outputscale[:, None, None])


def _independent_factor(
    kernel: str, points: Tensor, lengthscale: Tensor, outputscale: Tensor, noise: Tensor
) -> Tensor:
    """The Cholesky factor of ``K + s^2 I`` (the same numbers as :func:`independent_khat`,
    without keeping ``K``)."""
    Khat = _independent_k(kernel, points, lengthscale, outputscale)
    Khat.diagonal(dim1=-2, dim2=-1).add_(noise.unsqueeze(-1))
    return _cholesky(Khat)


def multitask_khat(
    kernel: str, points: Tensor, lengthscale: Tensor, task_covar: Tensor, noise: Tensor
) -> tuple[Tensor, Tensor]:
    """``K`` and ``K + diag(noise)`` of an LMC group in data-major order, ``(S d, S d)`` each.

    Args:
        kernel: kernel name.
        points: standardised training inputs ``(S, D)``.
        lengthscale: ``(Q, D)``; task_covar: ``(Q, d, d)``; noise: ``(d,)``.
    """
    S, d = points.shape[0], task_covar.shape[-1]
    pts = points.unsqueeze(0) / lengthscale.unsqueeze(-2)
    k = correlation(scaled_sq_dist(pts, pts), kernel)  # (Q, S, S)
    K = torch.einsum("qij,qtu->itju", k, task_covar).reshape(S * d, S * d)
    return K, K + torch.diag(noise.repeat(S))


def _cholesky(Khat: Tensor) -> Tensor:
    L, info = torch.linalg.cholesky_ex(Khat)
    if bool((info > 0).any()):
        raise torch.linalg.LinAlgError(
            "K + noise I is not positive definite in the frozen predictor; the noise floor is "
            "too low for this dtype (train in float64 or raise noise_floor)"
        )
    return L
