"""The QP wrapper (Clarabel) against scipy (SLSQP, bounded least squares) and the KKT conditions."""

import numpy as np
import pytest
import scipy.optimize
import torch
from conftest import random_spd

from torchfilt.dmc import solve_qp
from torchfilt.exceptions import ShapeError

D = torch.float64
#: SLSQP's own accuracy on these problems (ftol 1e-12).
SLSQP_TOL = 1e-7
#: Bounded-variable least squares (scipy's BVLS) is an exact active-set method; Clarabel's
#: interior-point iterate at QP_TOL = 1e-10 is within ~1e-9 of the vertex.
BVLS_TOL = 1e-8
#: KKT residuals (stationarity, feasibility, complementarity) at the default tolerance.
KKT_TOL = 1e-8


def t(a):
    return torch.tensor(a, dtype=D)


def random_qp(seed, n=8, m=12):
    rng = np.random.default_rng(seed)
    G = random_spd(rng, n, 3.0, cond=100.0)
    c = 5.0 * rng.standard_normal(n)
    A = rng.standard_normal((m, n))
    b = rng.uniform(0.1, 1.0, m)  # x = 0 is feasible
    return G, c, A, b


def kkt_residuals(G, c, A, b, x, z):
    stat = np.abs(G @ x + c + A.T @ z).max()
    feas = max(0.0, (A @ x - b).max())
    comp = np.abs(z * (b - A @ x)).max()
    return stat, feas, comp, z.min()


@pytest.mark.parametrize("seed", range(4))
def test_matches_slsqp_and_satisfies_kkt(seed):
    G, c, A, b = random_qp(seed)
    lb, ub = -0.5 * np.ones(8), 0.5 * np.ones(8)
    res = solve_qp(t(G), t(c), t(A), t(b), lb=t(lb), ub=t(ub))
    assert bool(res.converged)
    ref = scipy.optimize.minimize(
        lambda x: 0.5 * x @ G @ x + c @ x,
        np.zeros(8),
        jac=lambda x: G @ x + c,
        method="SLSQP",
        bounds=list(zip(lb, ub, strict=True)),
        constraints=[{"type": "ineq", "fun": lambda x: b - A @ x, "jac": lambda x: -A}],
        options={"ftol": 1e-12, "maxiter": 1000},
    )
    assert ref.success
    np.testing.assert_allclose(res.x.numpy(), ref.x, rtol=0, atol=SLSQP_TOL)
    assert float(res.objective) <= ref.fun + SLSQP_TOL
    # KKT on the full row set (A rows, then -x <= -lb, then x <= ub)
    Af = np.vstack([A, -np.eye(8), np.eye(8)])
    bf = np.concatenate([b, -lb, ub])
    stat, feas, comp, zmin = kkt_residuals(G, c, Af, bf, res.x.numpy(), res.multipliers.numpy())
    assert stat < KKT_TOL and feas < KKT_TOL and comp < KKT_TOL and zmin >= 0
    # some constraints are active (the test is not the unconstrained case)
    assert (res.multipliers > 1e-3).sum() >= 2


@pytest.mark.parametrize("seed", range(3))
def test_box_constrained_matches_bounded_least_squares(seed):
    rng = np.random.default_rng(10 + seed)
    M, d = rng.standard_normal((15, 6)), 3.0 * rng.standard_normal(15)
    # min 1/2 ||M x - d||^2  <=>  G = M^T M, c = -M^T d
    res = solve_qp(t(M.T @ M), t(-M.T @ d), lb=-0.3, ub=0.3)
    ref = scipy.optimize.lsq_linear(M, d, bounds=(-0.3, 0.3), method="bvls", tol=1e-14)
    np.testing.assert_allclose(res.x.numpy(), ref.x, rtol=0, atol=BVLS_TOL)
    assert np.isclose(np.abs(ref.x), 0.3).any()  # a bound is active


def test_batched_equals_looped_and_unconstrained_is_exact():
    probs = [random_qp(s, n=5, m=7) for s in range(6)]
    G, c, A, b = (
        t(np.stack([p[i] for p in probs])).reshape(2, 3, *probs[0][i].shape) for i in range(4)
    )
    batched = solve_qp(G, c, A, b, lb=-1.0, ub=1.0)
    assert batched.x.shape == (2, 3, 5) and bool(batched.converged.all())
    for i in range(2):
        for j in range(3):
            one = solve_qp(G[i, j], c[i, j], A[i, j], b[i, j], lb=-1.0, ub=1.0)
            torch.testing.assert_close(batched.x[i, j], one.x, rtol=0, atol=KKT_TOL)
    free = solve_qp(G, c)
    torch.testing.assert_close(free.x, -torch.linalg.solve(G, c), rtol=0, atol=KKT_TOL)


def test_infinite_bounds_are_dropped():
    G, c = torch.eye(2, dtype=D), t([-3.0, 3.0])
    res = solve_qp(G, c, lb=t([-np.inf, -1.0]), ub=t([1.0, np.inf]))
    torch.testing.assert_close(res.x, t([1.0, -1.0]), rtol=0, atol=KKT_TOL)
    assert res.multipliers.shape == (2,)


def test_infeasible_problem_does_not_converge():
    # x_1 <= -1 and -x_1 <= -1 (x_1 >= 1): empty
    res = solve_qp(
        torch.eye(2, dtype=D),
        torch.zeros(2, dtype=D),
        t([[1.0, 0.0], [-1.0, 0.0]]),
        t([-1.0, -1.0]),
    )
    assert not bool(res.converged)


def test_bad_inputs():
    I2 = torch.eye(2, dtype=D)
    with pytest.raises(ValueError, match="G must be positive definite"):
        solve_qp(t([[1.0, 0.0], [0.0, -1.0]]), torch.zeros(2, dtype=D))
    with pytest.raises(ValueError, match="G is not symmetric"):
        solve_qp(t([[1.0, 1.0], [0.0, 1.0]]), torch.zeros(2, dtype=D))
    with pytest.raises(ShapeError, match=r"c: expected shape \(\.\.\., 2\)"):
        solve_qp(I2, torch.zeros(3, dtype=D))
    with pytest.raises(ShapeError, match=r"A: expected shape \(\.\.\., m, 2\)"):
        solve_qp(I2, torch.zeros(2, dtype=D), torch.zeros(1, 3, dtype=D), torch.zeros(1, dtype=D))
    with pytest.raises(ShapeError, match=r"b: expected shape \(\.\.\., 1\)"):
        solve_qp(I2, torch.zeros(2, dtype=D), torch.zeros(1, 2, dtype=D), torch.zeros(2, dtype=D))
    with pytest.raises(ShapeError, match=r"lb: expected shape \(\.\.\., 2\)"):
        solve_qp(I2, torch.zeros(2, dtype=D), lb=torch.zeros(3, dtype=D))
    with pytest.raises(ValueError, match="b is required with A"):
        solve_qp(I2, torch.zeros(2, dtype=D), torch.zeros(1, 2, dtype=D))
