"""N4SID subspace identification: against the true system on noise-free data, against the
independent ``nfoursid`` package on noisy data (similarity-invariant quantities), and as the
start of a linear EM fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfilt.exceptions import InputError
from torchfilt.filters import kalman_filter
from torchfilt.models import LinearGaussianModel
from torchfilt.models.subspace import subspace_identify, subspace_order, subspace_start
from torchfilt.optim import StoppingOptions
from torchfilt.training import fit_em

nfoursid = pytest.importorskip("nfoursid.nfoursid")


def _system(seed=0, n=4, m=2, p=1, q=0.01, r=0.01):
    rng = np.random.default_rng(seed)
    V = np.linalg.qr(rng.standard_normal((n, n)))[0]
    A = V @ np.diag([0.9, 0.7, -0.6, 0.4][:n]) @ V.T
    H = rng.standard_normal((m, n))
    B = np.ones((n, p))
    return rng, A, H, B, q * np.eye(n), r * np.eye(m)


def _simulate(rng, A, H, B, Q, R, reps, T, noise=True):
    n, m, p = A.shape[0], H.shape[0], B.shape[1]
    u = rng.standard_normal((reps, T, p))
    y = np.zeros((reps, T, m))
    for k in range(reps):
        x = np.zeros(n)
        for t in range(T):
            x = A @ x + B @ u[k, t] + (rng.multivariate_normal(np.zeros(n), Q) if noise else 0)
            y[k, t] = H @ x + (rng.multivariate_normal(np.zeros(m), R) if noise else 0)
    return torch.tensor(y), torch.tensor(u)


def _markov(A, H, B, k):
    """``H A^j B``, ``j = 0..k-1``: the impulse response of ``x_t = A x_{t-1} + B u_t``."""
    return np.stack([H @ np.linalg.matrix_power(A, j) @ B for j in range(k)])


def _eig(A):
    return np.sort_complex(np.linalg.eigvals(np.asarray(A)))


def test_noise_free_data_give_the_true_system():
    rng, A, H, B, Q, R = _system()
    y, u = _simulate(rng, A, H, B, Q, R, reps=2, T=300, noise=False)
    fit = subspace_identify(y, u, order=4)
    M = fit.model
    np.testing.assert_allclose(_eig(M.A), _eig(A), atol=1e-8)
    got = _markov(M.A.numpy(), M.H.numpy(), M.B.numpy(), 8)
    np.testing.assert_allclose(got, _markov(A, H, B, 8), atol=1e-8)
    assert M.D is None and fit.x0.shape == (2, 4) and fit.P0.shape == (4, 4)
    # the simulation starts at x_{-1} = 0: the estimated initial states are 0
    np.testing.assert_allclose(fit.x0.numpy(), 0.0, atol=1e-7)
    order = subspace_order(y, u)
    assert order.suggested == 4
    # recordings of different lengths, as a list
    ragged = subspace_identify([y[0], y[1, :180]], [u[0], u[1, :180]], order=4)
    np.testing.assert_allclose(_eig(ragged.model.A), _eig(A), atol=1e-8)
    np.testing.assert_allclose(ragged.x0.numpy(), 0.0, atol=1e-7)


def test_feedthrough_and_no_input():
    rng, A, H, B, Q, R = _system(seed=1)
    y, u = _simulate(rng, A, H, B, Q, R, reps=1, T=300, noise=False)
    D = np.array([[0.5], [-1.0]])
    yD = y + u @ torch.tensor(D).mT
    M = subspace_identify(yD, u, order=4, feedthrough=True).model
    np.testing.assert_allclose(M.D.numpy(), D, atol=1e-8)
    np.testing.assert_allclose(_markov(M.A.numpy(), M.H.numpy(), M.B.numpy(), 5),
                               _markov(A, H, B, 5), atol=1e-8)  # fmt: skip
    # output only (a stochastic system): the dominant eigenvalue, from long data
    y2, _ = _simulate(rng, A, H, B * 0, np.eye(4) * 0.1, np.eye(2) * 0.01, reps=4, T=2000)
    M2 = subspace_identify(y2, order=4).model
    assert M2.B is None
    assert abs(float(torch.linalg.eigvals(M2.A).abs().max()) - 0.9) < 0.02


def test_noisy_data_agree_with_nfoursid():
    import pandas as pd

    rng, A, H, B, Q, R = _system()
    y, u = _simulate(rng, A, H, B, Q, R, reps=1, T=3000)
    fit = subspace_identify(y, u, order=4, block_rows=8)
    frame = pd.DataFrame(np.hstack([y[0].numpy(), u[0].numpy()]), columns=["y0", "y1", "u0"])
    ref = nfoursid.NFourSID(frame, output_columns=["y0", "y1"], input_columns=["u0"],
                            num_block_rows=8)  # fmt: skip
    ref.subspace_identification()
    ss, _ = ref.system_identification(rank=4)
    M = fit.model
    # nfoursid: s_{k+1} = A s_k + B u_k, y_k = C s_k + D u_k, the predictor form of
    # x_t = A x_{t-1} + B u_t (s_t = x_{t-1}): impulse response D, C B, C A B, ...
    ref_markov = np.stack(
        [ss.d] + [ss.c @ np.linalg.matrix_power(ss.a, j) @ ss.b for j in range(7)]
    )
    got = _markov(M.A.numpy(), M.H.numpy(), M.B.numpy(), 8)
    true = _markov(A, H, B, 8)
    # the two estimates agree with each other and with the truth to the noise level
    assert np.abs(got[1:] - ref_markov[1:]).max() < 0.05
    assert np.abs(got[1:] - true[1:]).max() < 0.05
    # the dominant eigenvalues (the weakest mode, 0.4, is poorly excited for both)
    np.testing.assert_allclose(_eig(M.A).real[[0, 2, 3]], _eig(ss.a).real[[0, 2, 3]], atol=0.03)
    np.testing.assert_allclose(_eig(M.A).real[[0, 3]], [-0.6, 0.9], atol=0.02)


def test_subspace_start_keeps_the_gauge_and_em_refines_it_to_the_true_likelihood():
    rng, A, H, B, Q, R = _system()
    y, u = _simulate(rng, A, H, B, Q, R, reps=4, T=500)
    user = LinearGaussianModel(
        torch.tensor(A) * 0, torch.tensor(H), torch.eye(4, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64), torch.zeros(4, 1, dtype=torch.float64),
    )  # fmt: skip
    start = subspace_start(user, y, u, known_channels=[0])
    np.testing.assert_allclose(start.model.H[0].numpy(), H[0], atol=1e-12)
    # the change of coordinates leaves the likelihood of the identified model unchanged
    raw = subspace_identify(y, u, order=4)

    def ll(model, x0, P0):
        return float(kalman_filter(model, y, u, x0=x0, P0=P0).log_likelihood.sum())

    assert abs(ll(start.model, start.x0, start.P0) - ll(raw.model, raw.x0, raw.P0)) < 1e-6
    true_ll = ll(LinearGaussianModel(*map(torch.tensor, (A, H, Q, R, B))), torch.zeros(4),
                 torch.eye(4, dtype=torch.float64))  # fmt: skip
    fit = fit_em(start.model, y, u, x0=start.x0, P0=start.P0, known_channels=[0],
                 iterations=40, stopping=StoppingOptions(tol=0.0, rtol=0.0))  # fmt: skip
    steps = y.shape[0] * y.shape[1]
    assert fit.log_likelihood > ll(start.model, start.x0, start.P0)
    # within a few nats per 1000 steps of the true model (the MLE is above the truth)
    assert (true_ll - fit.log_likelihood) / steps * 1000 < 3.0
    # a zero start is far worse after the same iterations
    zero = fit_em(user, y, u, x0=torch.zeros(4), P0=torch.eye(4, dtype=torch.float64),
                  known_channels=[0], iterations=40, stopping=StoppingOptions(tol=0.0, rtol=0.0))  # fmt: skip
    assert zero.log_likelihood < fit.log_likelihood


def test_errors():
    rng, A, H, B, Q, R = _system()
    y, u = _simulate(rng, A, H, B, Q, R, reps=1, T=100, noise=False)
    bad = y.clone()
    bad[0, 3, 0] = float("nan")
    with pytest.raises(InputError, match="complete data"):
        subspace_identify(bad, u, order=4)
    with pytest.raises(InputError, match="order"):
        subspace_identify(y, u, order=40, block_rows=6)
    with pytest.raises(InputError, match="too short"):
        subspace_identify(y[:, :10], u[:, :10], order=2, block_rows=6)


def test_stable_keeps_a_stable_estimate_as_it_is():
    rng, A, H, B, Q, R = _system(seed=3)
    y, u = _simulate(rng, A, H, B, Q, R, reps=2, T=300)
    plain = subspace_identify(y, u, order=4).model
    kept = subspace_identify(y, u, order=4, stable=True).model
    assert float(np.abs(np.linalg.eigvals(plain.A.numpy())).max()) < 1.0
    torch.testing.assert_close(kept.A, plain.A, rtol=0, atol=0)


def _observability(A, C, rows):
    return torch.tensor(np.concatenate([C @ np.linalg.matrix_power(A, j) for j in range(rows)]))


@pytest.mark.parametrize("seed", range(20))
def test_stable_shift_invariance_has_no_pole_outside_the_unit_circle(seed):
    from torchfilt.models.subspace import _shift_invariance

    rng = np.random.default_rng(seed)
    n, m = 3, 2
    # an exactly shift-invariant Gamma of an unstable system: the plain estimate recovers it
    V = rng.standard_normal((n, n))
    A = V @ np.diag([1.05, 0.8, -0.3]) @ np.linalg.inv(V)
    Gam = _observability(A, rng.standard_normal((m, n)), rows=6)
    plain = _shift_invariance(Gam, m, stable=False)
    np.testing.assert_allclose(_eig(plain), _eig(A), atol=1e-8)
    stab = _shift_invariance(Gam, m, stable=True)
    assert float(np.abs(np.linalg.eigvals(stab.numpy())).max()) <= 1.0 + 1e-12
    # and any Gamma at all (no structure): the bound is the projection's, not the data's
    G = torch.tensor(rng.standard_normal((12, n)) * rng.uniform(0.1, 10.0, n))
    assert float(np.abs(np.linalg.eigvals(_shift_invariance(G, m, stable=True).numpy())).max()) <= (
        1.0 + 1e-12
    )
