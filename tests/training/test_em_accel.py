"""SQUAREM-accelerated linear EM (``fit_em(accelerate=...)``) against a numpy reference of the
scheme built on the numpy closed-form EM of ``test_em_exact`` and the dense joint likelihood,
and against the optimum itself (a stationary point of the exact log-likelihood)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal
from test_em_exact import _em_problem, _fit_em, _joint_prior, _np_em, _simulate

import torchfilt.training.em_accel as em_accel
from torchfilt.exceptions import InputTypeError
from torchfilt.filters import kalman_filter
from torchfilt.models import CholeskyCovariance, LinearGaussianModel, StateSpaceModel
from torchfilt.optim import StoppingOptions
from torchfilt.training import fit_em

f64 = torch.float64


def _np_loglik(theta, x0, P0, u, y) -> float:
    """The exact log-likelihood by dense linear algebra (the joint Gaussian of all steps)."""
    A, H, B, Q, R = theta
    total = 0.0
    for i in range(y.shape[0]):
        mean, cov, G = _joint_prior(A, H, B, Q, R, x0, P0, u[i])
        S = G @ cov @ G.T + np.kron(np.eye(y.shape[1]), R)
        total += multivariate_normal(G @ mean, S).logpdf(y[i].reshape(-1))
    return float(total)


def _np_squarem(theta0, x0, P0, u, y, cycles, fixed=()):
    """The scheme of ``torchfilt.training.em_accel`` in numpy: S3 steplength in
    ``[-max_step, -1]``, kept where ``Q, R`` stay PSD and the likelihood is no lower than at the
    cycle's start (else halved towards -1), then a stabilising EM step."""

    def em(th):
        A, H, B, Q, R = th
        return list(_np_em(A, H, B, Q, R, x0, P0, u, y, [0], 1, fixed))

    theta, max_step = list(theta0), 1.0
    for _ in range(cycles):
        ll0 = _np_loglik(theta, x0, P0, u, y)
        t1 = em(theta)
        t2 = em(t1)
        r = [a - b for a, b in zip(t1, theta, strict=True)]
        v = [c - 2 * a + b for c, a, b in zip(t2, t1, theta, strict=True)]
        nr = np.sqrt(sum((x**2).sum() for x in r))
        nv = np.sqrt(sum((x**2).sum() for x in v))
        alpha = -min(max(nr / nv, 1.0), max_step) if nv > 0 else -1.0
        if alpha <= -max_step:
            max_step *= 4.0
        x = t2
        for _k in range(3):
            if alpha > -1.0 - 1e-3:
                break
            cand = [t - 2 * alpha * a + alpha**2 * b for t, a, b in zip(theta, r, v, strict=True)]
            psd = all(np.linalg.eigvalsh(cand[i]).min() >= 0 for i in (3, 4))
            if psd and _np_loglik(cand, x0, P0, u, y) >= ll0:
                x = cand
                break
            alpha = (alpha - 1.0) / 2.0
            max_step = max(1.0, -alpha)
        theta = em(x)
    return theta


def _matrices(model):
    return (
        model.A,
        model.H,
        model.B,
        model.transition.noise_cov(),
        model.measurement.noise_cov(),
    )


@pytest.mark.parametrize(("cycles", "fixed"), [(1, ()), (4, ()), (3, ("A",)), (3, ("Q", "H"))])
def test_accelerated_em_equals_a_numpy_squarem(cycles, fixed):
    theta, x0, P0, u, y = _em_problem()
    fit = _fit_em(theta, x0, P0, u, y, cycles, fixed=fixed)
    assert fit.iterations == cycles and fit.history[-1]["e_steps"] >= 3 * cycles
    want = _np_squarem(theta, x0, P0, u, y, cycles, fixed)
    for name, g, w in zip("AHBQR", _matrices(fit.model), want, strict=True):
        np.testing.assert_allclose(g.numpy(), w, atol=1e-9, rtol=0, err_msg=name)
    for name in fixed:  # a fixed block keeps its value exactly
        i = "AHBQR".index(name)
        assert np.array_equal(_matrices(fit.model)[i].numpy(), theta[i])


def test_first_cycle_is_three_plain_em_steps():
    theta, x0, P0, u, y = _em_problem(3)
    fast = _fit_em(theta, x0, P0, u, y, 1)
    plain = _fit_em(theta, x0, P0, u, y, 3, accelerate=False)
    for g, w in zip(_matrices(fast.model), _matrices(plain.model), strict=True):
        torch.testing.assert_close(g, w, atol=1e-12, rtol=0)


def test_a_refused_extrapolation_falls_back_to_plain_em(monkeypatch):
    """With every extrapolation refused, a cycle is three plain EM steps."""
    monkeypatch.setattr(em_accel, "_admissible", lambda em: False)
    theta, x0, P0, u, y = _em_problem(5)
    fast = _fit_em(theta, x0, P0, u, y, 3)
    plain = _fit_em(theta, x0, P0, u, y, 9, accelerate=False)
    for g, w in zip(_matrices(fast.model), _matrices(plain.model), strict=True):
        torch.testing.assert_close(g, w, atol=1e-11, rtol=0)


def test_accelerated_em_climbs_and_ends_at_a_stationary_point():
    """Under the full gauge (``H = I`` known, so ``A, Q, R`` are identified): monotone, above
    plain EM at the same number of E-steps, and at the end the exact log-likelihood's gradient
    in ``A, Q, R`` (autograd through the Kalman filter) vanishes."""
    rng = np.random.default_rng(2)
    A = np.array([[0.9, 0.2], [-0.1, 0.7]])
    H, B = np.eye(2), np.zeros((2, 1))
    Q, R = np.array([[0.2, 0.05], [0.05, 0.3]]), 0.1 * np.eye(2)
    x0, P0 = torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64)
    y = torch.tensor(
        np.stack(
            [
                _simulate(rng, A, H, B, Q, R, np.zeros(2), np.eye(2), np.zeros((150, 1)))
                for _ in range(4)
            ]
        )
    )
    start = (
        torch.tensor(0.5 * A),
        torch.tensor(H),
        torch.eye(2, dtype=f64),
        torch.eye(2, dtype=f64),
    )

    def fit(iterations, accelerate=None):
        return fit_em(
            LinearGaussianModel(*start), y, x0=x0, P0=P0, known_channels=[0, 1],
            iterations=iterations, accelerate=accelerate,
            stopping=StoppingOptions(tol=0.0, rtol=0.0),
        )  # fmt: skip

    fast = fit(200)
    lls = [fast.initial_log_likelihood] + [r["log_likelihood"] for r in fast.history]
    assert all(b >= a - 1e-9 * abs(a) for a, b in itertools.pairwise(lls))
    plain = fit(fast.history[4]["e_steps"], accelerate=False)
    assert fast.history[4]["log_likelihood"] >= plain.log_likelihood - 1e-9

    def grads(A, H, Q, R):
        A, H, Q, R = (t.detach().clone().requires_grad_(True) for t in (A, H, Q, R))
        ll = kalman_filter(LinearGaussianModel(A, H, Q, R), y, x0=x0, P0=P0).log_likelihood
        ll.sum().backward()
        # Q and R are symmetric: only the symmetric part of their gradient is a direction
        sym = [0.5 * (t.grad + t.grad.mT) for t in (Q, R)]  # type: ignore[union-attr]
        return torch.cat([A.grad.flatten(), *(g.flatten() for g in sym)])  # type: ignore[union-attr]

    m = fast.model
    g0 = grads(*start)
    g1 = grads(m.A, m.H, m.transition.noise_cov(), m.measurement.noise_cov())
    assert g1.abs().max() < 1e-5 * g0.abs().max()


def test_accelerate_is_checked():
    theta, x0, P0, u, y = _em_problem()
    with pytest.raises(InputTypeError, match="accelerate"):
        _fit_em(theta, x0, P0, u, y, 1, accelerate="yes")
    nonlinear = StateSpaceModel(
        lambda x: torch.tanh(x), lambda x: x[..., :1], Q=CholeskyCovariance(torch.eye(2, dtype=f64)),
        R=torch.eye(1, dtype=f64),
    )  # fmt: skip
    with pytest.raises(InputTypeError, match="accelerate"):
        fit_em(
            nonlinear, torch.zeros(1, 5, 1, dtype=f64), x0=torch.zeros(2, dtype=f64),
            P0=torch.eye(2, dtype=f64), known_channels=[0], accelerate=1,
        )  # fmt: skip
