"""Typed options of the fits, and every fit's defaults in one place.

The fits (:func:`~torchfilt.training.fit_likelihood`, :func:`~torchfilt.training.calibrate`,
:func:`~torchfilt.training.fit_measurement_only`, :func:`~torchfilt.training.fit_em` and the GP
hyperparameter training :meth:`~torchfilt.models.gp.GPModel.optimize`, which the GP fits
:meth:`~torchfilt.models.gp.GPTransition.fit` and :meth:`~torchfilt.models.gp.GPMeasurement.fit`
run) take the same keywords for the same ideas: a flat ``iterations=`` (the fit's budget) and four groups of options, each a
frozen dataclass here: ``optimizer=`` (:class:`OptimizerOptions`, or its name as a shortcut),
``windows=`` (:class:`WindowOptions`, the likelihood fits), ``stopping=``
(:class:`StoppingOptions`) and ``checkpoint=`` (:class:`CheckpointOptions`, or its path as a
shortcut); the distributed and pipeline hooks are ``hooks=`` (:class:`FitHooks`). ``None``
anywhere is the fit's default, read from its entry in :data:`DEFAULTS` (by
:func:`resolve_options`), so one table says where the fits differ and why:

================  =========  ======  ==========  ======  =======  ========  ================
fit               optimizer  lr      iterations  window  burn_in  patience  checkpoint every
================  =========  ======  ==========  ======  =======  ========  ================
likelihood        adam       auto    200         None    0        20        10
calibrate         adam       0.1     100         100     20       15        10
measurement_only  lbfgs      auto    30          None    0        20        1
em                (closed form or L-BFGS M-step) 100     --       --        1
gp                adam       0.05    200         --      --       --        (callback)
================  =========  ======  ==========  ======  =======  ========  ================

``lr="auto"`` (``None``) is 0.05 for Adam and 1 for L-BFGS; ``tol=None`` is ``1e-10`` for L-BFGS
and off for Adam (the likelihood fits), ``1e-9`` per measurement for EM. Why they differ:
calibration fits a few variance scales on long recordings, so it windows them (100 steps, 20 of
burn-in) and takes larger Adam steps; measurement-only learning has few, tightly identified
parameters and wants L-BFGS; an EM iteration is expensive and monotone, so it checkpoints every
iteration; a GP's optimiser state is checkpointed by the caller through its callback. The
recipe's ``[calibrate]`` and ``[measurement_only]`` keys are these fields, with these defaults
(:mod:`torchfilt.pipeline.recipe`), and the recipe reference shows each field's meaning from its
class's docstring (:func:`field_docs`).
"""

from __future__ import annotations

import difflib
import functools
import inspect
import math
import re
import warnings
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, TypeVar

from torchfilt.exceptions import ConvergenceWarning, InputError, InputTypeError

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "DEFAULTS",
    "CheckpointOptions",
    "FitDefaults",
    "FitHooks",
    "FitOptions",
    "OptimizerOptions",
    "StoppingOptions",
    "WindowOptions",
    "deprecated_fit_keywords",
    "field_docs",
    "resolve_options",
]

#: A decorated fit (:func:`deprecated_fit_keywords` keeps its type).
_F = TypeVar("_F", bound=Callable[..., Any])

#: Largest accepted learning rate of the likelihood fits.
MAX_LR = 100.0


def _at_least_one(**values: int) -> None:
    for name, v in values.items():
        if v < 1:
            raise InputError(f"{name} must be at least 1, got {v}")


@dataclass(frozen=True)
class OptimizerOptions:
    """The optimiser of a fit (its iteration budget is the fit's own ``iterations=``).

    Attributes:
        optimizer: ``"adam"`` or ``"lbfgs"`` (strong-Wolfe line search; best for a few parameters
            and tight optima).
        lr: learning rate; ``None``: the fit's default (see ``DEFAULTS``), else 0.05 for Adam and 1
            for L-BFGS.
        max_iter: L-BFGS inner steps per iteration.
        tolerance_change: L-BFGS's tolerance on the change of the loss or the parameters.
        tolerance_grad: L-BFGS's tolerance on the gradient.
        history_size: L-BFGS's curvature pairs.

    Raises:
        InputError: an unknown ``optimizer``, a learning rate that is not finite and positive
            (or too large), or a count below 1.
    """

    optimizer: Literal["adam", "lbfgs"] = "adam"
    lr: float | None = None
    max_iter: int = 20
    tolerance_change: float = 1e-14
    tolerance_grad: float = 1e-12
    history_size: int = 20

    def __post_init__(self) -> None:
        if self.optimizer not in ("adam", "lbfgs"):
            raise InputError(f"optimizer must be 'adam' or 'lbfgs', got {self.optimizer!r}")
        _at_least_one(max_iter=self.max_iter, history_size=self.history_size)
        lr = self.learning_rate
        if not (math.isfinite(lr) and 0 < lr <= MAX_LR):
            raise InputError(
                f"lr must be a finite positive number (at most {MAX_LR:g}), got {self.lr}"
            )

    @property
    def learning_rate(self) -> float:
        """``lr``, or the optimiser's default (0.05 for Adam, 1 for L-BFGS)."""
        if self.lr is None:
            return 0.05 if self.optimizer == "adam" else 1.0
        return float(self.lr)


@dataclass(frozen=True)
class WindowOptions:
    """The windows of a likelihood fit (see :mod:`torchfilt.training.likelihood`).

    Attributes:
        window: window length in steps (``None``: whole recordings; longer recordings are cut).
        burn_in: uncounted steps at the start of every window (an integer in [0, window)).
        start: where a later window starts: the previous pass's ``"filtered"`` or ``"smoothed"``
            estimate of the state just before it.
        refresh_every: iterations between refreshes of the window starts.
        per_iteration: at most this many windows per Adam iteration (``None``: all;
            ``"auto"``, the default: the fit's own, 64 for ``calibrate``, all for
            ``fit_likelihood`` and ``fit_measurement_only``). With more
            windows than that, each iteration steps on a random subset of ``per_iteration`` of
            them, drawn from ``(seed, iteration)`` alone (a resumed fit draws the same ones),
            its log-likelihood scaled by ``windows / per_iteration`` (an unbiased estimate of
            the full one); the full objective is evaluated every ``full_every`` iterations and
            at the end, for the stopping rules, the best parameters and the reported
            likelihood.
        full_every: iterations between evaluations of the full objective with subsets.
        seed: the seed of the subsets.

    Raises:
        InputError: an unknown ``start``, or a count below 1.
    """

    window: int | None = None
    burn_in: int = 0
    start: Literal["filtered", "smoothed"] = "filtered"
    refresh_every: int = 10
    per_iteration: int | Literal["auto"] | None = "auto"
    full_every: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.start not in ("filtered", "smoothed"):
            raise InputError(f"start must be 'filtered' or 'smoothed', got {self.start!r}")
        _at_least_one(refresh_every=self.refresh_every, full_every=self.full_every)
        if self.per_iteration not in (None, "auto"):
            if isinstance(self.per_iteration, bool) or not isinstance(self.per_iteration, int):
                raise InputError(
                    f"per_iteration must be an integer, 'auto' or None, got {self.per_iteration!r}"
                )
            _at_least_one(per_iteration=self.per_iteration)


@dataclass(frozen=True)
class StoppingOptions:
    """When a fit stops before its budget.

    Two convergence rules act on the loss ``L_k`` of the fit's records (per measurement for the
    likelihood fits and EM), each stopping with ``"converged"``:

    * ``tol``, per iteration: ``|L_k - L_{k-1}| <= tol * (1 + |L_k|)``;
    * ``rtol`` over a window of ``rtol_window`` iterations:
      ``|L_k - L_{k-w}| <= rtol * max(1, |L_k|)``. It is on by default (``rtol = 1e-6`` over
      ``w = 20`` iterations: a loss that moved by less than a millionth in twenty iterations has
      stopped moving; a fit that still creeps at that rate gains nothing a user would see), so a
      fit no longer spends its whole budget printing the same loss. A reference comparison that
      needs the optimum to the last digits passes a smaller ``rtol`` (or 0: off);
    * ``atol`` over the same window, in nats of the total objective: the total log-likelihood
      improved by less than ``atol`` nats per recording over the last ``rtol_window``
      iterations (``(L_{k-w} - L_k) * measurements / recordings < atol`` for a loss per
      measurement). Default ``0.01``: a likelihood-ratio difference of a hundredth of a nat
      per recording is far below any significance (a likelihood-ratio test at 5 % needs
      1.92 nats for one parameter), so a fit that gains less than that in twenty iterations has
      nothing left to find that the data could tell apart; ``rtol = 1e-6`` per measurement is
      0.004 nats in total on ~3600 measurements and lets a converged fit run its budget. It
      acts in the fits that know their measurement and recording counts (the likelihood fits
      and EM); 0: off.

    A ``patience`` set here counts as given: early stopping that cannot act (no held-out data)
    then warns (:class:`~torchfilt.exceptions.ConvergenceWarning`); the fit's default does not.

    Attributes:
        patience: early stopping: held-out evaluations without a better held-out likelihood on
            the validation recordings before the fit stops (``None``: the fit's default).
        validate_every: iterations between held-out evaluations.
        tol: the per-iteration rule (``None``: the fit's default, see ``DEFAULTS``; 0: off).
        rtol: the windowed rule's relative tolerance (0: off).
        rtol_window: its window ``w`` in iterations.
        atol: the windowed rule in nats per recording (0: off).

    Raises:
        InputError: a ``tol``, ``rtol`` or ``atol`` that is negative or not finite, or a count
            below 1.
    """

    patience: int | None = None
    validate_every: int = 1
    tol: float | None = None
    rtol: float = 1e-6
    rtol_window: int = 20
    atol: float = 0.01

    def __post_init__(self) -> None:
        _at_least_one(validate_every=self.validate_every, rtol_window=self.rtol_window)
        if self.patience is not None:
            _at_least_one(patience=self.patience)
        if self.tol is not None and not (math.isfinite(self.tol) and self.tol >= 0):
            raise InputError(f"tol must be finite and non-negative, got {self.tol}")
        if not (math.isfinite(self.rtol) and self.rtol >= 0):
            raise InputError(f"rtol must be finite and non-negative, got {self.rtol}")
        if not (math.isfinite(self.atol) and self.atol >= 0):
            raise InputError(f"atol must be finite and non-negative, got {self.atol}")

    def tolerance(self, optimizer: str) -> float:
        """``tol``, or the likelihood fits' default for ``optimizer`` (``1e-10`` for L-BFGS,
        off for Adam)."""
        if self.tol is None:
            return 1e-10 if optimizer == "lbfgs" else 0.0
        return float(self.tol)


@dataclass(frozen=True)
class CheckpointOptions:
    """Checkpoints of a fit: written atomically every ``every`` iterations, at the last one and
    when the fit stops by itself; resuming from one equals an uninterrupted fit bit for bit.

    Attributes:
        path: the checkpoint file (``None``: none).
        every: iterations between checkpoints (``None``: the fit's default).
        resume: continue from ``path`` if it exists.

    Raises:
        InputError: ``every`` below 1, or ``resume`` without a ``path``.
    """

    path: str | Path | None = None
    every: int | None = None
    resume: bool = False

    def __post_init__(self) -> None:
        if self.every is not None:
            _at_least_one(checkpoint_every=self.every)
        if self.resume and self.path is None:
            raise InputError(
                "resume=True needs checkpoint= (the file to continue from); give a checkpoint "
                "path or leave resume=False"
            )


@dataclass(frozen=True)
class FitHooks:
    """What a caller plugs into a fit's loop: the distributed and pipeline hooks.

    Attributes:
        project: called after every optimiser step to project the parameters back onto their
            feasible set in place (e.g. :meth:`~torchfilt.models.CalibratedModel.project_`).
        prepare: called before every evaluation of the likelihood (training, held-out, window
            starts), inside its autograd context: e.g. rebuilding a GP's differentiable twin.
        all_reduce: for a data-parallel fit: sums a flat tensor in place across the processes
            (e.g. ``torch.distributed.all_reduce`` with a CPU ``gloo`` group).
    """

    project: Callable[[], None] | None = None
    prepare: Callable[[], None] | None = None
    all_reduce: Callable[[Tensor], None] | None = None


@dataclass(frozen=True)
class FitDefaults:
    """One fit's defaults: its iteration budget and the four groups of options (every ``None``
    of a group here is resolved as the group's docstring says).

    Attributes:
        iterations: the fit's iteration budget: EM or optimiser iterations (a fit's own
            ``iterations=``, not an optimiser's option).
        optimizer: the optimiser.
        windows: the windows of the likelihood.
        stopping: the stopping rules.
        checkpoint: the checkpoints.
    """

    iterations: int = 200
    optimizer: OptimizerOptions = field(default_factory=OptimizerOptions)
    windows: WindowOptions = field(default_factory=WindowOptions)
    stopping: StoppingOptions = field(default_factory=lambda: StoppingOptions(patience=20))
    checkpoint: CheckpointOptions = field(default_factory=lambda: CheckpointOptions(every=10))


#: Each fit's defaults (the table of the module docstring), read-only.
DEFAULTS: Mapping[str, FitDefaults] = MappingProxyType(
    {
        "likelihood": FitDefaults(),
        "calibrate": FitDefaults(
            100,
            OptimizerOptions("adam", lr=0.1),
            WindowOptions(window=100, burn_in=20, per_iteration=64),
            StoppingOptions(patience=15),
        ),
        "measurement_only": FitDefaults(
            30, OptimizerOptions("lbfgs"), checkpoint=CheckpointOptions(every=1)
        ),
        "em": FitDefaults(
            100,
            # the gradient M-step of a non-linear model: L-BFGS, ``max_iter`` = m_step_iterations
            OptimizerOptions("lbfgs", lr=1.0, tolerance_change=1e-12, tolerance_grad=1e-10),
            stopping=StoppingOptions(patience=20, tol=1e-9),
            checkpoint=CheckpointOptions(every=1),
        ),
        "gp": FitDefaults(200, OptimizerOptions("adam", lr=0.05)),
    }
)


class FitOptions(NamedTuple):
    """A fit's options with every default filled in (:func:`resolve_options`).

    Attributes:
        iterations: the iteration budget.
        optimizer: the optimiser (``lr`` may stay ``None``: the optimiser's default).
        windows: the windows of a likelihood fit.
        stopping: the stopping rules (``patience`` set).
        patience_given: the caller set ``patience``: early stopping that cannot act warns.
        checkpoint: the checkpoints (``every`` set).
        hooks: the caller's hooks.
    """

    iterations: int
    optimizer: OptimizerOptions
    windows: WindowOptions
    stopping: StoppingOptions
    patience_given: bool
    checkpoint: CheckpointOptions
    hooks: FitHooks

    def warn_unused_patience(self, fit: str, instead: str) -> None:
        """Warn (:class:`~torchfilt.exceptions.ConvergenceWarning`) where the caller gave
        ``patience`` to ``fit``, a fit without early stopping on held-out data; ``instead``
        names a fit that has it."""
        if self.patience_given:
            warnings.warn(
                f"stopping: patience={self.stopping.patience} was given, but {fit} has no "
                "early stopping on held-out data: it stops at convergence (tol, rtol) or its "
                f"iteration budget. Early stopping is {instead}'s",
                ConvergenceWarning,
                stacklevel=4,
            )


def _typed(value: Any, name: str, cls: type, shortcut: tuple[type, ...], text: str) -> None:
    if value is not None and not isinstance(value, (cls, *shortcut)):
        raise InputTypeError(f"{name}: expected {text}, got {type(value).__name__}")


def resolve_options(
    fit: str,
    *,
    iterations: int | None = None,
    optimizer: OptimizerOptions | str | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    hooks: FitHooks | None = None,
) -> FitOptions:
    """The options of fit ``fit`` (a key of :data:`DEFAULTS`) from the caller's, every ``None``
    being the fit's default: ``iterations``; a string ``optimizer`` is
    ``OptimizerOptions(optimizer)`` and an ``lr`` of ``None`` the fit's learning rate; a
    ``patience`` or ``tol`` of ``None`` the fit's; a path ``checkpoint`` is
    ``CheckpointOptions(path)`` and an ``every`` of ``None`` the fit's.

    Raises:
        InputError: an iteration budget below 1. InputTypeError: an option of another type.
    """
    d = DEFAULTS[fit]
    if iterations is None:
        iterations = d.iterations
    if isinstance(iterations, bool) or not isinstance(iterations, int):
        raise InputTypeError(f"iterations: expected an integer, got {type(iterations).__name__}")
    if iterations < 1:
        raise InputError(
            f"iterations must be at least 1, got {iterations} (a fit of no iterations would "
            "return its start unchanged)"
        )
    _typed(optimizer, "optimizer", OptimizerOptions, (str,), "OptimizerOptions or a name")
    _typed(windows, "windows", WindowOptions, (), "WindowOptions")
    _typed(stopping, "stopping", StoppingOptions, (), "StoppingOptions")
    _typed(checkpoint, "checkpoint", CheckpointOptions, (str, Path), "CheckpointOptions or a path")
    _typed(hooks, "hooks", FitHooks, (), "FitHooks")
    if optimizer is None:
        opt = d.optimizer
    else:
        opt = OptimizerOptions(optimizer) if isinstance(optimizer, str) else optimizer  # type: ignore[arg-type]
        if opt.lr is None and d.optimizer.lr is not None:
            opt = replace(opt, lr=d.optimizer.lr)
    given = stopping is not None and stopping.patience is not None
    stop = d.stopping if stopping is None else stopping
    stop = replace(
        stop,
        patience=d.stopping.patience if stop.patience is None else stop.patience,
        tol=d.stopping.tol if stop.tol is None else stop.tol,
    )
    if checkpoint is None:
        ckpt = d.checkpoint
    else:
        ckpt = CheckpointOptions(checkpoint) if isinstance(checkpoint, str | Path) else checkpoint
        if ckpt.every is None:
            ckpt = replace(ckpt, every=d.checkpoint.every)
    win = d.windows if windows is None else windows
    if win.per_iteration == "auto":  # the fit's default (the likelihood fits: every window)
        fit_default = d.windows.per_iteration
        win = replace(win, per_iteration=None if fit_default == "auto" else fit_default)
    return FitOptions(
        iterations,
        opt,
        win,
        stop,
        given,
        ckpt,
        FitHooks() if hooks is None else hooks,
    )


def field_docs(cls: type) -> dict[str, str]:
    """The meaning of each field of an options dataclass, from its docstring's ``Attributes:``
    section (the one place it is written; the recipe reference shows it too)."""
    doc = cls.__doc__ or ""
    section = doc.split("Attributes:", 1)[1] if "Attributes:" in doc else ""
    section = section.replace("``", "`")
    out: dict[str, str] = {}
    name = None
    for line in section.splitlines():
        m = re.match(r"^\s{8}(\w+): (.*)$", line)
        if m:
            name = m.group(1)
            out[name] = m.group(2).strip()
        elif name is not None and line.strip():
            out[name] += " " + line.strip()
    return {f.name: out[f.name].rstrip(".") for f in fields(cls) if f.name in out}


# ------------------------------------------------------------------- deprecated keywords
#: The flat keywords of the fits before the option groups: old name -> (its group's keyword,
#: the field; ``None``: a plain rename).
_OLD_KEYWORDS: dict[str, tuple[str, str | None]] = {
    "params": ("parameters", None),
    "lr": ("optimizer", "lr"),
    "window": ("windows", "window"),
    "burn_in": ("windows", "burn_in"),
    "start": ("windows", "start"),
    "refresh_every": ("windows", "refresh_every"),
    "patience": ("stopping", "patience"),
    "validate_every": ("stopping", "validate_every"),
    "tol": ("stopping", "tol"),
    "rtol": ("stopping", "rtol"),
    "rtol_window": ("stopping", "rtol_window"),
    "checkpoint_every": ("checkpoint", "every"),
    "resume": ("checkpoint", "resume"),
    "project": ("hooks", "project"),
    "prepare": ("hooks", "prepare"),
    "all_reduce": ("hooks", "all_reduce"),
    # the fits' data is ``y`` everywhere (calibrate took ``recordings``)
    "recordings": ("y", None),
}
#: Old keywords that only some fits had (by function name); the others never took them, so
#: they are unknown keywords there, not deprecated ones.
_OLD_KEYWORD_FITS: dict[str, tuple[str, ...]] = {
    "recordings": ("calibrate", "calibrate_ray", "fit_measurement_only_ray"),
}
_GROUP_CLASS: dict[str, type] = {
    "optimizer": OptimizerOptions,
    "windows": WindowOptions,
    "stopping": StoppingOptions,
    "checkpoint": CheckpointOptions,
    "hooks": FitHooks,
}


def _fold_group(fit: str, group: str, current: Any, values: dict[str, Any], names: str) -> Any:
    """The value of keyword ``group`` with the old keywords' ``values`` folded in."""
    cls = _GROUP_CLASS[group]
    if isinstance(current, cls):
        raise InputError(
            f"{names} and {group}= both given: {names} is the deprecated spelling of a field of "
            f"{group}=; set it in {cls.__name__}(...) only"
        )
    if group == "optimizer":
        base = OptimizerOptions(current) if isinstance(current, str) else DEFAULTS[fit].optimizer  # type: ignore[arg-type]
        return replace(base, **values)
    if group == "windows":
        return replace(DEFAULTS[fit].windows, **values)
    if group == "checkpoint":
        return CheckpointOptions(current, **values)
    return cls(**values)  # stopping, hooks: only what the caller gave counts as given


def deprecated_fit_keywords(fit: str) -> Callable[[_F], _F]:
    """Decorate fit ``fit`` (a key of :data:`DEFAULTS`) so that its flat keywords of before the
    option groups (``lr=``, ``patience=``, ``window=``, ``checkpoint_every=``, ``params=``,
    ``project=``, ...) keep working for one release: each warns (``DeprecationWarning`` naming
    its new spelling) and is folded into its group before the call. Giving an old keyword with
    its group (``lr=`` with ``optimizer=OptimizerOptions(...)``) is an ``InputError``, and so is
    a keyword the fit does not have (a misspelling: the message names it, the closest keyword
    and every valid one, where Python would raise a ``TypeError``). The decorated function
    shows the fit's own signature (``help()``, the docs) and keeps its type.

    Raises:
        InputError: (from the decorated fit) an unknown keyword, or an old keyword with its group.
    """

    def decorate(func: _F) -> _F:
        sig = inspect.signature(func)
        known = {k: v for k, v in _OLD_KEYWORDS.items() if v[0] in sig.parameters}
        known = {k: v for k, v in known.items() if k not in sig.parameters}
        only = _OLD_KEYWORD_FITS
        known = {k: v for k, v in known.items() if func.__name__ in only.get(k, (func.__name__,))}
        name = func.__qualname__
        keywords = _keyword_names(sig)

        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if keywords is not None:
                _check_keywords(name, kwargs, keywords, known)
            old = [k for k in kwargs if k in known]
            if old:
                _fold(fit, name, kwargs, old, known)
            return func(*args, **kwargs)

        wrapper.__signature__ = sig  # type: ignore[attr-defined]
        return wrapper  # type: ignore[return-value]

    return decorate


def _keyword_names(sig: inspect.Signature) -> frozenset[str] | None:
    """The names a caller may pass by keyword (``None``: any, the function takes ``**``)."""
    params = sig.parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return frozenset(p.name for p in params if p.kind in kinds and p.name not in ("self", "cls"))


def _check_keywords(
    func: str, kwargs: dict[str, Any], keywords: frozenset[str], old: Collection[str]
) -> None:
    """Refuse a keyword of ``kwargs`` that is neither one of ``keywords`` nor a deprecated one
    (``old``), naming it, its closest keyword and every valid one."""
    unknown = [k for k in kwargs if k not in keywords and k not in old]
    if not unknown:
        return
    close = {k: difflib.get_close_matches(k, keywords, n=1) for k in unknown}
    hints = "; ".join(f"did you mean {m[0]}= for {k}=?" for k, m in close.items() if m)
    raise InputError(
        f"{func}: unexpected keyword argument(s) {unknown}"
        + (f" ({hints})" if hints else "")
        + f"; valid: {sorted(keywords)}"
    )


def _fold(
    fit: str,
    func: str,
    kwargs: dict[str, Any],
    old: list[str],
    known: dict[str, tuple[str, str | None]],
) -> None:
    """Fold the deprecated keywords ``old`` of ``kwargs`` into their groups, in place."""
    groups: dict[str, dict[str, Any]] = {}
    for k in old:
        group, attr = known[k]
        value = kwargs.pop(k)
        spelling = (
            f"{group}=" if attr is None else f"{group}={_GROUP_CLASS[group].__name__}({attr}=...)"
        )
        warnings.warn(
            f"{func}: {k}= is deprecated; pass {spelling}", DeprecationWarning, stacklevel=3
        )
        if attr is None:
            if kwargs.get(group) is not None:
                raise InputError(
                    f"{k}= and {group}= both given: {k}= is the old name; use {group}="
                )
            kwargs[group] = value
        else:
            groups.setdefault(group, {})[attr] = value
    for group, values in groups.items():
        names = ", ".join(f"{k}=" for k in old if known[k][0] == group)
        kwargs[group] = _fold_group(fit, group, kwargs.get(group), values, names)
