"""``GPModel``: a GPyTorch multi-output GP behind the :class:`ConditionalModel` contract.

Pipeline (all inside the model, so callers see raw units only):

    features  z = [x, u]                         (N, n + nu)
    base      b = prior_mean(x, u) | x | 0       (N, d)   (prior mean / increment / none)
    residual  r = target - b,  standardised per output; z standardised per feature
    GP        one batch GP per output group (same selected features, same observed rows)
    predict   mean = b + GP mean (de-standardised);  var = latent variance + likelihood noise

Training maximises the exact log marginal likelihood (or the ELBO of a sparse model) under
:func:`~torchfilt.models.gp.settings.exact_settings`. :meth:`GPModel.freeze` then caches every
training-set solve in a :class:`~torchfilt.models.gp.predictor.FrozenGP`, which :meth:`GPModel.predict`
uses; before freezing, :meth:`GPModel.predict` calls GPyTorch (exact settings).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Collection, Sequence
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction
from torchfilt.models.functional import FunctionModel
from torchfilt.models.gp.config import GPConfig, GroupSpec, resolve_inputs
from torchfilt.models.gp.data import MIN_POINTS, PairData
from torchfilt.models.gp.fit_setup import make_groups, noise_levels
from torchfilt.models.gp.group import GPGroup, GroupPosterior
from torchfilt.models.gp.optimize import Callback, load_checkpoint, train_groups
from torchfilt.models.gp.predictor import (
    AUTO_TOL,
    FrozenGP,
    FrozenOutput,
    VarianceMode,
    independent_block,
    multitask_block,
    sparse_block,
)
from torchfilt.models.gp.standardize import Standardizer
from torchfilt.numerics.dtypes import check_real_tensor
from torchfilt.optim import DEFAULTS, OptimizerOptions, deprecated_fit_keywords

__all__ = ["STATE_FORMAT", "GPModel"]

#: Tag of the plain-dict state written by :meth:`GPModel.to_state`.
STATE_FORMAT = "torchfilt.gp/1"
#: Hyperparameters of an exact model are trained on at most this many rows by default.
DEFAULT_SUBSET = 1000
#: Largest accepted learning rate (Adam on log-hyperparameters, natural-gradient step).
MAX_LR = 1.0
#: The defaults of :meth:`GPModel.optimize` (see :mod:`torchfilt.optim.options`).
_GP = DEFAULTS["gp"]
_GP_LR = _GP.optimizer.learning_rate


def _check_rate(name: str, rate: Any) -> float:
    """``rate`` as a float, refused unless a number in ``(0, MAX_LR]``."""
    if not isinstance(rate, numbers.Real) or not 0.0 < float(rate) <= MAX_LR:
        raise InputError(
            f"{name} must be a number in (0, {MAX_LR:g}], got {rate!r} (a step above "
            f"{MAX_LR:g} on the log-hyperparameters diverges)"
        )
    return float(rate)


class GPModel(ConditionalModel):
    """Base of :class:`~torchfilt.models.gp.GPTransition` and
    :class:`~torchfilt.models.gp.GPMeasurement`; build one with their ``fit`` or ``from_state``.

    Args:
        config: structure.
        groups: one :class:`GPGroup` per entry of ``config.groups``.
        input_std: standardiser of the features ``[x, u]``.
        target_std: standardiser of the residual targets.
        prior_mean: the nominal model, if ``config.prior_mean``.

    Raises:
        InputError: not one group per ``config`` group, or a ``prior_mean`` that does not match
            ``config.prior_mean`` (see :meth:`attach_prior_mean`).
    """

    role: ClassVar[str] = ""

    def __init__(
        self,
        config: GPConfig,
        groups: Sequence[GPGroup],
        input_std: Standardizer,
        target_std: Standardizer,
        prior_mean: Callable[..., Tensor] | None = None,
    ) -> None:
        super().__init__()
        if len(groups) != len(config.groups):
            raise InputError("one GPGroup per config group is required")
        self.config = config
        self.groups = torch.nn.ModuleList(groups)
        self.input_std = input_std
        self.target_std = target_std
        self.out_dim = config.out_dim
        self.in_dim = config.state_dim
        self.predictor: FrozenGP | None = None
        self._freeze_opts: dict[str, Any] | None = None
        self.history: list[float] = []
        self._prior: FunctionModel | None = None
        self.attach_prior_mean(prior_mean)

    # ------------------------------------------------------------------ prior mean
    def attach_prior_mean(self, prior_mean: Callable[..., Tensor] | None) -> None:
        """Attach the nominal model the GP learns the residual of (required after
        :meth:`from_state` when the model was trained with one; it is not serialised).

        Args:
            prior_mean: ``fn(x, u)`` or ``fn(x)``, ``(..., n) -> (..., d)``, broadcasting over
                leading dimensions; the same callable as at training time.

        Raises:
            InputError: ``prior_mean`` missing for a model trained with one, given for a model
                trained without one, or not callable.
        """
        if prior_mean is None:
            if self.config.prior_mean:
                raise InputError(
                    "prior_mean: this model was trained with a prior mean; pass the same "
                    "callable (prior_mean=fn) - callables are not serialised"
                )
            self._prior = None
            return
        if not self.config.prior_mean:
            raise InputError("prior_mean: this model was trained without a prior mean")
        if not callable(prior_mean):
            raise InputError(f"prior_mean must be callable, got {type(prior_mean).__name__}")
        # Kept outside the module tree: the GP's state dict never holds the nominal model.
        object.__setattr__(
            self,
            "_prior",
            FunctionModel(
                prior_mean,
                out_dim=self.config.out_dim,
                in_dim=self.config.state_dim,
                name="prior_mean",
            ),
        )

    def _base(self, x: Tensor, u: Tensor | None) -> Tensor | None:
        if self._prior is not None:
            return self._prior.predict(x, u).mean
        if self.config.increment:
            return x
        return None

    # ------------------------------------------------------------------ construction from data
    @classmethod
    def _from_pairs(
        cls,
        pairs: PairData,
        *,
        kernel: str = "rbf",
        structure: str = "independent",
        increment: bool = False,
        prior_mean: Callable[..., Tensor] | None = None,
        inputs: Sequence[int] | Sequence[Sequence[int]] | None = None,
        noise: float | Sequence[float] | Tensor | None = None,
        noise_floor: Literal["auto"] | float | Sequence[float] | Tensor = "auto",
        num_latents: int = 1,
        task_rank: int = 1,
        num_inducing: int = 256,
        seed: int = 0,
    ) -> GPModel:
        n = pairs.states.shape[-1]
        nu = 0 if pairs.inputs is None else pairs.inputs.shape[-1]
        d = pairs.targets.shape[-1]
        dtype = pairs.states.dtype
        target_name = "x_next" if cls.role == "transition" else "y"
        if cls.role == "transition" and d != n:
            raise ShapeError(f"x_next: {d} components, expected n = {n}")
        cfg0 = GPConfig(
            role=cls.role,  # type: ignore[arg-type]
            state_dim=n,
            input_dim=nu,
            out_dim=d,
            kernel=kernel,
            structure=structure,
            increment=increment,
            prior_mean=prior_mean is not None,
            num_latents=num_latents,
            task_rank=task_rank,
            num_inducing=num_inducing,
        )
        feats = pairs.features
        resid = _residual(pairs, prior_mean, increment)
        valid = torch.isfinite(resid)
        for j in range(d):
            cnt = int(valid[:, j].sum())
            if cnt < MIN_POINTS:
                raise InputError(
                    f"{target_name}[:, {j}]: {cnt} observed values; at least {MIN_POINTS} are needed"
                )
        input_std = Standardizer.fit(feats)
        target_std = Standardizer.fit(resid, valid)
        z_all = input_std(feats)
        y_all = torch.where(
            valid, target_std(torch.nan_to_num(resid)), torch.zeros((), dtype=dtype)
        )
        sel = resolve_inputs(inputs, d, feats.shape[-1], "inputs")
        const_out = [j for j in range(d) if bool(target_std.constant[j])]
        modelled = [j for j in range(d) if j not in const_out]
        # ---- output groups: same features and same observed rows share one batch GP
        specs: list[GroupSpec] = []
        if structure == "multitask":
            if len({sel[j] for j in modelled}) > 1:
                raise InputError("inputs: a multitask GP needs one input selection for all outputs")
            if modelled:
                specs.append(GroupSpec(tuple(modelled), sel[modelled[0]]))
        else:
            keys: dict[tuple[tuple[int, ...], bytes], list[int]] = {}
            for j in modelled:
                key = (sel[j], valid[:, j].cpu().numpy().tobytes())
                keys.setdefault(key, []).append(j)
            specs = [GroupSpec(tuple(outs), key[0]) for key, outs in keys.items()]
        gen = torch.Generator().manual_seed(seed)
        fixed, floor, init = noise_levels(
            specs, valid, z_all, y_all, target_std, noise, noise_floor, gen, d, dtype
        )
        config = GPConfig(
            **{
                **cfg0.to_dict(),
                "groups": tuple(specs),
                "noise_floor": tuple(float(v) for v in (floor * target_std.scale.pow(2))),
                "noise_fixed": fixed,
                "constant_outputs": tuple(const_out),
            }
        )
        groups = make_groups(config, valid, z_all, y_all, floor, init, gen)
        return cls(config, groups, input_std, target_std, prior_mean)

    # ------------------------------------------------------------------ training
    @deprecated_fit_keywords("gp")
    def optimize(
        self,
        iterations: int | None = None,
        *,
        optimizer: OptimizerOptions | Literal["adam"] | None = None,
        natural_lr: float = 0.1,
        subset: int | None = DEFAULT_SUBSET,
        batch_size: int = 1024,
        seed: int = 0,
        callback: Callback | None = None,
        progress: bool = True,
        resume: dict[str, Any] | None = None,
        fixed: Collection[str] = (),
    ) -> list[float]:
        """Train the hyperparameters (and variational parameters of a sparse model).

        Args:
            iterations: total Adam iterations (including those of a resumed run; default 200;
                0: none).
            optimizer: :class:`~torchfilt.optim.OptimizerOptions` of the Adam steps on the
                hyperparameters and inducing inputs (default ``lr`` 0.05, at most 1), or
                ``"adam"``. The keyword ``lr=`` of before still works for one release, with a
                ``DeprecationWarning``.
            natural_lr: natural-gradient step size for ``q(u)`` of a sparse model.
            subset: train an exact model's hyperparameters on a random subset of at most this
                many rows per group (default 1000; ``None``: all rows). The model still conditions
                on every row afterwards. An exact marginal-likelihood step costs O(S^3): measured
                here 0.07 s at S = 500, ~4 s at 2000 and ~30 s at 5000 per iteration (2 cores).
            batch_size: minibatch size of a sparse model.
            seed: seeds the subset and the minibatches (iteration ``k`` uses ``seed`` and ``k``,
                so a resumed run draws what an uninterrupted one would).
            callback: called after every iteration with a
                :class:`~torchfilt.models.gp.optimize.FitState`; returning ``True`` stops.
            progress: print a progress line to stderr every tenth of the run.
            resume: a checkpoint from ``FitState.checkpoint()`` to continue from.
            fixed: names of parameters held fixed (as ``named_parameters()`` gives them); they
                end bit-identical (the natural-gradient ``q(u)`` of a sparse model is always
                trained). An unknown name is an ``InputError``.

        Returns:
            The loss per iteration run (also appended to :attr:`history`).

        Raises:
            InputError: an optimizer other than Adam, an invalid rate or count, or an unknown
                ``fixed`` name.
        """
        if iterations is None:
            iterations = _GP.iterations
        if optimizer is None:
            optimizer = _GP.optimizer
        elif isinstance(optimizer, str):
            optimizer = OptimizerOptions(optimizer)  # type: ignore[arg-type]
        if not isinstance(optimizer, OptimizerOptions) or optimizer.optimizer != "adam":
            raise InputError(f"optimizer: a GP trains with Adam, got {optimizer!r}")
        lr = _GP_LR if optimizer.lr is None else _check_rate("lr", optimizer.lr)
        if (
            isinstance(iterations, bool)
            or not isinstance(iterations, numbers.Integral)
            or iterations < 0
        ):
            raise InputError(f"iterations must be a non-negative integer, got {iterations!r}")
        _check_rate("natural_lr", natural_lr)
        if subset is not None and subset < MIN_POINTS:
            raise InputError(f"subset must be at least {MIN_POINTS}, got {subset}")
        if batch_size < 1:
            raise InputError(f"batch_size must be positive, got {batch_size}")
        start, opt_state = 0, None
        if resume is not None:
            start, opt_state = load_checkpoint(self, resume)
        frozen = self._freeze_opts
        self.predictor = None
        losses = train_groups(
            self, iterations=iterations, lr=lr, natural_lr=natural_lr, subset=subset,
            batch_size=batch_size, seed=seed, callback=callback, progress=progress, start=start,
            optimizer_state=opt_state, fixed=fixed,
        )  # fmt: skip
        self.history.extend(losses)
        if frozen is not None:
            self.freeze(**frozen)
        return losses

    # ------------------------------------------------------------------ freezing
    def freeze(
        self,
        variance: VarianceMode = "auto",
        rank: int | None = None,
        *,
        tol: float = AUTO_TOL,
        chunk_size: int | None = None,
    ) -> GPModel:
        """Cache every training-set solve; :meth:`predict` then calls no GPyTorch code.

        Args:
            variance: ``"auto"`` (default: per output group, the smallest low-rank root whose
                predictive variance stays within ``tol`` of the exact one on validation points,
                else exact), ``"exact"`` (the cached Cholesky factor: exact, ``O(S^2)`` per
                point) or ``"lowrank"`` (a rank-``rank`` root: ``O(S r)`` per point, never below
                the exact variance). A sparse model always uses its own inducing-point form.
            rank: rank of the low-rank root (required for ``"lowrank"``).
            tol: relative variance tolerance of ``"auto"``.
            chunk_size: points per kernel chunk in large batches (``None``: from the training
                set's size, :func:`~torchfilt.models.gp.predictor.auto_chunk_size`).

        Returns:
            ``self``. :attr:`variance_forms` tells which form each group got.

        Raises:
            InputError: an invalid ``variance``, ``rank``, ``tol`` or ``chunk_size``.
        """
        if variance not in ("exact", "lowrank", "auto"):
            raise InputError(f"variance must be 'auto', 'exact' or 'lowrank', got {variance!r}")
        if variance == "lowrank" and (rank is None or rank < 1):
            raise InputError("rank: a positive rank is required for variance='lowrank'")
        if not tol > 0:
            raise InputError(f"tol must be positive, got {tol}")
        if chunk_size is not None and (isinstance(chunk_size, bool) or chunk_size < 1):
            raise InputError(f"chunk_size must be positive, got {chunk_size}")
        with torch.no_grad():
            blocks = self._blocks(variance, rank, tol, differentiable=False)
        self.predictor = FrozenGP(blocks, self.target_std.shift, self.out_dim, chunk_size)
        self._freeze_opts = {
            "variance": variance,
            "rank": rank,
            "tol": tol,
            "chunk_size": chunk_size,
        }
        return self

    def _blocks(
        self, variance: VarianceMode, rank: int | None, tol: float, *, differentiable: bool
    ) -> list[torch.nn.Module]:
        """One frozen block per output group (``differentiable``: keeping the graph from the
        hyperparameters, exact independent groups only)."""
        blocks: list[torch.nn.Module] = []
        ist, tst = self.input_std, self.target_std
        for grp, spec in zip(self.groups, self.config.groups, strict=True):
            assert isinstance(grp, GPGroup)
            feats = torch.tensor(spec.features, device=grp.train_x.device)
            outs = torch.tensor(spec.outputs, device=grp.train_x.device)
            common: dict[str, Any] = dict(
                kernel=self.config.kernel,
                outputs=outs,
                features=feats,
                in_shift=ist.shift[feats],
                in_scale=ist.scale[feats],
                hyper=grp.hyperparameters(detach=not differentiable),
                out_shift=tst.shift[outs],
                out_scale=tst.scale[outs],
            )
            exact_args: dict[str, Any] = dict(
                train_x=grp.train_x, train_y=grp.train_y, variance=variance, rank=rank, tol=tol
            )
            if grp.structure == "independent":
                blocks.append(
                    independent_block(**exact_args, **common, differentiable=differentiable)
                )
            elif grp.structure == "multitask":
                blocks.append(multitask_block(**exact_args, **common))
            else:
                strat = grp.gp.variational_strategy
                var_mean, var_chol = grp.gp.variational_moments()
                blocks.append(
                    sparse_block(
                        inducing=strat.inducing_points.detach(),
                        var_mean=var_mean.detach(),
                        var_chol=var_chol.detach(),
                        jitter=float(strat.jitter_val),
                        **common,
                    )
                )
        return blocks

    @property
    def freeze_options(self) -> dict[str, Any] | None:
        """The options of the last :meth:`freeze` (``None`` when not frozen)."""
        return None if self._freeze_opts is None else dict(self._freeze_opts)

    @property
    def has_twin(self) -> bool:
        """Whether :meth:`twin` is available (independent exact GPs)."""
        return self.config.structure == "independent"

    def twin(self) -> FrozenGP:
        """The frozen predictor's differentiable twin, built from the current hyperparameters.

        The same arithmetic as :meth:`freeze` with ``variance="exact"`` (Cholesky of
        ``K + s^2 I``, ``alpha``), but the autograd graph runs from the GP's raw hyperparameters
        (lengthscales, outputscales, likelihood noises) through the caches to the predictions, so
        a loss computed with ``model.predictor = model.twin()`` (e.g. a filter likelihood) has
        gradients in them. It equals the exact frozen predictor to rounding; a low-rank frozen
        form differs from it by at most its ``tol``. Build a new twin after every change of the
        hyperparameters (one ``S x S`` Cholesky per output group), and :meth:`freeze` again at
        the end. Independent exact groups only.

        Raises:
            InputError: the model has a multitask or sparse group.
        """
        if not self.has_twin:
            raise InputError(
                f"twin: only independent exact GPs have a differentiable twin; this model has "
                f"structure {self.config.structure!r}"
            )
        chunk = None if self._freeze_opts is None else self._freeze_opts["chunk_size"]
        with torch.enable_grad():
            blocks = self._blocks("exact", None, AUTO_TOL, differentiable=True)
        return FrozenGP(blocks, self.target_std.shift, self.out_dim, chunk)

    def hyperparameter_tensors(
        self, which: Literal["noise", "all"] = "all"
    ) -> list[torch.nn.Parameter]:
        """The raw (constrained by GPyTorch) parameters of the likelihood noises (``"noise"``),
        or of the noises, lengthscales and outputscales (``"all"``); fixed noises excluded. The
        mean constants are never included.

        Args:
            which: ``"noise"`` or ``"all"``.

        Returns:
            The parameters (each of any shape, as GPyTorch holds them).

        Raises:
            InputError: ``which`` is neither ``"noise"`` nor ``"all"``.
        """
        if which not in ("noise", "all"):
            raise InputError(f"which must be 'noise' or 'all', got {which!r}")
        out = []
        for name, p in self.groups.named_parameters():
            if not p.requires_grad:
                continue
            if "likelihood" in name or (which == "all" and "covar_module" in name):
                out.append(p)
        return out

    @property
    def variance_forms(self) -> list[tuple[str, int | None]]:
        """Per output group, the frozen variance form (``"exact"``, ``"lowrank"``,
        ``"sparse"``) and rank; empty when not frozen."""
        return [] if self.predictor is None else self.predictor.forms

    def unfreeze(self) -> GPModel:
        """Drop the frozen predictor; :meth:`predict` then calls GPyTorch (exact settings)."""
        self.predictor = None
        self._freeze_opts = None
        return self

    @property
    def frozen(self) -> bool:
        """Whether :meth:`predict` uses the frozen predictor."""
        return self.predictor is not None

    # ------------------------------------------------------------------ prediction
    def _features(self, x: Tensor, u: Tensor | None) -> Tensor:
        n, nu = self.config.state_dim, self.config.input_dim
        if not isinstance(x, Tensor):
            raise InputError(f"x must be a torch.Tensor, got {type(x).__name__}")
        check_real_tensor(x, "x")
        if x.dim() < 1 or x.shape[-1] != n:
            raise ShapeError(f"x: expected shape (..., P, n) with n = {n}, got {tuple(x.shape)}")
        if nu == 0:
            return x
        if u is None:
            raise InputError(
                f"u: this {type(self).__name__} was trained with inputs (nu = {nu}); pass u"
            )
        if u.shape[-1] != nu:
            raise ShapeError(f"u: expected shape (..., P, nu) with nu = {nu}, got {tuple(u.shape)}")
        try:
            u = u.to(x.dtype).expand(*x.shape[:-1], nu)
        except RuntimeError:
            raise ShapeError(
                f"u: shape {tuple(u.shape)} does not broadcast with x {tuple(x.shape)}"
            ) from None
        return torch.cat([x, u], -1)

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Predictive distribution at points.

        Args:
            x: states, shape ``(..., P, n)``.
            u: inputs, shape ``(..., P, nu)`` (broadcastable), if the model was trained with them;
                ignored otherwise.

        Returns:
            :class:`~torchfilt.models.Prediction` with ``mean (..., P, d)`` and ``var (..., P, d)``
            (latent variance + likelihood noise), or ``cov (..., P, d, d)`` for a multitask model.
        """
        z = self._features(x, u)
        out = self.predictor(z) if self.predictor is not None else self._gpytorch(z, False)
        base = self._base(x, u if self.config.input_dim else None)
        mean = out.mean if base is None else out.mean + base
        if out.cov is not None:
            return Prediction(mean, None, out.cov)
        return Prediction(mean, out.var)

    def predict_mean(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """The predictive mean alone, equal to ``predict(x, u).mean``; a frozen model skips the
        variance (for a low-rank or exact variance form, most of the work).

        Args:
            x: states, shape ``(..., P, n)``.
            u: inputs, shape ``(..., P, nu)`` (broadcastable), or ``None``, as in :meth:`predict`.

        Returns:
            The predictive mean, shape ``(..., P, d)``.
        """
        if self.predictor is None:
            return self.predict(x, u).mean
        z = self._features(x, u)
        mean = self.predictor.mean(z)
        base = self._base(x, u if self.config.input_dim else None)
        return mean if base is None else mean + base

    def predict_gpytorch(
        self, x: Tensor, u: Tensor | None = None, *, fast_pred_var: bool = False
    ) -> Prediction:
        """The same prediction computed by GPyTorch in eval mode (reference and benchmark path).

        Args:
            x: states, shape ``(..., P, n)``.
            u: inputs, shape ``(..., P, nu)`` (broadcastable), or ``None``, as in :meth:`predict`.
            fast_pred_var: GPyTorch's default numerics with LOVE instead of the exact settings.

        Returns:
            The :class:`~torchfilt.models.Prediction`: mean ``(..., P, d)`` and variance
            ``(..., P, d)`` (or covariance ``(..., P, d, d)`` for a multitask model).
        """
        z = self._features(x, u)
        out = self._gpytorch(z, fast_pred_var)
        base = self._base(x, u if self.config.input_dim else None)
        mean = out.mean if base is None else out.mean + base
        if out.cov is not None:
            return Prediction(mean, None, out.cov)
        return Prediction(mean, out.var)

    def _gpytorch(self, z: Tensor, fast_pred_var: bool) -> FrozenOutput:
        lead, d = z.shape[:-1], self.out_dim
        dtype = self.target_std.scale.dtype
        zf = self.input_std(z.reshape(-1, z.shape[-1]).to(dtype))
        N = zf.shape[0]
        mean = self.target_std.shift.expand(N, d).clone()
        var = zf.new_zeros(N, d)
        cov = zf.new_zeros(N, d, d) if self.config.structure == "multitask" else None
        sc, sh = self.target_std.scale, self.target_std.shift
        for grp, spec in zip(self.groups, self.config.groups, strict=True):
            assert isinstance(grp, GPGroup)
            post: GroupPosterior = grp.posterior(
                zf[:, list(spec.features)], fast_pred_var=fast_pred_var
            )
            outs = list(spec.outputs)
            mean[:, outs] = post.mean * sc[outs] + sh[outs]
            var[:, outs] = post.var * sc[outs].pow(2)
            if cov is not None and post.cov is not None:
                o = torch.tensor(outs, device=cov.device)
                s = sc[o]
                cov[:, o.unsqueeze(-1), o.unsqueeze(0)] = post.cov * (s.unsqueeze(-1) * s)
        return FrozenOutput(
            mean.reshape(*lead, d).to(z.dtype),
            var.reshape(*lead, d).to(z.dtype),
            None if cov is None else cov.reshape(*lead, d, d).to(z.dtype),
        )

    # ------------------------------------------------------------------ introspection
    @property
    def noise_variance(self) -> Tensor:
        """Likelihood noise variance per output, in target units, shape ``(d,)``."""
        out = self.target_std.scale.new_zeros(self.out_dim)
        for grp, spec in zip(self.groups, self.config.groups, strict=True):
            assert isinstance(grp, GPGroup)
            out[list(spec.outputs)] = grp.noise().detach()
        return out * self.target_std.scale.pow(2)

    def hyperparameters(self) -> dict[str, Tensor]:
        """Hyperparameters in target and input units (for logging).

        Returns:
            ``noise`` ``(d,)`` (variance), ``noise_floor`` ``(d,)``; for independent/sparse
            outputs ``outputscale`` ``(d,)`` (variance) and ``lengthscale.{j}`` per output ``j``
            (one per selected feature); for a multitask model ``task_covar`` ``(Q, d, d)`` and
            ``lengthscale.{q}`` per latent kernel.
        """
        sc2 = self.target_std.scale.pow(2)
        out: dict[str, Tensor] = {
            "noise": self.noise_variance,
            "noise_floor": torch.tensor(self.config.noise_floor, dtype=sc2.dtype),
        }
        os_ = sc2.new_zeros(self.out_dim)
        for grp, spec in zip(self.groups, self.config.groups, strict=True):
            assert isinstance(grp, GPGroup)
            h = grp.hyperparameters()
            fs = self.input_std.scale[list(spec.features)]
            if grp.structure == "multitask":
                s = self.target_std.scale[list(spec.outputs)]
                out["task_covar"] = h["task_covar"] * (s.unsqueeze(-1) * s.unsqueeze(-2))
                for q, ls in enumerate(h["lengthscale"]):
                    out[f"lengthscale.{q}"] = ls * fs
            else:
                for i, j in enumerate(spec.outputs):
                    os_[j] = h["outputscale"][i]
                    out[f"lengthscale.{j}"] = h["lengthscale"][i] * fs
        if self.config.structure != "multitask":
            out["outputscale"] = os_ * sc2
        return out

    # ------------------------------------------------------------------ serialisation
    def to_state(self) -> dict[str, Any]:
        """Plain tensors and dicts (no pickled callables) for ``torch.load(weights_only=True)``.

        A frozen model also stores its predictor's cache (:meth:`FrozenGP.cache`), so
        :meth:`from_state` does not choose the variance form again (only an exact form's
        Cholesky factor is recomputed). A prior-mean callable is not stored: re-attach it with
        ``from_state(..., prior_mean=fn)``.
        """
        return {
            "format": STATE_FORMAT,
            "class": type(self).__name__,
            "config": self.config.to_dict(),
            "state_dict": {k: v.detach().clone() for k, v in self.state_dict().items()},
            "predictor": None if self._freeze_opts is None else dict(self._freeze_opts),
            "frozen": None if self.predictor is None else self.predictor.cache(),
        }

    @classmethod
    def from_state(
        cls, state: dict[str, Any], prior_mean: Callable[..., Tensor] | None = None
    ) -> GPModel:
        """Rebuild a model written by :meth:`to_state`.

        Args:
            state: the dict from :meth:`to_state`.
            prior_mean: the nominal model, if the model was trained with one.

        Returns:
            The model (frozen again if it was frozen when saved).

        Raises:
            InputError: ``state`` is not a dict written by :meth:`to_state` (or holds another
                class), or ``prior_mean`` does not match the saved model.
        """
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            raise InputError(f"state: expected a dict written by to_state() ({STATE_FORMAT})")
        if cls.role and state.get("class") != cls.__name__:
            raise InputError(f"state: holds a {state.get('class')}, not a {cls.__name__}")
        config = GPConfig.from_dict(state["config"])
        sd: dict[str, Tensor] = state["state_dict"]
        dtype = sd["target_std.scale"].dtype
        groups = []
        for i, spec in enumerate(config.groups):
            tx, ty = sd[f"groups.{i}.train_x"], sd[f"groups.{i}.train_y"]
            g = len(spec.outputs)
            ones = torch.ones(g, dtype=dtype)
            groups.append(
                GPGroup(
                    config.structure,
                    tx.clone(),
                    ty.clone(),
                    kernel=config.kernel,
                    floor=ones * 1e-6,
                    noise_init=ones * 1e-2,
                    noise_fixed=config.noise_fixed,
                    num_latents=config.num_latents,
                    task_rank=config.task_rank,
                    # random initial values are overwritten by the state dict; a private
                    # generator keeps the user's global random stream untouched
                    generator=torch.Generator().manual_seed(0),
                    num_inducing=int(
                        sd.get(
                            f"groups.{i}.gp.variational_strategy.inducing_points",
                            torch.empty(0, config.num_inducing),
                        ).shape[-2]
                    ),
                )
            )
        zeros_in = torch.zeros(config.features, dtype=dtype)
        zeros_out = torch.zeros(config.out_dim, dtype=dtype)
        klass = _ROLES.get(config.role, cls) if not cls.role else cls
        model = klass(
            config,
            groups,
            Standardizer(zeros_in, zeros_in + 1),
            Standardizer(zeros_out, zeros_out + 1),
            prior_mean,
        )
        model.load_state_dict(sd)
        if state.get("predictor") and state.get("frozen"):
            model.predictor = FrozenGP.from_cache(state["frozen"])
            model._freeze_opts = dict(state["predictor"])
        elif state.get("predictor"):
            model.freeze(**state["predictor"])
        return model


#: Concrete class per role (filled by the subclasses' modules).
_ROLES: dict[str, type[GPModel]] = {}


def _residual(pairs: PairData, prior_mean: Callable[..., Tensor] | None, increment: bool) -> Tensor:
    """The GP's targets ``(N, d)``: the data's targets less the prior mean, the state or nothing."""
    n, d, dtype = pairs.states.shape[-1], pairs.targets.shape[-1], pairs.states.dtype
    base = pairs.states if increment else None  # a prior mean takes precedence
    if prior_mean is not None:
        if not callable(prior_mean):
            raise InputError(f"prior_mean must be callable, got {type(prior_mean).__name__}")
        nominal = FunctionModel(prior_mean, out_dim=d, in_dim=n, name="prior_mean")
        with torch.no_grad():
            base = nominal.predict(pairs.states, pairs.inputs).mean
        if not bool(torch.isfinite(base).all()):
            raise InputError("prior_mean returned non-finite values on the training states")
    return pairs.targets if base is None else pairs.targets - base.to(dtype)
