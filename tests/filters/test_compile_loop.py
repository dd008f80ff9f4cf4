"""Slow: every compiled path equals eager (per-step compile, the while-loop, the chunked loop with
a ragged last chunk where the while-loop cannot run, time-varying noise, the square-root form)."""

import pytest
import torch
from linear_support import make_problem, t64

from torchfilt import CKF, LinearGaussianModel
from torchfilt.models import TimeVarying

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def _fresh_compiler():
    """Each test compiles from scratch: a while-loop trace that failed (the graph-break test)
    otherwise leaves Dynamo state that makes the next trace warn about ``.grad`` of a non-leaf
    tensor, which this suite turns into an error."""
    torch.compiler.reset()
    yield
    torch.compiler.reset()


#: compiled kernels reorder floating-point operations (as in tests/filters/test_compile.py)
COMPILE_RTOL = 1e-9


@pytest.mark.parametrize(
    "opts",
    [
        {"compile": "step"},
        {"compile": "loop"},
        {"compile": "loop", "sqrt": True},
    ],
    ids=["step", "loop", "loop-sqrt"],
)
def test_compiled_paths_equal_eager_time_varying(opts):
    p = make_problem(12, n=2, m=1, T=7)
    Qt = torch.stack([t64(p["Q"]) * (1 + 0.2 * k) for k in range(7)])
    model = LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), TimeVarying(Qt), t64(p["R"]), B=t64(p["B"])
    )
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y, u = t64(p["y"]), t64(p["u"])
    sqrt = opts.get("sqrt", False)
    eager = CKF(model, sqrt=sqrt).filter(y, u, path="cubature", **kw)
    got = CKF(model, **opts).filter(y, u, path="cubature", **kw)
    assert got.numerics.execution == (
        "compiled-step" if opts["compile"] == "step" else "compiled-loop"
    )
    torch.testing.assert_close(got.mean, eager.mean, rtol=COMPILE_RTOL, atol=1e-12)
    torch.testing.assert_close(got.cov, eager.cov, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, eager.log_likelihood, rtol=COMPILE_RTOL, atol=0)


def test_model_with_a_graph_break_compiles_in_chunks():
    """A model that Dynamo cannot capture whole (here an explicit graph break) cannot run as one
    while-loop: the chunked loop compiles instead (in pieces), with the same result, and the
    result and the filter say so."""
    p = make_problem(13, n=2, m=1, T=5)
    A = t64(p["A"])

    def f(x):
        torch._dynamo.graph_break()
        return x @ A.mT

    from torchfilt import StateSpaceModel

    model = StateSpaceModel(f, lambda x: x[..., :1], Q=t64(p["Q"]), R=t64(p["R"])[:1, :1])
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y = t64(p["y"])[:, :1]
    eager = CKF(model).filter(y, **kw)
    filt = CKF(model, compile="loop", chunk=2)
    got = filt.filter(y, **kw)
    assert got.numerics.execution == "compiled-chunks"
    assert got.numerics.fallback is not None  # why the while-loop was left, for this run
    again = filt.filter(y, **kw)  # the failure is a keyed input of the next plan: no retrace
    assert again.numerics == got.numerics and len(filt._engine.trace_failures) == 1
    torch.testing.assert_close(got.mean, eager.mean, rtol=COMPILE_RTOL, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, eager.log_likelihood, rtol=COMPILE_RTOL, atol=0)


@pytest.mark.parametrize(
    ("compile", "execution"), [("loop", "compiled-chunks"), ("step", "compiled-step")]
)
def test_gradient_through_the_compiled_filter_equals_eager(compile, execution):
    """Likelihood training differentiates through the filter: under autograd ``compile="loop"``
    runs compiled chunks (the while-loop has no backward here), and ``compile="step"`` one step
    compiled forward and backward (without SIMD for small models); both gradients are eager's."""
    p = make_problem(11, n=2, m=1, T=4)

    def grad(compile):
        A = t64(p["A"]).requires_grad_()
        model = LinearGaussianModel(A, t64(p["H"]), t64(p["Q"]), t64(p["R"]))
        res = CKF(model, compile=compile).filter(
            t64(p["y"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
        )
        res.log_likelihood.backward()
        return A.grad, res.numerics.execution

    want, _ = grad(False)
    got, how = grad(compile)
    assert how == execution
    torch.testing.assert_close(got, want, rtol=COMPILE_RTOL, atol=1e-12)
