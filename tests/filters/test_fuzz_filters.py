"""Hypothesis suite over the filtering entry points (issue 12).

CKF.filter / CKF.smooth on models built from LinearGaussianModel and from StateSpaceModel
callables (correct ones and typical bugs: an output too small, the batch indexed instead of the
components), rts_smooth, and the metrics nees / nis / coverage / rmse. Each case either raises a
TorchfiltError or returns what the closed-form float64 Kalman filter and RTS smoother of
tests/reference.py give (see tests/fuzz_support.py for the contract).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st
from reference import kalman_filter, rts_smoother
from scipy import stats

from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import DivergenceWarning, ModelError, ShapeError
from torchfilt.filters import rts_smooth
from torchfilt.filters.metrics import coverage, nees, nis, rmse

D = torch.float64
#: CKF on a linear model vs the closed-form Kalman filter: exact up to round-off, amplified by the
#: covariance's conditioning (eigenvalues of Q, R, P0 within a factor 1e3 of each other here)
REF_RTOL = 1e-6
REF_ATOL = 1e-8
#: smallest eigenvalue of a returned covariance, relative to its largest
PSD_RTOL = 1e-9


def _spd(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    ev = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
    S = (q * ev) @ q.T
    return 0.5 * (S + S.T)


class Case:
    """A random linear-Gaussian problem with missing data."""

    def __init__(self, data: st.DataObject) -> None:
        self.n = data.draw(st.integers(1, 3), label="n")
        self.m = data.draw(st.integers(1, 2), label="m")
        self.T = data.draw(st.integers(1, 6), label="T")
        self.B = data.draw(st.sampled_from([None, 1, 2]), label="batch")
        seed = data.draw(st.integers(0, 2**32 - 1), label="seed")
        rng = np.random.default_rng(seed)
        n, m, T = self.n, self.m, self.T
        scale = 10.0 ** data.draw(st.integers(-2, 2), label="log10 scale")
        self.A = rng.uniform(-1.2, 1.2, (n, n))
        self.H = rng.uniform(-2.0, 2.0, (m, n))
        self.Q = _spd(rng, n, 1e-2, 1.0) * scale**2
        self.R = _spd(rng, m, 1e-2, 1.0) * scale**2
        self.P0 = _spd(rng, n, 1e-1, 10.0) * scale**2
        self.x0 = rng.standard_normal(n) * scale
        shape = (T, m) if self.B is None else (self.B, T, m)
        y = rng.standard_normal(shape) * scale * 3.0
        missing = data.draw(st.sampled_from([0.0, 0.2, 0.6, 1.0]), label="missing")
        fill = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]), label="fill")
        y[rng.uniform(size=shape) < missing] = fill
        self.y = y
        self.scale = scale
        self.nu = data.draw(st.sampled_from([0, 0, 1, 2]), label="nu")
        self.Bm = rng.uniform(-1.0, 1.0, (n, self.nu)) if self.nu else None
        self.u = rng.standard_normal((T, self.nu)) * scale if self.nu else None

    def torch(self, a: np.ndarray) -> torch.Tensor:
        return torch.tensor(a, dtype=D)

    def reference(self, seq: int | None):
        y = self.y if seq is None else self.y[seq]
        return kalman_filter(
            self.A, self.H, self.Q, self.R, y, self.x0, self.P0, B=self.Bm, u=self.u
        )

    def model(self) -> LinearGaussianModel:
        t = self.torch
        B = None if self.Bm is None else t(self.Bm)
        return LinearGaussianModel(t(self.A), t(self.H), t(self.Q), t(self.R), B=B)

    def u_tensor(self) -> torch.Tensor | None:
        return None if self.u is None else self.torch(self.u)

    def sequences(self) -> list[int | None]:
        return [None] if self.B is None else list(range(self.B))


def _close(got: torch.Tensor, want: np.ndarray, scale: float, what: str) -> None:
    g = got.detach().numpy()
    np.testing.assert_allclose(g, want, rtol=REF_RTOL, atol=REF_ATOL * scale, err_msg=what)


def _psd(cov: torch.Tensor, what: str) -> None:
    ev = torch.linalg.eigvalsh(cov)
    top = ev[..., -1:].abs().clamp_min(1e-300)
    assert bool((ev >= -PSD_RTOL * top).all()), f"{what}: not PSD, eigenvalues {ev.min()}"


def _check_filter_result(case: Case, res, warned: list) -> None:
    if not bool(torch.isfinite(res.mean).all()):
        assert any(issubclass(w.category, DivergenceWarning) for w in warned), (
            "non-finite estimates without a DivergenceWarning"
        )
        return
    for seq in case.sequences():
        ms, Ps, mps, Pps, ll = case.reference(seq)
        sl = (...,) if seq is None else (seq,)
        s2 = case.scale**2
        _close(res.mean[sl], ms, case.scale, "filtered mean")
        _close(res.cov[sl], Ps, s2, "filtered cov")
        _close(res.predicted_mean[sl], mps, case.scale, "predicted mean")
        _close(res.predicted_cov[sl], Pps, s2, "predicted cov")
        np.testing.assert_allclose(
            float(res.log_likelihood[sl]), ll, rtol=REF_RTOL, atol=1e-6, err_msg="log-likelihood"
        )
    _psd(res.cov, "filtered cov")
    _psd(res.predicted_cov, "predicted cov")


# ------------------------------------------------------------------- CKF on LinearGaussianModel
def check_ckf_linear(data: st.DataObject) -> None:
    case = Case(data)
    model = case.model()
    sqrt = data.draw(st.booleans(), label="sqrt")
    u = case.u_tensor()
    wrong_u = u is not None and data.draw(st.booleans(), label="wrong u width")
    if wrong_u:
        u = torch.cat([u, u], -1)
    res, warned = attempt(
        "CKF.filter (linear)",
        CKF(model, sqrt=sqrt).filter,
        case.torch(case.y),
        u,
        x0=case.torch(case.x0),
        P0=case.torch(case.P0),
    )
    if wrong_u:
        assert isinstance(res, Refused) and isinstance(res.error, ShapeError), res
        return
    assert not isinstance(res, Refused), f"a valid problem was refused: {res}"
    _check_filter_result(case, res, warned)


test_fuzz_ckf_linear, test_fuzz_ckf_linear_long = property_tests(
    check_ckf_linear, short=6, long=700
)


# ------------------------------------------------------- the exact path's converging recursions
def check_exact_converging(data: st.DataObject) -> None:
    """Long, fully observed recordings of a time-invariant model, one ``P0`` per sequence or one
    for all: the Riccati recursions stop once converged and the means' tail runs as a doubling
    scan or step by step. Every sequence equals the closed-form filter started from its own
    prior."""
    n = data.draw(st.integers(1, 3), label="n")
    m = data.draw(st.integers(1, 2), label="m")
    T = data.draw(st.sampled_from([5, 40, 150]), label="T")
    B = data.draw(st.integers(1, 3), label="batch")
    per_sequence = data.draw(st.booleans(), label="P0 per sequence")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    scale = 10.0 ** data.draw(st.integers(-2, 2), label="log10 scale")
    A = rng.uniform(-1.0, 1.0, (n, n))
    radius = data.draw(st.sampled_from([0.5, 0.95, 1.0]), label="spectral radius")
    A *= radius / max(abs(np.linalg.eigvals(A)).max(), 1e-12)
    H = rng.uniform(-2.0, 2.0, (m, n))
    Q, R = _spd(rng, n, 1e-2, 1.0) * scale**2, _spd(rng, m, 1e-2, 1.0) * scale**2
    P0s = [_spd(rng, n, 1e-1, 10.0) * scale**2 for _ in range(B if per_sequence else 1)]
    x0 = rng.standard_normal((B, n)) * scale
    nu = data.draw(st.sampled_from([0, 1]), label="nu")
    Bm = rng.uniform(-1.0, 1.0, (n, nu)) if nu else None
    u = rng.standard_normal((T, nu)) * scale if nu else None
    y = rng.standard_normal((B, T, m)) * scale * 3.0
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    model = LinearGaussianModel(t(A), t(H), t(Q), t(R), B=None if Bm is None else t(Bm))
    P0 = t(np.stack(P0s)) if per_sequence else t(P0s[0])
    res, _warned = attempt(
        "CKF.filter (linear, converging)",
        CKF(model).filter,
        t(y),
        None if u is None else t(u),
        x0=t(x0),
        P0=P0,
    )
    assert not isinstance(res, Refused), f"a valid problem was refused: {res}"
    assert res.path == "kalman"
    for b in range(B):
        ms, Ps, mps, _, ll = kalman_filter(
            A, H, Q, R, y[b], x0[b], P0s[b if per_sequence else 0], B=Bm, u=u
        )
        _close(res.mean[b], ms, scale, "filtered mean")
        _close(res.cov[b], Ps, scale**2, "filtered cov")
        _close(res.predicted_mean[b], mps, scale, "predicted mean")
        np.testing.assert_allclose(
            float(res.log_likelihood[b]), ll, rtol=REF_RTOL, atol=1e-6, err_msg="log-likelihood"
        )


test_fuzz_exact_converging, test_fuzz_exact_converging_long = property_tests(
    check_exact_converging, short=8, long=400
)


# ------------------------------------------------------------------- CKF on callables
_VARIANTS = ["correct", "first component", "first point", "first batch element", "sum", "int64"]


def _transition(variant: str, A: torch.Tensor, B: torch.Tensor | None):
    def f(x: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor:
        out = x @ A.mT if B is None else x @ A.mT + u @ B.mT
        if variant == "first component":  # (..., 1) instead of (..., n)
            return out[..., :1]
        if variant == "first point":  # x[:1]: indexes the points, not the components
            return out[..., :1, :]
        if variant == "first batch element":
            return out[:1]
        if variant == "int64":
            return out.round().long()
        if variant == "sum":
            return out.sum(-1)  # a scalar per point
        return out

    return f


def check_ckf_callables(data: st.DataObject) -> None:
    case = Case(data)
    A, H = case.torch(case.A), case.torch(case.H)
    fv = data.draw(st.sampled_from(_VARIANTS), label="f variant")
    hv = data.draw(st.sampled_from(_VARIANTS), label="h variant")
    h_fns = {
        "correct": lambda x: x @ H.mT,
        "first component": lambda x: (x @ H.mT)[..., :1],
        "first point": lambda x: (x @ H.mT)[..., :1, :],
        "first batch element": lambda x: (x @ H.mT)[:1],
        "sum": lambda x: (x @ H.mT).sum(-1),
        "int64": lambda x: (x @ H.mT).round().long(),
    }
    B = None if case.Bm is None else case.torch(case.Bm)
    model = StateSpaceModel(
        _transition(fv, A, B), h_fns[hv], Q=case.torch(case.Q), R=case.torch(case.R)
    )
    res, warned = attempt(
        "CKF.filter (callables)",
        CKF(model).filter,
        case.torch(case.y),
        case.u_tensor(),
        x0=case.torch(case.x0),
        P0=case.torch(case.P0),
    )
    if isinstance(res, Refused):
        # a correct model is never refused; a buggy one only with a ModelError
        assert (fv, hv) != ("correct", "correct"), res
        assert isinstance(res.error, ModelError), res
        return
    # accepted: then the result is that of the intended model (a "bug" that happens to give the
    # right shape, e.g. the first component of a one-state model, is harmless)
    _check_filter_result(case, res, warned)


test_fuzz_ckf_callables, test_fuzz_ckf_callables_long = property_tests(
    check_ckf_callables, short=6, long=500
)


# ------------------------------------------------------------------- smoother
def check_smooth(data: st.DataObject) -> None:
    case = Case(data)
    model = case.model()
    via = data.draw(st.sampled_from(["CKF.smooth", "rts_smooth"]), label="via")
    ckf = CKF(model)
    kw = dict(x0=case.torch(case.x0), P0=case.torch(case.P0))
    y = case.torch(case.y)
    u = case.u_tensor()
    if via == "CKF.smooth":
        sm, warned = attempt("CKF.smooth", ckf.smooth, y, u, **kw)
    else:
        fr, warned = attempt("CKF.filter (for rts_smooth)", ckf.filter, y, u, **kw)
        assert not isinstance(fr, Refused), fr
        sm, w2 = attempt("rts_smooth", rts_smooth, fr)
        warned = warned + w2
    assert not isinstance(sm, Refused), sm
    if not bool(torch.isfinite(sm.mean).all()):
        assert any(issubclass(w.category, DivergenceWarning) for w in warned)
        return
    for seq in case.sequences():
        ms, Ps, mps, Pps, _ = case.reference(seq)
        msm, Psm = rts_smoother(case.A, ms, Ps, mps, Pps)
        sl = (...,) if seq is None else (seq,)
        _close(sm.mean[sl], msm, case.scale, "smoothed mean")
        _close(sm.cov[sl], Psm, case.scale**2, "smoothed cov")
    _psd(sm.cov, "smoothed cov")


test_fuzz_smooth, test_fuzz_smooth_long = property_tests(check_smooth, short=5, long=400)


# ------------------------------------------------------------------- metrics
def check_metrics(data: st.DataObject) -> None:
    case = Case(data)
    res, _ = attempt(
        "CKF.filter (for metrics)",
        CKF(case.model()).filter,
        case.torch(case.y),
        case.u_tensor(),
        x0=case.torch(case.x0),
        P0=case.torch(case.P0),
    )
    assert not isinstance(res, Refused), res
    if not bool(torch.isfinite(res.mean).all()):
        return
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="truth seed"))
    x_true = torch.tensor(rng.standard_normal(tuple(res.mean.shape)) * case.scale, dtype=D)
    mean, cov = res.mean, res.cov
    M, P, X = mean.numpy(), cov.numpy(), x_true.numpy()

    got, _ = attempt("nees", nees, x_true, mean, cov)
    if not isinstance(got, Refused):
        e = X - M
        want = np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])
        np.testing.assert_allclose(got.numpy(), want, rtol=1e-6, atol=1e-9)

    got, _ = attempt("rmse", rmse, x_true, mean)
    if not isinstance(got, Refused):
        np.testing.assert_allclose(got.numpy(), np.sqrt(((X - M) ** 2).mean(-2)), rtol=1e-12)

    level = data.draw(st.sampled_from([0.5, 0.9, 0.95, 0.999]), label="level")
    got, _ = attempt("coverage", coverage, x_true, mean, cov, level)
    if not isinstance(got, Refused):
        z = stats.norm.ppf(0.5 + level / 2)
        sd = np.sqrt(np.clip(np.diagonal(P, axis1=-2, axis2=-1), 0, None))
        inside = np.abs(X - M) <= z * sd
        # an error exactly on the interval's edge may fall either way by round-off
        edge = np.isclose(np.abs(X - M), z * sd, rtol=1e-12)
        lo, hi = (inside & ~edge).mean(-2), (inside | edge).mean(-2)
        g = got.numpy()
        assert np.all(g >= lo - 1e-12) and np.all(g <= hi + 1e-12)

    got, _ = attempt("nis", nis, res)
    if not isinstance(got, Refused):
        val, dof = got
        obs = res.observed.numpy()
        E, S = res.innovation.numpy(), res.innovation_cov.numpy()
        want = np.zeros(obs.shape[:-1])
        for idx in np.ndindex(*obs.shape[:-1]):
            o = obs[idx]
            if o.any():
                e = E[idx][o]
                want[idx] = e @ np.linalg.solve(S[idx][np.ix_(o, o)], e)
        np.testing.assert_allclose(val.numpy(), want, rtol=1e-6, atol=1e-9)
        np.testing.assert_array_equal(dof.numpy(), obs.sum(-1))
        assert math.isfinite(float(val.sum()))


test_fuzz_metrics, test_fuzz_metrics_long = property_tests(check_metrics, short=5, long=300)


# ------------------------------------------------------------------- model construction
def _matrix(data: st.DataObject, rows: int, cols: int, label: str):
    kind = data.draw(
        st.sampled_from(["ok", "ok", "ok", "nan", "shape", "half", "int", "list", "asym", "neg"]),
        label=f"{label} kind",
    )
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label=f"{label} seed"))
    if rows == cols:
        M = _spd(rng, rows, 0.1, 1.0)
    else:
        M = rng.standard_normal((rows, cols))
    if kind == "nan":
        M[0, 0] = np.nan
    elif kind == "shape":
        M = rng.standard_normal((rows, cols + 1))
    elif kind == "asym" and rows == cols and rows > 1:
        M[0, 1] += 1.0
    elif kind == "neg" and rows == cols:
        M = -M
    if kind == "half":
        return torch.tensor(M, dtype=torch.float16), kind
    if kind == "int":
        return torch.tensor(np.round(M * 3), dtype=torch.int64), kind
    if kind == "list":
        return M.tolist(), kind
    return torch.tensor(M, dtype=D), kind


def check_model_construction(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 3), label="n")
    m = data.draw(st.integers(1, 2), label="m")
    A, ka = _matrix(data, n, n, "A")
    H, kh = _matrix(data, m, n, "H")
    Q, kq = _matrix(data, n, n, "Q")
    R, kr = _matrix(data, m, m, "R")
    model, _ = attempt("LinearGaussianModel", LinearGaussianModel, A, H, Q, R)
    kinds = {"A": ka, "H": kh, "Q": kq, "R": kr}
    fatal = {"nan", "shape", "half"}
    if isinstance(model, Refused):
        assert any(
            k in fatal or (name in "QR" and k in ("asym", "neg")) for name, k in kinds.items()
        ), (
            kinds,
            model,
        )
        return
    # accepted: nothing that the rules refuse slipped through (a 1x1 "asym" is symmetric; the
    # rounded "int" matrices and lists are real numbers)
    for name, k in kinds.items():
        assert k not in fatal, f"{name}: a {k} matrix was accepted"
        if name in "QR" and k == "neg":
            raise AssertionError(f"{name}: a negative definite covariance was accepted")
        if name in "QR" and k == "asym" and (n if name == "Q" else m) > 1:
            raise AssertionError(f"{name}: a non-symmetric covariance was accepted")
    y = torch.zeros(3, m, dtype=D)
    res, warned = attempt(
        "CKF.filter (constructed)",
        CKF(model).filter,
        y,
        x0=torch.zeros(n, dtype=D),
        P0=torch.eye(n, dtype=D),
    )
    if isinstance(res, Refused):
        return
    assert torch.isfinite(res.mean).all() or any(
        issubclass(w.category, DivergenceWarning) for w in warned
    )


test_fuzz_model_construction, test_fuzz_model_construction_long = property_tests(
    check_model_construction, short=8, long=400
)


def teardown_module() -> None:
    print_stats()
