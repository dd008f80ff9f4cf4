"""Cubature rules integrate polynomials of their degree exactly against N(0, I)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchfilt.cubature import GaussHermiteRule, SphericalRadialRule, UnscentedRule, sigma_points

#: round-off allowed, relative to the sum of the absolute terms of the cubature sum
MOMENT_RTOL = 1e-12


def gaussian_moment(exponents: np.ndarray) -> float:
    """E[prod_i x_i^k_i] for x ~ N(0, I): product of (k-1)!! for even k, 0 if any k is odd."""
    out = 1.0
    for k in exponents:
        if k % 2:
            return 0.0
        out *= math.prod(range(int(k) - 1, 0, -2)) if k else 1.0
    return out


def rule_moment(rule, exponents: np.ndarray) -> float:
    xi, wm, _ = rule.unit_points(len(exponents))
    vals = torch.prod(xi ** torch.tensor(exponents, dtype=xi.dtype), dim=-1)
    return float(wm @ vals)


def assert_exact(rule, exponents: np.ndarray) -> None:
    xi, wm, _ = rule.unit_points(len(exponents))
    vals = torch.prod(xi ** torch.tensor(exponents, dtype=xi.dtype), dim=-1)
    scale = float(wm.abs() @ vals.abs()) + 1.0
    got, want = float(wm @ vals), gaussian_moment(exponents)
    assert abs(got - want) <= MOMENT_RTOL * scale, (rule, exponents, got, want)


@st.composite
def monomial(draw, max_dim: int, degree: int):
    n = draw(st.integers(1, max_dim))
    exps = np.zeros(n, dtype=int)
    budget = draw(st.integers(0, degree))
    for _ in range(budget):
        exps[draw(st.integers(0, n - 1))] += 1
    return exps


@settings(max_examples=150, deadline=None)
@given(monomial(12, 3))
def test_third_degree_rule_is_exact(exps):
    assert_exact(SphericalRadialRule(3), exps)


@settings(max_examples=150, deadline=None)
@given(monomial(12, 5))
def test_fifth_degree_rule_is_exact(exps):
    assert_exact(SphericalRadialRule(5), exps)


@settings(max_examples=150, deadline=None)
@given(monomial(12, 3), st.floats(0.3, 2.0), st.floats(0.0, 2.0), st.floats(0.0, 3.0))
def test_unscented_rule_is_exact_to_degree_three(exps, alpha, beta, kappa):
    rule = UnscentedRule(alpha, beta, kappa)
    assert_exact(rule, exps)


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 4), st.integers(1, 5), st.data())
def test_gauss_hermite_rule_is_exact_per_variable(n, order, data):
    exps = np.array(data.draw(st.lists(st.integers(0, 2 * order - 1), min_size=n, max_size=n)))
    assert_exact(GaussHermiteRule(order), exps)


def test_exactness_check_can_fail():
    """The third-degree rule is not exact for x^4 (it gives n, not 3): the check detects it."""
    exps = np.array([4, 0, 0, 0, 0])
    assert abs(rule_moment(SphericalRadialRule(3), exps) - gaussian_moment(exps)) > 1.0
    with pytest.raises(AssertionError):
        assert_exact(SphericalRadialRule(3), exps)


@pytest.mark.parametrize(
    "rule", [SphericalRadialRule(3), SphericalRadialRule(5), UnscentedRule(), GaussHermiteRule(3)]
)
@pytest.mark.parametrize("n", [1, 2, 5])
def test_weights_sum_to_one_and_points_count(rule, n):
    xi, wm, wc = rule.unit_points(n)
    assert float(wm.sum()) == pytest.approx(1.0, abs=1e-14)
    assert xi.shape == (rule.num_points(n), n)
    # second moment identity, which the filters rely on: sum wc xi xi^T = I
    assert torch.allclose((xi * wc[:, None]).T @ xi, torch.eye(n, dtype=xi.dtype), atol=1e-12)


def test_sigma_points_reproduce_mean_and_cov():
    rule = SphericalRadialRule(3)
    mean = torch.randn(7, 4, dtype=torch.float64)
    A = torch.randn(7, 4, 4, dtype=torch.float64)
    P = A @ A.mT + torch.eye(4)
    X = sigma_points(mean, torch.linalg.cholesky(P), rule.unit_points(4)[0])
    _, wm, wc = rule.unit_points(4)
    m = wm @ X
    d = X - m.unsqueeze(-2)
    assert torch.allclose(m, mean, atol=1e-12)
    assert torch.allclose(d.mT @ (d * wc[:, None]), P, atol=1e-10)


def test_rule_argument_errors():
    with pytest.raises(ValueError, match="degree"):
        SphericalRadialRule(4)
    with pytest.raises(ValueError, match="order"):
        GaussHermiteRule(0)
    with pytest.raises(ValueError, match="n must be"):
        SphericalRadialRule().unit_points(0)
    with pytest.raises(ValueError, match="lambda"):
        UnscentedRule(kappa=-5.0).unit_points(3)
