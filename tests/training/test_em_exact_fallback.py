"""The exact E-step of ``fit_em`` in the square-root form where the standard one breaks.

The model: a 4-state linear-Gaussian model from the robot-arm log of
``scripts/bench_real_logs.py`` (an EM iterate, rounded): process-noise eigenvalues from 2e-9 to
8e-3 and a pole at 1.27. Over 200 steps the standard-form filter's covariance loses
definiteness (a ``PrecisionWarning``) and its log-likelihood is thousands of nats off; the
reference is the same recursion in 40-digit arithmetic (``mpmath``, which torch depends on).
"""

from __future__ import annotations

import itertools
import warnings

import mpmath
import pytest
import torch

from torchfilt.exceptions import PrecisionWarning
from torchfilt.filters import kalman_smoother
from torchfilt.models import LinearGaussianModel
from torchfilt.training import fit_em
from torchfilt.training.em_exact import exact_smoother

D = torch.float64
A = torch.tensor(
    [
        [0.3317, -0.3260, -0.8992, 3.3058],
        [-0.0789, 1.2007, 0.5876, 0.8448],
        [-0.1647, -0.3111, 1.1053, 1.3897],
        [-0.0864, 0.0827, -0.2805, 1.0881],
    ],
    dtype=D,
)
L = torch.tensor(
    [
        [9.2e-2, 0, 0, 0],
        [1.16e-3, 1e-4, 0, 0],
        [-1.08e-3, -1e-4, 5e-4, 0],
        [-4.27e-3, -2e-4, 1e-4, 1e-4],
    ],
    dtype=D,
)
H = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D)
R = torch.tensor([[1e-4]], dtype=D)
X0, P0 = torch.zeros(4, dtype=D), torch.eye(4, dtype=D)


def _model() -> LinearGaussianModel:
    return LinearGaussianModel(A, H, L @ L.mT, R)


def _y(T: int = 200) -> torch.Tensor:
    return torch.randn(T, 1, generator=torch.Generator().manual_seed(0), dtype=D)


def _reference_log_likelihood(y: torch.Tensor) -> float:
    """The Kalman filter's log-likelihood in 40-digit arithmetic (textbook recursion)."""
    mp = mpmath.mp
    mp.dps = 40
    A_, H_, Q_ = (mpmath.matrix(x.tolist()) for x in (A, H, L @ L.mT))
    r = mpmath.mpf(float(R))
    x, P, ll = mpmath.matrix(4, 1), mpmath.eye(4), mpmath.mpf(0)
    for v in y[:, 0].tolist():
        x, P = A_ * x, A_ * P * A_.T + Q_
        S = (H_ * P * H_.T)[0, 0] + r
        e = mpmath.mpf(v) - (H_ * x)[0, 0]
        K = P * H_.T / S
        x, P = x + K * e, P - K * H_ * P
        ll += -(mpmath.log(2 * mpmath.pi * S) + e * e / S) / 2
    return float(ll)


def test_the_standard_form_breaks_on_this_model() -> None:
    """The premise: the standard form warns and is far off the 40-digit reference; the
    square-root form is on it."""
    y = _y()
    want = _reference_log_likelihood(y)
    with pytest.warns(PrecisionWarning, match="lost positive definiteness"):
        std = kalman_smoother(_model(), y, x0=X0, P0=P0)
    assert abs(float(std.filtered.log_likelihood.sum()) - want) > 1000.0
    sq = kalman_smoother(_model(), y, x0=X0, P0=P0, sqrt=True)
    assert float(sq.filtered.log_likelihood.sum()) == pytest.approx(want, rel=1e-9)


def test_exact_smoother_takes_the_square_root_form_where_the_standard_one_breaks() -> None:
    y = _y()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the broken standard form's warning is not passed on
        sm = exact_smoother(_model(), y, None, X0, P0)
    sq = kalman_smoother(_model(), y, x0=X0, P0=P0, sqrt=True)
    assert float(sm.filtered.log_likelihood.sum()) == pytest.approx(
        _reference_log_likelihood(y), rel=1e-9
    )
    assert torch.equal(sm.mean, sq.mean) and torch.equal(sm.cov, sq.cov)


def test_exact_smoother_keeps_the_standard_form_where_it_is_sound() -> None:
    """A stable model: the standard form's result, bit for bit (no second pass)."""
    m = LinearGaussianModel(0.5 * torch.eye(4, dtype=D), H, 0.1 * torch.eye(4, dtype=D), R)
    y = _y(50)
    sm = exact_smoother(m, y, None, X0, P0)
    std = kalman_smoother(m, y, x0=X0, P0=P0)
    assert torch.equal(sm.mean, std.mean) and torch.equal(sm.cov, std.cov)
    assert sm.filtered.log_likelihood.sum() == std.filtered.log_likelihood.sum()


def test_fit_em_starts_from_the_right_likelihood_and_climbs() -> None:
    """fit_em from the model (A and Q learned, H and R known): its start is the 40-digit
    log-likelihood (the standard form's was thousands of nats off), and EM (SQUAREM cycles by
    default) never lowers it and ends with finite parameters. Before, the E-step used the
    standard form alone."""
    y = _y()
    fit = fit_em(_model(), y, x0=X0, P0=P0, known_channels=[0], fixed=("H", "R"), iterations=5)
    assert fit.initial_log_likelihood == pytest.approx(_reference_log_likelihood(y), rel=1e-9)
    lls = [fit.initial_log_likelihood] + [h["log_likelihood"] for h in fit.history]
    assert all(b >= a - 1e-9 * abs(a) for a, b in itertools.pairwise(lls))
    assert lls[-1] > lls[0]
    assert bool(torch.isfinite(fit.model.A).all())
