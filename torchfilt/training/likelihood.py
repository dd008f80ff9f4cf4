"""Maximum likelihood through the filter: fit any model's parameters by the CKF's innovation
log-likelihood.

For measurements ``y_{1:T}`` the cubature Kalman filter gives, at every step, the predicted
measurement ``y^-_k`` and its covariance ``P_yy,k``; the prediction-error decomposition

    log p(y_{1:T} | theta) ~= sum_k log N(y_k; y^-_k(theta), P_yy,k(theta))

is exact for a linear-Gaussian model and the CKF's Gaussian approximation otherwise.
:func:`fit_likelihood` maximises it over ``theta`` (any ``nn.Parameter`` of the model: a drag
constant, a sensor bias, a learnable ``Q`` or ``R`` from :mod:`torchfilt.models.params`, the
variance scales of a :class:`~torchfilt.models.CalibratedModel`) with gradients through the
batched filter.

What matters to a filter is how its predictions fail over many steps; a one-step fit cannot see
slowly drifting errors, the filter likelihood can.

**Windows.** Long recordings are cut into windows of ``window`` steps, all filtered as one batch.
Consecutive windows overlap by ``burn_in`` steps, and the first ``burn_in`` steps of every window
(the first window of a recording included) are not counted in the likelihood: they let the filter
forget its start, so a diffuse or misplaced start never dominates the fit, and every other step is
counted exactly once (both are fields of ``windows=``, a :class:`~torchfilt.optim.WindowOptions`). A recording's first window starts from its prior ``N(x0, P0)``; each later
window starts from the previous pass's estimate of the state just before it (``start="filtered"``,
the default, or ``"smoothed"``, the RTS estimate), refreshed every ``refresh_every`` iterations
with the current parameters. ``x0`` may itself be a learnable tensor listed in ``parameters``.

**Subsets of windows.** With more windows than ``per_iteration``, each Adam iteration steps on
``per_iteration`` windows drawn by :func:`window_subset` from ``(seed, iteration)`` alone, their
log-likelihood scaled by ``windows / per_iteration``: an unbiased estimate of the full objective
and its gradient, at a fraction of the cost. The full objective is evaluated (without a graph)
every ``full_every`` iterations and at the last one; those evaluations, recorded as
``"objective"``, drive the stopping rules and the choice of the returned parameters. In a
data-parallel fit each process draws its subset from its own windows (the sum stays an unbiased
estimate, but the steps differ from those of one process on all recordings; give
``per_iteration=None`` for the same steps).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule
from torchfilt.exceptions import DivergenceWarning, InputError, InputTypeError, ShapeError
from torchfilt.filters import CKF, FilterResult, rts_smooth
from torchfilt.filters.inputs import check_model_input
from torchfilt.io import atomic_write
from torchfilt.io.progress import ProgressBar
from torchfilt.models import StateSpaceModel
from torchfilt.numerics import gaussian_log_prob, safe_cholesky
from torchfilt.numerics.dtypes import check_real_tensor
from torchfilt.optim import (
    CheckpointFile,
    CheckpointOptions,
    EarlyStopping,
    FitHooks,
    FitLoop,
    FitOptions,
    GuardedStep,
    OptimizerOptions,
    Outcome,
    StoppingOptions,
    WindowOptions,
    deprecated_fit_keywords,
    fingerprint,
    free_parameters,
    resolve_options,
    restore,
    snapshot,
)
from torchfilt.training.data import FitData, Sequences, as_sequences
from torchfilt.training.windows import _Windows, window_data, window_subset

__all__ = [
    "LikelihoodFit",
    "LikelihoodState",
    "Sequences",
    "fit_likelihood",
    "step_log_likelihood",
    "window_data",
    "window_subset",
]

#: Checkpoint format identifier.
_CKPT_SCHEMA = "torchfilt.likelihood-checkpoint/1"


def step_log_likelihood(res: FilterResult) -> Tensor:
    """Per-step innovation log-likelihood ``log N(y_k; y^-_k, P_yy,k)`` over observed components.

    Args:
        res: a filter result with innovations ``(..., T, m)`` (NaN where unobserved), innovation
            covariances ``(..., T, m, m)`` and the observed mask ``(..., T, m)``.

    Returns:
        ``(..., T)``; 0 at a step with no observed component. Its sum over ``T`` equals
        ``res.log_likelihood``.
    """
    obs = res.observed
    o = obs.to(res.innovation_cov.dtype)
    P = res.innovation_cov * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o)
    L = safe_cholesky(P, name="innovation covariance")
    e = torch.where(obs, res.innovation, torch.zeros_like(res.innovation))
    return gaussian_log_prob(e, L, dim=o.sum(-1))


# ----------------------------------------------------------------------------------- data
class _Recs(NamedTuple):
    y: Tensor  # (R, T, m), NaN-padded
    u: Tensor | None  # (R, T, nu), zero-padded
    x0: Tensor  # (R, n)
    P0: Tensor  # (R, n, n)
    lengths: list[int]


def _check_float(t: Tensor, name: str) -> None:
    if not t.is_floating_point():
        raise InputTypeError(
            f"{name}: expected a floating-point tensor (float32 or float64), got {t.dtype}; "
            "convert it with .double() (an integer tensor cannot hold missing values as NaN)"
        )
    check_real_tensor(t, name)  # float16 / bfloat16: refused, never upcast


def _stack(
    seqs: Tensor | Sequence[Tensor], name: str, fill: float, dtype: torch.dtype
) -> tuple[Tensor, list[int]]:
    if isinstance(seqs, Tensor):
        if seqs.dim() < 2:
            raise ShapeError(f"{name}: expected shape (..., T, d), got {tuple(seqs.shape)}")
        _check_float(seqs, name)
        if seqs.shape[-2] == 0 or any(int(d) == 0 for d in seqs.shape[:-2]):
            raise InputError(
                f"{name}: a recording has no steps (shape {tuple(seqs.shape)}); give at least one"
            )
        t = seqs.reshape(-1, *seqs.shape[-2:])
        return t.to(dtype), [int(t.shape[-2])] * int(t.shape[0])
    seqs = list(seqs)
    if not seqs:
        raise InputError(f"{name}: no recordings given")
    for i, s in enumerate(seqs):
        if not isinstance(s, Tensor) or s.dim() != 2:
            raise ShapeError(f"{name}[{i}]: expected a tensor of shape (T, d)")
        if s.shape[-1] != seqs[0].shape[-1]:
            raise ShapeError(
                f"{name}[{i}]: has {s.shape[-1]} columns, {name}[0] has {seqs[0].shape[-1]}"
            )
        _check_float(s, f"{name}[{i}]")
        if s.shape[0] == 0:
            raise InputError(f"{name}[{i}]: the recording has no steps; give at least one")
    T = max(int(s.shape[0]) for s in seqs)
    out = torch.full((len(seqs), T, int(seqs[0].shape[-1])), fill, dtype=dtype)
    for i, s in enumerate(seqs):
        out[i, : s.shape[0]] = s.to(dtype)
    return out, [int(s.shape[0]) for s in seqs]


def _prior_batch(v: Tensor, R: int, shape: tuple[int, ...], name: str) -> Tensor:
    if v.shape == shape:
        return v.expand(R, *shape)
    if (
        v.dim() >= len(shape)
        and v.shape[-len(shape) :] == shape
        and v.numel() == R * math.prod(shape)
    ):
        return v.reshape(R, *shape)
    raise ShapeError(
        f"{name}: expected {shape} or one per recording ({R}, {', '.join(map(str, shape))}), "
        f"got {tuple(v.shape)}"
    )


def _recordings(
    model: StateSpaceModel,
    y: Tensor | Sequence[Tensor],
    u: Tensor | Sequence[Tensor] | None,
    x0: Tensor | None,
    P0: Tensor | None,
    dtype: torch.dtype,
    prefix: str = "",
) -> _Recs:
    n, m = model.state_dim, model.obs_dim
    Y, lengths = _stack(y, prefix + "y", math.nan, dtype)
    if Y.shape[-1] != m:
        raise ShapeError(f"{prefix}y: expected m = {m} columns, got {Y.shape[-1]}")
    R, T = int(Y.shape[0]), int(Y.shape[1])
    U = None
    if u is not None:
        U, ulen = _stack(u, prefix + "u", 0.0, dtype)
        check_model_input(model, U, prefix + "u")
        if U.shape[0] != R or ulen != lengths:
            raise ShapeError(
                f"{prefix}u: needs one input row per measurement row of every recording "
                f"(y lengths {lengths[:5]}, u lengths {ulen[:5]})"
            )
        if not bool(torch.isfinite(U).all()):
            raise InputError(f"{prefix}u: contains non-finite entries; inputs cannot be missing")
    if not isinstance(x0, Tensor) or not isinstance(P0, Tensor):
        raise InputError(f"{prefix}x0 and {prefix}P0 must be tensors")
    _check_float(x0, prefix + "x0")
    _check_float(P0, prefix + "P0")
    X0 = _prior_batch(x0.to(dtype), R, (n,), prefix + "x0")
    C0 = _prior_batch(P0.to(dtype), R, (n, n), prefix + "P0")
    _check_prior(X0, C0, prefix)
    del T
    return _Recs(Y, U, X0, C0, lengths)


def _check_prior(X0: Tensor, C0: Tensor, prefix: str) -> None:
    """Refuse a non-finite prior and a ``P0`` that is not symmetric positive definite, before
    any filter pass (a filter would only fail on it after the first pass's work)."""
    if not bool(torch.isfinite(X0.detach()).all()):
        raise InputError(f"{prefix}x0: contains non-finite entries")
    P = C0.detach()
    if not bool(torch.isfinite(P).all()):
        raise InputError(f"{prefix}P0: contains non-finite entries")
    scale = P.abs().amax(dim=(-2, -1), keepdim=True).clamp_min(torch.finfo(P.dtype).tiny)
    if bool(((P - P.mT).abs() > 1e-8 * scale).any()):
        raise InputError(f"{prefix}P0: must be symmetric")
    _, info = torch.linalg.cholesky_ex(P)
    if bool((info > 0).any()):
        bad = int(torch.nonzero(info.reshape(-1) > 0)[0])
        raise InputError(
            f"{prefix}P0: must be positive definite (recording {bad} is not: its Cholesky "
            "factorisation fails); give a covariance such as a positive multiple of the identity"
        )


# ----------------------------------------------------------------------------------- results
class LikelihoodState(NamedTuple):
    """What the per-iteration callback sees.

    Attributes:
        iteration: iterations done (1-based).
        iterations: the budget.
        loss: negative log-likelihood per counted measurement (training windows).
        log_likelihood: the training log-likelihood (sum over counted steps).
        validation: held-out log-likelihood per measurement, when evaluated this iteration.
        elapsed: seconds since the fit started (this process).
    """

    iteration: int
    iterations: int
    loss: float
    log_likelihood: float
    validation: float | None
    elapsed: float


@dataclass
class LikelihoodFit:
    """Outcome of :func:`fit_likelihood`. The model holds the best parameters found.

    Attributes:
        log_likelihood: training log-likelihood at the returned parameters (counted steps).
        per_measurement: the same per counted measurement.
        initial_log_likelihood: training log-likelihood before the fit.
        validation: held-out log-likelihood per measurement at the returned parameters.
        iterations: iterations run.
        best_iteration: iteration whose parameters are returned (0: the initial ones): the best
            held-out likelihood with ``validation``; else the last iteration, or an earlier one
            whose training loss was lower.
        stopped: why the loop ended: ``"iterations"``, ``"converged"``, ``"early stopping"``,
            ``"callback"`` or ``"non-finite"``.
        measurements: counted measurement components.
        windows: windows per iteration (data-parallel: of all processes).
        history: one record per iteration (``iteration``, ``loss``, ``validation``, ``elapsed``).
        elapsed: seconds of the whole fit.
    """

    log_likelihood: float
    per_measurement: float
    initial_log_likelihood: float
    validation: float | None
    iterations: int
    best_iteration: int
    stopped: str
    measurements: int
    windows: int
    history: list[dict[str, Any]] = field(default_factory=list)
    elapsed: float = 0.0


@deprecated_fit_keywords("likelihood")
def fit_likelihood(
    model: StateSpaceModel,
    y: FitData,
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    parameters: Iterable[nn.Parameter] | None = None,
    fixed: Collection[str] = (),
    validation: FitData | None = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    hooks: FitHooks | None = None,
    progress: bool = False,
    callback: Callable[[LikelihoodState], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    sqrt: bool = False,
    rule: CubatureRule | None = None,
    compile: bool = False,
) -> LikelihoodFit:
    """Maximise the CKF's innovation log-likelihood over a model's parameters.

    Input convention (:mod:`torchfilt.filters`): step ``t`` predicts ``x_t`` from ``x_{t-1}``
    with the input row ``u[..., t, :]`` and updates with ``y[..., t, :]``, passing the same row
    to the measurement; the prior ``N(x0, P0)`` is the belief about ``x_{-1}``.

    The flat keywords of before (``params``, ``lr``, ``window``, ``burn_in``, ``start``,
    ``refresh_every``, ``patience``, ``validate_every``, ``tol``, ``rtol``, ``rtol_window``,
    ``checkpoint_every``, ``resume``, ``project``, ``prepare``, ``all_reduce``) still work for
    one release, with a ``DeprecationWarning`` naming their new spelling.

    Args:
        model: the state-space model; converted to ``dtype`` in place. It ends holding the best
            parameters found (by held-out likelihood when ``validation`` is given, else by
            training likelihood).
        y: measurements ``(..., T, m)`` (a batch of recordings), a list of ``(T_i, m)`` of
            different lengths, a :class:`~torchfilt.training.data.Sequences`, or a list of
            :class:`~torchfilt.io.Recording` (row 0 the prior's time; see
            :mod:`torchfilt.training.data`). NaN marks a missing component.
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None`` (``None`` when ``y`` is
            a ``Sequences`` or recordings, which carry their own).
        x0: prior mean ``(n,)`` shared, or one per recording ``(..., n)`` (a ``Sequences``' own
            ``x0``, when given, is used instead).
        P0: prior covariance ``(n, n)`` or one per recording ``(..., n, n)`` (likewise).
        parameters: the parameters to fit (default: every parameter of ``model`` with
            ``requires_grad``). Positive-definite ``Q``/``R`` and bounded constants come from
            :mod:`torchfilt.models.params`: ``DiagonalCovariance`` (log-diagonal),
            ``CholeskyCovariance`` (Cholesky factor with a log diagonal), ``ScalarCovariance``
            (log variance), ``Positive`` (softplus), ``Bounded`` (logit).
        fixed: names of parameters held fixed, as ``model.named_parameters()`` gives them
            (e.g. ``"transition.A"``): they are left out of the fit and end bit-identical; an
            unknown name is an :class:`~torchfilt.exceptions.InputError`.
        validation: held-out data for early stopping, of any kind ``y`` accepts (a
            ``Sequences`` to give inputs or its own prior; without one, the training prior).
        iterations: iteration budget (default 200; an L-BFGS iteration runs up to
            ``max_iter`` inner steps).
        optimizer: the optimiser, :class:`~torchfilt.optim.OptimizerOptions` or its name
            (``"adam"``, the default, or ``"lbfgs"``: strong-Wolfe line search, best for a few
            parameters and tight optima); its ``lr`` defaults to 0.05 for Adam, 1 for L-BFGS.
        windows: the windows of the likelihood, :class:`~torchfilt.optim.WindowOptions`
            (default whole recordings; see the module docstring).
        stopping: the stopping rules, :class:`~torchfilt.optim.StoppingOptions`: early stopping
            on ``validation`` (``patience`` 20 evaluations, every ``validate_every``
            iterations), ``tol`` (default ``1e-10`` for L-BFGS, off for Adam) and the windowed
            ``rtol`` (default ``1e-6`` over 20 iterations). A ``patience`` given without
            ``validation`` warns (:class:`~torchfilt.exceptions.ConvergenceWarning`).
        checkpoint: checkpoints, :class:`~torchfilt.optim.CheckpointOptions` or the file's path
            (atomic, every 10 iterations by default); with ``resume=True`` an existing one is
            continued, and the result equals an uninterrupted fit.
        hooks: :class:`~torchfilt.optim.FitHooks`. ``project`` is called after every optimiser
            step to project the parameters back onto their feasible set in place (e.g.
            :meth:`~torchfilt.models.CalibratedModel.project_`); ``prepare`` before every
            evaluation of the likelihood (training, held-out, window starts), inside its
            autograd context: e.g. rebuilding a GP's differentiable twin
            (:meth:`~torchfilt.models.gp.GPModel.twin`) from its current hyperparameters;
            ``all_reduce``, for a data-parallel fit, sums a flat tensor in place across the
            processes (e.g. ``torch.distributed.all_reduce`` with a CPU ``gloo`` group). Each
            process passes its own recordings (whole recordings: window starts come from
            filtering them) and the same ``validation`` (or none); the log-likelihood, the
            measurement count and the gradient are summed over the processes, so every process
            takes the same steps and ends with the parameters of one fit on all recordings (up
            to the order of the sums). A callback that stops one process stops all. Give each
            process its own ``checkpoint`` file; each also keeps the checkpoint before it, so
            that after a lost process a resume starts every process from the same iteration.
        progress: show a progress bar on stderr.
        callback: called after every iteration with a :class:`LikelihoodState`; return ``True``
            to stop.
        dtype: floating dtype of the fit (float64 by default).
        sqrt: use the square-root CKF.
        rule: cubature rule (default the third-degree spherical-radial rule).
        compile: compile the filter step with ``torch.compile`` (pays on one or a few long
            windows; see ``scripts/bench_calibrate.py``).

    Returns:
        A :class:`LikelihoodFit`.

    Raises:
        InputError, ShapeError: invalid arguments; RunError: a checkpoint of another fit.
    """
    o = resolve_options(
        "likelihood", iterations=iterations, optimizer=optimizer, windows=windows,
        stopping=stopping, checkpoint=checkpoint, hooks=hooks,
    )  # fmt: skip
    return _fit_likelihood(
        model, y, u, x0=x0, P0=P0, parameters=parameters, fixed=fixed, validation=validation,
        options=o, progress=progress, callback=callback, dtype=dtype, sqrt=sqrt, rule=rule,
        compile=compile,
    )  # fmt: skip


def _fit_likelihood(
    model: StateSpaceModel,
    y: FitData,
    u: Tensor | Sequence[Tensor] | None,
    *,
    x0: Tensor,
    P0: Tensor,
    parameters: Iterable[nn.Parameter] | None,
    fixed: Collection[str],
    validation: FitData | None,
    options: FitOptions,
    progress: bool,
    callback: Callable[[LikelihoodState], bool | None] | None,
    dtype: torch.dtype,
    sqrt: bool,
    rule: CubatureRule | None,
    compile: bool,
) -> LikelihoodFit:
    """:func:`fit_likelihood` with its options resolved (:func:`~torchfilt.optim.resolve_options`):
    the body that :func:`~torchfilt.training.calibrate` and
    :func:`~torchfilt.training.fit_measurement_only` share with their own defaults."""
    o = options
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    if o.windows.per_iteration is not None and o.optimizer.optimizer != "adam":
        raise InputError(
            f"per_iteration={o.windows.per_iteration}: subsets of windows need optimizer='adam' "
            "(L-BFGS's line search needs a deterministic objective); give "
            "WindowOptions(per_iteration=None)"
        )
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    model.to(dtype)
    data = as_sequences(y, u, x0=x0, P0=P0)
    recs = _recordings(model, data.y, data.u, data.x0, data.P0, dtype)
    plist = free_parameters(model, parameters, fixed, what="parameters")
    val = None
    if validation is not None:
        v = as_sequences(validation, x0=recs.x0[0], P0=recs.P0[0], name="validation")
        val = _recordings(model, v.y, v.u, v.x0, v.P0, dtype, "validation.")
        if int(torch.isfinite(val.y).sum()) == 0:
            raise InputError("validation.y: no measurement observed")
    obj = _Objective(
        model, recs, val, data.x0, o.windows, CKF(model, rule=rule, sqrt=sqrt, compile=compile),
        o.hooks.prepare, o.hooks.all_reduce,
    )  # fmt: skip
    return _run(obj, plist, o, callback, progress)


class _Objective:
    """The training windows and held-out recordings of a likelihood fit, and their
    log-likelihoods (summed over the processes of a data-parallel fit)."""

    def __init__(
        self,
        model: StateSpaceModel,
        recs: _Recs,
        val: _Recs | None,
        x0: Tensor | None,
        options: WindowOptions,
        filt: CKF,
        prepare: Callable[[], None] | None,
        all_reduce: Callable[[Tensor], None] | None,
    ) -> None:
        self.model, self.recs, self.val, self.options = model, recs, val, options
        self.filt, self.prepare, self.all_reduce = filt, prepare, all_reduce
        self.win = win = window_data(recs.y, recs.u, recs.lengths, options.window, options.burn_in)
        counted = int((torch.isfinite(win.y) & win.counted.unsqueeze(-1)).sum())
        if counted == 0:
            raise InputError("y: no measurement is counted (all missing, or burn_in covers them)")
        windows, recordings = int(win.y.shape[0]), len(recs.lengths)
        if all_reduce is not None:  # the counts of the whole fit, as one process on all recordings
            total = self.summed(torch.tensor([float(counted), float(windows), float(recordings)]))
            counted, windows, recordings = int(total[0]), int(total[1]), int(total[2])
        self.counted, self.windows, self.recordings = counted, windows, recordings
        # subsets of windows: when the whole fit has more windows than per_iteration (the same
        # decision on every process of a data-parallel fit: the full evaluations are collectives)
        k = options.per_iteration  # resolved: never "auto" here
        self.subsets = isinstance(k, int) and windows > k
        self.val_count = 0 if val is None else int(torch.isfinite(val.y).sum())
        self.first = win.start == 0
        # windows that start a recording take the learnable prior mean, with its graph
        self.x0 = x0 if isinstance(x0, Tensor) and x0.requires_grad else None

    def summed(self, *values: Tensor) -> Tensor:
        """The values flattened into one float64 tensor, summed over the processes."""
        flat = torch.cat([v.detach().reshape(-1).to(torch.float64) for v in values])
        if self.all_reduce is not None:
            self.all_reduce(flat)
        return flat

    @torch.no_grad()
    def starts(self) -> tuple[Tensor, Tensor]:
        """Initial means ``(W, n)`` and covariances ``(W, n, n)`` of the windows."""
        recs, win, first = self.recs, self.win, self.first
        wx0, wP0 = recs.x0[win.rec].detach().clone(), recs.P0[win.rec].detach().clone()
        if bool(first.all()):
            return wx0, wP0
        if self.prepare is not None:
            self.prepare()
        res = self.filt.filter(recs.y, recs.u, x0=recs.x0.detach(), P0=recs.P0.detach())
        if self.options.start == "smoothed":
            sm = rts_smooth(res)
            mean, cov = sm.mean, sm.cov
        else:
            mean, cov = res.mean, res.cov
        later = ~first
        idx = win.start[later] - 1
        wx0[later] = mean[win.rec[later], idx]
        wP0[later] = cov[win.rec[later], idx]
        return wx0, wP0

    def subset(self, iteration: int) -> Tensor | None:
        """This process's windows of ``iteration`` (``None``: all of them)."""
        k = self.options.per_iteration
        local = int(self.win.y.shape[0])
        if not self.subsets or not isinstance(k, int) or local <= k:
            return None
        return window_subset(local, k, self.options.seed, iteration)

    def train(self, wx0: Tensor, wP0: Tensor, subset: Tensor | None = None) -> Tensor:
        """The training log-likelihood of this process's windows (with its graph); of the
        windows ``subset`` only, scaled by ``windows / len(subset)`` (an unbiased estimate)."""
        if self.prepare is not None:
            self.prepare()
        win, first = self.win, self.first
        if subset is not None:
            win = _Windows(
                win.y[subset], None if win.u is None else win.u[subset], win.counted[subset],
                win.rec[subset], win.start[subset],
            )  # fmt: skip
            first, wx0, wP0 = first[subset], wx0[subset], wP0[subset]
        if self.x0 is not None:
            X0 = _prior_batch(
                self.x0.to(wx0.dtype), int(self.recs.y.shape[0]), (self.model.state_dim,), "x0"
            )
            wx0 = torch.where(first.unsqueeze(-1), X0[win.rec], wx0)
        # without a burn-in every step is counted (the others are padding, all missing): the
        # summed log-likelihood alone, whose gradient the exact path has in closed form
        whole = self.options.burn_in == 0
        outputs = ("log_likelihood",) if whole else None
        with warnings.catch_warnings():
            # a trial step of the optimiser may diverge: the fit scores it -inf and steps back
            warnings.simplefilter("ignore", DivergenceWarning)
            res = self.filt.filter(win.y, win.u, x0=wx0, P0=wP0, outputs=outputs)
        if whole:
            total = res.log_likelihood.sum()
        else:
            ll = step_log_likelihood(res)
            total = (ll * win.counted.to(ll.dtype)).sum()
        if subset is None:
            return total
        return total * (int(self.win.y.shape[0]) / int(subset.numel()))

    def guarded_train(self, wx0: Tensor, wP0: Tensor, subset: Tensor | None = None) -> Tensor:
        """:meth:`train`, NaN where a factorisation in the model failed (a model that calls
        ``torch.linalg.cholesky`` itself): a failed evaluation is a non-finite one, which the
        line search shortens and :class:`~torchfilt.optim.GuardedStep` steps back from."""
        try:
            return self.train(wx0, wP0, subset)
        except torch.linalg.LinAlgError:
            return torch.tensor(math.nan, dtype=self.recs.y.dtype)

    def total(self, wx0: Tensor, wP0: Tensor) -> float:
        """The training log-likelihood summed over the processes (no gradient)."""
        with torch.no_grad():
            return float(self.summed(self.guarded_train(wx0, wP0).reshape(1))[0])

    def held_out(self) -> float:
        """The held-out log-likelihood per measurement."""
        val = self.val
        assert val is not None
        with torch.no_grad():
            if self.prepare is not None:
                self.prepare()
            try:
                res = self.filt.filter(val.y, val.u, x0=val.x0, P0=val.P0)
            except torch.linalg.LinAlgError:  # a failed factorisation scores as non-finite
                return math.nan
        return float(res.log_likelihood.sum()) / self.val_count

    def loss(
        self, plist: list[nn.Parameter], wx0: Tensor, wP0: Tensor, subset: Tensor | None = None
    ) -> Tensor:
        """The loss per counted measurement and its gradient in ``plist`` (``+inf`` where it
        is not finite, without a gradient): an optimiser's closure; on the windows ``subset``
        only, an unbiased estimate of it."""
        counted = self.counted
        if self.all_reduce is None:
            loss = -self.guarded_train(wx0, wP0, subset) / counted
            if bool(torch.isfinite(loss)):
                loss.backward()
                return loss.detach()
            # +inf, not NaN: L-BFGS's line search then shortens the step
            return torch.full_like(loss.detach(), math.inf)
        # data-parallel: local sums, then one collective for the loss and the gradient (called on
        # every process whatever its loss, so that none waits forever)
        ll = self.guarded_train(wx0, wP0, subset)
        if bool(torch.isfinite(ll)):
            (-ll).backward()
        grads = [
            torch.full_like(p, math.nan)
            if not bool(torch.isfinite(ll))
            else (torch.zeros_like(p) if p.grad is None else p.grad)
            for p in plist
        ]
        flat = self.summed(ll.reshape(1), *grads)
        offset = 1
        for p in plist:
            k = p.numel()
            p.grad = (flat[offset : offset + k] / counted).reshape(p.shape).to(p.dtype)
            offset += k
        total = (-flat[0] / counted).to(ll.dtype)
        return total if bool(torch.isfinite(total)) else torch.full_like(total, math.inf)


def _run(
    obj: _Objective,
    plist: list[nn.Parameter],
    o: FitOptions,
    callback: Callable[[LikelihoodState], bool | None] | None,
    progress: bool,
) -> LikelihoodFit:
    """The fitting loop of :func:`fit_likelihood` on the objective ``obj``."""
    opt_o, stop_o, ckpt_o = o.optimizer, o.stopping, o.checkpoint
    iterations, counted, tol = o.iterations, obj.counted, stop_o.tolerance(opt_o.optimizer)
    guarded = GuardedStep(plist, opt_o, o.hooks.project)
    ckpt = None
    if ckpt_o.path is not None:
        fp = fingerprint(obj.recs.y, obj.recs.u, *snapshot(plist))
        ckpt = CheckpointFile(
            ckpt_o.path, fp, schema=_CKPT_SCHEMA, kind="likelihood", write=atomic_write,
            all_reduce=obj.all_reduce,
        )  # fmt: skip
    val_score = obj.held_out if obj.val is not None else None
    early = EarlyStopping(
        stop_o, val_score, lambda: snapshot(plist), patience_given=o.patience_given
    )
    bar = ProgressBar("fit likelihood", iterations, enabled=progress)
    loop = FitLoop(
        iterations=iterations, progress=bar, callback=callback, all_reduce=obj.all_reduce,
        stopping=early, tol=tol, rtol=stop_o.rtol, rtol_window=stop_o.rtol_window,
        atol=stop_o.atol, scale=counted / obj.recordings,
        monitor="objective" if obj.subsets else "loss", checkpoint=ckpt, every=int(ckpt_o.every or 1),
    )  # fmt: skip
    wx0: Tensor | None = None
    wP0: Tensor | None = None
    initial: float | None = None
    # without held-out data: the parameters with the lowest training loss seen (loss, values, it)
    best_train: tuple[float, list[Tensor], int] = (math.inf, snapshot(plist), 0)
    ck = loop.resume() if ckpt_o.resume else None
    if ck is not None:
        restore(plist, ck["params"])
        guarded.optimizer.load_state_dict(ck["optimizer"])
        wx0, wP0, initial = ck["wx0"], ck["wP0"], float(ck["initial"])
        best_train = (
            float(ck["best_train_loss"]),
            [t.clone() for t in ck["best_train_params"]],
            int(ck["best_train_iteration"]),
        )
    t_start = time.perf_counter()
    if wx0 is None or wP0 is None:
        wx0, wP0 = obj.starts()
    if initial is None:
        initial = obj.total(wx0, wP0)
        early.best_score = obj.held_out() if obj.val is not None else initial / counted
        if obj.subsets:  # the start, scored by the full objective
            best_train = (-initial / counted, best_train[1], 0)
    full_every = obj.options.full_every

    def step(it: int) -> Outcome:
        nonlocal wx0, wP0, best_train
        if it > 1 and (it - 1) % obj.options.refresh_every == 0:
            wx0, wP0 = obj.starts()
        assert wx0 is not None and wP0 is not None
        ux0, uP0 = wx0, wP0

        subset = obj.subset(it)

        def closure() -> Tensor:
            guarded.optimizer.zero_grad()
            return obj.loss(plist, ux0, uP0, subset)

        res = guarded(closure)
        loss = res.loss
        # it scores the parameters before the step (with subsets: only an estimate)
        if not obj.subsets and res.loss_finite and loss < best_train[0]:
            best_train = (loss, res.good, it - 1)
        if res.status == "retry":
            return Outcome(None)
        if res.status == "failed":
            return Outcome(None, abort="non-finite")
        elapsed = time.perf_counter() - t_start
        rec: dict[str, Any] = {"iteration": it, "loss": loss, "elapsed": elapsed}
        if obj.subsets and (it % full_every == 0 or it == iterations):
            # the full objective at the parameters after the step
            rec["objective"] = objective = -obj.total(wx0, wP0) / counted
            if math.isfinite(objective) and objective < best_train[0]:
                best_train = (objective, snapshot(plist), it)
        vscore = early.observe(it)
        if vscore is not None:
            rec["validation"] = vscore
        info = f"-loglik/meas {loss:.5g}" + ("" if vscore is None else f", held-out {vscore:.5g}")
        state = LikelihoodState(it, iterations, loss, -loss * counted, vscore, elapsed)
        return Outcome(rec, state, info)

    def payload() -> dict[str, Any]:
        return {
            "params": snapshot(plist),
            "optimizer": guarded.optimizer.state_dict(),
            "wx0": wx0,
            "wP0": wP0,
            "initial": initial,
            "best_train_loss": best_train[0],
            "best_train_params": best_train[1],
            "best_train_iteration": best_train[2],
        }

    stopped = loop.run(step, payload)
    return _finish(obj, plist, loop, early, best_train, stopped, initial, t_start)


def _finish(
    obj: _Objective,
    plist: list[nn.Parameter],
    loop: FitLoop,
    early: EarlyStopping,
    best_train: tuple[float, list[Tensor], int],
    stopped: str,
    initial: float,
    t_start: float,
) -> LikelihoodFit:
    """The result of a likelihood fit. The returned parameters: the best held-out ones; without
    held-out data the last (finite) ones, unless an earlier iteration scored a better training
    loss."""
    it, counted = loop.iteration, obj.counted
    best_it = early.best_iteration
    if obj.val is not None:
        restore(plist, early.best_params)
    else:
        best_it = it if stopped != "non-finite" else max(it - 1, 0)
    wx0, wP0 = obj.starts()
    final = obj.total(wx0, wP0)
    if obj.val is None and -final / counted > best_train[0]:
        restore(plist, best_train[1])
        best_it = best_train[2]
        wx0, wP0 = obj.starts()
        final = obj.total(wx0, wP0)
    vfinal = obj.held_out() if obj.val is not None else None
    return LikelihoodFit(
        log_likelihood=final,
        per_measurement=final / counted,
        initial_log_likelihood=initial,
        validation=vfinal,
        iterations=len(loop.history),
        best_iteration=best_it,
        stopped=stopped,
        measurements=counted,
        windows=obj.windows,
        history=loop.history,
        elapsed=time.perf_counter() - t_start,
    )
