"""The execution plan (torchfilt.filters.plan): one pure decision of the path a run takes, what
the result records, fallbacks as inputs of the plan (never state left on a filter), the engine
names that are no longer public, and the online API's errors (issue 24 item 2)."""

import math

import pytest
import torch
from linear_support import make_problem, t64

from torchfilt import CKF, ConstrainedCKF, LinearGaussianModel
from torchfilt.exceptions import InputError, InputTypeError, ModelError
from torchfilt.filters import GaussianFilter, kalman_filter
from torchfilt.filters.plan import Fallback, LinearFacts, PlanOptions, PlanSettings, plan
from torchfilt.systems import reaction

CPU = torch.device("cpu")
SETTINGS = PlanSettings()


def _linear(p):
    return LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))


def _plan(model, options, **kw):
    kw.setdefault("batch", torch.Size([3]))
    kw.setdefault("records_grad", False)
    return plan(model, options, device=CPU, settings=SETTINGS, **kw)


def test_plan_is_pure_and_decides_every_cubature_execution():
    model = _linear(make_problem(0))
    loop = PlanOptions("loop", state_dim=3, obs_dim=2)
    assert _plan(model, loop) == _plan(model, loop)
    assert _plan(model, PlanOptions(state_dim=3, obs_dim=2)).execution == "eager"
    assert _plan(model, PlanOptions("auto")).execution == "compiled-step"
    assert _plan(model, PlanOptions("step")).execution == "compiled-step"
    assert _plan(model, loop).execution == "compiled-loop"
    grad = _plan(model, loop, records_grad=True)
    assert grad.execution == "compiled-chunks" and "autograd" in grad.fallback
    failed = _plan(model, loop, fallbacks=(Fallback("compiled-loop", "Unsupported: x"),))
    assert failed.execution == "compiled-chunks"
    assert failed.numerics.fallback == "compiled-loop: Unsupported: x"
    cuda = torch.device("cuda")
    graphed = plan(model, PlanOptions(), batch=torch.Size([3]), records_grad=False, device=cuda,
                   settings=SETTINGS, graphed=True)  # fmt: skip
    assert graphed.execution == "graphed" and graphed.on_failure == "nan"
    with pytest.raises(InputError, match="CUDA device"):
        _plan(model, PlanOptions(), graphed=True)


def test_plan_resolves_kernels_and_failure_mode_from_the_settings():
    model = _linear(make_problem(0))
    opts = PlanOptions(state_dim=3, obs_dim=2)
    assert _plan(model, opts).small_kernels == "library"
    assert _plan(model, opts, batch=torch.Size([64])).small_kernels == "unrolled"
    lib = plan(model, opts, batch=torch.Size([64]), records_grad=False, device=CPU,
               settings=PlanSettings(small_kernels="library"))  # fmt: skip
    assert lib.small_kernels == "library"
    free = plan(model, opts, batch=torch.Size([3]), records_grad=False, device=CPU,
                settings=PlanSettings(sync_free=True))  # fmt: skip
    assert free.on_failure == "nan"
    assert _plan(model, PlanOptions("step", state_dim=3, obs_dim=2)).small_kernels == "unrolled"


def test_plan_chooses_the_exact_runner():
    model = _linear(make_problem(0))
    opts = PlanOptions(state_dim=3, obs_dim=2)
    shared = LinearFacts(1, 0)
    assert _plan(model, opts, path="auto", linear=shared).execution == "kalman-riccati"
    assert _plan(model, opts, path="auto", linear=LinearFacts(None, 0)).execution == "kalman-fast"
    assert _plan(model, opts, path="auto", linear=shared, records_grad=True).execution == (
        "kalman-fast"
    )
    sqrt = PlanOptions(sqrt=True, state_dim=3, obs_dim=2)
    assert _plan(model, sqrt, path="auto", linear=shared).execution == "kalman-sequential"
    after = _plan(model, opts, path="auto", linear=shared,
                  fallbacks=(Fallback("kalman-riccati", "a covariance failed to factor"),))  # fmt: skip
    assert after.execution == "kalman-fast" and "kalman-riccati" in after.fallback
    assert _plan(model, opts, path="auto", parallel=True).execution == "kalman-parallel"
    assert _plan(model, opts, path="cubature").family == "cubature"
    with pytest.raises(InputError, match="path must be"):
        _plan(model, opts, path="fast")


def test_plan_takes_the_adjoint_for_a_recorded_likelihood_only():
    """The closed-form gradient serves a recorded run that keeps only the log-likelihood, in the
    plain form, where the host may synchronise, and not once it has failed for the run."""
    model = _linear(make_problem(0))
    opts = PlanOptions(state_dim=3, obs_dim=2)
    only = LinearFacts(1, 0, likelihood_only=True)
    adj = _plan(model, opts, path="auto", linear=only, records_grad=True)
    assert adj.execution == "kalman-adjoint" and adj.adjoint and adj.records_grad
    assert _plan(model, opts, path="auto", linear=only).execution == "kalman-riccati"
    more = LinearFacts(1, 0, likelihood_only=False)
    assert _plan(model, opts, path="auto", linear=more, records_grad=True).execution == (
        "kalman-fast"
    )
    sqrt = PlanOptions(sqrt=True, state_dim=3, obs_dim=2)
    assert _plan(model, sqrt, path="auto", linear=only, records_grad=True).execution == (
        "kalman-sequential"
    )
    traced = plan(model, opts, batch=torch.Size([3]), records_grad=True, device=CPU,
                  settings=PlanSettings(sync_free=True), path="auto", linear=only)  # fmt: skip
    assert traced.execution == "kalman-fast"
    why = Fallback("kalman-adjoint", "a second derivative needs the recorded graph")
    after = _plan(model, opts, path="auto", linear=only, records_grad=True, fallbacks=(why,))
    assert after.execution == "kalman-fast" and not after.adjoint
    assert after.numerics.fallback == "kalman-adjoint: a second derivative needs the recorded graph"


def test_results_record_the_plan():
    p = make_problem(1)
    model = _linear(p)
    args, kw = (t64(p["y"]), t64(p["u"])), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    res = CKF(model).filter(*args, **kw, path="cubature")
    want = _plan(model, PlanOptions(state_dim=3, obs_dim=2), batch=torch.Size([]))
    assert res.numerics == want.numerics
    exact = kalman_filter(model, *args, **kw)
    assert exact.numerics.execution in ("kalman-fast", "kalman-riccati", "kalman-sequential")
    sq = kalman_filter(model, *args, **kw, sqrt=True)
    assert sq.numerics.execution == "kalman-sequential"
    par = kalman_filter(model, *args, **kw, parallel=True)
    assert par.numerics.execution == "kalman-parallel"


def test_graphed_refusal_is_the_plans_and_names_the_reason():
    filt = ConstrainedCKF(reaction.model(), lower=[0.0, 0.0], upper=[100.0, 100.0])
    opts = filt._options
    with pytest.raises(ModelError, match="NDDR solver decides on the host"):
        _plan(reaction.model(), opts, graphed=True)
    assert _plan(reaction.model(), opts).refused is not None
    compiled = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0], compile=True)
    assert _plan(reaction.model(), compiled._options).execution == "compiled-step"


def test_no_engine_names_on_the_filter():
    for name in ("run_chunk", "run_loop", "numerics_path", "small_kernels"):
        assert not hasattr(GaussianFilter, name), name


def _deprecated_calls():
    p = make_problem(2)
    filt = CKF(_linear(p))
    y, u, kw = t64(p["y"]), t64(p["u"]), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    inputs = filt._prepare(y, u, **kw)
    T = p["y"].shape[0]
    return {
        "prepare": (lambda: filt.prepare(y, u, **kw), lambda v: v.batch == inputs.batch),
        "run": (lambda: filt.run(inputs), lambda v: v.numerics.execution == "eager"),
        "scan": (lambda: filt.scan(inputs), lambda v: len(v[0]) == T),
        "step_function": (lambda: filt.step_function(CPU), lambda v: v == filt._step.step),
        "execution": (lambda: filt.execution(torch.Size([4])), lambda v: v == "eager"),
        "loop_fallback": (lambda: filt.loop_fallback, lambda v: v is None),
    }


@pytest.mark.parametrize(
    "name", ["prepare", "run", "scan", "step_function", "execution", "loop_fallback"]
)
def test_deprecated_engine_names_warn_and_still_work(name):
    call, check = _deprecated_calls()[name]
    with pytest.deprecated_call(match=f"GaussianFilter.{name} is deprecated"):
        value = call()
    assert check(value)


def test_a_known_trace_failure_is_keyed_by_shape_and_visible():
    """A while-loop that failed to trace for one recording shape is an input of the next plans
    for that shape only, and each such result says why."""
    p = make_problem(3)
    filt = CKF(_linear(p), compile="loop")
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y = t64(p["y"])
    inputs = filt._prepare(y, **kw)
    other = filt._prepare(y[:-1], **kw)
    key = next(iter(_keys(filt, inputs)))
    filt._engine.trace_failures[key] = Fallback("compiled-loop", "Unsupported: test")
    assert filt._plan(inputs, filt._engine.known_fallbacks(inputs)).execution == "compiled-chunks"
    assert filt._plan(other, filt._engine.known_fallbacks(other)).execution == "compiled-loop"


def _keys(filt, inputs):
    from torchfilt.filters.engine import _loop_key

    return {_loop_key(inputs)}


def test_online_errors_name_the_argument():
    p = make_problem(4)
    filt = CKF(LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"])))
    P0 = t64(p["P0"])
    with pytest.raises(InputTypeError, match="x0 must be floating point"):
        filt.init(torch.zeros(3, dtype=torch.long), P0)
    with pytest.raises(InputTypeError, match="x0"):
        filt.init(object(), P0)  # type: ignore[arg-type]
    state = filt.predict(filt.init(t64(p["m0"]), P0))
    with pytest.raises(InputTypeError, match="y must be floating point"):
        filt.update(state, torch.zeros(2, dtype=torch.long))
    with pytest.raises(InputTypeError, match=r"y must be a torch\.Tensor"):
        filt.update(state, [0.0, 0.0])  # type: ignore[arg-type]
    with pytest.raises(InputTypeError, match=r"y must be a torch\.Tensor"):
        filt.update(state, 3)  # type: ignore[arg-type]
    start = filt.init(t64(p["m0"]), P0)
    with pytest.raises(InputError, match="u contains non-finite"):
        filt.predict(start, torch.tensor([math.nan], dtype=torch.float64))
    with pytest.raises(InputTypeError, match="u must be floating point"):
        filt.predict(start, torch.tensor([1]))


def _constrained_problem():
    sim = reaction.simulate_truth(runs=2, seed=1)
    y = sim.measurements[:, :8].clone()
    y[:, 3] = float("nan")
    return y, dict(x0=reaction.prior_mean(), P0=reaction.prior_cov())


def test_constrained_online_equals_eager():
    """The constrained step run online (predict / update one measurement at a time) through the
    façade's online API equals the whole-recording eager run to 1e-12 in float64."""
    y, kw = _constrained_problem()
    filt = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0])
    want = filt.filter(y, **kw)
    state = filt.init(kw["x0"], kw["P0"])
    means, covs = [], []
    for t in range(y.shape[-2]):
        state, _ = filt.update(filt.predict(state), y[..., t, :])
        means.append(state.mean)
        covs.append(state.cov)
    torch.testing.assert_close(torch.stack(means, -2), want.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(torch.stack(covs, -3), want.cov, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_constrained_compiled_equals_eager_tightly():
    """The constrained step compiled by the common engine (one compiled call per step, as the
    plan says) equals the eager run to 1e-12 in float64."""
    y, kw = _constrained_problem()
    eager = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0]).filter(y, **kw)
    filt = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0], compile=True)
    got = filt.filter(y, **kw)
    assert got.numerics.execution == "compiled-step"
    torch.testing.assert_close(got.mean, eager.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.cov, eager.cov, rtol=1e-12, atol=1e-12)


def test_constrained_filter_keeps_the_parents_contract():
    """ConstrainedCKF.filter / smooth take the CKF's arguments: ``outputs=`` selects fields,
    ``path="kalman"`` and ``parallel=True`` are refused (no exact path for a boxed step), and
    ``path="auto"`` runs the constrained step even for a linear model."""
    y, kw = _constrained_problem()
    filt = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0])
    full = filt.filter(y, **kw)
    part = filt.filter(y, **kw, outputs=("mean", "log_likelihood"))
    assert torch.equal(part.mean, full.mean) and part.cov.numel() == 0
    for bad in (dict(path="kalman"), dict(parallel=True)):
        with pytest.raises(ModelError, match="no closed-form Kalman counterpart"):
            filt.filter(y, **kw, **bad)
        with pytest.raises(ModelError, match="no closed-form Kalman counterpart"):
            filt.smooth(y, **kw, **bad)
    p = make_problem(5, missing=0.0)
    lin = ConstrainedCKF(_linear(p), -1e6, 1e6)
    res = lin.filter(t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]))
    assert res.numerics.execution == "eager" and res.path == "cubature"
