"""The batched cubature (sigma-point) Gaussian filter: a scan of pure predict and update steps.

The steps and their equations are in :mod:`torchfilt.filters.steps`. :class:`GaussianFilter` binds a
model, a cubature rule and the options, and offers the whole-recording ``filter`` / ``smooth`` /
``graphed`` and the online ``init`` / ``predict`` / ``update``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule, SphericalRadialRule
from torchfilt.exceptions import InputError, ShapeError
from torchfilt.filters import steps
from torchfilt.filters.inputs import FilterInputs, check_inputs, check_prior, model_noise, observed
from torchfilt.filters.kalman import (
    Path,
    _keep,
    kalman_filter,
    kalman_smoother,
    select_outputs,
    select_path,
)
from torchfilt.filters.results import (
    FilterResult,
    RecordSink,
    SmootherResult,
    StepRecord,
    concat_records,
    stack_records,
    warn_nonfinite,
)
from torchfilt.filters.steps import Belief, Noise, PredictCache, UnitPoints, UpdateStats
from torchfilt.models import StateSpaceModel
from torchfilt.numerics import no_host_sync, safe_cholesky
from torchfilt.numerics.small import SMALL_BATCH, SMALL_MAX
from torchfilt.settings import (
    NumericsPath,
    current_skip_guard_checks,
    current_small_matrix_kernels,
    small_matrix_kernels,
)

if TYPE_CHECKING:
    from torchfilt.filters.graphed import GraphedFilter

__all__ = ["CKF", "FilterState", "GaussianFilter", "StepFunction"]

#: Steps run with Dynamo's guard checks before a compiled step may skip them (see ``scan``).
_GUARD_WARMUP_STEPS = 2
#: Steps per compiled chunk of the time loop (``compile=True``): the chunk is unrolled into one
#: graph, so the per-call overhead is paid once per chunk; longer chunks compile for longer.
DEFAULT_CHUNK = 10
#: Where each :class:`StepRecord` field has its time dimension in a :class:`FilterResult`.
_TIME_DIMS = {
    "mean": -2,
    "cov": -3,
    "predicted_mean": -2,
    "predicted_cov": -3,
    "measurement_mean": -2,
    "innovation": -2,
    "innovation_cov": -3,
    "log_likelihood": -1,
    "cross_cov": -3,
}

#: ``step(points, belief, y_t, obs_t, u_t, Q, R) -> (belief, record, aux)``: one filter step.
StepFunction = Callable[
    [UnitPoints, Belief, Tensor, Tensor, "Tensor | None", Noise, Noise],
    "tuple[Belief, StepRecord, tuple[Tensor, ...]]",
]


def _noise_at(noise: Noise, index: Callable[[Tensor], Tensor] | None) -> Noise:
    """``noise`` at one step: each present tensor through ``index`` (its time dimension taken
    at that step), or ``noise`` itself for a constant noise (``index`` None)."""
    if index is None:
        return noise
    return Noise(*(None if v is None else index(v) for v in noise))


class FilterState(NamedTuple):
    """The belief of an online filter (:meth:`GaussianFilter.init`) and its time index.

    Attributes:
        mean: ``(..., n)``. cov: ``(..., n, n)``.
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
            trace into one graph: :attr:`loop_fallback` says why) it compiles chunks of ``chunk``
            steps unrolled into one graph each instead (long first compile), and the result's
            ``numerics.execution`` says ``"compiled-chunks"``. ``"step"`` compiles the per-step
            function only (one compiled call per step); ``True`` (``"auto"``) takes ``"step"``,
            whose compile is the shortest and which serves gradients. Under compilation a
            covariance that fails its Cholesky factorisation turns the sequence to NaN instead of
            being jittered. The eager path (the default) is the one to debug with: every op runs
            as written, and a failed factorisation is retried with jitter and reported.
        chunk: steps per compiled chunk of the time loop, where the while-loop cannot be used. A
            recording whose length is not a multiple compiles its last, shorter chunk too.
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
            raise TypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")
        if point_variance not in ("total", "mean"):
            raise ValueError(f"point_variance must be 'total' or 'mean', got {point_variance!r}")
        self.model = model
        self.rule = rule if rule is not None else SphericalRadialRule(3)
        if not isinstance(self.rule, CubatureRule):
            raise TypeError(f"rule must be a CubatureRule, got {type(self.rule).__name__}")
        self.sqrt = bool(sqrt)
        self.redraw = bool(redraw)
        self.point_variance = point_variance
        n = model.state_dim
        if self.sqrt and not self.rule.weights_nonnegative(n):
            raise ValueError(
                f"sqrt=True needs non-negative covariance weights; {self.rule!r} has a negative "
                f"weight in dimension {n}"
            )
        mode: Literal["auto", "step", "loop"] | None
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
        #: None (eager), "step" (one compiled call per step), "loop" (compiled chunks of steps) or
        #: "auto" (True: "step")
        self.compile_mode = mode
        self.chunk = int(chunk)
        self._compiled = self.compile_mode is not None
        self._compiled_steps: dict[str, StepFunction] = {}
        self._compiled_chunks: dict[str, Callable[..., Any]] = {}
        self._compiled_loops: dict[str, Callable[..., Any]] = {}
        self._loop_shapes: dict[tuple[Any, ...], list[tuple[tuple[int, ...], torch.dtype]]] = {}
        #: why the while-loop could not be compiled for this filter (then chunks run), or None
        self.loop_fallback: str | None = None

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
        """One filter step: :func:`~torchfilt.filters.steps.predict` then
        :func:`~torchfilt.filters.steps.update`, with this filter's options.

        This is the function that :meth:`scan` runs, ``compile=True`` compiles and
        :class:`~torchfilt.filters.GraphedFilter` captures. A subclass with a different step
        (:class:`~torchfilt.filters.ConstrainedCKF`) overrides it.

        Args:
            points: the rule's unit points in the run's dtype and device.
            belief: the filtered belief about ``x_{t-1}``, ``mean (..., n)``, ``cov (..., n, n)``.
            y: measurement ``(..., m)``, missing entries set to 0. obs: bool ``(..., m)``.
            u: inputs ``(..., nu)`` or ``None``.
            Q: process noise of the step. R: measurement noise of the step.

        Returns:
            The filtered belief about ``x_t``, the step's :class:`~torchfilt.filters.StepRecord`
            and extra per-step outputs (none here).
        """
        pred, cache = steps.predict(
            belief,
            self.model,
            u,
            points,
            sqrt=self.sqrt,
            point_variance=self.point_variance,
            noise=Q,
        )
        post, stats = steps.update(
            pred,
            y,
            obs,
            self.model,
            points,
            u=u,
            sqrt=self.sqrt,
            redraw=self.redraw,
            point_variance=self.point_variance,
            noise=R,
            cache=cache,
        )
        record = StepRecord(
            mean=post.mean,
            cov=post.cov,
            predicted_mean=pred.mean,
            predicted_cov=pred.cov,
            measurement_mean=stats.measurement_mean,
            innovation=stats.innovation,
            innovation_cov=stats.innovation_cov,
            log_likelihood=stats.log_likelihood,
            cross_cov=cache.cross_cov,
        )
        return post, record, ()

    def step_function(self, device: torch.device) -> StepFunction:
        """The per-step function :meth:`step`, compiled (once per device type) when ``compile=True``."""
        if not self._compiled:
            return self.step
        fn = self._compiled_steps.get(device.type)
        if fn is None:
            # On the CPU a C++ wrapper around the generated kernels removes most of the per-call
            # Python overhead, which dominates when few sequences are filtered.
            options: dict[str, Any] | None = {"cpp_wrapper": True} if device.type == "cpu" else None
            fn = torch.compile(self.step, dynamic=False, options=options)
            self._compiled_steps[device.type] = fn
        return fn

    # ------------------------------------------------------------------ whole recordings
    def prepare(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        mask: Tensor | None = None,
    ) -> FilterInputs:
        """Check and broadcast a recording (arguments as in :meth:`filter`) for :meth:`scan`."""
        return check_inputs(self.model, y, u, x0, P0, mask)

    def small_kernels(self, batch: torch.Size) -> str:
        """The small-matrix kernels a run of batch shape ``batch`` uses: ``"unrolled"`` or
        ``"library"`` (``settings.small_matrix_kernels``; ``"auto"`` resolved once per run)."""
        n, m = self.model.state_dim, self.model.obs_dim
        if max(n, m) > SMALL_MAX:
            return "library"
        if self._compiled:
            return "unrolled"  # what tracing always chooses
        mode = current_small_matrix_kernels()
        if mode != "auto":
            return mode
        return "unrolled" if math.prod(batch) >= SMALL_BATCH else "library"

    def execution(self, batch: torch.Size, inputs: FilterInputs | None = None) -> str:
        """The execution a run of batch shape ``batch`` takes: ``"eager"``, ``"compiled-step"``,
        ``"compiled-loop"`` (one ``torch.while_loop``), or ``"compiled-chunks"`` where
        ``compile="loop"`` cannot use the while-loop: autograd records (``inputs`` or the model's
        parameters need gradients), or the step could not be traced into one
        (:attr:`loop_fallback` says why)."""
        mode = self.compile_mode
        if mode == "auto":
            mode = "step"
        if mode == "loop" and (
            self.loop_fallback is not None or (inputs is not None and self._records_grad(inputs))
        ):
            return "compiled-chunks"
        return {None: "eager", "step": "compiled-step", "loop": "compiled-loop"}[mode]

    def _records_grad(self, inputs: FilterInputs) -> bool:
        """Whether autograd records a run of ``inputs`` (the while-loop has no backward here)."""
        if not torch.is_grad_enabled():
            return False
        tensors = [inputs.y, inputs.x0, inputs.P0] + ([] if inputs.u is None else [inputs.u])
        tensors += list(self.model.parameters())
        return any(t.requires_grad for t in tensors)

    def numerics_path(self, inputs: FilterInputs, execution: str | None = None) -> NumericsPath:
        """The :class:`~torchfilt.settings.NumericsPath` a :meth:`scan` of ``inputs`` takes now."""
        if execution is None:
            execution = self.execution(inputs.batch, inputs)
        nan = self._compiled or no_host_sync()
        return NumericsPath(execution, self.small_kernels(inputs.batch), "nan" if nan else "jitter")

    def scan(
        self,
        inputs: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]]:
        """Run the step over time from the prior, handing it each step's data and noise.

        Args:
            inputs: from :meth:`prepare`.
            step_fn: the step to run; default :meth:`step_function` for the data's device.
            sink: a :class:`~torchfilt.filters.results.RecordSink` that takes the records
                instead of the returned list (which is then empty); not with a compiled loop.

        Returns:
            One :class:`~torchfilt.filters.StepRecord` and one tuple of extra outputs per step.
        """
        if step_fn is None:
            execution = self.execution(inputs.batch, inputs)
            if execution in ("compiled-loop", "compiled-chunks"):
                if sink is not None:
                    raise InputError("sink: a compiled loop returns chunk records; pass no sink")
                if execution == "compiled-loop":
                    done = self._try_while(inputs)
                    if done is not None:
                        return done
                return self._chunked(inputs)
            step_fn = self.step_function(inputs.y.device)
        kernels = self.small_kernels(inputs.batch)
        with contextlib.ExitStack() as ctx:
            if not self._compiled:
                ctx.enter_context(small_matrix_kernels(kernels))  # type: ignore[arg-type]
            return self._loop(inputs, step_fn, ctx, sink)

    def _loop(
        self,
        inp: FilterInputs,
        step_fn: StepFunction,
        ctx: contextlib.ExitStack,
        sink: RecordSink | None = None,
    ) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]]:
        T = inp.y.shape[-2]
        belief = self._prior_belief(inp)
        mean = belief.mean
        f, h = self.model.transition, self.model.measurement
        const_Q = None if f.time_varying_noise else self._noise_of(f, 0, mean)
        const_R = None if h.time_varying_noise else self._noise_of(h, 0, mean)
        pts = steps.unit_points(self.rule, mean.shape[-1], mean)
        # A compiled step sees tensors of identical shape, dtype, device and strides at every step
        # once the first steps have fixed the strides, so Dynamo's guard checks (~0.1 ms per call)
        # can be skipped from then on, when settings.skip_guard_checks allows it.
        skip = step_fn in self._compiled_steps.values() and current_skip_guard_checks()
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for t in range(T):
            if skip and t == _GUARD_WARMUP_STEPS:
                ctx.enter_context(torch.compiler.set_stance(skip_guard_eval_unsafe=True))
            Q = const_Q if const_Q is not None else self._noise_of(f, t, mean)
            R = const_R if const_R is not None else self._noise_of(h, t, mean)
            ut = None if inp.u is None else inp.u[..., t, :]
            belief, rec, extra = step_fn(
                pts, belief, inp.y[..., t, :], inp.obs[..., t, :], ut, Q, R
            )
            if sink is not None:
                sink.append(rec)
            else:
                records.append(rec)
            extras.append(extra)
        return records, extras

    def run_chunk(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: tuple[Noise, ...],
        R: tuple[Noise, ...],
    ) -> tuple[Belief, StepRecord, tuple[Tensor, ...]]:
        """``K`` steps of :meth:`step` in one call: the unit ``compile=True`` compiles.

        Args:
            points, belief: as in :meth:`step`.
            y: measurements ``(..., K, m)``, missing set to 0. obs: bool ``(..., K, m)``.
            u: inputs ``(..., K, nu)`` or ``None``. Q, R: the ``K`` steps' noises.

        Returns:
            The belief after the ``K`` steps, a :class:`~torchfilt.filters.StepRecord` whose
            fields carry a time dimension of length ``K`` (as in a
            :class:`~torchfilt.filters.FilterResult`) and the stacked extra outputs.
        """
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for k in range(y.shape[-2]):
            ut = None if u is None else u[..., k, :]
            belief, rec, extra = self.step(
                points, belief, y[..., k, :], obs[..., k, :], ut, Q[k], R[k]
            )
            records.append(rec)
            extras.append(extra)
        res = stack_records(records, obs)
        stacked = StepRecord(
            **{f: getattr(res, f) for f in StepRecord._fields if f != "log_likelihood"},
            log_likelihood=torch.stack([r.log_likelihood for r in records], dim=-1),
        )
        ex = tuple(torch.stack([e[i] for e in extras], dim=-1) for i in range(len(extras[0])))
        return belief, stacked, ex

    def _chunk_function(self, device: torch.device) -> Callable[..., Any]:
        fn = self._compiled_chunks.get(device.type)
        if fn is None:
            # the C++ wrapper removes the per-call Python overhead, but calls the library kernels
            # that larger matrices need through a slow proxy (no C shim for cholesky_ex)
            small = max(self.model.state_dim, self.model.obs_dim) <= SMALL_MAX
            cpp = device.type == "cpu" and small
            options: dict[str, Any] | None = {"cpp_wrapper": True} if cpp else None
            fn = torch.compile(self.run_chunk, dynamic=False, options=options)
            self._compiled_chunks[device.type] = fn
        return fn

    def _chunked(self, inp: FilterInputs) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]]:
        """The time loop in compiled chunks of ``self.chunk`` steps; returns one record per chunk
        (fields with a time dimension) for :func:`~torchfilt.filters.results.concat_records`."""
        T = inp.y.shape[-2]
        belief = self._prior_belief(inp)
        mean = belief.mean
        f, h = self.model.transition, self.model.measurement
        const_Q = None if f.time_varying_noise else self._noise_of(f, 0, mean)
        const_R = None if h.time_varying_noise else self._noise_of(h, 0, mean)
        pts = steps.unit_points(self.rule, mean.shape[-1], mean)
        fn = self._chunk_function(inp.y.device)
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for t0 in range(0, T, self.chunk):
            t1 = min(T, t0 + self.chunk)
            Q = tuple(
                const_Q if const_Q is not None else self._noise_of(f, t, mean)
                for t in range(t0, t1)
            )
            R = tuple(
                const_R if const_R is not None else self._noise_of(h, t, mean)
                for t in range(t0, t1)
            )
            u = None if inp.u is None else inp.u[..., t0:t1, :]
            belief, rec, extra = fn(
                pts, belief, inp.y[..., t0:t1, :], inp.obs[..., t0:t1, :], u, Q, R
            )
            records.append(rec)
            extras.append(extra)
        return records, extras

    def run_loop(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: Noise,
        R: Noise,
        outputs: tuple[Tensor, ...],
        varying: tuple[bool, bool],
        select: tuple[int, ...],
    ) -> tuple[Tensor, ...]:
        """All ``T`` steps of :meth:`step` as one ``torch.while_loop``: the unit
        ``compile="loop"`` compiles (the step is traced once, the loop runs inside the compiled
        code).

        Args:
            points, belief: as in :meth:`step` (``belief.sqrt`` is carried in the square-root
                form only).
            y: measurements ``(..., T, m)``, missing set to 0. obs: bool ``(..., T, m)``.
            u: inputs ``(..., T, nu)`` or ``None``.
            Q, R: the noises; where ``varying`` says so, their tensors carry a leading time
                dimension ``T``.
            outputs: time-major buffers ``(T, *shape)``, one per entry of ``select``.
            varying: whether ``Q`` and ``R`` change over time.
            select: which of the step's outputs (the :class:`~torchfilt.filters.StepRecord`
                fields, then the extra outputs) the buffers take.

        Returns:
            The buffers filled, in the same order.
        """
        T = y.shape[-2]
        sq = self.sqrt
        nb = len(outputs)
        noise = (Q.cov, Q.sqrt, R.cov, R.sqrt)
        present = tuple(v is not None for v in noise)
        carried = tuple(v for v in noise if v is not None)
        nn_ = len(carried)
        # every tensor the body reads is carried (and cloned back), not captured: Dynamo would
        # lift each view of a captured tensor as its own input, and aliased inputs are refused
        start = 4 if sq else 3

        def cond(t: Tensor, *rest: Tensor) -> Tensor:
            return t < T

        def body(t: Tensor, *rest: Tensor) -> tuple[Tensor, ...]:
            mean, cov = rest[0], rest[1]
            chol = rest[2] if sq else None
            bufs = rest[start - 1 : start - 1 + nb]
            nz = rest[start - 1 + nb : start - 1 + nb + nn_]
            pf = rest[start - 1 + nb + nn_ :]
            idx = t.reshape(1)

            def pick(x: Tensor, dim: int) -> Tensor:
                return x.index_select(dim, idx).squeeze(dim)

            it = iter(nz)
            Qc, Qs, Rc, Rs = (next(it) if p else None for p in present)
            at = lambda v: pick(v, 0)  # noqa: E731
            Qt = _noise_at(Noise(Qc, Qs), at if varying[0] else None)
            Rt = _noise_at(Noise(Rc, Rs), at if varying[1] else None)
            ut = None if u is None else pick(u, -2)
            post, rec, extra = self.step(
                UnitPoints(*pf), Belief(mean, cov, chol), pick(y, -2), pick(obs, -2), ut, Qt, Rt
            )
            vals = (*rec, *extra)
            picked = (vals[i] for i in select)
            new = tuple(
                b.index_copy(0, idx, v.unsqueeze(0)) for b, v in zip(bufs, picked, strict=True)
            )
            # carried values keep the metadata (strides included) they entered with
            head: tuple[Tensor, ...] = (t + 1, post.mean.contiguous(), post.cov.contiguous())
            if sq:
                assert post.sqrt is not None
                head += (post.sqrt.contiguous(),)
            return head + new + tuple(v.clone() for v in nz) + tuple(p.clone() for p in pf)

        init: tuple[Tensor, ...] = (torch.zeros((), dtype=torch.int64, device=y.device),)
        init += (belief.mean.contiguous(), belief.cov.contiguous())
        if sq:
            assert belief.sqrt is not None
            init += (belief.sqrt.contiguous(),)
        init += tuple(outputs) + carried + tuple(points)
        out = torch.while_loop(cond, body, init)
        return tuple(out[start : start + nb])

    def _loop_function(self, device: torch.device) -> Callable[..., Any]:
        fn = self._compiled_loops.get(device.type)
        if fn is None:
            # the C++ wrapper runs the loop itself in C++: no Python between the steps
            options: dict[str, Any] | None = {"cpp_wrapper": True} if device.type == "cpu" else None
            fn = torch.compile(self.run_loop, dynamic=False, fullgraph=True, options=options)
            self._compiled_loops[device.type] = fn
        return fn

    def _try_while(
        self, inp: FilterInputs, keep: Collection[str] | None = None
    ) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]] | None:
        """:meth:`_while`, or ``None`` after recording in :attr:`loop_fallback` why the step
        could not be traced into one while-loop (the caller then compiles chunks, where a
        genuine error of the model raises again)."""
        try:
            return self._while(inp, keep)
        except RuntimeError as exc:  # Dynamo's "unsupported" errors are RuntimeErrors
            self.loop_fallback = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
            return None

    def _while(
        self, inp: FilterInputs, keep: Collection[str] | None = None
    ) -> tuple[list[StepRecord], list[tuple[Tensor, ...]]]:
        """The whole time loop as one compiled ``torch.while_loop`` (:meth:`run_loop`); returns
        one record with a time dimension (as a chunk of :meth:`_chunked`). Only the record
        fields in ``keep`` (default all) are stored; the others are empty tensors."""
        T = inp.y.shape[-2]
        belief = self._prior_belief(inp)
        mean = belief.mean
        f, h = self.model.transition, self.model.measurement
        pts = steps.unit_points(self.rule, mean.shape[-1], mean)

        def noise(side: nn.Module) -> tuple[Noise, bool]:
            if not side.time_varying_noise:
                return self._noise_of(side, 0, mean), False
            per = [self._noise_of(side, t, mean) for t in range(T)]

            def stack(i: int) -> Tensor | None:
                vals = [v for p in per if (v := p[i]) is not None]
                return torch.stack(vals) if len(vals) == T else None

            return Noise(stack(0), stack(1)), True

        (Q, q_var), (R, r_var) = noise(f), noise(h)
        key = (tuple(inp.y.shape), None if inp.u is None else tuple(inp.u.shape), mean.dtype,
               mean.device, q_var, r_var)  # fmt: skip
        shapes = self._loop_shapes.get(key)
        if shapes is None:  # one eager step tells the outputs' shapes and dtypes
            first = lambda v: v[0]  # noqa: E731
            with torch.no_grad():
                _, rec, extra = self.step(
                    pts, belief, inp.y[..., 0, :], inp.obs[..., 0, :],
                    None if inp.u is None else inp.u[..., 0, :],
                    _noise_at(Q, first if q_var else None), _noise_at(R, first if r_var else None),
                )  # fmt: skip
            shapes = [(tuple(v.shape), v.dtype) for v in (*rec, *extra)]
            self._loop_shapes[key] = shapes
        nrec = len(StepRecord._fields)
        select = tuple(
            i
            for i in range(len(shapes))
            if i >= nrec or keep is None or StepRecord._fields[i] in keep
        )
        bufs = tuple(mean.new_zeros((T, *shapes[i][0]), dtype=shapes[i][1]) for i in select)
        fn = self._loop_function(inp.y.device)
        filled = fn(pts, belief, inp.y, inp.obs, inp.u, Q, R, bufs, (q_var, r_var), select)
        out = dict(zip(select, filled, strict=True))
        empty = mean.new_empty(0)
        fields = {
            name: out[i].movedim(0, _TIME_DIMS[name]) if i in out else empty
            for i, name in enumerate(StepRecord._fields)
        }
        extra = tuple(out[i].movedim(0, -1) for i in range(nrec, len(shapes)))
        return [StepRecord(**fields)], [extra]

    def _prior_belief(self, inp: FilterInputs) -> Belief:
        """The belief a run starts from: fresh copies of ``x0`` and ``P0`` (under
        inference_mode they are inference tensors like every later belief, so a compiled first
        step or chunk does not compile a variant of its own), factored in the square-root form
        only (the plain form factors the covariance in the step)."""
        mean, cov = inp.x0.clone(), inp.P0.clone()
        return Belief(mean, cov, safe_cholesky(cov, name="P0") if self.sqrt else None)

    def _noise_of(self, side: nn.Module, step: int, like: Tensor) -> Noise:
        cov = model_noise(side, step, like)
        return Noise(cov, None if cov is None or not self.sqrt else steps.noise_sqrt(cov))

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

        Step ``t`` predicts from ``x_{t-1}`` with ``u[..., t, :]`` (the prior ``N(x0, P0)`` is
        ``x_{-1}``) and then updates with ``y[..., t, :]``.

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
            A :class:`~torchfilt.filters.FilterResult` (its ``path`` says which path ran). A step with no observed component is a
            pure prediction (its log-likelihood term is 0). A sequence whose covariance cannot be
            factored even with jitter (or, in the square-root form, whose factor loses
            definiteness) becomes NaN from that step on and a
            :class:`~torchfilt.exceptions.DivergenceWarning` is emitted; the rest of the batch is
            unaffected. ``numerics`` says which path ran.
        """
        # -- exact Kalman path for linear models (torchfilt.filters.kalman) -------------------
        if select_path(self.model, path=path, parallel=parallel, redraw=self.redraw):
            return kalman_filter(
                self.model, y, u, x0=x0, P0=P0, mask=mask, sqrt=self.sqrt, parallel=parallel,
                outputs=outputs,
            )  # fmt: skip
        # -------------------------------------------------------------------------------------
        keep = _keep(outputs)
        inputs = self.prepare(y, u, x0=x0, P0=P0, mask=mask)
        res = self.run(inputs, keep=keep)
        warn_nonfinite(res, stacklevel=3)
        return select_outputs(res, outputs)

    def run(self, inputs: FilterInputs, keep: Collection[str] | None = None) -> FilterResult:
        """:meth:`scan` the prepared ``inputs`` into a result (no divergence warning).

        Args:
            inputs: from :meth:`prepare`.
            keep: the result fields to store (default all; see :class:`RecordSink`).
        """
        path = self.numerics_path(inputs)
        done = self._try_while(inputs, keep) if path.execution == "compiled-loop" else None
        if done is not None:
            (rec,), _ = done
            fields = {k: v for k, v in rec._asdict().items() if k != "log_likelihood"}
            ll = rec.log_likelihood
            return FilterResult(
                **fields,
                observed=self._observed(inputs),
                log_likelihood=ll.sum(-1) if ll.numel() else ll,
                numerics=path,
            )
        if path.execution in ("compiled-loop", "compiled-chunks"):
            records, _ = self.scan(inputs)
            path = self.numerics_path(inputs)  # a while-loop that could not be traced fell back
            return concat_records(records, self._observed(inputs), path)
        sink = RecordSink(inputs.y.shape[-2], keep)
        self.scan(inputs, sink=sink)
        return sink.result(self._observed(inputs), path)

    @staticmethod
    def _observed(inp: FilterInputs) -> Tensor:
        return inp.obs.expand(*inp.batch, *inp.obs.shape[-2:])

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
            x0: prior mean ``(..., n)``. P0: prior covariance ``(..., n, n)``; both fixed.
            warmup: eager runs before the capture.
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

        Arguments as in :meth:`filter`. Returns a :class:`~torchfilt.filters.SmootherResult` with
        smoothed means ``(..., T, n)`` and covariances ``(..., T, n, n)``.
        """
        from torchfilt.filters.smoother import rts_smooth

        # -- exact Kalman path for linear models (torchfilt.filters.kalman) -------------------
        if select_path(self.model, path=path, parallel=parallel, redraw=self.redraw):
            return kalman_smoother(
                self.model, y, u, x0=x0, P0=P0, mask=mask, sqrt=self.sqrt, parallel=parallel
            )
        return rts_smooth(self.filter(y, u, x0=x0, P0=P0, mask=mask, path="cubature"))

    # ------------------------------------------------------------------ online use
    def init(self, x0: Tensor, P0: Tensor) -> FilterState:
        """Start an online filter from the prior ``N(x0, P0)`` (the belief about ``x_{-1}``).

        Args:
            x0: prior mean ``(..., n)``. P0: prior covariance ``(..., n, n)``, symmetric PSD.

        Returns:
            A :class:`FilterState` at ``t = -1``. Call :meth:`predict` then :meth:`update` for each
            measurement; with the same data this gives :meth:`filter`'s estimates.
        """
        x0 = torch.as_tensor(x0)
        P0 = torch.as_tensor(P0, device=x0.device)
        if not x0.is_floating_point():
            raise TypeError(f"x0 must be floating point, got {x0.dtype}")
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
        return FilterState(mean, cov, safe_cholesky(cov, name="P0"), -1, False)

    def _check_state(self, state: FilterState, what: str) -> None:
        if not isinstance(state, FilterState):
            raise InputError(
                f"state: {what} needs the FilterState of init/predict/update, got "
                f"{type(state).__name__}"
            )

    def _step_input(self, name: str, v: Tensor | None, dim: int, like: Tensor) -> Tensor | None:
        if v is None:
            return None
        v = torch.as_tensor(v, device=like.device)
        if not v.is_floating_point():
            raise TypeError(f"{name} must be floating point, got {v.dtype}")
        v = v.to(like.dtype)
        if v.dim() < 1 or (dim >= 0 and v.shape[-1] != dim):
            raise ShapeError(f"{name}: expected shape (..., {dim}), got {tuple(v.shape)}")
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
            raise TypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        v = self._step_input("y", y, self.model.obs_dim, like)
        assert v is not None
        m = None if mask is None else torch.as_tensor(mask).unsqueeze(-2)
        return v, observed(v.unsqueeze(-2), m).squeeze(-2)

    def predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Predict the next state: the belief about ``x_{t+1}`` from the one about ``x_t``.

        Args:
            state: from :meth:`init` or :meth:`update` (or :meth:`predict`: predicting twice skips
                a measurement).
            u: inputs ``(..., nu)`` driving this step, or ``None``.

        Returns:
            The predicted :class:`FilterState` at ``t + 1``.
        """
        self._check_state(state, "predict")
        u = self._step_input("u", u, -1, state.mean)
        if u is not None and not bool(torch.isfinite(u).all()):
            raise ValueError("u contains non-finite entries; inputs cannot be missing")
        t = state.t + 1
        Q = self._noise_of(self.model.transition, t, state.mean)
        pts = steps.unit_points(self.rule, self.model.state_dim, state.mean)
        batch = torch.broadcast_shapes(state.mean.shape[:-1], () if u is None else u.shape[:-1])
        with small_matrix_kernels(self.small_kernels(batch)):  # type: ignore[arg-type]
            pred, cache = steps.predict(
                state.belief,
                self.model,
                u,
                pts,
                sqrt=self.sqrt,
                point_variance=self.point_variance,
                noise=Q,
            )
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
            u: the inputs ``(..., nu)`` of this step, if the measurement model takes them.
            mask: optional bool ``(..., m)``; ``False`` marks a component missing.

        Returns:
            The filtered :class:`FilterState` and the step's
            :class:`~torchfilt.filters.steps.UpdateStats` (predicted measurement, innovation
            and its covariance, log-likelihood term).
        """
        self._check_state(state, "update")
        if not state.predicted:
            raise InputError(
                "state: update needs a predicted state; call predict(state, u) first (the prior "
                "of init is the belief about x_{-1}, as in filter())"
            )
        y, obs = self._measurement(y, mask, state.mean)
        u = self._step_input("u", u, -1, state.mean)
        try:
            batch = torch.broadcast_shapes(state.mean.shape[:-1], obs.shape[:-1])
        except RuntimeError:
            raise ShapeError(
                f"y: batch shape {tuple(obs.shape[:-1])} does not broadcast with the state's "
                f"{tuple(state.mean.shape[:-1])}"
            ) from None
        R = self._noise_of(self.model.measurement, state.t, state.mean)
        pts = steps.unit_points(self.rule, self.model.state_dim, state.mean)
        with small_matrix_kernels(self.small_kernels(batch)):  # type: ignore[arg-type]
            post, stats = steps.update(
                self._expand(state, batch),
                y,
                obs,
                self.model,
                pts,
                u=u,
                sqrt=self.sqrt,
                redraw=self.redraw,
                point_variance=self.point_variance,
                noise=R,
                cache=state.cache,
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
    """
