"""The batched cubature (sigma-point) Gaussian filter: a small façade over a step, a plan and an
engine.

The step's equations are in :mod:`torchfilt.filters.steps` (bound to the options by
:class:`~torchfilt.filters.cubature_step.CubatureStep`); how a run executes is decided by
:func:`~torchfilt.filters.plan.plan` and carried out by :mod:`torchfilt.filters.engine`.
:class:`GaussianFilter` binds a model, a cubature rule and the options, and offers the
whole-recording ``filter`` / ``smooth`` / ``graphed`` and the online ``init`` / ``predict`` /
``update``.
"""

from __future__ import annotations

import warnings
from collections.abc import Collection
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule, SphericalRadialRule
from torchfilt.exceptions import InputError, InputTypeError, ShapeError
from torchfilt.filters.cubature_step import CubatureStep
from torchfilt.filters.engine import Engine, OnlineStep, StepFunction, TraceFailure, records_grad
from torchfilt.filters.forecast_core import Forecast, free_run_with, k_step_ahead_with
from torchfilt.filters.inputs import (
    FilterInputs,
    check_inputs,
    check_model_input,
    check_prior,
    observed,
)
from torchfilt.filters.kalman import _keep, kalman_filter, kalman_smoother, select_outputs
from torchfilt.filters.plan import (
    CompileMode,
    ExecutionPlan,
    Fallback,
    Path,
    PlanOptions,
    exact_path,
    plan,
)
from torchfilt.filters.results import (
    FilterResult,
    RecordSink,
    SmootherResult,
    StepRecord,
    warn_nonfinite,
)
from torchfilt.filters.steps import Belief, Noise, PredictCache, UnitPoints, UpdateStats
from torchfilt.models import StateSpaceModel
from torchfilt.numerics import safe_cholesky
from torchfilt.numerics.dtypes import check_real_tensor
from torchfilt.settings import small_matrix_kernels

if TYPE_CHECKING:
    from torchfilt.filters.graphed import GraphedFilter

__all__ = ["CKF", "FilterState", "GaussianFilter", "StepFunction"]

#: Steps per compiled chunk of the time loop (``compile=True``): the chunk is unrolled into one
#: graph, so the per-call overhead is paid once per chunk; longer chunks compile for longer.
DEFAULT_CHUNK = 10


def _deprecated(old: str, new: str) -> None:
    warnings.warn(
        f"GaussianFilter.{old} is deprecated and will be removed in the next release; {new}",
        DeprecationWarning,
        stacklevel=3,
    )


class FilterState(NamedTuple):
    """The belief of an online filter (:meth:`GaussianFilter.init`) and its time index.

    Attributes:
        mean: the belief's mean, shape ``(..., n)``.
        cov: the belief's covariance, shape ``(..., n, n)``.
        sqrt: lower factor of ``cov`` ``(..., n, n)`` (propagated by the square-root form).
        t: time index of the belief: ``-1`` for the prior, ``t`` after the ``t``-th prediction
            (0-based) and its update. Time-varying noise is read at this index.
        predicted: whether the belief is a prediction not yet updated.
        cache: what the prediction computed for the update (its propagated points), or None.
    """

    mean: Tensor
    cov: Tensor
    sqrt: Tensor | None
    t: int
    predicted: bool
    cache: PredictCache | None = None

    @property
    def belief(self) -> Belief:
        """The state's :class:`~torchfilt.filters.steps.Belief`."""
        return Belief(self.mean, self.cov, self.sqrt)


class GaussianFilter(nn.Module):
    """Batched, differentiable sigma-point Gaussian filter and RTS smoother.

    With the default third-degree spherical-radial rule this is the cubature Kalman filter (CKF);
    with :class:`~torchfilt.cubature.UnscentedRule` it is the UKF, with
    :class:`~torchfilt.cubature.GaussHermiteRule` the Gauss-Hermite filter.

    Args:
        model: the state-space model.
        rule: cubature rule; default :class:`~torchfilt.cubature.SphericalRadialRule` (degree 3).
        sqrt: propagate Cholesky factors with QR triangularisation (square-root CKF, Arasaratnam &
            Haykin 2009). Needs non-negative covariance weights.
        redraw: re-draw the update's points from the predicted covariance (default, as Arasaratnam &
            Haykin). ``False`` reuses the propagated points, as filterpy's CubatureKalmanFilter
            does: then ``P_yy`` and ``P_xy`` miss the spread that ``Q`` adds between the two stages.
        point_variance: how per-point model variances (GP) enter Q and R: ``"total"`` averages them
            over the cubature points (law of total variance), ``"mean"`` evaluates them at the mean
            only.
        compile: ``"loop"`` compiles the whole time loop as one ``torch.while_loop`` over the
            step (the step is traced once; on the CPU the loop runs in the generated C++, so one
            or a few sequences pay no Python per step; one compile per recording shape and set of
            ``outputs``). Where the while-loop cannot run (autograd records, or the step does not
            trace into one graph: ``numerics.fallback`` says why) it compiles chunks of ``chunk``
            steps unrolled into one graph each instead (long first compile), and the result's
            ``numerics.execution`` says ``"compiled-chunks"``. ``"step"`` compiles the per-step
            function only (one compiled call per step); ``True`` (``"auto"``) takes ``"step"``,
            whose compile is the shortest and which serves gradients: on the re-entry model
            (RK4, 10 sub-steps), 64 x 100, one likelihood + gradient takes 0.09 s after a cold
            compile of about 75 s on the 2-core machine (0.9 s eager), where the chunks
            ``"loop"`` falls back to under autograd had not compiled after 15 minutes; use
            ``True`` for gradients of a large step. Under compilation a
            covariance that fails its Cholesky factorisation turns the sequence to NaN instead of
            being jittered. The eager path (the default) is the one to debug with: every op runs
            as written, and a failed factorisation is retried with jitter and reported.
        chunk: steps per compiled chunk of the time loop, where the while-loop cannot be used. A
            recording whose length is not a multiple compiles its last, shorter chunk too.

    Raises:
        InputTypeError: ``model`` is not a :class:`~torchfilt.models.StateSpaceModel` or
            ``rule`` not a :class:`~torchfilt.cubature.CubatureRule`.
        InputError: an invalid ``point_variance``, ``compile`` or ``chunk``, or ``sqrt=True``
            with a rule that has a negative covariance weight.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        rule: CubatureRule | None = None,
        sqrt: bool = False,
        redraw: bool = True,
        point_variance: Literal["total", "mean"] = "total",
        compile: bool | Literal["auto", "step", "loop"] = False,
        chunk: int = DEFAULT_CHUNK,
    ) -> None:
        super().__init__()
        if not isinstance(model, StateSpaceModel):
            raise InputTypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")
        if point_variance not in ("total", "mean"):
            raise InputError(f"point_variance must be 'total' or 'mean', got {point_variance!r}")
        self.model = model
        self.rule = rule if rule is not None else SphericalRadialRule(3)
        if not isinstance(self.rule, CubatureRule):
            raise InputTypeError(f"rule must be a CubatureRule, got {type(self.rule).__name__}")
        self.sqrt = bool(sqrt)
        self.redraw = bool(redraw)
        self.point_variance = point_variance
        n = model.state_dim
        if self.sqrt and not self.rule.weights_nonnegative(n):
            raise InputError(
                f"sqrt=True needs non-negative covariance weights; {self.rule!r} has a negative "
                f"weight in dimension {n}"
            )
        mode: CompileMode
        if isinstance(compile, bool):
            mode = "auto" if compile else None
        elif compile in ("auto", "step", "loop"):
            mode = compile
        else:
            raise InputError(
                f"compile must be False, True, 'auto', 'step' or 'loop', got {compile!r}"
            )
        if int(chunk) < 1:
            raise InputError(f"chunk must be at least 1, got {chunk}")
        self.chunk = int(chunk)
        step = CubatureStep(model, self.rule, self.sqrt, self.redraw, point_variance)
        self._setup(step, PlanOptions(mode, self.sqrt, self.redraw, n, model.obs_dim))

    def _setup(self, step: OnlineStep, options: PlanOptions) -> None:
        """Bind the step the engines run and the options the plan reads."""
        self._step = step
        self._options = options
        self._engine = Engine(step, self.chunk)

    @property
    def compile_mode(self) -> CompileMode:
        """The normalised ``compile=`` option: None (eager), ``"auto"``, ``"step"``, ``"loop"``."""
        return self._options.compile

    @property
    def loop_fallback(self) -> str | None:
        """Deprecated: the last reason a compiled while-loop could not be traced. Read the
        result's ``numerics.fallback`` instead (it says why for that run)."""
        _deprecated("loop_fallback", "read the result's numerics.fallback")
        failures = list(self._engine.trace_failures.values())
        return failures[-1].reason if failures else None

    # ------------------------------------------------------------------ the step
    def step(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: Noise,
        R: Noise,
    ) -> tuple[Belief, StepRecord, tuple[Tensor, ...]]:
        """One filter step with this filter's options: the step the engines run (see
        :meth:`CubatureStep.step <torchfilt.filters.cubature_step.CubatureStep.step>`).

        Args:
            points: the rule's unit points in the run's dtype and device.
            belief: the filtered belief about ``x_{t-1}``, mean ``(..., n)``, covariance
                ``(..., n, n)``.
            y: measurement, shape ``(..., m)``, missing entries set to 0.
            obs: which components of ``y`` are observed, boolean, shape ``(..., m)``.
            u: the input row of the step, shape ``(..., nu)``, or ``None``.
            Q: process noise of the step.
            R: measurement noise of the step.

        Returns:
            The filtered belief about ``x_t`` (mean ``(..., n)``, covariance ``(..., n, n)``),
            the step's :class:`~torchfilt.filters.results.StepRecord` and extra per-step
            outputs (none for the cubature step; each of shape ``(...)`` plus its own
            trailing dimensions).
        """
        return self._step.step(points, belief, y, obs, u, Q, R)

    # ------------------------------------------------------------------ plan and run
    def _plan(
        self,
        inputs: FilterInputs,
        fallbacks: tuple[Fallback, ...] = (),
        *,
        graphed: bool = False,
        grad: bool | None = None,
    ) -> ExecutionPlan:
        """The plan of a cubature run of the prepared ``inputs``."""
        return plan(
            self.model,
            self._options,
            batch=inputs.batch,
            records_grad=records_grad(inputs, self.model) if grad is None else grad,
            device=inputs.y.device,
            graphed=graphed,
            fallbacks=fallbacks,
        )

    def _exact(self, path: Path, parallel: bool) -> bool:
        """Whether a run with these options takes the exact Kalman path (the plan's
        :func:`~torchfilt.filters.plan.exact_path`)."""
        return exact_path(
            self.model,
            path=path,
            parallel=parallel,
            redraw=self.redraw,
            no_exact=self._options.no_exact,
        )

    def _prepare(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> FilterInputs:
        """Check and broadcast a recording (arguments as in :meth:`filter`)."""
        return check_inputs(self.model, y, u, x0, P0, mask)

    def _run(self, inputs: FilterInputs, keep: Collection[str] | None = None) -> FilterResult:
        """Plan a run of the prepared ``inputs`` and run it (no divergence warning); a compiled
        while-loop that cannot be traced is planned again with that fallback."""
        fallbacks = self._engine.known_fallbacks(inputs)
        try:
            return self._engine.run(self._plan(inputs, fallbacks), inputs, keep)
        except TraceFailure as failure:
            fallbacks += (failure.fallback,)
        return self._engine.run(self._plan(inputs, fallbacks), inputs, keep)

    def _scan(
        self,
        inputs: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> tuple[ExecutionPlan, list[StepRecord], list[tuple[Tensor, ...]]]:
        """The plan of a run of ``inputs`` and its per-step (or per-chunk) records and extras
        (a while-loop that cannot be traced is planned again with that fallback)."""
        fallbacks = self._engine.known_fallbacks(inputs)
        try:
            p = self._plan(inputs, fallbacks)
            return (p, *self._engine.scan(p, inputs, step_fn, sink))
        except TraceFailure as failure:
            fallbacks += (failure.fallback,)
        p = self._plan(inputs, fallbacks)
        return (p, *self._engine.scan(p, inputs, step_fn, sink))

    def _capture(
        self, y: Tensor, u: Tensor | None, *, x0: Tensor, P0: Tensor
    ) -> tuple[FilterInputs, ExecutionPlan, Engine]:
        """What :class:`~torchfilt.filters.GraphedFilter` captures: the prepared inputs, the
        graphed plan (refused where the step decides on the host) and the engine."""
        inputs = self._prepare(y, u, x0=x0, P0=P0)
        return inputs, self._plan(inputs, graphed=True, grad=False), self._engine

    # ------------------------------------------------------------------ whole recordings
    def filter(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
        path: Path = "auto",
        parallel: bool = False,
        outputs: Collection[str] | None = None,
    ) -> FilterResult:
        """Filter measurement sequences.

        Input convention (:mod:`torchfilt.filters`): step ``t`` predicts ``x_t`` from
        ``x_{t-1}`` with the input row ``u[..., t, :]`` and updates with ``y[..., t, :]``,
        passing the same row to the measurement; the prior ``N(x0, P0)`` is the belief about
        ``x_{-1}``.

        Args:
            y: measurements, shape ``(..., T, m)``. Non-finite entries (NaN) are missing.
            u: inputs, shape ``(..., T, nu)``, or ``None``.
            x0: prior mean, shape ``(..., n)``.
            P0: prior covariance, shape ``(..., n, n)``, symmetric positive definite.
            mask: optional boolean ``(..., T, m)``; ``False`` marks a component as missing. Its
                trailing ``(T, m)`` must equal ``y``'s.
            path: ``"auto"`` (default) runs the closed-form Kalman filter
                (:mod:`torchfilt.filters.kalman`) for a linear-Gaussian model and the sigma-point
                filter otherwise; ``"kalman"`` or ``"cubature"`` forces one (for testing).
            parallel: run the parallel-in-time (associative scan) Kalman filter; linear models
                only.
            outputs: names of the result fields to return (e.g. ``("mean", "log_likelihood")``);
                the others are empty tensors. On the exact path the others are never stored.

        Returns:
            A :class:`~torchfilt.filters.FilterResult` (its ``path`` says which path ran). A step
            with no observed component is a pure prediction (its log-likelihood term is 0). A
            sequence whose covariance cannot be factored even with jitter (or, in the square-root
            form, whose factor loses definiteness) becomes NaN from that step on and a
            :class:`~torchfilt.exceptions.DivergenceWarning` is emitted; the rest of the batch is
            unaffected. ``numerics`` says which path ran (the plan of
            :func:`~torchfilt.filters.plan.plan`).
        """
        if self._exact(path, parallel):
            return kalman_filter(
                self.model, y, u, x0=x0, P0=P0, mask=mask, sqrt=self.sqrt, parallel=parallel,
                outputs=outputs,
            )  # fmt: skip
        keep = _keep(outputs)
        inputs = self._prepare(y, u, x0=x0, P0=P0, mask=mask)
        res = self._run(inputs, keep=keep)
        warn_nonfinite(res, stacklevel=3)
        return select_outputs(res, outputs)

    def graphed(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        warmup: int = 2,
    ) -> GraphedFilter:
        """Capture a whole filtering run of this shape into a CUDA graph (GPU only).

        The returned :class:`~torchfilt.filters.GraphedFilter` replays all ``T`` steps with one
        graph launch; its ``filter(y, u, mask=...)`` takes new data of the same shape. Combine with
        ``compile=True`` for fused kernels. See :mod:`torchfilt.filters.graphed` for the limits.

        Args:
            y: example measurements ``(..., T, m)`` on a CUDA device.
            u: example inputs ``(..., T, nu)`` or ``None``.
            x0: prior mean ``(..., n)``, fixed.
            P0: prior covariance ``(..., n, n)``, fixed.
            warmup: eager runs before the capture.

        Raises:
            ModelError: the filter's step cannot be captured (its plan says why).
        """
        from torchfilt.filters.graphed import GraphedFilter

        return GraphedFilter(self, y, u, x0=x0, P0=P0, warmup=warmup)

    def smooth(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
        path: Path = "auto",
        parallel: bool = False,
    ) -> SmootherResult:
        """Filter, then run the Rauch-Tung-Striebel smoother backwards (cubature RTS; for a
        linear-Gaussian model the exact smoother, sequential or with ``parallel=True`` by
        associative scan).

        Args:
            y: measurements, shape ``(..., T, m)``. Non-finite entries (NaN) are missing.
            u: inputs, shape ``(..., T, nu)``, or ``None``.
            x0: prior mean, shape ``(..., n)``.
            P0: prior covariance, shape ``(..., n, n)``, symmetric positive definite.
            mask: optional boolean ``(..., T, m)``; ``False`` marks a component as missing.
            path: ``"auto"``, ``"kalman"`` or ``"cubature"``, as in :meth:`filter`.
            parallel: the parallel-in-time exact smoother (linear models only).

        Returns:
            A :class:`~torchfilt.filters.SmootherResult` with smoothed means ``(..., T, n)`` and
            covariances ``(..., T, n, n)``.
        """
        from torchfilt.filters.smoother import rts_smooth

        if self._exact(path, parallel):
            return kalman_smoother(
                self.model, y, u, x0=x0, P0=P0, mask=mask, sqrt=self.sqrt, parallel=parallel
            )
        return rts_smooth(self.filter(y, u, x0=x0, P0=P0, mask=mask, path="cubature"))

    def free_run(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        burn_in: int = 0,
        mask: Tensor | None = None,
        path: Path = "auto",
    ) -> Forecast:
        """Free-run simulation after filtering ``burn_in`` measurements, with this filter's rule
        and options: :func:`~torchfilt.filters.free_run`.

        Args:
            y: measurements ``(..., T, m)``; NaN entries are missing.
            u: inputs ``(..., T, nu)`` or ``None``.
            x0: prior mean ``(..., n)``.
            P0: prior covariance ``(..., n, n)``.
            burn_in: how many leading measurements are filtered, ``0 <= burn_in <= T``.
            mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
            path: ``"auto"``, ``"kalman"`` or ``"cubature"``, as in :meth:`filter`.

        Returns:
            A :class:`~torchfilt.filters.Forecast`: state ``(..., T, n)``, ``(..., T, n, n)``
            and output ``(..., T, m)``, ``(..., T, m, m)`` moments.

        Raises:
            InputError: ``burn_in`` negative or over ``T``, or bad inputs.
            ModelError: a filter with a step of its own (the constrained CKF).
        """
        return free_run_with(self, y, u, x0=x0, P0=P0, burn_in=burn_in, mask=mask, path=path)

    def k_step_ahead(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        horizon: int,
        mask: Tensor | None = None,
        path: Path = "auto",
    ) -> Forecast:
        """For every time ``t`` the prediction of ``x_t`` and ``y_t`` from the measurements up
        to ``t - horizon``, with this filter's rule and options:
        :func:`~torchfilt.filters.k_step_ahead`.

        Args:
            y: measurements ``(..., T, m)``; NaN entries are missing.
            u: inputs ``(..., T, nu)`` or ``None``.
            x0: prior mean ``(..., n)``.
            P0: prior covariance ``(..., n, n)``.
            horizon: ``k >= 0``, the number of prediction steps ahead.
            mask: optional bool ``(..., T, m)``; ``False`` marks a component missing.
            path: ``"auto"``, ``"kalman"`` or ``"cubature"``, as in :meth:`filter`.

        Returns:
            A :class:`~torchfilt.filters.Forecast`: state ``(..., T, n)``, ``(..., T, n, n)``
            and output ``(..., T, m)``, ``(..., T, m, m)`` moments.

        Raises:
            InputError: ``horizon`` negative, or bad inputs.
            ModelError: a filter with a step of its own (the constrained CKF).
        """
        return k_step_ahead_with(self, y, u, x0=x0, P0=P0, horizon=horizon, mask=mask, path=path)

    # ------------------------------------------------------------------ deprecated engine names
    def prepare(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> FilterInputs:
        """Deprecated: check a recording; :meth:`filter` does it."""
        _deprecated("prepare", "call filter(); the inputs are checked there")
        return self._prepare(y, u, x0=x0, P0=P0, mask=mask)

    def run(self, inputs: FilterInputs, keep: Collection[str] | None = None) -> FilterResult:
        """Deprecated: run prepared inputs; call :meth:`filter`."""
        _deprecated("run", "call filter()")
        return self._run(inputs, keep)

    def scan(
        self,
        inputs: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]]:
        """Deprecated: the per-step records of prepared inputs; call :meth:`filter`."""
        _deprecated("scan", "call filter()")
        _, records, extras = self._scan(inputs, step_fn, sink)
        return records, extras

    def step_function(self, device: torch.device) -> StepFunction:
        """Deprecated: the (compiled) step; :meth:`step` is the step."""
        _deprecated("step_function", "the engines compile the step; call filter()")
        like = torch.empty(0, device=device)
        return self._engine.step_function(self._online_plan(torch.Size(), like), like.device)

    def execution(self, batch: torch.Size, inputs: FilterInputs | None = None) -> str:
        """Deprecated: the execution a run would take; read the result's ``numerics``."""
        _deprecated("execution", "read the result's numerics.execution")
        if inputs is None:
            return self._online_plan(torch.Size(batch), torch.empty(0)).execution
        return self._plan(inputs, self._engine.known_fallbacks(inputs)).execution

    # ------------------------------------------------------------------ online use
    def init(self, x0: Tensor, P0: Tensor) -> FilterState:
        """Start an online filter from the prior ``N(x0, P0)`` (the belief about ``x_{-1}``).

        Args:
            x0: prior mean ``(..., n)``.
            P0: prior covariance ``(..., n, n)``, symmetric PSD.

        Returns:
            A :class:`FilterState` at ``t = -1``. Call :meth:`predict` then :meth:`update` for each
            measurement; with the same data this gives :meth:`filter`'s estimates.

        Raises:
            InputTypeError: ``x0`` or ``P0`` is not a floating-point tensor (or convertible).
            InputError: the prior is invalid (not finite, or ``P0`` not symmetric).
            ShapeError: ``x0`` or ``P0`` does not match the state dimension.
        """
        x0 = self._as_tensor("x0", x0, None)
        P0 = self._as_tensor("P0", P0, x0.device)
        check_real_tensor(P0, "P0", integers=True)
        if not x0.is_floating_point():
            raise InputTypeError(f"x0 must be floating point, got {x0.dtype}")
        check_real_tensor(x0, "x0")
        dtype = torch.promote_types(x0.dtype, P0.dtype) if P0.is_floating_point() else x0.dtype
        x0, P0 = x0.to(dtype), P0.to(dtype)
        check_prior(x0, P0, self.model.state_dim)
        try:
            batch = torch.broadcast_shapes(x0.shape[:-1], P0.shape[:-2])
        except RuntimeError:
            raise ShapeError(
                f"x0 {tuple(x0.shape)} and P0 {tuple(P0.shape)}: batch shapes do not broadcast"
            ) from None
        n = self.model.state_dim
        mean = x0.expand(*batch, n).contiguous()
        cov = P0.expand(*batch, n, n).contiguous()
        state = FilterState(mean, cov, safe_cholesky(cov, name="P0"), -1, False)
        self._check_prior_state(state)
        return state

    def _check_prior_state(self, state: FilterState) -> None:
        """A hook for a filter whose prior must satisfy more (the constrained CKF's box)."""

    @staticmethod
    def _as_tensor(name: str, v: Any, device: torch.device | None) -> Tensor:
        if isinstance(v, Tensor):
            return v if device is None else v.to(device)
        try:
            return torch.as_tensor(v, device=device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InputTypeError(
                f"{name} must be a tensor (or convertible to one), got {type(v).__name__}: {exc}"
            ) from None

    def _check_state(self, state: FilterState, what: str) -> None:
        if not isinstance(state, FilterState):
            raise InputError(
                f"state: {what} needs the FilterState of init/predict/update, got "
                f"{type(state).__name__}"
            )

    def _step_input(self, name: str, v: Tensor | None, dim: int, like: Tensor) -> Tensor | None:
        if v is None:
            return None
        v = self._as_tensor(name, v, like.device)
        if not v.is_floating_point():
            raise InputTypeError(f"{name} must be floating point, got {v.dtype}")
        check_real_tensor(v, name)
        v = v.to(like.dtype)
        if v.dim() < 1 or (dim >= 0 and v.shape[-1] != dim):
            want = "nu" if dim < 0 else dim
            raise ShapeError(f"{name}: expected shape (..., {want}), got {tuple(v.shape)}")
        return v

    @staticmethod
    def _expand(state: FilterState, batch: torch.Size) -> Belief:
        """The state's belief expanded to ``batch`` (a batched measurement of an unbatched state)."""
        n = state.mean.shape[-1]
        if state.mean.shape[:-1] == batch:
            return state.belief
        sq = None if state.sqrt is None else state.sqrt.expand(*batch, n, n)
        return Belief(state.mean.expand(*batch, n), state.cov.expand(*batch, n, n), sq)

    def _measurement(self, y: Tensor, mask: Tensor | None, like: Tensor) -> tuple[Tensor, Tensor]:
        """One step's measurement ``(..., m)`` in ``like``'s dtype and which components are
        observed (finite and ``mask``)."""
        if not isinstance(y, Tensor):
            raise InputTypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        v = self._step_input("y", y, self.model.obs_dim, like)
        assert v is not None
        m = None if mask is None else torch.as_tensor(mask).unsqueeze(-2)
        return v, observed(v.unsqueeze(-2), m).squeeze(-2)

    def _online_plan(self, batch: torch.Size, like: Tensor) -> ExecutionPlan:
        """The plan of a step of batch shape ``batch`` on ``like``'s device without autograd
        (an online step takes its small-matrix kernels from it)."""
        empty = like.new_empty(0)
        inputs = FilterInputs(empty, empty, None, empty, empty, batch)
        return self._plan(inputs, grad=False)

    def predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Predict the next state: the belief about ``x_{t+1}`` from the one about ``x_t``.

        Args:
            state: from :meth:`init` or :meth:`update` (or :meth:`predict`: predicting twice skips
                a measurement).
            u: the input row of the step being predicted (``u[..., t + 1, :]`` of a recording,
                the input convention of :mod:`torchfilt.filters`), ``(..., nu)``, or ``None``.

        Returns:
            The predicted :class:`FilterState` at ``t + 1``.

        Raises:
            InputTypeError: ``u`` is not floating point.
            InputError: ``u`` is not finite, or ``state`` is not a filter state.
            ShapeError: ``u`` has the wrong shape.
        """
        self._check_state(state, "predict")
        u = self._step_input("u", u, -1, state.mean)
        if u is not None and not bool(torch.isfinite(u).all()):
            raise InputError("u contains non-finite entries; inputs cannot be missing")
        check_model_input(self.model, u)
        t = state.t + 1
        Q = self._step.noise(self.model.transition, t, state.mean)
        pts = self._step.points(state.mean)
        batch = torch.broadcast_shapes(state.mean.shape[:-1], () if u is None else u.shape[:-1])
        kernels = self._online_plan(batch, state.mean).small_kernels
        with small_matrix_kernels(kernels):  # type: ignore[arg-type]
            pred, cache = self._step.predict(state.belief, u, pts, Q)
        return FilterState(pred.mean, pred.cov, pred.sqrt, t, True, cache)

    def update(
        self,
        state: FilterState,
        y: Tensor,
        u: Tensor | None = None,
        *,
        mask: Tensor | None = None,
    ) -> tuple[FilterState, UpdateStats]:
        """Condition the predicted state on one measurement ``y_t``.

        Args:
            state: the predicted :class:`FilterState` (from :meth:`predict`).
            y: measurement ``(..., m)``; NaN components are missing (an all-NaN ``y`` leaves the
                state as predicted).
            u: the input row of this step (the one :meth:`predict` took), ``(..., nu)``, if the
                measurement model takes it.
            mask: optional bool ``(..., m)``; ``False`` marks a component missing.

        Returns:
            The filtered :class:`FilterState` and the step's
            :class:`~torchfilt.filters.steps.UpdateStats` (predicted measurement, innovation
            and its covariance, log-likelihood term).

        Raises:
            InputTypeError: ``y`` is not a floating-point tensor, or ``u`` not floating point.
            InputError: ``state`` is not a predicted state.
            ShapeError: ``y``'s batch shape does not broadcast with the state's, or ``y`` or
                ``u`` has the wrong shape.
        """
        self._check_state(state, "update")
        if not state.predicted:
            raise InputError(
                "state: update needs a predicted state; call predict(state, u) first (the prior "
                "of init is the belief about x_{-1}, as in filter())"
            )
        y, obs = self._measurement(y, mask, state.mean)
        u = self._step_input("u", u, -1, state.mean)
        check_model_input(self.model, u)
        try:
            batch = torch.broadcast_shapes(state.mean.shape[:-1], obs.shape[:-1])
        except RuntimeError:
            raise ShapeError(
                f"y: batch shape {tuple(obs.shape[:-1])} does not broadcast with the state's "
                f"{tuple(state.mean.shape[:-1])}"
            ) from None
        R = self._step.noise(self.model.measurement, state.t, state.mean)
        pts = self._step.points(state.mean)
        kernels = self._online_plan(batch, state.mean).small_kernels
        with small_matrix_kernels(kernels):  # type: ignore[arg-type]
            post, stats = self._step.update(
                self._expand(state, batch), y, obs, u, pts, R, state.cache
            )
        return FilterState(post.mean, post.cov, post.sqrt, state.t, False), stats


class CKF(GaussianFilter):
    """Cubature Kalman filter: :class:`GaussianFilter` with the third-degree spherical-radial rule.

    ``CKF(model, rule=UnscentedRule())`` is the UKF; any :class:`~torchfilt.cubature.CubatureRule`
    may be given.

    Example:
        >>> import torch, torchfilt
        >>> model = torchfilt.LinearGaussianModel(
        ...     A=torch.eye(2), H=torch.eye(1, 2), Q=0.01 * torch.eye(2), R=torch.eye(1))
        >>> y = torch.randn(8, 50, 1)                      # 8 sequences of 50 steps
        >>> res = torchfilt.CKF(model).filter(y, x0=torch.zeros(2), P0=torch.eye(2))
        >>> res.mean.shape
        torch.Size([8, 50, 2])

    Raises:
        InputTypeError: ``model`` is not a :class:`~torchfilt.models.StateSpaceModel` or
            ``rule`` not a :class:`~torchfilt.cubature.CubatureRule`.
        InputError: an invalid option (see :class:`GaussianFilter`).
    """
