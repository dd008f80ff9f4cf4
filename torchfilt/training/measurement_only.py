"""Learning a state-space model from measurements alone (no logged states).

Two methods, chosen by ``method`` of :func:`fit_measurement_only` (``"both"`` runs both and
keeps the better by held-out likelihood; the default ``"auto"`` runs the second only where EM
stalls: :mod:`torchfilt.training.method_choice`):

``"em"`` (:func:`fit_em`): expectation-maximisation with the cubature RTS smoother.
    *E-step*: the CKF and the RTS smoother give the smoothed moments of every state and of every
    consecutive pair ``(x_{t-1}, x_t)`` (for a linear-Gaussian model the exact Kalman filter and
    RTS smoother of :func:`~torchfilt.filters.kalman_smoother`, batched over the recordings); the pair's cross-covariance is the smoothed lag-one
    covariance ``Cov(x_{t-1}, x_t | y) = G_{t-1} P^s_t`` (``G`` the smoother gain). The prior
    ``N(x0, P0)`` is ``x_{-1}``, and it is smoothed too, so that the first transition is counted.
    *M-step*: for a linear-Gaussian model, the closed form on the expected sufficient statistics
    (``A, B, Q``; the rows of ``H`` outside ``known_channels``; ``R``), which is exact EM: the
    likelihood never decreases (a start for it from the data alone, in the model's gauge:
    :func:`~torchfilt.models.subspace_start`, N4SID). For any other model (a GP transition such as
    :class:`~torchfilt.models.InducingTransition`), a few L-BFGS steps on the *expected
    complete-data log-likelihood*

        Q(theta) = sum_t E_q[log N(x_t; f(x_{t-1}, u_t), Q + V_f)] + sum_t E_q[log N(y_t; h(x_t), R + V_h)]

    with the expectation under the smoothed Gaussian of ``(x_{t-1}, x_t)`` (of ``x_t`` for the
    measurement term) taken by the same cubature rule as the filter (``4 n`` points per pair for
    the third-degree rule), in blocks: the noise covariances, the maps, the noise again (if that
    joint step lowers the filter likelihood, the maps alone, then the noises alone; a partly
    observed step counts with the density of its observed components). We chose this
    deterministic expectation over sampling trajectories from the smoothed posterior because it has no Monte Carlo error, so the EM likelihood trace
    can be checked for monotonicity exactly (up to the Gaussian approximation of the E-step), it
    is reproducible without a generator, and it is the moment matching the filter itself does;
    it still accounts for the smoothed uncertainty of the GP's *inputs* (errors in variables),
    which a fit on smoothed means alone would ignore. A step that lowers ``Q`` is undone
    (generalised EM). Because the E-step of a non-linear model is the CKF's Gaussian
    approximation, a higher ``Q`` does not guarantee a higher likelihood: a step that lowers the
    filter's likelihood is halved until it does not (at most ``backtracks`` times, else undone), so the
    likelihood trace is monotone by construction there; for a linear-Gaussian model it is
    monotone because the EM is exact.

``"likelihood"``: direct maximisation of the CKF's innovation likelihood with
    :func:`~torchfilt.training.fit_likelihood` (windows, burn-in, checkpoints, resume) over every
    learnable parameter of the model; with an :class:`~torchfilt.models.InducingTransition` the
    inducing inputs and inducing outputs play the role of the unknown training targets.

**The gauge.** A state-space model is defined only up to a change of state coordinates
``x -> T x`` (``A -> T A T^{-1}``, ``H -> H T^{-1}``, ``Q -> T Q T^T``): from measurements alone,
every ``T`` fits equally well. Something must pin the coordinates: torchfilt requires the
measurement map of at least one channel to be *known* (``known_channels``: a datasheet sensor
model whose parameters are not learned). Without it the fit wanders along the flat directions of
the likelihood, the learned states have no physical meaning, and state-level metrics (RMSE,
NEES against ground truth) are meaningless; :func:`check_gauge` therefore refuses with a
:class:`~torchfilt.exceptions.GaugeError`. With fewer known channels than states (``m < n``) the
coordinates are pinned only partly: invariants (eigenvalues of ``A``, the transfer function, the
output spectrum, the likelihood) are identified, individual matrix entries need not be.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn

from torchfilt.cubature import CubatureRule, SphericalRadialRule
from torchfilt.exceptions import FitError, InputError, InputTypeError, ModelError
from torchfilt.io import atomic_write
from torchfilt.io.progress import ProgressBar
from torchfilt.models import (
    StateSpaceModel,
)
from torchfilt.optim import (
    CheckpointFile,
    CheckpointOptions,
    FitHooks,
    FitLoop,
    OptimizerOptions,
    Outcome,
    StoppingOptions,
    WindowOptions,
    deprecated_fit_keywords,
    failed_step,
    fingerprint,
    free_parameters,
    resolve_options,
)
from torchfilt.training.data import FitData, as_sequences
from torchfilt.training.em_accel import Squarem
from torchfilt.training.em_steps import (
    SmoothedPairs,
    _EMProblem,
    _Lin,
    _linear_start,
    _Reducer,
    _summed,
    compile_mode,
    smoothed_pairs,
)
from torchfilt.training.gauge import check_gauge
from torchfilt.training.likelihood import (
    LikelihoodFit,
    LikelihoodState,
    _fit_likelihood,
    _recordings,
)
from torchfilt.training.method_choice import fit_both_methods, held_out_scaled, method_checkpoint
from torchfilt.training.noise_scale import NoiseScale, check_holdout, scales_by_default

__all__ = [
    "EMFit",
    "EMState",
    "MeasurementOnlyFit",
    "SmoothedPairs",
    "check_gauge",
    "fit_em",
    "fit_measurement_only",
    "smoothed_pairs",
]

_EM_SCHEMA = "torchfilt.em-checkpoint/1"


class EMState(NamedTuple):
    """What the per-iteration callback of :func:`fit_em` sees.

    Attributes:
        iteration: iterations done (1-based).
        iterations: the budget.
        log_likelihood: the innovation log-likelihood at the parameters after this iteration.
        elapsed: seconds since the fit started (this process).
    """

    iteration: int
    iterations: int
    log_likelihood: float
    elapsed: float


@dataclass
class EMFit:
    """Outcome of :func:`fit_em`.

    Attributes:
        model: the fitted model (the same object as passed in, updated in place, except for a
            linear-Gaussian model, which is returned as a new :class:`LinearGaussianModel`).
        log_likelihood: innovation log-likelihood at the returned parameters.
        initial_log_likelihood: at the initial parameters.
        iterations: EM iterations run.
        stopped: ``"iterations"``, ``"converged"``, ``"callback"`` or ``"no improvement"`` (a
            non-linear M-step lowered the likelihood even after ``backtracks`` halvings).
        measurements: observed measurement components.
        history: one record per iteration: ``iteration``, ``log_likelihood`` (at the parameters
            after that iteration's M-step), ``elapsed``, and with SQUAREM ``e_steps`` (E-steps
            run so far; see ``fit_em``'s ``accelerate``).
        elapsed: seconds of the whole fit.
    """

    model: StateSpaceModel
    log_likelihood: float
    initial_log_likelihood: float
    iterations: int
    stopped: str
    measurements: int
    history: list[dict[str, Any]] = field(default_factory=list)
    elapsed: float = 0.0


@dataclass
class MeasurementOnlyFit:
    """Outcome of :func:`fit_measurement_only`.

    Attributes:
        model: the fitted model. Use it, not the model given to the fit: when the process
            noise is scaled (``noise_scale``), the given model holds the fit before the scale.
        method: ``"em"`` or ``"likelihood"``.
        log_likelihood: innovation log-likelihood of the training data at the returned
            parameters (for ``"likelihood"`` with windows: over the counted steps).
        per_measurement: the same per counted measurement.
        known_channels: the gauge.
        iterations: iterations run.
        stopped: why the loop ended.
        history: per-iteration records of the method.
        elapsed: seconds of the whole fit.
        detail: the method's own result (:class:`EMFit` or :class:`LikelihoodFit`).
        initial_log_likelihood: the training log-likelihood at the parameters the fit started
            from, before any step.
        candidates: records of candidate starts; :func:`fit_measurement_only` fits the one
            model it is given and leaves this empty (a ``states = "none"`` run scores its
            candidate starts itself and records them in the bundle's training record).
        noise_scale: when the noise was scaled (``noise_scale="held-out"``, or ``"auto"``
            where it applies), the held-out choice of the scale of the
            transition variance (:class:`~torchfilt.training.noise_scale.NoiseScale`), which
            ``model`` carries; the record above is the fit's on the data it saw (before the
            scale). ``None`` otherwise.
        compared: with ``method="auto"`` or ``"both"``, one record per method (``method``, ``score``: the
            log-likelihood it was compared by, ``basis``: ``"held-out"``, ``"validation"`` or
            ``"training"``, ``kept``, and its fit's ``log_likelihood``, ``iterations``,
            ``stopped``, ``elapsed``, or the ``error`` it failed with, or why it was
            ``skipped``); empty otherwise.
    """

    model: StateSpaceModel
    method: str
    log_likelihood: float
    per_measurement: float
    known_channels: list[int]
    iterations: int
    stopped: str
    history: list[dict[str, Any]]
    elapsed: float
    detail: EMFit | LikelihoodFit
    initial_log_likelihood: float = math.nan
    candidates: list[dict[str, Any]] = field(default_factory=list)
    noise_scale: NoiseScale | None = None
    compared: list[dict[str, Any]] = field(default_factory=list)


# ----------------------------------------------------------------------------------- EM
@deprecated_fit_keywords("em")
def fit_em(
    model: StateSpaceModel,
    y: FitData,
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    known_channels: Sequence[int] | None,
    fixed: Collection[str] = (),
    iterations: int | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    hooks: FitHooks | None = None,
    progress: bool = False,
    callback: Callable[[EMState], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    rule: CubatureRule | None = None,
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    backtracks: int = 4,
    compile: bool | Literal["step", "loop"] = False,
    accelerate: bool | None = None,
) -> EMFit:
    """Expectation-maximisation with the RTS smoother (exact Kalman for a linear-Gaussian model,
    cubature otherwise; see the module docstring).

    The flat keywords of before (``tol``, ``rtol``, ``rtol_window``, ``checkpoint_every``,
    ``resume``, ``all_reduce``) still work for one release, with a ``DeprecationWarning`` naming
    their new spelling.

    Args:
        model: the model to fit. A :class:`~torchfilt.models.LinearGaussianModel` (or any model
            :func:`~torchfilt.models.linear_system` recognises, with constant noise) gets the
            closed-form M-step on ``A, B, Q``, the rows of ``H`` outside ``known_channels`` and
            ``R``; any other model gets L-BFGS steps on the expected complete-data
            log-likelihood over its parameters with ``requires_grad`` (measurement-map
            parameters of known channels are refused by :func:`check_gauge`), its noise
            covariances in closed form where their map reports no per-point variance
            (:mod:`torchfilt.training.em_noise`).
        y: measurements ``(..., T, m)``, a list of ``(T_i, m)``, a
            :class:`~torchfilt.training.data.Sequences`, or a list of
            :class:`~torchfilt.io.Recording` (row 0 the prior's time; see
            :mod:`torchfilt.training.data`); NaN is missing. The closed-form ``R`` and ``H``
            updates use the steps with every component observed.
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None`` (``None`` when ``y``
            is a ``Sequences`` or recordings, which carry their own).
        x0: prior mean ``(n,)`` or one per recording ``(..., n)`` (fixed; a ``Sequences``' own
            ``x0``, when given, is used instead).
        P0: prior covariance ``(n, n)`` or ``(..., n, n)`` (fixed; likewise).
        known_channels: the gauge: measurement channels whose map is known (at least one).
        fixed: blocks held fixed. For the closed-form M-step the matrices ``"A"``, ``"B"``,
            ``"Q"``, ``"H"``, ``"R"`` (a fixed block keeps its value exactly; the free ones take
            their closed form given it); for the gradient M-step names of
            ``model.named_parameters()``. An unknown name is an ``InputError``.
        iterations: EM iterations (default 100).
        stopping: :class:`~torchfilt.optim.StoppingOptions`: ``tol`` stops when the
            log-likelihood per measurement changes by less than it in an iteration (default
            ``1e-9``); ``rtol``, ``rtol_window`` stop (``"converged"``) when the negative
            log-likelihood per measurement ``L`` moved by at most ``rtol * max(1, |L_k|)`` over
            the last ``rtol_window`` iterations (default ``1e-6`` over 20; 0: off). No
            early stopping on held-out data: a ``patience`` given warns.
        checkpoint: :class:`~torchfilt.optim.CheckpointOptions` or the file's path (atomic,
            every iteration by default); with ``resume=True`` an existing one is continued and
            the result equals an uninterrupted fit.
        hooks: :class:`~torchfilt.optim.FitHooks`; EM uses ``all_reduce`` alone: for a
            data-parallel fit it sums a flat tensor in place across the processes (e.g.
            ``torch.distributed.all_reduce`` with a CPU ``gloo`` group). Each process passes its
            own recordings and runs the E-step on them; the linear M-step sums the expected
            sufficient statistics over the processes (one collective) before the closed form,
            the gradient M-step sums ``Q`` and its gradient at every L-BFGS evaluation (one
            collective each), and the backtracking and stopping decisions use the summed filter
            log-likelihood, so every process takes the same steps and ends with the parameters
            of one EM on all recordings (up to the order of the sums). A callback that stops one
            process stops all. Give each process its own ``checkpoint`` file; each also keeps the
            checkpoint before it, so that after a lost process a resume starts all from the same
            iteration.
        progress: show a progress bar on stderr.
        callback: called after every iteration with an :class:`EMState`; return ``True`` to
            stop.
        dtype: floating dtype (float64 by default).
        rule: cubature rule of the filter and of the M-step expectation (default third degree).
        learn_measurement_noise: update ``R`` (linear) / include the measurement term in the
            M-step (others).
        m_step_iterations: L-BFGS iterations per M-step (non-linear models). A maps block
            that found nothing is left out of the next M-steps, 1, 2, 4, then 8 at a time, and
            tried again (ECM: :data:`~torchfilt.training.em_steps.MAPS_IDLE_SHARE`).
        backtracks: step halvings of a non-linear M-step that lowered the filter likelihood
            before it is undone (0: undone at once) and the next block of the M-step is tried:
            the joint step, then the maps alone, then the noises alone (an iteration where none
            raises the likelihood stops the fit with ``"no improvement"``).
        compile: compile the cubature filter of a non-linear model's E-steps and likelihood
            checks (``torch.compile``, as :class:`~torchfilt.CKF`'s ``compile``): ``"loop"`` (or
            ``True``) compiles its whole time loop, about 10 times faster per run on small
            batches, after a first compile per recording shape (8 s quiet, 38 s loaded on the
            2A -> B reaction, 8 x 400, on the 2-core machine); pays
            once a fit runs more than a few dozen filters (each iteration runs one, plus one per
            step halving). ``"step"`` compiles the step only. A linear-Gaussian model's exact
            E-step is not affected.
        accelerate: SQUAREM (Varadhan & Roland 2008) for the closed-form M-step of a
            linear-Gaussian model: each iteration is one cycle of two EM steps, an
            extrapolation along them (kept only where ``Q`` and ``R`` stay positive
            semi-definite and the likelihood does not drop) and a stabilising EM step, so three
            E-steps (more where the extrapolation is shortened), and it never lowers the
            likelihood (:mod:`torchfilt.training.em_accel`). It climbs further where plain EM has
            a slow tail (the 4-state model of ``scripts/bench_learning.py``: the level
            dynamax's EM ends at in 0.08 to 0.10 s, plain EM in 0.14 s). ``True`` for another
            model: the same cycle over the gradient M-step (:meth:`Squarem.cycle_gradient
            <torchfilt.training.em_accel.Squarem.cycle_gradient>`): three or four M-steps per
            iteration, never worse than two plain ones (on the robot-arm GP of
            ``scripts/bench_real_logs.py`` 30 iterations climbed to 2416.8; 100 plain
            iterations reach 2411.6; both still climbing). ``None``
            (default): on for a linear-Gaussian model, off otherwise; ``False``: plain EM, one
            E-step (one M-step) per iteration.

    Returns:
        An :class:`EMFit` (log-likelihoods and ``measurements`` summed over the processes).

    Raises:
        GaugeError: no gauge.
        InputError: an invalid argument (a ``ShapeError`` for a wrong shape).
        InputTypeError: an argument of the wrong type (such as a complex tensor).
        RunError: a checkpoint of another fit.
        ModelError: time-varying noise.
        FitError: the log-likelihood at the start is not finite, or a step failed (a
            factorisation in the model that failed, a non-finite log-likelihood after an
            M-step); the message names ``fit_em`` and the step (the initial E-step, or the
            iteration and its E-step or M-step). A trial step of a non-linear M-step whose
            filter fails is rejected like one that lowers the likelihood.
    """
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    o = resolve_options(
        "em", iterations=iterations, stopping=stopping, checkpoint=checkpoint, hooks=hooks
    )
    if o.hooks.project is not None or o.hooks.prepare is not None:
        raise InputError("hooks: fit_em uses all_reduce alone (no project or prepare)")
    o.warn_unused_patience("fit_em", "fit_measurement_only(method='likelihood', validation=...)")
    iterations, stop_o, ckpt_o = o.iterations, o.stopping, o.checkpoint
    all_reduce = o.hooks.all_reduce
    tol = stop_o.tolerance("lbfgs")
    if m_step_iterations < 1:
        raise InputError(f"m_step_iterations must be at least 1, got {m_step_iterations}")
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if model.transition.time_varying_noise or model.measurement.time_varying_noise:
        raise ModelError("fit_em: time-varying Q or R cannot be learned; give constant noise")
    model.to(dtype)
    known = check_gauge(model, known_channels)
    rule = SphericalRadialRule() if rule is None else rule
    data = as_sequences(y, u, x0=x0, P0=P0)
    recs = _recordings(model, data.y, data.u, data.x0, data.P0, dtype)
    Y = recs.y
    reduce = None if all_reduce is None else _Reducer(all_reduce)
    # the steps of each recording (a shorter one is NaN-padded: those steps are no transitions)
    valid = torch.arange(Y.shape[-2]).unsqueeze(0) < torch.tensor(recs.lengths).unsqueeze(-1)
    counts = torch.tensor([float(torch.isfinite(Y).sum()), float(len(recs.lengths))])
    counted, recordings = (int(c) for c in _summed(reduce, counts)[0])
    if counted == 0:
        raise InputError("y: no measurement observed")
    lin = _linear_start(model, dtype, known)
    plist = _em_parameters(model, lin, fixed)
    em = _EMProblem(
        model, lin, plist, recs, valid, known, rule, reduce, learn_measurement_noise,
        m_step_iterations, backtracks, frozenset(fixed), compile_mode(compile),
    )  # fmt: skip
    squarem = _accelerator(accelerate, em)
    ckpt = None
    if ckpt_o.path is not None:
        ckpt = CheckpointFile(
            ckpt_o.path, fingerprint(em.Y, em.U, em.X0, em.C0, *em.state()), schema=_EM_SCHEMA,
            kind="EM", write=atomic_write, all_reduce=reduce,
        )  # fmt: skip
    bar = ProgressBar("fit EM", iterations, enabled=progress)
    loop = FitLoop(
        iterations=iterations, progress=bar, callback=callback, all_reduce=reduce,
        rtol=stop_o.rtol, rtol_window=stop_o.rtol_window, atol=stop_o.atol,
        scale=counted / recordings, checkpoint=ckpt, every=int(ckpt_o.every or 1),
    )  # fmt: skip
    initial: float | None = None
    ck = loop.resume() if ckpt_o.resume else None
    if ck is not None:
        em.load(list(ck["state"]))
        initial = float(ck["initial"])
        if squarem is not None and "squarem" in ck:
            squarem.load(ck["squarem"])
        if "ecm" in ck:
            em.ecm_load(ck["ecm"])
    t_start = time.perf_counter()
    ll, sp = _initial_e_step(em)
    if initial is None:
        initial = ll

    def step(it: int) -> Outcome:
        nonlocal ll, sp
        ll_new, sp_new, stalled = _em_iteration(em, it, ll, sp, squarem)
        change = (ll_new - ll) / counted
        ll, sp = ll_new, sp_new
        elapsed = time.perf_counter() - t_start
        done = "no improvement" if stalled else ("converged" if abs(change) <= tol else None)
        record = {"iteration": it, "log_likelihood": ll, "loss": -ll / counted, "elapsed": elapsed}
        if squarem is not None:
            record["e_steps"] = squarem.e_steps
        return Outcome(
            record,
            EMState(it, iterations, ll, elapsed),
            f"loglik/meas {ll / counted:.6g}",
            done,
        )

    def payload() -> dict[str, Any]:
        body: dict[str, Any] = {"state": em.state(), "initial": initial, "ecm": em.ecm_state()}
        if squarem is not None:
            body["squarem"] = squarem.state()
        return body

    stopped = loop.run(step, payload)
    history = loop.history
    return EMFit(
        model=em.current(),
        log_likelihood=ll,
        initial_log_likelihood=initial,
        iterations=len(history),
        stopped=stopped,
        measurements=counted,
        history=history,
        elapsed=time.perf_counter() - t_start,
    )


def _em_parameters(
    model: StateSpaceModel, lin: _Lin | None, fixed: Collection[str]
) -> list[nn.Parameter]:
    """The parameters of a gradient M-step (none for the closed form, whose ``fixed`` names
    are checked against its blocks).

    Raises:
        InputError: a name in ``fixed`` that is no parameter or block.
        InputTypeError: ``fixed`` is a string.
    """
    if lin is None:
        return free_parameters(model, None, fixed, what="model")
    if isinstance(fixed, str):
        raise InputTypeError(f"fixed: expected a collection of names, got {fixed!r}")
    blocks = {"A", "Q", "H", "R"} | ({"B"} if lin.B is not None else set())
    unknown = [name for name in fixed if name not in blocks]
    if unknown:
        raise InputError(
            f"fixed: {unknown[0]!r} is no block of the closed-form M-step of this linear "
            f"model (its blocks: {sorted(blocks)})"
        )
    return []


def _accelerator(accelerate: bool | None, em: _EMProblem) -> Squarem | None:
    """The SQUAREM state of a fit with ``accelerate`` (``None``: on for a linear model, off for
    the gradient M-step).

    Raises:
        InputTypeError: ``accelerate`` is not ``True``, ``False`` or ``None``.
    """
    if accelerate is not None and not isinstance(accelerate, bool):
        raise InputTypeError(f"accelerate: expected True, False or None, got {accelerate!r}")
    if em.lin is None:
        return Squarem() if accelerate else None
    return None if accelerate is False else Squarem()


def _initial_e_step(em: _EMProblem) -> tuple[float, SmoothedPairs]:
    """The E-step at the start of :func:`fit_em`.

    Raises:
        FitError: a factorisation failed, or the log-likelihood is not finite.
    """
    with failed_step("fit_em", "the initial E-step (before iteration 1)"):
        ll, sp = em.e_step()
    if not math.isfinite(ll):
        raise FitError(
            f"fit_em: the initial E-step (before iteration 1): the log-likelihood at the start "
            f"is {ll} (the filter failed on the starting parameters); start from a model whose "
            "filter likelihood is finite on the data (e.g. a linear fit: "
            "InducingTransition.model_from_linear, or smaller inducing outputs and noise closer "
            "to the data)",
            fit="fit_em",
            step="initial E-step",
        )
    return ll, sp


def _em_iteration(
    em: _EMProblem, it: int, ll: float, sp: SmoothedPairs, squarem: Squarem | None = None
) -> tuple[float, SmoothedPairs, bool]:
    """Iteration ``it`` of :func:`fit_em`: the M-step and the E-step after it (a SQUAREM
    cycle with ``squarem``).

    Raises:
        FitError: a factorisation failed, or the log-likelihood after it is not finite.
    """
    with failed_step("fit_em", lambda: f"iteration {it}, {em.phase}"):
        step = em.m_step if squarem is None else partial(squarem.iterate, em)
        ll_new, sp_new, stalled = step(ll, sp)
    if not math.isfinite(ll_new):
        raise FitError(
            f"fit_em: iteration {it}, E-step after the M-step: the log-likelihood is "
            f"{ll_new} (it was {ll:.6g} before the M-step); the M-step's parameters left "
            "the region where the filter is defined",
            fit="fit_em",
            step=f"iteration {it}",
        )
    return ll_new, sp_new, stalled


# ----------------------------------------------------------------------------------- front
@deprecated_fit_keywords("measurement_only")
def fit_measurement_only(
    model: StateSpaceModel,
    y: FitData,
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor,
    P0: Tensor,
    known_channels: Sequence[int] | None,
    fixed: Collection[str] = (),
    validation: FitData | None = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    hooks: FitHooks | None = None,
    progress: bool = False,
    callback: Callable[[EMState | LikelihoodState], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    rule: CubatureRule | None = None,
    method: Literal["auto", "both", "em", "likelihood"] = "auto",
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    accelerate: bool | None = None,
    compile: bool | Literal["step", "loop"] = False,
    noise_scale: Literal["auto", "none", "held-out"] = "auto",
    holdout: float = 0.2,
) -> MeasurementOnlyFit:
    """Learn a state-space model from measurements alone (no states), by EM or by the filter's
    likelihood (see the module docstring).

    The flat keywords of before (``window``, ``burn_in``, ``lr``, ``tol``, ``rtol``,
    ``rtol_window``, ``checkpoint_every``, ``resume``, ``all_reduce``) still work for one
    release, with a ``DeprecationWarning`` naming their new spelling.

    Args:
        model: the model, with the gauge fixed: the maps of ``known_channels`` must not depend on
            learned parameters. For ``"likelihood"`` its learnable parameters are those with
            ``requires_grad`` (a GP transition such as
            :class:`~torchfilt.models.InducingTransition`, learnable ``Q``/``R`` from
            :mod:`torchfilt.models.params`).
        y: measurements ``(..., T, m)``, a list of ``(T_i, m)``, a
            :class:`~torchfilt.training.data.Sequences`, or a list of
            :class:`~torchfilt.io.Recording` (row 0 the prior's time; see
            :mod:`torchfilt.training.data`); NaN is missing.
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None`` (``None`` when ``y``
            is a ``Sequences`` or recordings, which carry their own).
        x0: prior mean ``(n,)`` or ``(..., n)`` (a ``Sequences``' own ``x0``, when given, is
            used instead).
        P0: prior covariance ``(n, n)`` or ``(..., n, n)`` (likewise).
        known_channels: the gauge (see :func:`check_gauge`).
        fixed: the parameters held fixed (see :func:`fit_em` and
            :func:`~torchfilt.training.fit_likelihood`).
        validation: held-out data, of any kind ``y`` accepts: for the likelihood method's
            early stopping, the choice of ``"auto"`` and the noise scale.
        iterations: EM iterations, or optimiser iterations (default 30).
        optimizer: of :func:`~torchfilt.training.fit_likelihood` (``"likelihood"`` only;
            default L-BFGS).
        windows: of :func:`~torchfilt.training.fit_likelihood` (``"likelihood"`` only; default
            whole recordings).
        stopping: :class:`~torchfilt.optim.StoppingOptions` (``tol``: EM per measurement,
            default ``1e-9``; likelihood: that of ``fit_likelihood``).
        checkpoint: :class:`~torchfilt.optim.CheckpointOptions` or the file's path (every
            iteration by default); resuming equals an uninterrupted fit.
        hooks: :class:`~torchfilt.optim.FitHooks`: ``all_reduce`` for a data-parallel fit over
            processes with their own recordings (see :func:`fit_em` and
            :func:`~torchfilt.training.fit_likelihood`).
        progress: show a progress bar.
        callback: per-iteration callback (an :class:`EMState` or a
            :class:`~torchfilt.training.LikelihoodState`); return ``True`` to stop.
        dtype: floating dtype.
        rule: cubature rule.
        method: ``"em"`` (:func:`fit_em`), ``"likelihood"``
            (:func:`~torchfilt.training.fit_likelihood`), ``"both"``: both, each from its own
            copy of ``model`` (left as given), the higher held-out log-likelihood kept, or
            ``"auto"`` (the default): EM, and the likelihood method too (the better kept as
            with ``"both"``) where EM stopped with ``"no improvement"`` or failed
            (:mod:`~torchfilt.training.method_choice`; the result's ``compared``). With
            ``"auto"`` and ``"both"`` a ``checkpoint`` file ``run.pt`` becomes ``run.em.pt``
            and ``run.likelihood.pt``.
        learn_measurement_noise: of :func:`fit_em` (``"em"`` only).
        m_step_iterations: of :func:`fit_em` (``"em"`` only).
        accelerate: of :func:`fit_em` (``"em"`` only): ``True`` runs SQUAREM cycles over the
            gradient M-step of a non-linear model (each iteration three or four M-steps), for
            a slow EM tail; ``None``: on for a linear-Gaussian model only.
        compile: compile the cubature filter (``torch.compile``). ``"em"``: as
            :func:`fit_em`'s ``compile``. ``"likelihood"``: any true value compiles one filter
            step, forward and backward, run at every step (``"step"`` and ``"loop"`` included:
            under autograd the time loop is not compiled). On one 300-step recording of the Van
            der Pol case (``scripts/_oscillator_case.py``) one likelihood + gradient took 0.12 s
            compiled against 0.41 s eager, after a first compile of 32 s on the 2-core
            machine: it pays once a fit runs more than about a hundred filters (an L-BFGS
            iteration runs up to 20). Default ``False``.
        noise_scale: ``"held-out"``: after the fit, scale the transition's variance by the
            largest factor (1 to 64) whose innovation likelihood on held-out data is within
            1.92 nats of the best (:mod:`torchfilt.training.noise_scale`), against a fitted
            ``Q`` that is too small for new data. The data are ``validation`` when given,
            else held out from ``y``: the last ``holdout`` of the recordings, whole, when
            there are at least 5, else the last ``holdout`` of every recording; the fit
            sees the rest (with ``validation``, all of ``y``). Only factors of 1 and up are
            tried: the fitted noise is inflated, never shrunk. The choice is the result's
            ``noise_scale``. ``"auto"`` (the default):
            ``"held-out"`` when there is held-out data to score (``validation``, or at least
            30 held-out steps in all), the model's process noise can be scaled (a
            ``LinearGaussianModel`` with a constant ``Q``, or a plain ``StateSpaceModel``), and
            ``fixed`` holds neither ``"Q"`` nor a ``"transition."`` parameter; else
            ``"none"`` (:func:`~torchfilt.training.noise_scale.scales_by_default`).
            ``"none"``: the model as fitted, on all of ``y``.
        holdout: the fraction of each recording held out when the noise is scaled without
            ``validation`` (default 0.2).

    Returns:
        A :class:`MeasurementOnlyFit`.

    Raises:
        GaugeError: no gauge (see :func:`check_gauge`).
        InputError: an invalid argument.
        FitError: the fit cannot go on: the log-likelihood at the start is not finite, or a
            step failed; the message names the fit (``fit_em``, or
            ``fit_measurement_only(method="likelihood")``) and the step. The likelihood method
            never leaves the finite region: an evaluation that fails (a non-finite value or a
            failed factorisation) is scored ``+inf``, so the line search shortens the step, and
            a step that ends non-finite is undone (:class:`~torchfilt.optim.GuardedStep`).
    """
    if method not in ("auto", "both", "em", "likelihood"):
        raise InputError(f"method must be 'auto', 'both', 'em' or 'likelihood', got {method!r}")
    if method == "likelihood" and accelerate is not None:
        raise InputError("accelerate: of method='em' only (SQUAREM cycles of EM's M-steps)")
    if noise_scale not in ("auto", "none", "held-out"):
        raise InputError(f"noise_scale must be 'auto', 'none' or 'held-out', got {noise_scale!r}")
    check_holdout(holdout)
    mode = compile_mode(compile)  # refuses anything but False, True, "step" or "loop"
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    known = check_gauge(model, known_channels)
    o = resolve_options(
        "measurement_only", iterations=iterations, optimizer=optimizer, windows=windows,
        stopping=stopping, checkpoint=checkpoint, hooks=hooks,
    )  # fmt: skip
    if method in ("auto", "both"):

        def one(m: str, start: StateSpaceModel, fy: FitData) -> MeasurementOnlyFit:
            return fit_measurement_only(
                start, fy, None, x0=x0, P0=P0, known_channels=known, fixed=fixed,
                validation=validation, iterations=iterations, optimizer=optimizer,
                windows=windows, stopping=stopping, checkpoint=method_checkpoint(o.checkpoint, m),
                hooks=hooks, progress=progress, callback=callback, dtype=dtype, rule=rule,
                method=m, learn_measurement_noise=learn_measurement_noise,  # type: ignore[arg-type]
                m_step_iterations=m_step_iterations, accelerate=accelerate if m == "em" else None,
                compile=compile, noise_scale="none",
            )  # fmt: skip

        return fit_both_methods(
            one, model, as_sequences(y, u, x0=x0, P0=P0), validation, holdout, noise_scale,
            always=method == "both", fixed=tuple(fixed), dtype=dtype, rule=rule,
            all_reduce=o.hooks.all_reduce,
        )  # fmt: skip
    if noise_scale != "none":
        data = as_sequences(y, u, x0=x0, P0=P0)
        if noise_scale == "held-out" or scales_by_default(
            model, data, holdout, validation=validation is not None, fixed=fixed,
            all_reduce=o.hooks.all_reduce,
        ):  # fmt: skip

            def fit(fy: FitData) -> MeasurementOnlyFit:
                return fit_measurement_only(
                    model, fy, None, x0=x0, P0=P0, known_channels=known, fixed=fixed,
                    validation=validation, iterations=iterations, optimizer=optimizer,
                    windows=windows, stopping=stopping, checkpoint=checkpoint, hooks=hooks,
                    progress=progress, callback=callback, dtype=dtype, rule=rule,
                    method=method, learn_measurement_noise=learn_measurement_noise,
                    m_step_iterations=m_step_iterations, accelerate=accelerate, compile=compile,
                    noise_scale="none",
                )  # fmt: skip

            return held_out_scaled(
                fit, model, data, validation, holdout,
                dtype=dtype, rule=rule, all_reduce=o.hooks.all_reduce,
            )  # fmt: skip
    if method == "em":
        em = fit_em(
            model, y, u, x0=x0, P0=P0, known_channels=known, fixed=fixed,
            iterations=o.iterations, stopping=stopping, checkpoint=o.checkpoint, hooks=hooks,
            progress=progress, callback=callback, dtype=dtype, rule=rule,
            learn_measurement_noise=learn_measurement_noise, m_step_iterations=m_step_iterations,
            compile=mode, accelerate=accelerate,
        )  # fmt: skip
        return MeasurementOnlyFit(
            model=em.model,
            method="em",
            log_likelihood=em.log_likelihood,
            per_measurement=em.log_likelihood / em.measurements,
            known_channels=known,
            iterations=em.iterations,
            stopped=em.stopped,
            history=em.history,
            elapsed=em.elapsed,
            detail=em,
            initial_log_likelihood=em.initial_log_likelihood,
        )
    name = 'fit_measurement_only(method="likelihood")'
    with failed_step(name, "the likelihood fit"):
        lf = _fit_likelihood(
            model, y, u, x0=x0, P0=P0, parameters=None, fixed=fixed, validation=validation,
            options=o, progress=progress, callback=callback, dtype=dtype, sqrt=False, rule=rule,
            compile=mode is not False,
        )  # fmt: skip
    _check_likelihood_fit(lf, name)
    return MeasurementOnlyFit(
        model=model,
        method="likelihood",
        log_likelihood=lf.log_likelihood,
        per_measurement=lf.per_measurement,
        known_channels=known,
        iterations=lf.iterations,
        stopped=lf.stopped,
        history=lf.history,
        elapsed=lf.elapsed,
        detail=lf,
        initial_log_likelihood=lf.initial_log_likelihood,
    )


def _check_likelihood_fit(lf: LikelihoodFit, name: str) -> None:
    """Refuse a likelihood fit whose start or result is not finite, naming the step.

    Raises:
        FitError: the log-likelihood at the start, or at the returned parameters, is not finite.
    """
    if not math.isfinite(lf.initial_log_likelihood):
        raise FitError(
            f"{name}: the start (the log-likelihood before iteration 1) is "
            f"{lf.initial_log_likelihood}: the filter fails on the starting parameters; start "
            "from a model whose filter likelihood is finite on the data (e.g. a linear fit: "
            "InducingTransition.model_from_linear, or smaller inducing outputs and noise closer "
            "to the data)",
            fit=name,
            step="start",
        )
    if not math.isfinite(lf.log_likelihood):
        it = lf.iterations + (1 if lf.stopped == "non-finite" else 0)
        raise FitError(
            f"{name}: iteration {it}, the likelihood evaluation of the optimiser's step: the "
            f"log-likelihood is {lf.log_likelihood} (it was {lf.initial_log_likelihood:.6g} at "
            "the start)",
            fit=name,
            step=f"iteration {it}",
        )
