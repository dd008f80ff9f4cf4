"""The compiled-path tests of the default suite: a tiny linear model on the cubature path,
compile=True (the compiled step) and compile="loop" (one while-loop) equal eager;
tests/filters/test_compile.py and test_compile_loop.py have the slow ones."""

import torch
from linear_support import make_problem, t64

from torchfilt import CKF, LinearGaussianModel

#: compiled kernels reorder floating-point operations (as in tests/filters/test_compile.py)
COMPILE_RTOL = 1e-9


def test_compiled_step_equals_eager_linear():
    p = make_problem(11, n=2, m=1, T=4)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y, u = t64(p["y"]), t64(p["u"])
    eager = CKF(model).filter(y, u, path="cubature", **kw)
    got = CKF(model, compile=True).filter(y, u, path="cubature", **kw)
    assert got.numerics.execution == "compiled-step"
    torch.testing.assert_close(got.mean, eager.mean, rtol=COMPILE_RTOL, atol=1e-12)
    torch.testing.assert_close(got.cov, eager.cov, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(
        got.innovation, eager.innovation, rtol=COMPILE_RTOL, atol=1e-12, equal_nan=True
    )
    torch.testing.assert_close(got.log_likelihood, eager.log_likelihood, rtol=COMPILE_RTOL, atol=0)


def test_compiled_while_loop_equals_eager_linear():
    """compile="loop": the whole time loop as one compiled torch.while_loop, with missing data,
    inputs and ``outputs=`` (only the kept fields are stored)."""
    p = make_problem(12, n=2, m=1, T=5)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y, u = t64(p["y"]), t64(p["u"])
    eager = CKF(model).filter(y, u, path="cubature", **kw)
    filt = CKF(model, compile="loop")
    with torch.no_grad():
        got = filt.filter(y, u, path="cubature", **kw)
    assert got.numerics.execution == "compiled-loop", got.numerics.fallback
    for name in ("mean", "predicted_mean", "innovation", "cross_cov"):
        torch.testing.assert_close(
            getattr(got, name), getattr(eager, name), rtol=COMPILE_RTOL, atol=1e-12, equal_nan=True
        )
    torch.testing.assert_close(got.cov, eager.cov, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, eager.log_likelihood, rtol=COMPILE_RTOL, atol=0)
    with torch.no_grad():
        part = filt.filter(y, u, path="cubature", **kw, outputs=("mean", "log_likelihood"))
    assert part.cov.numel() == 0 and part.numerics.execution == "compiled-loop"
    torch.testing.assert_close(part.mean, eager.mean, rtol=COMPILE_RTOL, atol=1e-12)
