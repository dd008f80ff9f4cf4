"""The one decision of how a filter run executes: :func:`plan` and its :class:`ExecutionPlan`.

Which path a run takes used to be decided in several places; it is decided here only, by a pure
function of what a run knows before it starts: the filter's options, the model, the prepared
inputs' batch shape, whether autograd records, the device, the settings in force
(:mod:`torchfilt.settings`) and the fallbacks already known for this run (a compiled while-loop
that could not be traced, a factorisation that failed in a fast runner). The engines
(:mod:`torchfilt.filters.engine`, the exact runners of :mod:`torchfilt.filters.kalman`) only
carry the plan out, and every :class:`~torchfilt.filters.FilterResult` records it in its
``numerics`` field (:attr:`ExecutionPlan.numerics`).

A fallback is an input of the plan, never state left on a filter: an engine that cannot carry
out a plan asks :func:`plan` again with a :class:`Fallback` naming what failed and why, and the
new plan's ``fallback`` says so in the result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import torch

from torchfilt.exceptions import InputError, ModelError
from torchfilt.models import StateSpaceModel, linear_system
from torchfilt.numerics import no_host_sync
from torchfilt.numerics.small import SMALL_BATCH, SMALL_MAX
from torchfilt.settings import (
    NumericsPath,
    SmallKernels,
    current_skip_guard_checks,
    current_small_matrix_kernels,
)

__all__ = [
    "CompileMode",
    "ExecutionPlan",
    "Fallback",
    "LinearFacts",
    "PlanOptions",
    "PlanSettings",
    "exact_path",
    "plan",
]

Path = Literal["auto", "cubature", "kalman"]
#: ``compile=`` of a filter, normalised: None (eager), "auto" (True), "step" or "loop".
CompileMode = Literal["auto", "step", "loop"] | None

#: below this many bytes of results the fast exact runner stacks per-step lists (fewer operations
#: per step); above it, it writes into preallocated outputs (no second copy)
_INPLACE_BYTES = 1 << 24


@dataclass(frozen=True)
class PlanOptions:
    """The options of a filter that the plan reads.

    Attributes:
        compile: the normalised ``compile=`` option (None, ``"auto"``, ``"step"``, ``"loop"``).
        sqrt: square-root form. redraw: re-drawn update points (the exact path needs them).
        state_dim, obs_dim: the model's dimensions (for the small-matrix kernels).
        host_decisions: why the filter's step decides on the host every step (then it runs
            eager or one compiled call per step only, and cannot be captured into a CUDA
            graph), or None.
        no_exact: why the filter's step has no closed-form Kalman counterpart (then
            ``path="auto"`` runs the step and ``path="kalman"`` or ``parallel=True`` is
            refused), or None.
    """

    compile: CompileMode = None
    sqrt: bool = False
    redraw: bool = True
    state_dim: int = 1
    obs_dim: int = 1
    host_decisions: str | None = None
    no_exact: str | None = None


@dataclass(frozen=True)
class PlanSettings:
    """The settings of :mod:`torchfilt.settings` in force when a run starts.

    Attributes:
        small_kernels: ``settings.small_matrix_kernels`` (``"auto"``, ``"unrolled"``,
            ``"library"``).
        sync_free: no host synchronisation allowed (``settings.sync_free`` or tracing).
        skip_guard_checks: ``settings.skip_guard_checks``.
    """

    small_kernels: SmallKernels = "auto"
    sync_free: bool = False
    skip_guard_checks: bool = False

    @classmethod
    def current(cls) -> PlanSettings:
        """The settings in force in the calling block."""
        return cls(current_small_matrix_kernels(), no_host_sync(), current_skip_guard_checks())


class Fallback(NamedTuple):
    """An execution that was tried for this run and failed, and why.

    Attributes:
        execution: what failed (an :attr:`ExecutionPlan.execution` value).
        reason: the failure, in one line.
    """

    execution: str
    reason: str


class LinearFacts(NamedTuple):
    """What the exact runners' choice needs to know of a checked linear recording.

    Attributes:
        covariance_batch: how many covariance sequences the Riccati runner would keep (1 when
            the covariances are shared by the batch), or None when they depend on the data.
        result_bytes: bytes of the per-step results kept.
        likelihood_only: the run keeps the log-likelihood and no other per-step field (then,
            while autograd records, its gradient can come from the closed-form backward pass
            of :mod:`torchfilt.filters.kalman_adjoint`).
    """

    covariance_batch: int | None
    result_bytes: int
    likelihood_only: bool = False


@dataclass(frozen=True)
class ExecutionPlan:
    """How a run executes. Built by :func:`plan` only.

    Attributes:
        family: ``"kalman"`` (the closed-form filter) or ``"cubature"``.
        execution: for the cubature family ``"eager"``, ``"compiled-step"``,
            ``"compiled-loop"``, ``"compiled-chunks"`` or ``"graphed"``; for the exact one
            ``"kalman-parallel"``, ``"kalman-adjoint"``, ``"kalman-riccati"``,
            ``"kalman-fast"`` or ``"kalman-sequential"``.
        small_kernels: ``"unrolled"`` or ``"library"``.
        on_failure: ``"jitter"`` or ``"nan"`` (see :class:`~torchfilt.settings.NumericsPath`).
        parallel: the exact path's parallel-in-time scan.
        adjoint: the exact path's log-likelihood by the no-graph filter, its gradient by the
            closed-form backward pass (:mod:`torchfilt.filters.kalman_adjoint`).
        sqrt: the square-root form.
        compiled: the step runs under ``torch.compile``.
        skip_guards: a compiled step may skip Dynamo's guard checks after a run's first steps
            (``settings.skip_guard_checks``).
        records_grad: autograd records the run.
        inplace: the exact runners write into preallocated outputs (no autograd, large results).
        fallback: why the plan is not the first choice for this run (what failed), or None.
        refused: why the filter cannot be captured into a CUDA graph, or None.
    """

    family: Literal["kalman", "cubature"]
    execution: str
    small_kernels: str = "library"
    on_failure: str = "jitter"
    parallel: bool = False
    adjoint: bool = False
    sqrt: bool = False
    compiled: bool = False
    skip_guards: bool = False
    records_grad: bool = False
    inplace: bool = False
    fallback: str | None = None
    refused: str | None = field(default=None, compare=False)

    @property
    def numerics(self) -> NumericsPath:
        """The :class:`~torchfilt.settings.NumericsPath` a result of this plan records."""
        return NumericsPath(self.execution, self.small_kernels, self.on_failure, self.fallback)


def exact_path(
    model: StateSpaceModel,
    *,
    path: Path,
    parallel: bool,
    redraw: bool = True,
    no_exact: str | None = None,
) -> bool:
    """Whether a Gaussian filter takes the exact Kalman path.

    ``"auto"`` takes it for every model :func:`~torchfilt.models.linear_system` recognises (a
    sigma-point filter with re-drawn update points is exact on a linear model, so only the cost
    changes); ``"kalman"`` insists on it and ``"cubature"`` refuses it. ``parallel=True`` needs it.
    ``no_exact`` (why the filter's step has no closed-form counterpart) keeps every run off it.

    Raises:
        InputError: an unknown ``path``, or ``parallel=True`` with ``path="cubature"``.
        ModelError: ``path="kalman"`` or ``parallel=True`` for a model that is not linear, or
            for a filter with ``no_exact``.
    """
    if path not in ("auto", "cubature", "kalman"):
        raise InputError(f"path must be 'auto', 'cubature' or 'kalman', got {path!r}")
    if path == "cubature":
        if parallel:
            raise InputError(
                "parallel=True runs the exact Kalman path; it cannot use path='cubature'"
            )
        return False
    if no_exact is not None:
        if path == "kalman" or parallel:
            what = "parallel=True" if parallel else "path='kalman'"
            raise ModelError(f"{what} runs the exact Kalman path; {no_exact}")
        return False
    linear = linear_system(model) is not None
    if not linear and (path == "kalman" or parallel):
        what = "parallel=True" if parallel else "path='kalman'"
        raise ModelError(
            f"{what} needs a linear-Gaussian model (a LinearGaussianModel or a model with a "
            f"linear_system() method); {type(model).__name__} is not one. For nonlinear models use "
            "torchfilt.filters.iterated_smoother(..., parallel=True)"
        )
    if path == "auto" and not redraw:
        # without re-drawn points the CKF's P_yy misses Q: not the Kalman filter, keep its answer
        return False
    return linear


def _kernels(options: PlanOptions, batch: torch.Size, compiled: bool, mode: SmallKernels) -> str:
    """The small-matrix kernels of a run: resolved once per run from its batch size."""
    if max(options.state_dim, options.obs_dim) > SMALL_MAX:
        return "library"
    if compiled:
        return "unrolled"  # what tracing always chooses
    if mode != "auto":
        return mode
    return "unrolled" if math.prod(batch) >= SMALL_BATCH else "library"


def _exact_runner(
    options: PlanOptions,
    parallel: bool,
    grad: bool,
    facts: LinearFacts | None,
    failed: set[str],
    sync_free: bool,
) -> str:
    """The exact runner: parallel scan, or the first of adjoint / Riccati / fast / sequential
    that applies and has not failed for this run.

    The adjoint serves a recorded run that keeps only the log-likelihood (the gradient of no
    other field is known in closed form), in the plain form, where the host may synchronise (its
    runners check their factorisations on the host)."""
    if parallel:
        return "kalman-parallel"
    candidates = []
    if grad and not options.sqrt and not sync_free and facts is not None and facts.likelihood_only:
        candidates.append("kalman-adjoint")
    if not options.sqrt and not grad and facts is not None and facts.covariance_batch is not None:
        candidates.append("kalman-riccati")
    if not options.sqrt:
        candidates.append("kalman-fast")
    candidates.append("kalman-sequential")
    return next(c for c in candidates if c not in failed or c == "kalman-sequential")


def _cubature_execution(
    options: PlanOptions, grad: bool, graphed: bool, device: torch.device, failed: set[str]
) -> tuple[str, str | None]:
    """The cubature execution and why the first choice was left (or None)."""
    if graphed:
        if options.host_decisions is not None:
            raise ModelError(
                "graphed: the filter's step cannot be captured into a CUDA graph "
                f"({options.host_decisions}); use filter(), or compile=True"
            )
        if device.type != "cuda":
            raise InputError(
                f"y: a CUDA graph needs measurements on a CUDA device, got {device}; on the CPU "
                "use CKF(..., compile=True)"
            )
        return "graphed", None
    mode = options.compile
    if mode is None:
        return "eager", None
    if mode == "auto" or options.host_decisions is not None:
        # a step that decides on the host is split into several graphs, which a compiled
        # chunk or while-loop cannot hold: one compiled call per step
        return "compiled-step", None
    if mode == "step":
        return "compiled-step", None
    if grad:
        return "compiled-chunks", "autograd records (the while-loop has no backward)"
    if "compiled-loop" in failed:
        return "compiled-chunks", None
    return "compiled-loop", None


def plan(
    model: StateSpaceModel | None,
    options: PlanOptions,
    *,
    batch: torch.Size,
    records_grad: bool,
    device: torch.device,
    settings: PlanSettings | None = None,
    path: Path = "cubature",
    parallel: bool = False,
    linear: LinearFacts | None = None,
    graphed: bool = False,
    fallbacks: tuple[Fallback, ...] = (),
) -> ExecutionPlan:
    """Decide how a run executes (pure: the same arguments give the same plan).

    Args:
        model: the state-space model, or None where the caller has checked a linear model
            already (then ``path`` says the family: ``"kalman"`` or ``"cubature"``).
        options: the filter's options (:class:`PlanOptions`).
        batch: the prepared inputs' batch shape.
        records_grad: whether autograd records the run (inputs or parameters need gradients).
        device: where the run's data live (a CUDA graph needs a CUDA device).
        settings: the settings in force (default: those of the calling block).
        path: ``"auto"``, ``"kalman"`` or ``"cubature"`` (see :func:`exact_path`).
        parallel: the parallel-in-time exact filter.
        linear: for the exact path, the facts of the checked recording (:class:`LinearFacts`).
        graphed: the run is captured into a CUDA graph.
        fallbacks: executions already tried for this run and how they failed.

    Returns:
        The :class:`ExecutionPlan`.

    Raises:
        InputError, ModelError: as :func:`exact_path`; ModelError also for ``graphed`` of a
            filter whose step decides on the host, InputError for ``graphed`` off CUDA.
    """
    settings = settings if settings is not None else PlanSettings.current()
    failed = {f.execution for f in fallbacks}
    why = "; ".join(f"{f.execution}: {f.reason}" for f in fallbacks) or None
    refused = None
    if options.host_decisions is not None:
        refused = f"the step decides on the host ({options.host_decisions})"
    if model is None:
        exact = path == "kalman"
    else:
        exact = exact_path(
            model, path=path, parallel=parallel, redraw=options.redraw, no_exact=options.no_exact
        )
    if exact:
        runner = _exact_runner(options, parallel, records_grad, linear, failed, settings.sync_free)
        big = linear is not None and linear.result_bytes > _INPLACE_BYTES
        return ExecutionPlan(
            family="kalman",
            execution=runner,
            # the fast and Riccati runners call the library kernels directly
            small_kernels="library"
            if runner in ("kalman-adjoint", "kalman-fast", "kalman-riccati")
            else _kernels(options, batch, False, settings.small_kernels),
            on_failure="nan" if settings.sync_free else "jitter",
            parallel=parallel,
            adjoint=runner == "kalman-adjoint",
            sqrt=options.sqrt,
            records_grad=records_grad,
            inplace=not records_grad and big,
            fallback=why,
            refused=refused,
        )
    execution, first = _cubature_execution(options, records_grad, graphed, device, failed)
    compiled = options.compile is not None
    nan = compiled or graphed or settings.sync_free
    return ExecutionPlan(
        family="cubature",
        execution=execution,
        small_kernels=_kernels(options, batch, compiled, settings.small_kernels),
        on_failure="nan" if nan else "jitter",
        sqrt=options.sqrt,
        compiled=compiled,
        skip_guards=compiled and settings.skip_guard_checks,
        records_grad=records_grad,
        fallback=why if why is not None else first,
        refused=refused,
    )
