"""Hypothesis suites over the online API and the exact path in float32 (issue 24, item 10).

Online: ``init`` / ``predict`` / ``update`` on random linear-Gaussian problems, valid or with one
argument corrupted (half precision, integers, inputs for a model without any or of the wrong
width, a non-finite input, a prior of the wrong shape or indefinite, measurements of the wrong
width). A corrupted case must be refused with a TorchfiltError that names the corrupted argument;
a valid one must equal the closed-form float64 Kalman filter of tests/reference.py step by step.

Exact path in float32: 10^4 steps of a poorly observable constant-acceleration model, the
float64 run of the same data the reference. Each case is one of: a TorchfiltError naming an
argument; a DivergenceWarning (PrecisionWarning) where the float64 reference says the float32
run is wrong; a result equal to the float64 reference within float32 tolerance. Anything else
(wrong and silent) fails. See tests/fuzz_support.py for the contract and the counts.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from fuzz_support import STATS, Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st
from reference import kalman_filter

from torchfilt import CKF, LinearGaussianModel
from torchfilt.exceptions import DivergenceWarning

D = torch.float64
REF_RTOL, REF_ATOL = 1e-6, 1e-8

#: the corruption of an online case, and the argument its refusal must name
CORRUPTIONS = {
    "none": None,
    "y float16": "y",
    "y bfloat16": "y",
    "y int64": "y",
    "y wrong width": "y",
    "u without inputs": "u",
    "u wrong width": "u",
    "u non-finite": "u",
    "u float16": "u",
    "x0 wrong shape": "x0",
    "x0 float16": "x0",
    "P0 indefinite": "P0",
    "P0 float16": "P0",
}


def _spd(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    S = (q * np.exp(rng.uniform(np.log(lo), np.log(hi), n))) @ q.T
    return 0.5 * (S + S.T)


def _run_online(filt: CKF, y: torch.Tensor, u: torch.Tensor | None, x0, P0):
    """The online filter over ``y (T, m)``: filtered means and covariances per step."""
    state = filt.init(x0, P0)
    means, covs = [], []
    for t in range(y.shape[0]):
        state = filt.predict(state, None if u is None else u[t])
        state, _ = filt.update(state, y[t])
        means.append(state.mean)
        covs.append(state.cov)
    return torch.stack(means), torch.stack(covs)


def check_online(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 3), label="n")
    m = data.draw(st.integers(1, 2), label="m")
    T = data.draw(st.integers(1, 5), label="T")
    nu = data.draw(st.sampled_from([0, 1, 2]), label="nu")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    scale = 10.0 ** data.draw(st.integers(-2, 2), label="log10 scale")
    corruption = data.draw(st.sampled_from(sorted(CORRUPTIONS)), label="corruption")
    A, H = rng.uniform(-1.2, 1.2, (n, n)), rng.uniform(-2.0, 2.0, (m, n))
    Q, R = _spd(rng, n, 1e-2, 1.0) * scale**2, _spd(rng, m, 1e-2, 1.0) * scale**2
    P0, x0 = _spd(rng, n, 1e-1, 10.0) * scale**2, rng.standard_normal(n) * scale
    Bm = rng.uniform(-1.0, 1.0, (n, nu)) if nu else None
    u = rng.standard_normal((T, nu)) * scale if nu else None
    y = rng.standard_normal((T, m)) * scale * 3.0
    y[rng.uniform(size=(T, m)) < 0.2] = np.nan
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    model = LinearGaussianModel(t(A), t(H), t(Q), t(R), B=None if Bm is None else t(Bm))
    args = {"y": t(y), "u": None if u is None else t(u), "x0": t(x0), "P0": t(P0)}
    what = CORRUPTIONS[corruption]
    if corruption.startswith("u") and (corruption == "u without inputs") != (nu == 0):
        corruption, what = "none", None  # the corruption does not apply to this model
    if corruption == "y float16":
        args["y"] = args["y"].half()
    elif corruption == "y bfloat16":
        args["y"] = args["y"].bfloat16()
    elif corruption == "y int64":
        args["y"] = torch.zeros(T, m, dtype=torch.int64)
    elif corruption == "y wrong width":
        args["y"] = torch.zeros(T, m + 1, dtype=D)
    elif corruption == "u without inputs":
        args["u"] = torch.ones(T, data.draw(st.integers(1, 3), label="u width"), dtype=D)
    elif corruption == "u wrong width":
        args["u"] = torch.ones(T, nu + 1, dtype=D)
    elif corruption == "u non-finite":
        args["u"] = args["u"].clone()
        args["u"][-1, 0] = math.nan
    elif corruption == "u float16":
        args["u"] = args["u"].half()
    elif corruption == "x0 wrong shape":
        args["x0"] = torch.zeros(n + 1, dtype=D)
    elif corruption == "x0 float16":
        args["x0"] = args["x0"].half()
    elif corruption == "P0 indefinite":
        args["P0"] = -args["P0"]
    elif corruption == "P0 float16":
        args["P0"] = args["P0"].half()
    res, _ = attempt(
        "online init/predict/update", _run_online, CKF(model), args["y"], args["u"],
        args["x0"], args["P0"],
    )  # fmt: skip
    if what is not None:
        assert isinstance(res, Refused), f"{corruption}: not refused, returned"
        assert what in str(res.error).split(":")[0] or str(res.error).startswith(what), (
            f"{corruption}: the refusal does not name {what}: {res.error}"
        )
        return
    assert not isinstance(res, Refused), f"a valid problem was refused: {res}"
    ms, Ps, *_ = kalman_filter(A, H, Q, R, y, x0, P0, B=Bm, u=u)
    got_m, got_P = res
    np.testing.assert_allclose(got_m.numpy(), ms, rtol=REF_RTOL, atol=REF_ATOL * scale)
    np.testing.assert_allclose(got_P.numpy(), Ps, rtol=REF_RTOL, atol=REF_ATOL * scale**2)


test_fuzz_online, test_fuzz_online_long = property_tests(check_online, short=25, long=600)


# ------------------------------------------------------------- the exact path in float32
T32, B32 = 10_000, 8
_A = torch.tensor([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], dtype=D)
_H = torch.tensor([[1.0, 0.0, 0.0]], dtype=D)
_G = torch.tensor([[1 / 6], [0.5], [1.0]], dtype=D)


def _filter(q: float, r: float, y: torch.Tensor, dtype: torch.dtype, sqrt: bool):
    model = LinearGaussianModel(
        _A.to(dtype), _H.to(dtype), (q * _G @ _G.T).to(dtype), (r * torch.eye(1, dtype=D)).to(dtype)
    )
    x0, P0 = torch.zeros(B32, 3, dtype=dtype), 10.0 * torch.eye(3, dtype=dtype)
    return attempt(
        f"exact path {str(dtype).removeprefix('torch.')}",
        CKF(model, sqrt=sqrt).filter, y.to(dtype), x0=x0, P0=P0, path="kalman",
    )  # fmt: skip


def check_float32_exact(data: st.DataObject) -> None:
    q = 10.0 ** data.draw(st.integers(-8, -1), label="log10 q")
    r = 10.0 ** data.draw(st.integers(-2, 2), label="log10 r")
    sqrt = data.draw(st.booleans(), label="sqrt")
    kind = data.draw(st.sampled_from(["simulated", "zero-mean"]), label="data")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), label="seed"))
    v = torch.randn(B32, T32, 1, generator=g, dtype=D) * r**0.5
    if kind == "simulated":
        w = torch.randn(T32, B32, 1, generator=g, dtype=D) * q**0.5 @ _G.T  # (T, B, 3)
        x, xs = torch.zeros(B32, 3, dtype=D), []
        for t in range(T32):
            x = x @ _A.T + w[t]
            xs.append(x)
        y = torch.stack(xs, -2) @ _H.T + v
    else:
        y = v
    ref, warned64 = _filter(q, r, y, D, sqrt)
    assert not isinstance(ref, Refused), f"float64 refused: {ref}"
    assert not warned64, [str(w.message) for w in warned64]
    res, warned = _filter(q, r, y, torch.float32, sqrt)
    assert not isinstance(res, Refused), f"float32 refused: {res}"
    e = (res.mean.double() - ref.mean).unsqueeze(-1)
    P = ref.cov.expand(*ref.mean.shape, 3)
    nees = float((e.mT @ torch.linalg.solve(P, e)).mean())
    ratio = res.cov.double().diagonal(dim1=-2, dim2=-1) / ref.cov.diagonal(dim1=-2, dim2=-1)
    lo, hi = float(ratio.min()), float(ratio.max())
    wrong = not (nees <= 1.0 and 0.5 <= lo and hi <= 2.0)
    equal = nees <= 0.05 and 0.95 <= lo and hi <= 1.05
    diverged = any(issubclass(w.category, DivergenceWarning) for w in warned)
    outcome = (
        "warned, wrong" if diverged and wrong else
        "warned, not wrong" if diverged else
        "equal" if equal else
        "silent, wrong" if wrong else "silent, off by less than its uncertainty"
    )  # fmt: skip
    STATS["exact path float32 vs float64"][outcome] += 1
    assert outcome != "silent, wrong", (
        f"float32 silently wrong: NEES vs float64 {nees:.3g}, variance ratio [{lo:.3g}, {hi:.3g}]"
    )
    assert outcome != "silent, off by less than its uncertainty", (nees, lo, hi)


test_fuzz_float32_exact, test_fuzz_float32_exact_long = property_tests(
    check_float32_exact, short=2, long=12
)


def teardown_module() -> None:
    print_stats()
