"""Typed options of the fits, and every fit's defaults in one place.

The fits (:func:`~torchfilt.training.fit_likelihood`, :func:`~torchfilt.training.calibrate`,
:func:`~torchfilt.training.fit_measurement_only`, :func:`~torchfilt.training.fit_em` and the GP
hyperparameter training :meth:`~torchfilt.models.gp.GPModel.optimize`) share four groups of
options: the optimiser, the windows of the likelihood, the stopping rules and the checkpoints.
Each group is a frozen dataclass here; a fit's keyword defaults are read from its entry in
:data:`DEFAULTS`, so one table says where the fits differ and why:

================  =========  ======  ==========  ======  =======  ========  ================
fit               optimizer  lr      iterations  window  burn_in  patience  checkpoint_every
================  =========  ======  ==========  ======  =======  ========  ================
likelihood        adam       auto    200         None    0        20        10
calibrate         adam       0.1     150         100     20       15        10
measurement_only  lbfgs      auto    100         None    0        20        1
em                (closed form or L-BFGS M-step) 100     --       --        1
gp                adam       0.05    200         --      --       --        (callback)
================  =========  ======  ==========  ======  =======  ========  ================

``lr="auto"`` (``None``) is 0.05 for Adam and 1 for L-BFGS; ``tol=None`` is ``1e-10`` for L-BFGS
and off for Adam (the likelihood fits), ``1e-9`` per measurement for EM. Why they differ:
calibration fits a few variance scales on long recordings, so it windows them (100 steps, 20 of
burn-in) and takes larger Adam steps; measurement-only learning has few, tightly identified
parameters and wants L-BFGS; an EM iteration is expensive and monotone, so it checkpoints every
iteration; a GP's optimiser state is checkpointed by the caller through its callback.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Literal

from torchfilt.exceptions import InputError

__all__ = [
    "DEFAULTS",
    "CheckpointOptions",
    "FitDefaults",
    "OptimizerOptions",
    "StoppingOptions",
    "WindowOptions",
    "stopping_options",
]

#: Largest accepted learning rate of the likelihood fits.
MAX_LR = 100.0


def _at_least_one(**values: int) -> None:
    for name, v in values.items():
        if v < 1:
            raise InputError(f"{name} must be at least 1, got {v}")


@dataclass(frozen=True)
class OptimizerOptions:
    """The optimiser of a fit.

    Attributes:
        optimizer: ``"adam"`` or ``"lbfgs"`` (strong-Wolfe line search; best for a few
            parameters and tight optima).
        lr: learning rate; ``None``: 0.05 for Adam, 1 for L-BFGS.
        iterations: iteration budget (an L-BFGS iteration runs up to ``max_iter`` inner steps).
        max_iter: L-BFGS inner steps per iteration.
        tolerance_change: L-BFGS's tolerance on the change of the loss or the parameters.
        tolerance_grad: L-BFGS's tolerance on the gradient.
        history_size: L-BFGS's curvature pairs.
    """

    optimizer: Literal["adam", "lbfgs"] = "adam"
    lr: float | None = None
    iterations: int = 200
    max_iter: int = 20
    tolerance_change: float = 1e-14
    tolerance_grad: float = 1e-12
    history_size: int = 20

    def __post_init__(self) -> None:
        if self.optimizer not in ("adam", "lbfgs"):
            raise InputError(f"optimizer must be 'adam' or 'lbfgs', got {self.optimizer!r}")
        it = self.iterations
        if isinstance(it, bool) or not isinstance(it, int) or it < 1:
            raise InputError(
                f"iterations must be at least 1 (an integer), got {it!r} (a fit of no "
                "iterations would return its start unchanged)"
            )
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
        window: window length in steps (``None``: whole recordings).
        burn_in: uncounted steps at the start of every window.
        start: where a later window starts: the previous pass's ``"filtered"`` or
            ``"smoothed"`` estimate of the state just before it.
        refresh_every: iterations between refreshes of the window starts.
    """

    window: int | None = None
    burn_in: int = 0
    start: Literal["filtered", "smoothed"] = "filtered"
    refresh_every: int = 10

    def __post_init__(self) -> None:
        if self.start not in ("filtered", "smoothed"):
            raise InputError(f"start must be 'filtered' or 'smoothed', got {self.start!r}")
        _at_least_one(refresh_every=self.refresh_every)


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
      needs the optimum to the last digits passes a smaller ``rtol`` (or 0: off).

    Attributes:
        patience: stop after this many held-out evaluations without improvement.
        validate_every: iterations between held-out evaluations.
        tol: the per-iteration rule (``None``: the fit's default, see :data:`DEFAULTS`; 0: off).
        rtol: the windowed rule's relative tolerance (0: off).
        rtol_window: its window ``w`` in iterations.
        patience_given: ``patience`` was given by the caller (not a default): early stopping
            that cannot act (no held-out data) then warns.
    """

    patience: int = 20
    validate_every: int = 1
    tol: float | None = None
    rtol: float = 1e-6
    rtol_window: int = 20
    patience_given: bool = False

    def __post_init__(self) -> None:
        _at_least_one(
            patience=self.patience,
            validate_every=self.validate_every,
            rtol_window=self.rtol_window,
        )
        if self.tol is not None and not (math.isfinite(self.tol) and self.tol >= 0):
            raise InputError(f"tol must be finite and non-negative, got {self.tol}")
        if not (math.isfinite(self.rtol) and self.rtol >= 0):
            raise InputError(f"rtol must be finite and non-negative, got {self.rtol}")

    def tolerance(self, optimizer: str) -> float:
        """``tol``, or the likelihood fits' default for ``optimizer`` (``1e-10`` for L-BFGS,
        off for Adam)."""
        if self.tol is None:
            return 1e-10 if optimizer == "lbfgs" else 0.0
        return float(self.tol)


def stopping_options(
    default: StoppingOptions,
    patience: int | None,
    validate_every: int,
    tol: float | None,
    rtol: float | None = None,
    rtol_window: int | None = None,
) -> StoppingOptions:
    """A fit's :class:`StoppingOptions` from its keyword arguments, ``None`` meaning the fit's
    ``default``. ``patience`` counts as given (``patience_given``: early stopping that cannot
    act then warns) when it differs from the default."""
    given = patience is not None and patience != default.patience
    return StoppingOptions(
        default.patience if patience is None else patience,
        validate_every,
        tol,
        default.rtol if rtol is None else rtol,
        default.rtol_window if rtol_window is None else rtol_window,
        patience_given=given,
    )


@dataclass(frozen=True)
class CheckpointOptions:
    """Checkpoints of a fit: written atomically every ``every`` iterations, at the last one and
    when the fit stops by itself; resuming from one equals an uninterrupted fit bit for bit.

    Attributes:
        path: the checkpoint file (``None``: none).
        every: iterations between checkpoints.
        resume: continue from ``path`` if it exists.
    """

    path: str | Path | None = None
    every: int = 10
    resume: bool = False

    def __post_init__(self) -> None:
        _at_least_one(checkpoint_every=self.every)
        if self.resume and self.path is None:
            raise InputError(
                "resume=True needs checkpoint= (the file to continue from); give a checkpoint "
                "path or leave resume=False"
            )


@dataclass(frozen=True)
class FitDefaults:
    """One fit's defaults: the four groups of options."""

    optimizer: OptimizerOptions = field(default_factory=OptimizerOptions)
    window: WindowOptions = field(default_factory=WindowOptions)
    stopping: StoppingOptions = field(default_factory=StoppingOptions)
    checkpoint: CheckpointOptions = field(default_factory=CheckpointOptions)


#: Each fit's defaults (the table of the module docstring), read-only.
DEFAULTS: Mapping[str, FitDefaults] = MappingProxyType(
    {
        "likelihood": FitDefaults(),
        "calibrate": FitDefaults(
            OptimizerOptions("adam", lr=0.1, iterations=150),
            WindowOptions(window=100, burn_in=20),
            StoppingOptions(patience=15),
        ),
        "measurement_only": FitDefaults(
            OptimizerOptions("lbfgs", iterations=100), checkpoint=CheckpointOptions(every=1)
        ),
        "em": FitDefaults(
            # the gradient M-step of a non-linear model: L-BFGS, ``max_iter`` = m_step_iterations
            OptimizerOptions(
                "lbfgs", lr=1.0, iterations=100, tolerance_change=1e-12, tolerance_grad=1e-10
            ),
            stopping=StoppingOptions(tol=1e-9),
            checkpoint=CheckpointOptions(every=1),
        ),
        "gp": FitDefaults(OptimizerOptions("adam", lr=0.05, iterations=200)),
    }
)
