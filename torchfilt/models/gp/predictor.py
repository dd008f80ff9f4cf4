"""The frozen predictor: a GP's posterior with every training-set solve cached, in plain torch.

After training, ``alpha = (K + s^2 I)^{-1} (y - c)`` and a factor for the variance do not change. A
prediction at ``N`` points then costs kernel evaluations against the ``S`` training (or ``M``
inducing) inputs, one matrix product for the mean and one for the variance:

    mean = c + k*^T alpha
    var  = s_f^2 - q(k*) + s^2,  q(k*) = k*^T (K + s^2 I)^{-1} k*

with three forms of ``q``:

* ``"exact"``: ``q = |L^{-1} k*|^2`` with the cached Cholesky factor ``L`` (``O(S^2)`` per point);
* ``"lowrank"``: ``q = |R^T k*|^2`` with a rank-``r`` root ``R`` (:mod:`~torchfilt.models.gp.root`;
  ``O(S r)`` per point; the variance is never below the exact one);
* ``"sparse"`` (SVGP): ``var = s_f^2 + j + k*^T W k* + s^2`` with ``W = L^{-T} (S_u - I) L^{-1}``,
  ``L L^T = K_uu + j I`` (``j`` GPyTorch's variational jitter), the SVGP's own predictive variance.

``variance="auto"`` picks, per output group, the smallest rank whose variance stays within ``tol``
(relative, latent + noise) of the exact one on validation points (training inputs and jittered
copies), and the exact form if no rank does. No GPyTorch call, no solve of the training system per
step, differentiable in the points (autograd). Large batches are processed in chunks of
``chunk_size`` points; by default as many as keep one chunk's kernel rows (every block's
outputs x points x training or inducing points) under ``CHUNK_ENTRIES`` entries, and at least
``CHUNK_SIZE``. A chunk is one round of small kernel operations, whose dispatch, not their
arithmetic, dominates a filter step's cost at the batch sizes of a fit: a step of 23 windows x 6
cubature points (138 points) cost 1.2 times one of 16 windows in two chunks of 128, and 1.05
times in one. Inputs are standardised and outputs de-standardised inside.

Outputs fitted on rows of their own (a measurement missing at other times than another's)
become one block each. The low-rank and sparse blocks of one kernel, rank and input set run as
one stacked block (their points padded with zeros of zero weight): one round of kernel
operations instead of one per output. On Plaza2's four range outputs a call took 0.30 ms
against 0.58 ms at 138 points, and 0.08 ms against 0.25 ms at 6.

This module holds the predictor and the functions that freeze a group; the frozen blocks (one per
output group) and the kernel matrices they are built from are in :mod:`~torchfilt.models.gp.blocks`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError
from torchfilt.models.gp.blocks import (
    _Block,
    _cholesky,
    _independent_factor,
    _IndependentBlock,
    _MultitaskBlock,
    independent_khat,
    multitask_khat,
    stack_key,
)
from torchfilt.models.gp.kernels import correlation, scaled_sq_dist
from torchfilt.models.gp.root import (
    ANCHOR_SHARE,
    anchor_basis,
    eigen_basis,
    lowrank_root,
    ritz_root,
)

__all__ = [
    "AUTO_RANKS",
    "AUTO_TOL",
    "CACHE_FORMAT",
    "CHUNK_ENTRIES",
    "CHUNK_SIZE",
    "FrozenGP",
    "FrozenOutput",
    "VarianceMode",
]

VarianceMode = Literal["exact", "lowrank", "auto"]

#: Tag of the plain-dict cache written by :meth:`FrozenGP.cache`.
CACHE_FORMAT = "torchfilt.frozen/1"
#: Fewest points per kernel chunk of the automatic chunk size.
CHUNK_SIZE = 128
#: Kernel-row entries (outputs x points x training points, summed over the blocks) per chunk of
#: the automatic chunk size: 2^21, 16 MiB in float64.
CHUNK_ENTRIES = 2**21
#: Ranks tried by ``variance="auto"``, smallest first.
AUTO_RANKS = (16, 32, 64, 128, 256, 512)
#: Default tolerance of ``variance="auto"``: relative error of the predictive variance.
AUTO_TOL = 0.05
#: Training points (at most) used to validate a low-rank root, and jitters (in lengthscales).
AUTO_POINTS = 256
AUTO_JITTERS = (0.1, 0.5)


def _stacked(blocks: Sequence[nn.Module]) -> list[nn.Module]:
    """``blocks`` with each set of two or more that stack (:func:`stack_key`) replaced, at the
    place of its first, by one :meth:`_IndependentBlock.stacked` block."""
    keys = [stack_key(b) for b in blocks]
    groups: dict[tuple[object, ...], list[_IndependentBlock]] = {}
    for b, key in zip(blocks, keys, strict=True):
        if key is not None:
            assert isinstance(b, _IndependentBlock)
            groups.setdefault(key, []).append(b)
    out: list[nn.Module] = []
    done: set[tuple[object, ...]] = set()
    for b, key in zip(blocks, keys, strict=True):
        if key is None or len(groups[key]) == 1:
            out.append(b)
        elif key not in done:
            done.add(key)
            out.append(_IndependentBlock.stacked(groups[key]))
    return out


def auto_chunk_size(blocks: Sequence[nn.Module]) -> int:
    """Points per chunk whose kernel rows have at most :data:`CHUNK_ENTRIES` entries, summed over
    ``blocks`` (each block's training or inducing points ``(g, S, D)`` give ``g S`` entries per
    point; a multitask block's ``d^2`` output pairs count too), and at least :data:`CHUNK_SIZE`."""
    per_point = 0
    for blk in blocks:
        points = getattr(blk, "points", None)
        if not isinstance(points, Tensor):
            continue
        entries = int(points.shape[:-1].numel())
        task_covar = getattr(blk, "task_covar", None)
        if isinstance(task_covar, Tensor):
            entries *= int(task_covar.shape[-1]) ** 2
        per_point += entries
    return max(CHUNK_SIZE, CHUNK_ENTRIES // max(per_point, 1))


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


class FrozenGP(nn.Module):
    """A trained GP model's posterior with all training-set solves cached.

    Build it with :meth:`GPModel.freeze() <torchfilt.models.gp.GPModel.freeze>`; call it on raw
    (unstandardised) features ``[x, u]``.

    Args:
        blocks: one frozen block per output group.
        fill_mean: mean of the outputs no block covers (constant outputs), shape ``(d,)``;
            their variance is 0.
        out_dim: number of outputs ``d``.
        chunk_size: points per kernel chunk (``None``: :func:`auto_chunk_size` of the blocks).
    """

    fill_mean: Tensor

    def __init__(
        self,
        blocks: Sequence[nn.Module],
        fill_mean: Tensor,
        out_dim: int,
        chunk_size: int | None = None,
    ) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(blocks)
        #: the blocks the predictions run on: those that stack (one kernel, rank and feature
        #: set, each output fitted on its own rows) as one block (:func:`stack_key`)
        self.runs = nn.ModuleList(_stacked(blocks))
        self.register_buffer("fill_mean", fill_mean.detach().clone(), persistent=False)
        self.out_dim = int(out_dim)
        self.chunk_size = auto_chunk_size(blocks) if chunk_size is None else int(chunk_size)
        self.correlated = any(isinstance(b, _MultitaskBlock) for b in blocks)
        d = self.out_dim
        first = self.runs[0] if len(self.runs) == 1 else None
        self._whole = isinstance(first, _Block) and bool(
            torch.equal(first.outputs.cpu(), torch.arange(d))
        )

    @property
    def forms(self) -> list[tuple[str, int | None]]:
        """``(form, rank)`` of each block (output group)."""
        return [(b.form, b.rank) for b in self.blocks]  # type: ignore[misc]

    def cache(self) -> dict[str, Any]:
        """The frozen state as plain tensors and dicts (for ``torch.load(weights_only=True)``).

        Everything :meth:`from_cache` needs to rebuild the predictor without choosing a variance
        form again (the expensive part of freezing): each block's form and rank, ``alpha``, the
        low-rank root or sparse factor, hyperparameters and standardisation. An exact block's
        Cholesky factor (``S x S`` per output) is not stored: :meth:`from_cache` recomputes it,
        one Cholesky per output group.
        """
        blocks = []
        for b in self.blocks:
            assert isinstance(b, _Block)
            blocks.append(
                {
                    "class": "multitask" if isinstance(b, _MultitaskBlock) else "independent",
                    "kernel": b.kernel,
                    "form": b.form,
                    "rank": b.rank,
                    "args": {k: v.detach().clone() for k, v in b.cache_args.items()},
                }
            )
        return {
            "format": CACHE_FORMAT,
            "out_dim": self.out_dim,
            "chunk_size": self.chunk_size,
            "fill_mean": self.fill_mean.detach().clone(),
            "blocks": blocks,
        }

    @classmethod
    def from_cache(cls, cache: dict[str, Any]) -> FrozenGP:
        """Rebuild a predictor from :meth:`cache` (no variance-form selection, no root).

        Raises:
            InputError: ``cache`` is not a predictor cache, or is inconsistent (also a
                ``ValueError``).
        """
        if not isinstance(cache, dict) or cache.get("format") != CACHE_FORMAT:
            raise InputError(f"cache: not a frozen-predictor cache ({CACHE_FORMAT})")
        blocks: list[nn.Module] = []
        for i, b in enumerate(cache["blocks"]):
            form, kernel, args = str(b["form"]), str(b["kernel"]), dict(b["args"])
            if form not in ("exact", "lowrank", "sparse"):
                raise InputError(f"cache: blocks[{i}]: unknown variance form {form!r}")
            rank = None if b["rank"] is None else int(b["rank"])
            if b["class"] == "independent":
                if form == "exact":
                    args["factor"] = _independent_factor(
                        kernel,
                        args["points"],
                        args["lengthscale"],
                        args["outputscale"],
                        args["noise"],
                    )
                blocks.append(_IndependentBlock(kernel=kernel, form=form, rank=rank, **args))
            elif b["class"] == "multitask":
                if form == "exact":
                    args["factor"] = _cholesky(
                        multitask_khat(
                            kernel,
                            args["points"],
                            args["lengthscale"],
                            args["task_covar"],
                            args["noise"],
                        )[1]
                    )
                blocks.append(_MultitaskBlock(kernel=kernel, form=form, rank=rank, **args))
            else:
                raise InputError(f"cache: blocks[{i}]: unknown block class {b['class']!r}")
        return cls(blocks, cache["fill_mean"], int(cache["out_dim"]), int(cache["chunk_size"]))

    def forward(self, z: Tensor) -> FrozenOutput:
        """Predictive moments at features.

        Args:
            z: standardised features, shape ``(..., F)``.

        Returns:
            The predictive mean and variance, each of shape ``(..., d)`` (a multitask model
            also gives the covariance ``(..., d, d)``).

        Raises:
            InputError: ``z`` is on another device than the model.
        """
        if z.device != self.fill_mean.device:
            raise InputError(
                f"x is on {z.device} but the GP model is on {self.fill_mean.device}; move one "
                "of them with .to()"
            )
        lead = z.shape[:-1]
        flat = z.reshape(-1, z.shape[-1]).to(self.fill_mean.dtype)
        d = self.out_dim
        if flat.shape[0] <= self.chunk_size:
            m, v, c = self._chunk(flat)
        else:
            parts = [
                self._chunk(flat[i : i + self.chunk_size])
                for i in range(0, flat.shape[0], self.chunk_size)
            ]
            m = torch.cat([p[0] for p in parts])
            v = torch.cat([p[1] for p in parts])
            c = None if parts[0][2] is None else torch.cat([p[2] for p in parts])  # type: ignore[misc]
        return FrozenOutput(
            m.reshape(*lead, d).to(z.dtype),
            v.reshape(*lead, d).to(z.dtype),
            None if c is None else c.reshape(*lead, d, d).to(z.dtype),
        )

    def mean(self, z: Tensor) -> Tensor:
        """The predictive mean alone: the same numbers as ``forward(z).mean`` without the
        variance's work.

        Args:
            z: standardised features, shape ``(..., F)``.

        Returns:
            The predictive mean, shape ``(..., d)``.

        Raises:
            InputError: ``z`` is on another device than the model.
        """
        if z.device != self.fill_mean.device:
            raise InputError(
                f"x is on {z.device} but the GP model is on {self.fill_mean.device}; move one "
                "of them with .to()"
            )
        lead = z.shape[:-1]
        flat = z.reshape(-1, z.shape[-1]).to(self.fill_mean.dtype)
        m = torch.cat(
            [
                self._chunk_mean(flat[i : i + self.chunk_size])
                for i in range(0, max(flat.shape[0], 1), self.chunk_size)
            ]
        )
        return m.reshape(*lead, self.out_dim).to(z.dtype)

    def _chunk_mean(self, z: Tensor) -> Tensor:
        if self._whole:
            return self.runs[0].mean(z)  # type: ignore[operator]
        mean = self.fill_mean.expand(z.shape[0], self.out_dim)
        for blk in self.runs:
            assert isinstance(blk, _Block)
            mean = mean.index_copy(1, blk.outputs, blk.mean(z))
        return mean

    def _chunk(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        if self._whole:
            out: tuple[Tensor, Tensor, Tensor | None] = self.runs[0](z)
            return out
        N, d = z.shape[0], self.out_dim
        mean = self.fill_mean.expand(N, d)
        var = z.new_zeros(N, d)
        cov = z.new_zeros(N, d, d) if self.correlated else None
        for blk in self.runs:
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


# ---------------------------------------------------------------------- building blocks


def _validation_points(train_x: Tensor, lengthscale: Tensor) -> Tensor:
    """Training inputs and jittered copies (standardised) on which a low-rank root is checked."""
    gen = torch.Generator(device="cpu").manual_seed(0)
    S = train_x.shape[0]
    idx = torch.randperm(S, generator=gen)[: min(S, AUTO_POINTS)].to(train_x.device)
    base = train_x[idx]
    ls = lengthscale.reshape(-1, train_x.shape[-1]).amin(0)
    out = [base]
    for j in AUTO_JITTERS:
        noise = torch.randn(base.shape, generator=gen, dtype=base.dtype).to(base.device)
        out.append(base + j * ls * noise)
    return torch.cat(out)


def _choose_form(
    variance: VarianceMode,
    rank: int | None,
    tol: float,
    K: Tensor,
    Khat: Tensor,
    L: Tensor,
    rows: Tensor,
    prior: Tensor,
) -> tuple[str, int | None, Tensor]:
    """Pick the variance form: exact (factor ``L``) or low rank (a root).

    Args:
        variance, rank, tol: the user's options.
        K: noise-free kernel matrix ``(B, S, S)``; Khat: ``K + s^2 I``; L: its Cholesky factor.
        rows: validation kernel rows ``(B, V, S)`` (``variance="auto"`` only).
        prior: prior variance + noise, ``(B,)`` or per validation row ``(B, V)`` (``"auto"``).
    """
    S = Khat.shape[-1]
    if variance == "exact":
        return "exact", None, L
    if variance == "lowrank":
        assert rank is not None
        return "lowrank", min(rank, S), lowrank_root(K, Khat, L, rank)
    ranks = [r for r in AUTO_RANKS if r <= S // 4]  # beyond S/4 exact is as cheap
    if not ranks:
        return "exact", None, L
    p = prior.unsqueeze(-1) if prior.dim() == 1 else prior
    w = torch.linalg.solve_triangular(L, rows.mT, upper=False)
    exact = p - w.pow(2).sum(-2)  # (B, V)
    top, share = ranks[-1], ANCHOR_SHARE
    eig = eigen_basis(Khat, top - top // share)
    anchors = anchor_basis(K, L, top // share)
    for r in ranks:
        basis = torch.cat([eig[..., : r - r // share], anchors[..., : r // share]], -1)
        root = ritz_root(Khat, basis)
        approx = p - (rows @ root).pow(2).sum(-1)
        rel = (approx - exact).abs() / exact.clamp_min(torch.finfo(exact.dtype).tiny)
        if float(rel.max()) <= tol:
            return "lowrank", r, root
    return "exact", None, L


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
    variance: VarianceMode,
    rank: int | None,
    tol: float = AUTO_TOL,
    differentiable: bool = False,
) -> _IndependentBlock:
    """Freeze an exact independent group: Cholesky of ``K + s^2 I``, ``alpha`` and the factor.

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
        variance: ``"exact"``, ``"lowrank"`` or ``"auto"``.
        rank: rank of the low-rank root.
        tol: tolerance of ``"auto"``.
        differentiable: keep the autograd graph from ``hyper`` to the block's caches (the
            differentiable twin, :meth:`GPModel.twin <torchfilt.models.gp.GPModel.twin>`;
            ``variance="exact"`` only).
    """
    if differentiable and variance != "exact":
        raise InputError("differentiable: a differentiable block takes variance='exact'")
    ls, os_, noise, c = (
        hyper["lengthscale"],
        hyper["outputscale"],
        hyper["noise"],
        hyper["constant"],
    )
    pts = train_x.unsqueeze(0) / ls.unsqueeze(-2)  # (g, S, D)
    points = train_x.unsqueeze(0).expand(ls.shape[0], -1, -1)
    K, Khat = independent_khat(kernel, points, ls, os_, noise)
    L = _cholesky(Khat)
    alpha = torch.cholesky_solve((train_y - c.unsqueeze(-1)).unsqueeze(-1), L).squeeze(-1)
    rows = prior = K.new_zeros(0)
    if variance == "auto":
        v = _validation_points(train_x, ls) / ls.unsqueeze(-2)  # (g, V, D)
        rows = os_[:, None, None] * correlation(scaled_sq_dist(v, pts), kernel)
        prior = os_ + noise
    form, r, factor = _choose_form(variance, rank, tol, K, Khat, L, rows, prior)
    return _IndependentBlock(
        kernel=kernel,
        form=form,
        rank=r,
        outputs=outputs,
        features=features,
        in_shift=in_shift,
        in_scale=in_scale,
        lengthscale=ls,
        points=points,
        alpha=alpha,
        const=c,
        outputscale=os_,
        noise=noise,
        extra_diag=torch.zeros_like(os_),
        out_shift=out_shift,
        out_scale=out_scale,
        factor=factor,
        differentiable=differentiable,
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
    L = _cholesky(Kuu)
    Linv = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
    C = var_chol.tril()
    middle = Linv.mT @ (C @ C.mT - eye) @ Linv
    alpha = (Linv.mT @ var_mean.unsqueeze(-1)).squeeze(-1)
    return _IndependentBlock(
        kernel=kernel,
        form="sparse",
        rank=None,
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
        factor=0.5 * (middle + middle.mT),
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
    variance: VarianceMode,
    rank: int | None,
    tol: float = AUTO_TOL,
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
    K, Khat = multitask_khat(kernel, train_x, ls, B, noise)
    L = _cholesky(Khat)
    resid = (train_y.T - c).reshape(-1, 1)  # data-major: row i * d + t
    alpha = torch.cholesky_solve(resid, L).squeeze(-1)
    rows = prior = K.new_zeros(0)
    if variance == "auto":
        v = _validation_points(train_x, ls).unsqueeze(0) / ls.unsqueeze(-2)  # (Q, V, D)
        kv = correlation(scaled_sq_dist(v, pts), kernel)  # (Q, V, S)
        V = kv.shape[1]
        rows = torch.einsum("qns,qtu->ntsu", kv, B).reshape(V * d, S * d).unsqueeze(0)
        prior = (B.sum(0).diagonal() + noise).repeat(V).unsqueeze(0)  # (1, V d)
    form, r, factor = _choose_form(
        variance, rank, tol, K.unsqueeze(0), Khat.unsqueeze(0), L.unsqueeze(0), rows, prior
    )
    return _MultitaskBlock(
        kernel=kernel,
        form=form,
        rank=r,
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
        factor=factor.squeeze(0),
    )
