"""The batched bounded least-squares solver against SciPy (BVLS and least_squares), in float64."""

import warnings

import numpy as np
import pytest
import scipy.optimize as so
import torch
from conftest import BATCH_SHAPES

from torchfilt.exceptions import ConvergenceWarning, InputError, ShapeError
from torchfilt.numerics import Box, SolverStatus, batched_jacobian, bounded_least_squares

D = torch.float64
#: the linear box-QP solution agrees with BVLS (an exact active-set method) to round-off
QP_ATOL = 1e-10
#: nonlinear solutions: both solvers stop near 1e-8 in the J^T J metric
NL_ATOL = 1e-6
#: cost is never worse than SciPy's by more than round-off
COST_RTOL = 1e-9
#: two solutions of the same problem computed in a batch and alone
BATCH_ATOL = 1e-12
#: float32 stops at the cost's round-off, sqrt(2 ROUNDOFF eps_32 F) ~ 2e-3 in the J^T J metric
F32_ATOL = 5e-3
#: Gauss-Newton converges only linearly on the strongly curved random problems: allow the iterations
MAX_ITER = 300
#: implicit-function derivative vs an independent autograd Hessian solve
GRAD_RTOL = 1e-7


def t(a):
    return torch.tensor(a, dtype=D)


def random_box(rng, n, k_inf=1):
    """Bounds around 0 tight enough that solutions sit on the boundary; some sides infinite."""
    lo = -rng.uniform(0.1, 0.6, n)
    hi = rng.uniform(0.1, 0.6, n)
    lo[rng.choice(n, k_inf, replace=False)] = -np.inf
    hi[rng.choice(n, k_inf, replace=False)] = np.inf
    return lo, hi


def kkt_violation(x, g, lo, hi, scale):
    """Max violation of the box KKT conditions: g = 0 inside, g >= 0 at lower, g <= 0 at upper."""
    at_lo = np.isclose(x, lo, rtol=0, atol=1e-12)
    at_hi = np.isclose(x, hi, rtol=0, atol=1e-12)
    viol = np.where(at_lo, np.maximum(-g, 0), np.where(at_hi, np.maximum(g, 0), np.abs(g)))
    return viol.max() / scale


@pytest.mark.parametrize("seed", range(4))
def test_linear_equals_exact_box_qp(seed):
    """r = A x - b: the solver lands on BVLS's solution, with several components on the boundary."""
    rng = np.random.default_rng(seed)
    B, k, n = 40, 7, 4
    A = rng.standard_normal((B, k, n))
    b = 3.0 * rng.standard_normal((B, k))
    lo, hi = random_box(rng, n)
    res = bounded_least_squares(
        lambda x: (t(A) @ x.unsqueeze(-1)).squeeze(-1) - t(b),
        torch.zeros(B, n, dtype=D),
        Box(t(lo), t(hi)),
    )
    assert bool(res.converged.all())
    ref = np.stack(
        [so.lsq_linear(A[i], b[i], bounds=(lo, hi), method="bvls", tol=1e-15).x for i in range(B)]
    )
    x = res.x.numpy()
    np.testing.assert_allclose(x, ref, atol=QP_ATOL, rtol=0)
    on_boundary = np.isclose(ref, lo, atol=1e-12) | np.isclose(ref, hi, atol=1e-12)
    assert on_boundary.any(axis=1).mean() > 0.5, "the test problems must exercise the bounds"
    # and the KKT conditions hold independently of any reference solution
    for i in range(B):
        g = A[i].T @ (A[i] @ x[i] - b[i])
        assert kkt_violation(x[i], g, lo, hi, np.abs(A[i].T @ b[i]).max()) < QP_ATOL


def test_linear_unbounded_equals_lstsq():
    rng = np.random.default_rng(11)
    A, b = rng.standard_normal((9, 3)), rng.standard_normal(9)
    res = bounded_least_squares(lambda x: t(A) @ x - t(b), torch.zeros(3, dtype=D))
    np.testing.assert_allclose(res.x.numpy(), np.linalg.lstsq(A, b, rcond=None)[0], atol=QP_ATOL)
    assert int(res.iterations) <= 2


def nddr_problem(rng, B, n, sig=0.1):
    """Reconciliation-like problems: a Gaussian prior around c plus a nonlinear measurement z of a
    state drawn from that prior (consistent data, as in a filter)."""
    c = rng.uniform(-0.5, 0.5, (B, n))
    P = 0.2 * np.eye(n) + 0.05
    Lp = np.linalg.cholesky(P)
    Wp = np.linalg.inv(Lp)

    def g_np(x):
        return np.array(
            [np.exp(0.5 * x[0]) + 0.5 * x[1] ** 3, np.sin(x[1]) + x[-1] + 0.3 * x[-1] ** 3]
        )

    x_true = c + rng.standard_normal((B, n)) @ Lp.T
    z = np.array([g_np(x) for x in x_true]) + sig * rng.standard_normal((B, 2))

    def r_np(x, i):
        return np.concatenate([Wp @ (x - c[i]), (z[i] - g_np(x)) / sig])

    def r_t(x):
        g = torch.stack(
            [
                torch.exp(0.5 * x[..., 0]) + 0.5 * x[..., 1] ** 3,
                torch.sin(x[..., 1]) + x[..., -1] + 0.3 * x[..., -1] ** 3,
            ],
            -1,
        )
        prior = ((x - t(c)).unsqueeze(-2) @ t(Wp).mT).squeeze(-2)
        return torch.cat([prior, (t(z) - g) / sig], -1)

    return c, r_np, r_t


@pytest.mark.parametrize("seed", range(3))
def test_nonlinear_matches_scipy_least_squares(seed):
    rng = np.random.default_rng(100 + seed)
    B, n = 30, 3
    c, r_np, r_t = nddr_problem(rng, B, n)
    lo, hi = random_box(rng, n)
    res = bounded_least_squares(r_t, t(np.clip(c, lo, hi)), Box(t(lo), t(hi)), max_iter=MAX_ITER)
    assert bool(res.converged.all())
    boundary = 0
    for i in range(B):
        ref = so.least_squares(
            r_np,
            np.clip(c[i], lo, hi),
            bounds=(lo, hi),
            args=(i,),
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        np.testing.assert_allclose(res.x[i].numpy(), ref.x, atol=NL_ATOL, rtol=0)
        assert float(res.cost[i]) <= ref.cost * (1 + COST_RTOL) + 1e-14
        boundary += int(np.any(np.isclose(ref.x, lo, atol=1e-9) | np.isclose(ref.x, hi, atol=1e-9)))
    assert boundary >= B // 4, "the test problems must exercise the bounds"


def test_rosenbrock_solution_on_the_boundary():
    """SciPy's documented example: Rosenbrock with x2 >= 1.5 has its minimum on that bound."""

    def r_t(x):
        return torch.stack([10 * (x[..., 1] - x[..., 0] ** 2), 1 - x[..., 0]], -1)

    def r_np(x):
        return np.array([10 * (x[1] - x[0] ** 2), 1 - x[0]])

    lo, hi = np.array([-np.inf, 1.5]), np.array([np.inf, np.inf])
    res = bounded_least_squares(r_t, t([2.0, 2.0]), Box(t(lo), t(hi)))
    ref = so.least_squares(r_np, [2.0, 2.0], bounds=(lo, hi), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(res.x.numpy(), ref.x, atol=NL_ATOL)
    assert float(res.x[1]) == 1.5 and int(res.status) > 0


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
def test_batched_equals_loop(batch):
    gen = torch.Generator().manual_seed(3)
    A = torch.randn(*batch, 5, 3, dtype=D, generator=gen)
    b = 2 * torch.randn(*batch, 5, dtype=D, generator=gen)
    lo = -0.3 * torch.ones(3, dtype=D)
    box = Box(lo, torch.tensor([0.4, np.inf, 0.2], dtype=D))

    def make(A, b):
        return lambda x: (
            (A @ x.unsqueeze(-1)).squeeze(-1) - b + 0.1 * torch.sin(x).sum(-1, keepdim=True)
        )

    res = bounded_least_squares(make(A, b), torch.zeros(*batch, 3, dtype=D), box)
    assert res.x.shape == (*batch, 3) and res.iterations.shape == batch
    for idx in np.ndindex(*batch):
        one = bounded_least_squares(make(A[idx], b[idx]), torch.zeros(3, dtype=D), box)
        assert torch.allclose(res.x[idx], one.x, atol=BATCH_ATOL, rtol=0)
        assert int(res.iterations[idx]) == int(one.iterations)


def test_residual_may_broadcast_the_start_point():
    """x0 of shape (n,) against data of batch (4,): the solver expands x0."""
    gen = torch.Generator().manual_seed(4)
    b = torch.randn(4, 2, dtype=D, generator=gen)
    res = bounded_least_squares(lambda x: x - b, torch.zeros(2, dtype=D), Box(-0.5, 0.5, n=2))
    assert res.x.shape == (4, 2)
    assert torch.equal(res.x, b.clamp(-0.5, 0.5))


def test_float32():
    rng = np.random.default_rng(5)
    c, _, r_t = nddr_problem(rng, 8, 3)
    lo, hi = random_box(rng, 3)
    r64 = bounded_least_squares(r_t, t(np.clip(c, lo, hi)), Box(t(lo), t(hi)), max_iter=MAX_ITER)

    def r32(x):
        return r_t(x.double()).float()

    res = bounded_least_squares(
        r32,
        torch.tensor(np.clip(c, lo, hi), dtype=torch.float32),
        Box(t(lo), t(hi)),
        max_iter=MAX_ITER,
    )
    assert res.x.dtype == torch.float32 and bool(res.converged.all())
    assert torch.allclose(res.x.double(), r64.x, atol=F32_ATOL)


def test_start_outside_the_box_is_projected():
    res = bounded_least_squares(lambda x: x - 0.25, t([5.0, -5.0]), Box(0.0, 1.0, n=2))
    assert torch.allclose(res.x, t([0.25, 0.25]), atol=BATCH_ATOL)


def test_nonconvergence_is_reported_and_warned():
    """One iteration on a curved problem is not enough: status MAX_ITER and a named warning."""
    rng = np.random.default_rng(6)
    c, _, r_t = nddr_problem(rng, 5, 3)
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        res = bounded_least_squares(r_t, t(c), Box(n=3), max_iter=1)
    assert bool((res.status == SolverStatus.MAX_ITER).all())
    assert not bool(res.converged.any())
    assert bool((res.iterations == 1).all())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = bounded_least_squares(r_t, t(c), Box(n=3), max_iter=1, warn=False)
    assert torch.equal(quiet.x, res.x)


def test_nonfinite_residual_is_reported():
    bad = torch.tensor([True, False])

    def r(x):
        return torch.where(bad.unsqueeze(-1), torch.full_like(x, float("nan")), x - 1.0)

    with pytest.warns(ConvergenceWarning, match="nonfinite: 1"):
        res = bounded_least_squares(r, t([[1.0, 0.0], [-1.0, 0.0]]), Box(-2.0, 2.0, n=2))
    assert int(res.status[0]) == SolverStatus.NONFINITE and int(res.status[1]) > 0
    assert torch.allclose(res.x[1], t([1.0, 1.0]), atol=BATCH_ATOL)


def test_tolerance_is_met():
    """At convergence the reported optimality sqrt(delta) is within the requested tolerance."""
    rng = np.random.default_rng(7)
    c, _, r_t = nddr_problem(rng, 20, 3)
    res = bounded_least_squares(r_t, t(c), Box(-0.2, 0.3, n=3), tol=1e-10)
    conv = res.status == SolverStatus.CONVERGED
    assert bool(conv.any())
    assert bool((res.optimality[conv] <= 1e-10).all())


def test_batched_jacobian_matches_autograd():
    gen = torch.Generator().manual_seed(8)
    x = torch.randn(6, 3, dtype=D, generator=gen)

    def fn(x):
        return torch.stack([x[..., 0] * x[..., 1], torch.exp(x[..., 2]), x.sum(-1)], -1)

    _, J = batched_jacobian(fn, x)
    for i in range(6):
        ref = torch.autograd.functional.jacobian(fn, x[i])
        assert torch.allclose(J[i], ref, atol=BATCH_ATOL)


def test_gradcheck_affine_residual_with_active_bounds():
    """The solution is differentiable in the data and the bounds (exact for an affine residual)."""
    gen = torch.Generator().manual_seed(9)
    A = torch.randn(2, 5, 3, dtype=D, generator=gen).requires_grad_()
    b = (2 * torch.randn(2, 5, dtype=D, generator=gen)).requires_grad_()
    lo = torch.full((3,), -0.3, dtype=D, requires_grad=True)
    hi = torch.full((3,), 0.4, dtype=D, requires_grad=True)

    def sol(A, b, lo, hi):
        return bounded_least_squares(
            lambda x: (A @ x.unsqueeze(-1)).squeeze(-1) - b, torch.zeros(2, 3, dtype=D), Box(lo, hi)
        ).x

    x = sol(A, b, lo, hi)
    active = ((x == lo) | (x == hi)).detach()
    assert bool(active.any()) and bool((~active).any())
    assert torch.autograd.gradcheck(sol, (A, b, lo, hi), eps=1e-6, atol=1e-6)


def test_gradient_nonlinear_equals_implicit_function_theorem():
    """dx*/db = -H^{-1} d(grad F)/db at an interior solution, with H from torch's own Hessian."""
    gen = torch.Generator().manual_seed(10)
    A = torch.randn(5, 3, dtype=D, generator=gen)
    b = 2 * torch.randn(5, dtype=D, generator=gen)

    def res_fn(x, b):
        return A @ x - b + 0.1 * torch.sin(x).sum(-1, keepdim=True)

    def sol(b):
        return bounded_least_squares(lambda x: res_fn(x, b), torch.zeros(3, dtype=D), tol=1e-12).x

    x = sol(b).detach()
    H = torch.autograd.functional.hessian(lambda xx: 0.5 * (res_fn(xx, b) ** 2).sum(), x)
    Gb = torch.autograd.functional.jacobian(
        lambda bb: torch.autograd.functional.jacobian(
            lambda xx: 0.5 * (res_fn(xx, bb) ** 2).sum(), x, create_graph=True
        ),
        b,
    )
    want = -torch.linalg.solve(H, Gb)
    got = torch.autograd.functional.jacobian(sol, b)
    assert torch.allclose(got, want, rtol=GRAD_RTOL, atol=1e-12)


def test_argument_errors():
    with pytest.raises(ShapeError, match="bounds: dimension 2"):
        bounded_least_squares(lambda x: x, torch.zeros(3, dtype=D), Box(0.0, 1.0, n=2))
    with pytest.raises(InputError, match="x0: expected real numbers"):
        bounded_least_squares(lambda x: x, torch.zeros(3, dtype=torch.long))
    with pytest.raises(ShapeError, match="do not broadcast"):
        bounded_least_squares(
            lambda x: torch.zeros(3, 2, dtype=D) + x.sum(), torch.zeros(4, 2, dtype=D)
        )
    with pytest.raises(ValueError, match="tol must be positive"):
        bounded_least_squares(lambda x: x, torch.zeros(2, dtype=D), tol=0.0)
    with pytest.raises(ShapeError, match="jacobian returned shape"):
        bounded_least_squares(
            lambda x: x, torch.zeros(2, dtype=D), jacobian=lambda x: torch.eye(3, dtype=D)
        )


def test_explicit_jacobian_gives_the_same_solution():
    rng = np.random.default_rng(12)
    A, b = rng.standard_normal((4, 6, 3)), rng.standard_normal((4, 6))
    box = Box(-0.2, 0.2, n=3)

    def r(x):
        return (t(A) @ x.unsqueeze(-1)).squeeze(-1) - t(b)

    auto = bounded_least_squares(r, torch.zeros(4, 3, dtype=D), box)
    expl = bounded_least_squares(r, torch.zeros(4, 3, dtype=D), box, jacobian=lambda x: t(A))
    assert torch.allclose(auto.x, expl.x, atol=BATCH_ATOL)


def test_badly_scaled_prior_matches_the_kalman_update():
    """A filter-like prior whose precision spans 1e17 (states 1e5 ft and 1e-3, correlation 0.9):
    the Jacobi-scaled solve still lands on the closed-form update, in whitened units."""
    rng = np.random.default_rng(13)
    B = 20
    sd = np.array([1e2, 1e1, 3e-6])
    C = np.array([[1.0, -0.6, 0.87], [-0.6, 1.0, -0.9], [0.87, -0.9, 1.0]])
    P = C * np.outer(sd, sd)
    assert np.linalg.cond(P) > 1e16
    Lp = np.linalg.cholesky(P)
    Wp = np.linalg.inv(Lp)
    c = np.array([1.4e5, 2e4, 1e-3]) + rng.standard_normal((B, 3)) @ Lp.T
    H, sig = np.array([[0.7, 0.2, 0.0]]), 100.0
    z = c @ H.T + sig * rng.standard_normal((B, 1))
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + sig**2)
    x_exact = c + (z - c @ H.T) @ K.T

    def r(x):
        prior = ((x - t(c)).unsqueeze(-2) @ t(Wp).mT).squeeze(-2)
        return torch.cat([prior, (t(z) - x @ t(H).mT) / sig], -1)

    res = bounded_least_squares(r, t(c), Box(t([-np.inf, -np.inf, 0.0]), None))
    assert bool(res.converged.all())
    whitened = (res.x.numpy() - x_exact) @ Wp.T
    assert np.abs(whitened).max() < 1e-9
