"""The engines that run a filter step over time, generic over the :class:`Step` protocol.

A :class:`Step` is one predict-and-update step function plus what a run of it needs (the prior,
the noise at a step, the rule's points). :class:`Engine` runs any step in the way an
:class:`~torchfilt.filters.plan.ExecutionPlan` says: the eager loop (each step as written), one
compiled call per step, compiled chunks of unrolled steps, or the whole time loop as one compiled
``torch.while_loop``; :class:`~torchfilt.filters.GraphedFilter` captures its step loop into a
CUDA graph. The engine decides nothing: the plan does (:func:`~torchfilt.filters.plan.plan`).
Compiled callables are cached on the engine by device type; a while-loop that could not be traced
is recorded, keyed by the recording's shape, in :attr:`Engine.trace_failures`, and is an input of
the next plan for that shape (never a switch that silently changes other runs).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection
from typing import Any, Protocol

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError
from torchfilt.filters.inputs import FilterInputs
from torchfilt.filters.plan import ExecutionPlan, Fallback
from torchfilt.filters.results import (
    FilterResult,
    RecordSink,
    StepRecord,
    concat_records,
    stack_records,
)
from torchfilt.filters.steps import Belief, Noise, PredictCache, UnitPoints, UpdateStats
from torchfilt.models import StateSpaceModel
from torchfilt.numerics.small import SMALL_MAX
from torchfilt.settings import small_matrix_kernels

__all__ = ["Engine", "OnlineStep", "Step", "StepFunction", "TraceFailure", "records_grad"]

#: Steps run with Dynamo's guard checks before a compiled step may skip them.
_GUARD_WARMUP_STEPS = 2
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
Records = tuple[list[StepRecord], list[tuple[Tensor, ...]]]


class Step(Protocol):
    """What an engine runs: one filter step and what a run of it needs.

    Attributes:
        model: the state-space model (its ``transition`` and ``measurement`` give the noise).
        sqrt: whether beliefs carry a Cholesky factor (the square-root form).
    """

    model: StateSpaceModel
    sqrt: bool

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
        """Predict ``x_t`` from the belief about ``x_{t-1}`` and update with ``y (..., m)``;
        returns the new belief, the step's record and extra per-step outputs."""
        ...

    def prior(self, inputs: FilterInputs) -> Belief:
        """The belief a run starts from (about ``x_{-1}``)."""
        ...

    def noise(self, side: nn.Module, t: int, like: Tensor) -> Noise:
        """The noise of ``side`` (``model.transition`` or ``model.measurement``) at step ``t``."""
        ...

    def points(self, like: Tensor) -> UnitPoints:
        """The unit points in ``like``'s dtype and device."""
        ...


class OnlineStep(Step, Protocol):
    """A :class:`Step` whose predict and update can also be run one at a time (online)."""

    def predict(
        self, belief: Belief, u: Tensor | None, points: UnitPoints, Q: Noise
    ) -> tuple[Belief, PredictCache]:
        """The prediction of ``x_{t+1}`` from the belief about ``x_t``."""
        ...

    def update(
        self,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        points: UnitPoints,
        R: Noise,
        cache: PredictCache | None,
    ) -> tuple[Belief, UpdateStats]:
        """The update of a predicted belief with ``y (..., m)``."""
        ...


class TraceFailure(RuntimeError):
    """A compiled execution could not be traced; :attr:`fallback` says which and why."""

    def __init__(self, fallback: Fallback) -> None:
        super().__init__(fallback.reason)
        self.fallback = fallback


def records_grad(inputs: FilterInputs, model: nn.Module) -> bool:
    """Whether autograd records a run of ``inputs`` through ``model``."""
    if not torch.is_grad_enabled():
        return False
    tensors = [inputs.y, inputs.x0, inputs.P0] + ([] if inputs.u is None else [inputs.u])
    tensors += list(model.parameters())
    return any(t.requires_grad for t in tensors)


def _noise_at(noise: Noise, index: Callable[[Tensor], Tensor] | None) -> Noise:
    """``noise`` at one step: each present tensor through ``index`` (its time dimension taken
    at that step), or ``noise`` itself for a constant noise (``index`` None)."""
    if index is None:
        return noise
    return Noise(*(None if v is None else index(v) for v in noise))


def _observed(inp: FilterInputs) -> Tensor:
    return inp.obs.expand(*inp.batch, *inp.obs.shape[-2:])


def _loop_key(inp: FilterInputs) -> tuple[Any, ...]:
    """What a compiled while-loop is traced for: the recording's shapes, dtype and device."""
    u = None if inp.u is None else tuple(inp.u.shape)
    return (tuple(inp.y.shape), u, inp.x0.dtype, inp.x0.device.type)


class Engine:
    """Runs a :class:`Step` as an :class:`~torchfilt.filters.plan.ExecutionPlan` says.

    Args:
        step: the step to run.
        chunk: steps per compiled chunk (``"compiled-chunks"``).
    """

    def __init__(self, step: Step, chunk: int) -> None:
        self.step = step
        self.chunk = chunk
        self._steps: dict[str, StepFunction] = {}
        self._chunks: dict[str, Callable[..., Any]] = {}
        self._loops: dict[str, Callable[..., Any]] = {}
        self._loop_shapes: dict[tuple[Any, ...], list[tuple[tuple[int, ...], torch.dtype]]] = {}
        #: why the while-loop could not be traced, by recording key (shape, dtype, device)
        self.trace_failures: dict[tuple[Any, ...], Fallback] = {}

    def known_fallbacks(self, inputs: FilterInputs) -> tuple[Fallback, ...]:
        """The failures already seen for a recording like ``inputs`` (inputs of the plan)."""
        known = self.trace_failures.get(_loop_key(inputs))
        return () if known is None else (known,)

    # ------------------------------------------------------------------ compiled callables
    def step_function(self, plan: ExecutionPlan, device: torch.device) -> StepFunction:
        """The step, compiled (once per device type) when the plan compiles."""
        if not plan.compiled:
            return self.step.step
        key = f"{device.type}-grad" if plan.records_grad else device.type
        fn = self._steps.get(key)
        if fn is None:
            options = self._step_options(device, plan.records_grad)
            fn = torch.compile(self.step.step, dynamic=False, options=options)
            self._steps[key] = fn
        return fn

    def _step_options(self, device: torch.device, grad: bool) -> dict[str, Any] | None:
        """Inductor's options for a compiled step on ``device`` (forward and backward when
        ``grad``)."""
        if device.type != "cpu":
            return None
        # On the CPU a C++ wrapper around the generated kernels removes most of the per-call
        # Python overhead, which dominates when few sequences are filtered.
        options: dict[str, Any] = {"cpp_wrapper": True}
        model = self.step.model
        if grad and max(model.state_dim, model.obs_dim) <= SMALL_MAX:
            # Under autograd the forward and backward graphs hold many small kernels; vectorising
            # them (SIMD) buys little on matrices this small and costs a third of the cold
            # compile: re-entry's 64 x 100 gradient compiled in 43 s against 63 s, for 0.086 s
            # per call against 0.069 s (scripts/results/cpu-2026-12-03-reentry-compile/).
            options["cpp.simdlen"] = 1
        return options

    def _chunk_function(self, device: torch.device) -> Callable[..., Any]:
        fn = self._chunks.get(device.type)
        if fn is None:
            # the C++ wrapper removes the per-call Python overhead, but calls the library kernels
            # that larger matrices need through a slow proxy (no C shim for cholesky_ex)
            model = self.step.model
            small = max(model.state_dim, model.obs_dim) <= SMALL_MAX
            cpp = device.type == "cpu" and small
            options: dict[str, Any] | None = {"cpp_wrapper": True} if cpp else None
            fn = torch.compile(self._run_chunk, dynamic=False, options=options)
            self._chunks[device.type] = fn
        return fn

    def _loop_function(self, device: torch.device) -> Callable[..., Any]:
        fn = self._loops.get(device.type)
        if fn is None:
            # the C++ wrapper runs the loop itself in C++: no Python between the steps
            options: dict[str, Any] | None = {"cpp_wrapper": True} if device.type == "cpu" else None
            fn = torch.compile(self._run_loop, dynamic=False, fullgraph=True, options=options)
            self._loops[device.type] = fn
        return fn

    # ------------------------------------------------------------------ runs
    def run(
        self, plan: ExecutionPlan, inputs: FilterInputs, keep: Collection[str] | None = None
    ) -> FilterResult:
        """Run ``inputs`` as ``plan`` says into a result (no divergence warning).

        Raises:
            TraceFailure: the plan's compiled while-loop could not be traced (it is recorded in
                :attr:`trace_failures`; plan again with its fallback).
        """
        return _RUNS[plan.execution](self, plan, inputs, keep)

    def scan(
        self,
        plan: ExecutionPlan,
        inputs: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> Records:
        """The step loop of ``plan`` from the prior: one record and one tuple of extra outputs per
        step (into ``sink`` instead, when given), or one record per chunk for a compiled loop."""
        return _SCANS[plan.execution](self, plan, inputs, step_fn, sink)

    def _steps_scan(
        self,
        plan: ExecutionPlan,
        inp: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> Records:
        fn = step_fn if step_fn is not None else self.step_function(plan, inp.y.device)
        with contextlib.ExitStack() as ctx:
            if not plan.compiled:
                ctx.enter_context(small_matrix_kernels(plan.small_kernels))  # type: ignore[arg-type]
            return self._loop(plan, inp, fn, ctx, sink)

    def _loop(
        self,
        plan: ExecutionPlan,
        inp: FilterInputs,
        step_fn: StepFunction,
        ctx: contextlib.ExitStack,
        sink: RecordSink | None = None,
    ) -> Records:
        T = inp.y.shape[-2]
        step = self.step
        belief = step.prior(inp)
        mean = belief.mean
        f, h = step.model.transition, step.model.measurement
        const_Q = None if f.time_varying_noise else step.noise(f, 0, mean)
        const_R = None if h.time_varying_noise else step.noise(h, 0, mean)
        pts = step.points(mean)
        # A compiled step sees tensors of identical shape, dtype, device and strides at every step
        # once the first steps have fixed the strides, so Dynamo's guard checks (~0.1 ms per call)
        # can be skipped from then on, when settings.skip_guard_checks allows it.
        skip = plan.skip_guards and step_fn in self._steps.values()
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for t in range(T):
            if skip and t == _GUARD_WARMUP_STEPS:
                ctx.enter_context(torch.compiler.set_stance(skip_guard_eval_unsafe=True))
            Q = const_Q if const_Q is not None else step.noise(f, t, mean)
            R = const_R if const_R is not None else step.noise(h, t, mean)
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

    def _run_steps(
        self, plan: ExecutionPlan, inp: FilterInputs, keep: Collection[str] | None
    ) -> FilterResult:
        sink = RecordSink(inp.y.shape[-2], keep)
        self._steps_scan(plan, inp, sink=sink)
        return sink.result(_observed(inp), plan.numerics)

    def _run_chunks(
        self, plan: ExecutionPlan, inp: FilterInputs, keep: Collection[str] | None
    ) -> FilterResult:
        records, _ = self._chunked(plan, inp)
        return concat_records(records, _observed(inp), plan.numerics)

    def _run_while(
        self, plan: ExecutionPlan, inp: FilterInputs, keep: Collection[str] | None
    ) -> FilterResult:
        (rec,), _ = self._try_while(plan, inp, keep)
        fields = {k: v for k, v in rec._asdict().items() if k != "log_likelihood"}
        ll = rec.log_likelihood
        return FilterResult(
            **fields,
            observed=_observed(inp),
            log_likelihood=ll.sum(-1) if ll.numel() else ll,
            numerics=plan.numerics,
        )

    # ------------------------------------------------------------------ compiled chunks
    def _run_chunk(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: tuple[Noise, ...],
        R: tuple[Noise, ...],
    ) -> tuple[Belief, StepRecord, tuple[Tensor, ...]]:
        """``K`` steps in one call (the unit a compiled chunk compiles): ``y (..., K, m)``,
        ``obs (..., K, m)``, ``u (..., K, nu)`` or None, the ``K`` steps' noises. Returns the
        belief after them, one record with a time dimension ``K`` and the stacked extras."""
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for k in range(y.shape[-2]):
            ut = None if u is None else u[..., k, :]
            belief, rec, extra = self.step.step(
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

    def _chunked(
        self,
        plan: ExecutionPlan,
        inp: FilterInputs,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> Records:
        """The time loop in compiled chunks of ``self.chunk`` steps; one record per chunk."""
        _no_sink(sink)
        T = inp.y.shape[-2]
        step = self.step
        belief = step.prior(inp)
        mean = belief.mean
        f, h = step.model.transition, step.model.measurement
        const_Q = None if f.time_varying_noise else step.noise(f, 0, mean)
        const_R = None if h.time_varying_noise else step.noise(h, 0, mean)
        pts = step.points(mean)
        fn = self._chunk_function(inp.y.device)
        records: list[StepRecord] = []
        extras: list[tuple[Tensor, ...]] = []
        for t0 in range(0, T, self.chunk):
            t1 = min(T, t0 + self.chunk)
            Q = tuple(
                const_Q if const_Q is not None else step.noise(f, t, mean) for t in range(t0, t1)
            )
            R = tuple(
                const_R if const_R is not None else step.noise(h, t, mean) for t in range(t0, t1)
            )
            u = None if inp.u is None else inp.u[..., t0:t1, :]
            belief, rec, extra = fn(
                pts, belief, inp.y[..., t0:t1, :], inp.obs[..., t0:t1, :], u, Q, R
            )
            records.append(rec)
            extras.append(extra)
        return records, extras

    # ------------------------------------------------------------------ compiled while-loop
    def _run_loop(
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
        """All ``T`` steps as one ``torch.while_loop`` (the unit a compiled loop compiles).

        ``y (..., T, m)``, ``obs (..., T, m)``, ``u (..., T, nu)`` or None; ``Q``, ``R`` carry a
        leading time dimension ``T`` where ``varying`` says so; ``outputs`` are time-major
        buffers ``(T, *shape)``, one per entry of ``select`` (which of the step's outputs, the
        record fields then the extras, they take). Returns the buffers filled.
        """
        T = y.shape[-2]
        sq = self.step.sqrt
        step = self.step.step
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
            post, rec, extra = step(
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

    def _try_while(
        self,
        plan: ExecutionPlan,
        inp: FilterInputs,
        keep: Collection[str] | None = None,
        step_fn: StepFunction | None = None,
        sink: RecordSink | None = None,
    ) -> Records:
        """:meth:`_while`; a step that cannot be traced into one while-loop is recorded in
        :attr:`trace_failures` and raised as a :class:`TraceFailure` (the caller plans again:
        compiled chunks, where a genuine error of the model raises again)."""
        _no_sink(sink)
        try:
            return self._while(inp, keep)
        except RuntimeError as exc:  # Dynamo's "unsupported" errors are RuntimeErrors
            reason = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
            failure = Fallback(plan.execution, reason)
            self.trace_failures[_loop_key(inp)] = failure
            raise TraceFailure(failure) from exc

    def _while(self, inp: FilterInputs, keep: Collection[str] | None = None) -> Records:
        """The whole time loop as one compiled ``torch.while_loop``; one record with a time
        dimension. Only the record fields in ``keep`` (default all) are stored."""
        T = inp.y.shape[-2]
        step = self.step
        belief = step.prior(inp)
        mean = belief.mean
        f, h = step.model.transition, step.model.measurement
        pts = step.points(mean)

        def noise(side: nn.Module) -> tuple[Noise, bool]:
            if not side.time_varying_noise:
                return step.noise(side, 0, mean), False
            per = [step.noise(side, t, mean) for t in range(T)]

            def stacked(i: int) -> Tensor | None:
                vals = [v for p in per if (v := p[i]) is not None]
                return torch.stack(vals) if len(vals) == T else None

            return Noise(stacked(0), stacked(1)), True

        (Q, q_var), (R, r_var) = noise(f), noise(h)
        key = (tuple(inp.y.shape), None if inp.u is None else tuple(inp.u.shape), mean.dtype,
               mean.device, q_var, r_var)  # fmt: skip
        shapes = self._loop_shapes.get(key)
        if shapes is None:  # one eager step tells the outputs' shapes and dtypes
            first = lambda v: v[0]  # noqa: E731
            with torch.no_grad():
                _, rec, extra = step.step(
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


def _no_sink(sink: RecordSink | None) -> None:
    if sink is not None:
        raise InputError("sink: a compiled loop returns chunk records; pass no sink")


def _scan_while(
    engine: Engine,
    plan: ExecutionPlan,
    inp: FilterInputs,
    step_fn: StepFunction | None,
    sink: RecordSink | None,
) -> Records:
    return engine._try_while(plan, inp, None, step_fn, sink)


#: what :meth:`Engine.run` does for each ``plan.execution`` of the cubature family
_RUNS: dict[str, Callable[..., FilterResult]] = {
    "eager": Engine._run_steps,
    "compiled-step": Engine._run_steps,
    "compiled-chunks": Engine._run_chunks,
    "compiled-loop": Engine._run_while,
}
#: what :meth:`Engine.scan` does for each ``plan.execution`` (``"graphed"``: the step loop that
#: :class:`~torchfilt.filters.GraphedFilter` captures)
_SCANS: dict[str, Callable[..., Records]] = {
    "eager": Engine._steps_scan,
    "compiled-step": Engine._steps_scan,
    "graphed": Engine._steps_scan,
    "compiled-chunks": Engine._chunked,
    "compiled-loop": _scan_while,
}
