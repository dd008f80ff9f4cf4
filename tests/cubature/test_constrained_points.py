"""Box constraints and the CCKF's constrained cubature points and weights (spec cckf.md s.2)."""

import math

import numpy as np
import pytest
import torch
from conftest import BATCH_SHAPES, TIGHT, random_spd
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import constrained_points_ref

from torchfilt.cubature import SphericalRadialRule, constrained_points, sigma_points
from torchfilt.exceptions import ShapeError
from torchfilt.numerics import Box

D = torch.float64
#: weights sum to one up to round-off of 2n additions
SUM_ATOL = 1e-14
#: agreement with the NumPy/SciPy point-by-point reference
REF_ATOL = 1e-12


def t(a):
    return torch.tensor(a, dtype=D)


# ------------------------------------------------------------------------------------------ Box
def test_box_rejects_lower_above_upper():
    with pytest.raises(ValueError, match=r"lower > upper at index \[1\]: 2.0 > 1.0"):
        Box(t([0.0, 2.0]), t([1.0, 1.0]))


def test_box_rejects_nan_and_empty():
    with pytest.raises(ValueError, match="lower contains NaN"):
        Box(t([0.0, float("nan")]), t([1.0, 1.0]))
    with pytest.raises(ValueError, match="empty"):
        Box(t([float("inf"), 0.0]), None)


def test_box_shape_errors():
    with pytest.raises(ShapeError, match=r"upper: expected shape \(\.\.\., n\) with n = 3"):
        Box(t([0.0, 0.0, 0.0]), t([1.0, 1.0]))
    with pytest.raises(ShapeError, match="lower: expected shape"):
        Box(t([0.0, 0.0, 0.0]), None, n=2)
    with pytest.raises(ShapeError, match="do not broadcast"):
        Box(torch.zeros(3, 2, dtype=D), torch.ones(4, 2, dtype=D))
    with pytest.raises(ValueError, match="scalar bound needs"):
        Box(0.0, 1.0)


def test_box_one_sided_project_contains():
    box = Box(lower=[0.0, float("-inf")], upper=None)
    assert box.dim == 2 and torch.isinf(box.upper).all()
    x = t([[-1.0, -5.0], [2.0, 3.0]])
    assert torch.equal(box.project(x), t([[0.0, -5.0], [2.0, 3.0]]))
    assert box.contains(x).tolist() == [False, True]
    assert box.bounded and not Box(n=3).bounded


# ---------------------------------------------------------------------------------------- points
@st.composite
def gaussian_in_box(draw):
    """A random box (some sides infinite), a covariance and a mean inside the box."""
    n = draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-3.0, 0.0, n)
    hi = lo + rng.uniform(0.01, 4.0, n)
    lo[rng.random(n) < 0.25] = -np.inf
    hi[rng.random(n) < 0.25] = np.inf
    span_lo = np.where(np.isfinite(lo), lo, -5.0)
    span_hi = np.where(np.isfinite(hi), hi, 5.0)
    u = rng.random(n)
    u[rng.random(n) < 0.15] = 0.0  # some means exactly on a bound
    m = span_lo + u * (span_hi - span_lo)
    P = random_spd(rng, n, scale=draw(st.floats(1e-3, 10.0)), cond=draw(st.floats(1.0, 1e3)))
    theta = draw(st.sampled_from(["paper", "std"]))
    return m, P, lo, hi, theta


@settings(max_examples=200, deadline=None)
@given(gaussian_in_box())
def test_weights_and_points_properties(case):
    """Weights are >= 0 and sum to 1; every point is in the box; points follow their directions."""
    m, P, lo, hi, theta = case
    n = len(m)
    box = Box(t(lo), t(hi))
    S = torch.linalg.cholesky(t(P))
    cp = constrained_points(t(m), S, box, theta=theta)
    assert cp.points.shape == (2 * n, n) and cp.weights.shape == (2 * n,)
    assert bool((cp.weights >= 0).all())
    assert abs(float(cp.weights.sum()) - 1.0) <= SUM_ATOL
    assert bool(box.contains(cp.points).all())
    assert bool(((cp.lam >= 0) & (cp.lam <= 1)).all())
    # X_i = m + lambda_i dx_i: the projection inside only removed round-off
    dx = SphericalRadialRule(3).unit_points(n, dtype=D)[0] @ S.mT
    raw = t(m) + cp.lam.unsqueeze(-1) * dx
    scale = 1.0 + float(np.abs(m).max() + dx.abs().max())
    assert torch.allclose(cp.points, raw, atol=1e-13 * scale, rtol=0)
    # and the NumPy reference, written independently from the spec, agrees
    X_ref, w_ref = constrained_points_ref(m, P, lo, hi, theta)
    np.testing.assert_allclose(cp.points.numpy(), X_ref, atol=REF_ATOL * scale, rtol=0)
    np.testing.assert_allclose(cp.weights.numpy(), w_ref, atol=REF_ATOL, rtol=0)


def test_no_bounds_gives_the_ckf_points_and_weights():
    rng = np.random.default_rng(0)
    n = 4
    m, P = rng.standard_normal(n), random_spd(rng, n)
    S = torch.linalg.cholesky(t(P))
    cp = constrained_points(t(m), S, Box(n=n))
    xi, wm, _ = SphericalRadialRule(3).unit_points(n, dtype=D)
    assert torch.equal(cp.points, sigma_points(t(m), S, xi))
    assert torch.allclose(cp.weights, wm, rtol=0, atol=TIGHT * 1e-3)
    assert bool(torch.isinf(cp.theta).all())


def test_hand_computed_one_dimensional_case():
    """n = 1, mean 1, sd 2, box [0, 10]: theta+ = 4.5, theta- = 0.5, the lower point sits on 0."""
    cp = constrained_points(t([1.0]), t([[2.0]]), Box(t([0.0]), t([10.0])))
    assert torch.allclose(cp.theta, t([4.5, 0.5]), rtol=0, atol=TIGHT)
    assert torch.allclose(cp.points.squeeze(-1), t([3.0, 0.0]), rtol=0, atol=TIGHT)
    Phi = lambda z: 0.5 * (1 + math.erf(z / math.sqrt(2)))  # noqa: E731
    Fa, Fb = Phi(4.5) - 0.5, Phi(0.5) - 0.5
    assert torch.allclose(cp.weights, t([Fa / (Fa + Fb), Fb / (Fa + Fb)]), rtol=0, atol=TIGHT)


def test_std_reading_scales_theta_by_sqrt_n():
    """n = 2, diagonal P: the 'std' weights equal the 'paper' weights at sqrt(2) theta."""
    m, S, box = t([1.0, 2.0]), torch.diag(t([1.0, 0.5])), Box(t([0.0, 0.0]), t([5.0, 2.5]))
    paper = constrained_points(m, S, box, theta="paper")
    std = constrained_points(m, S, box, theta="std")
    assert torch.equal(paper.points, std.points) and torch.equal(paper.theta, std.theta)
    Phi = torch.special.ndtr
    F = Phi(math.sqrt(2) * paper.theta) - 0.5
    want = torch.cat([F[:2] / (F[:2] + F[2:]), F[2:] / (F[:2] + F[2:])]) / 2
    assert torch.allclose(std.weights, want, rtol=0, atol=TIGHT)
    assert not torch.allclose(std.weights, paper.weights, atol=1e-3)


def test_degenerate_pair_on_a_corner_gets_equal_weights():
    """Mean at the corner (0, 0) and a direction (1, -1): both points of the pair sit on the mean."""
    S = torch.linalg.cholesky(t([[1.0, -0.9], [-0.9, 1.0]]))
    cp = constrained_points(t([0.0, 0.0]), S, Box(t([0.0, 0.0]), None))
    assert float(cp.theta[0]) == 0.0 and float(cp.theta[2]) == 0.0
    assert torch.allclose(cp.weights[[0, 2]], t([0.25, 0.25]), rtol=0, atol=TIGHT)
    assert torch.equal(cp.points[0], t([0.0, 0.0])) and torch.equal(cp.points[2], t([0.0, 0.0]))


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
def test_batched_equals_loop(batch):
    gen = torch.Generator().manual_seed(1)
    m = torch.rand(*batch, 3, dtype=D, generator=gen)
    A = torch.randn(*batch, 3, 3, dtype=D, generator=gen)
    S = torch.linalg.cholesky(A @ A.mT + 0.1 * torch.eye(3, dtype=D))
    lo = -torch.rand(*batch, 3, dtype=D, generator=gen)
    box = Box(lo, t([1.0, float("inf"), 2.0]))
    cp = constrained_points(m, S, box, theta="std")
    for idx in np.ndindex(*batch):
        one = constrained_points(m[idx], S[idx], Box(lo[idx], box.upper), theta="std")
        assert torch.allclose(cp.points[idx], one.points, rtol=0, atol=1e-15)
        assert torch.allclose(cp.weights[idx], one.weights, rtol=0, atol=1e-15)


def test_gradients_are_finite_with_infinite_bounds():
    m = t([0.5, 0.2]).requires_grad_()
    L = t([[1.0, 0.0], [0.3, 0.8]]).requires_grad_()
    cp = constrained_points(m, L, Box(t([0.0, float("-inf")]), t([float("inf"), 1.0])))
    (cp.points.sum() + (cp.weights * torch.arange(4, dtype=D)).sum()).backward()
    assert torch.isfinite(m.grad).all() and torch.isfinite(L.grad).all()
    assert float(m.grad.abs().sum()) > 0


def test_argument_errors():
    with pytest.raises(ValueError, match="theta must be"):
        constrained_points(t([0.0]), t([[1.0]]), Box(n=1), theta="sd")
    with pytest.raises(ShapeError, match="sqrt: expected shape"):
        constrained_points(t([0.0, 0.0]), t([[1.0]]), Box(n=2))
    with pytest.raises(ShapeError, match="box: dimension 3"):
        constrained_points(t([0.0, 0.0]), torch.eye(2, dtype=D), Box(n=3))
