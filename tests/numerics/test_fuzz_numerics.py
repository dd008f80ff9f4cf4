"""Hypothesis suite over the numerics entry points (issue 12): bounded_least_squares against
scipy.optimize.lsq_linear, Box against its definition, solve_dare / steady_state_kalman against the
Riccati equation and scipy.linalg.solve_discrete_are. See tests/fuzz_support.py for the contract.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.optimize as so
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics import Box, bounded_least_squares, solve_dare, steady_state_kalman

D = torch.float64
#: our cost is never worse than BVLS's (an exact active-set method) beyond round-off
COST_RTOL = 1e-8
COST_ATOL = 1e-12
#: the DARE residual relative to the size of its terms
DARE_RTOL = 1e-8
#: our Riccati solution vs SciPy's (a Schur method), relative
SCIPY_RTOL = 1e-6


# ------------------------------------------------------------------- bounded least squares
_RESIDUAL_FORMS = ["torch", "torch", "torch", "detach", "numpy", "scalar"]


def check_lsq(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 4), label="n")
    k = data.draw(st.integers(1, 6), label="k")
    B = data.draw(st.sampled_from([None, 1, 3]), label="batch")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    lead = () if B is None else (B,)
    A = rng.standard_normal((*lead, k, n)) * 10.0 ** rng.uniform(-1, 1)
    b = rng.standard_normal((*lead, k))
    lo = rng.uniform(-1.0, 0.2, (*lead, n))
    hi = lo + rng.uniform(0.0, 1.5, (*lead, n))
    lo[rng.uniform(size=lo.shape) < 0.3] = -np.inf
    hi[rng.uniform(size=hi.shape) < 0.3] = np.inf
    bounds_batch = data.draw(st.sampled_from(["same", "none", "mismatch"]), label="bounds batch")
    if bounds_batch == "none":
        lo_b, hi_b = lo.reshape(-1, n)[0], hi.reshape(-1, n)[0]
        lo = np.broadcast_to(lo_b, lo.shape).copy()
        hi = np.broadcast_to(hi_b, hi.shape).copy()
    elif bounds_batch == "mismatch":
        lo_b, hi_b = np.tile(lo.reshape(-1, n)[:1], (5, 1)), np.tile(hi.reshape(-1, n)[:1], (5, 1))
    else:
        lo_b, hi_b = lo, hi
    box = Box(torch.tensor(lo_b, dtype=D), torch.tensor(hi_b, dtype=D))
    x0 = torch.tensor(rng.standard_normal((*lead, n)) * 2.0, dtype=D)
    At, bt = torch.tensor(A, dtype=D), torch.tensor(b, dtype=D)
    form = data.draw(st.sampled_from(_RESIDUAL_FORMS), label="residual form")

    def residual(x: torch.Tensor):
        r = (At @ x.unsqueeze(-1)).squeeze(-1) - bt
        if form == "detach":
            return r.detach()
        if form == "numpy":
            return r.detach().numpy()
        if form == "scalar":
            return 0.5 * (r**2).sum(-1)
        return r

    sol, _ = attempt(
        "bounded_least_squares", bounded_least_squares, residual, x0, box, max_iter=200, warn=False
    )
    if isinstance(sol, Refused):
        if form != "torch":
            assert isinstance(sol.error, InputError)  # includes ShapeError
        elif bounds_batch == "mismatch" and B not in (None, 1):
            assert isinstance(sol.error, ShapeError)
        else:
            raise AssertionError(f"a valid problem was refused: {sol}")
        return
    assert form == "torch", f"a {form} residual was accepted"
    assert not (bounds_batch == "mismatch" and B not in (None, 1)), "mismatched bounds accepted"
    x = sol.x.numpy()
    assert np.all(x >= np.broadcast_to(lo_b, x.shape) - 0) and np.all(x <= hi_b + 0)
    Ab = np.broadcast_to(A, (*x.shape[:-1], k, n))
    bb = np.broadcast_to(b, (*x.shape[:-1], k))
    lob = np.broadcast_to(lo_b, x.shape)
    hib = np.broadcast_to(hi_b, x.shape)
    for idx in np.ndindex(*x.shape[:-1]):
        ref = so.lsq_linear(Ab[idx], bb[idx], bounds=(lob[idx], hib[idx]), method="bvls", tol=1e-15)
        cost = 0.5 * float(np.sum((Ab[idx] @ x[idx] - bb[idx]) ** 2))
        assert cost <= ref.cost * (1 + COST_RTOL) + COST_ATOL, (cost, ref.cost)
        np.testing.assert_allclose(float(sol.cost[idx]), cost, rtol=1e-9, atol=1e-12)


test_fuzz_lsq, test_fuzz_lsq_long = property_tests(check_lsq, short=6, long=500)


# ------------------------------------------------------------------- Box
_BOUND = st.one_of(
    st.none(),
    st.floats(-5, 5),
    st.lists(
        st.floats(allow_nan=True, allow_infinity=True, width=64, min_value=None, max_value=None),
        min_size=0,
        max_size=3,
    ),
)


def check_box(data: st.DataObject) -> None:
    lower = data.draw(_BOUND, label="lower")
    upper = data.draw(_BOUND, label="upper")
    n = data.draw(st.sampled_from([None, 1, 2, 3]), label="n")
    box, _ = attempt("Box", Box, lower, upper, n=n)
    if isinstance(box, Refused):
        return
    lo, hi = box.lower.numpy(), box.upper.numpy()
    assert not np.isnan(lo).any() and not np.isnan(hi).any()
    assert np.all(lo <= hi)
    if isinstance(lower, list) and lower:
        np.testing.assert_array_equal(lo, np.asarray(lower, dtype=np.float64))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    x = torch.tensor(rng.standard_normal((4, box.dim)) * 10.0, dtype=D)
    p, _ = attempt("Box.project", box.project, x)
    assert not isinstance(p, Refused)
    assert bool(box.contains(p).all())
    assert torch.equal(box.project(p), p)
    inside = box.contains(x)
    assert torch.equal(inside, (p == x).all(-1))
    want = np.minimum(np.maximum(x.numpy(), lo), hi)
    np.testing.assert_array_equal(p.numpy(), want)


test_fuzz_box, test_fuzz_box_long = property_tests(check_box, short=10, long=600)


# ------------------------------------------------------------------- DARE
def check_dare(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 3), label="n")
    m = data.draw(st.integers(1, 2), label="m")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    A = rng.uniform(-1.5, 1.5, (n, n))
    C = rng.uniform(-2.0, 2.0, (m, n))
    kind = data.draw(st.sampled_from(["generic", "zero C column", "zero Q", "singular R", "nan"]))
    G = rng.standard_normal((n, n))
    Q = G @ G.T + 1e-2 * np.eye(n)
    H = rng.standard_normal((m, m))
    R = H @ H.T + 1e-1 * np.eye(m)
    if kind == "zero C column":
        C[:, 0] = 0.0
    elif kind == "zero Q":
        Q = np.zeros((n, n))
    elif kind == "singular R":
        R = np.zeros((m, m))
    elif kind == "nan":
        A[0, 0] = np.nan
    use_gain = data.draw(st.booleans(), label="steady_state_kalman")
    args = [torch.tensor(M, dtype=D) for M in (A, C, Q, R)]
    if use_gain:
        out, _ = attempt("steady_state_kalman", steady_state_kalman, *args)
        Sigma = None if isinstance(out, Refused) else out.pred_cov
    else:
        out, _ = attempt("solve_dare", solve_dare, *args)
        Sigma = None if isinstance(out, Refused) else out
    if Sigma is None:
        assert kind != "generic" or _scipy_fails_or_unstable(A, C, Q, R), out
        return
    assert kind not in ("nan", "singular R"), f"{kind} accepted"
    S = Sigma.numpy()
    assert np.isfinite(S).all()
    assert np.allclose(S, S.T, rtol=0, atol=1e-10 * max(1.0, np.abs(S).max()))
    assert np.linalg.eigvalsh(S).min() >= -1e-9 * max(1.0, np.abs(S).max())
    Syy = C @ S @ C.T + R
    K = S @ C.T @ np.linalg.inv(Syy)
    rhs = A @ (S - K @ Syy @ K.T) @ A.T + Q
    size = max(1.0, np.abs(rhs).max(), np.abs(S).max())
    assert np.abs(S - rhs).max() <= DARE_RTOL * size, "Riccati residual"
    # stabilising: the closed loop A (I - K C) has spectral radius < 1
    rho = np.abs(np.linalg.eigvals(A @ (np.eye(n) - K @ C))).max()
    assert rho < 1.0 + 1e-9, f"closed-loop spectral radius {rho}"
    if kind == "generic":
        ref = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
        np.testing.assert_allclose(S, ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL * size)


def _scipy_fails_or_unstable(A, C, Q, R) -> bool:
    """Whether the generic problem really has no stabilising solution (SciPy agrees)."""
    try:
        S = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
    except (np.linalg.LinAlgError, ValueError):
        return True
    K = S @ C.T @ np.linalg.inv(C @ S @ C.T + R)
    return bool(np.abs(np.linalg.eigvals(A @ (np.eye(len(A)) - K @ C))).max() >= 1.0 - 1e-6)


test_fuzz_dare, test_fuzz_dare_long = property_tests(check_dare, short=6, long=500)


def teardown_module() -> None:
    print_stats()
