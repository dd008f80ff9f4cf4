"""The DARE solver and steady-state gain: scipy agreement, closed forms, and the non-detectable cases."""

import numpy as np
import pytest
import scipy.linalg
import torch
from conftest import random_spd

from torchfilt.dmc import (
    FOPDT,
    IPDT,
    StepResponseModel,
    integrating_fractionator,
    realize,
    steady_gain,
)
from torchfilt.exceptions import InputError, NotDetectableError, ShapeError
from torchfilt.numerics import check_detectable, solve_dare, steady_state_kalman

D = torch.float64
#: Relative agreement with scipy's solve_discrete_are called directly on the dual pair (the library
#: wraps the same solver: this checks the dual-form transposition, symmetrisation and gain formula).
SCIPY_RTOL = 1e-9
#: Relative residual of our solution in the Riccati equation.
RESIDUAL_TOL = 1e-12
#: Agreement between two computations of the same gain (per-CV decoupled vs full DARE): scipy's QZ
#: method is accurate to ~1e-10 on the 40-state full problem.
GAIN_ATOL = 1e-9


def t(a):
    return torch.tensor(a, dtype=D)


def scipy_filter_dare(A, C, Q, R):
    """Filter-form DARE via scipy's control-form solver on the dual system."""
    return scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)


def residual(A, C, Q, R, S):
    K = S @ C.T @ np.linalg.inv(C @ S @ C.T + R)
    rhs = A @ (S - K @ C @ S) @ A.T + Q
    return np.abs(rhs - S).max() / max(np.abs(S).max(), 1.0)


def random_system(rng, n, m, unstable):
    A = rng.standard_normal((n, n))
    A *= (1.3 if unstable else 0.9) / max(abs(np.linalg.eigvals(A)))
    return A, rng.standard_normal((m, n)), random_spd(rng, n, 0.5), random_spd(rng, m, 1.0)


@pytest.mark.parametrize("unstable", [False, True], ids=["stable", "unstable"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dare_matches_scipy_random(seed, unstable):
    rng = np.random.default_rng(seed)
    A, C, Q, R = random_system(rng, 5, 2, unstable)
    ref = scipy_filter_dare(A, C, Q, R)
    got = solve_dare(t(A), t(C), t(Q), t(R)).numpy()
    np.testing.assert_allclose(got, ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL * np.abs(ref).max())
    assert residual(A, C, Q, R, got) < RESIDUAL_TOL


def test_dare_batched_equals_looped():
    rng = np.random.default_rng(3)
    systems = [random_system(rng, 4, 2, unstable=bool(i % 2)) for i in range(6)]
    A, C, Q, R = (
        t(np.stack([s[i] for s in systems])).reshape(3, 2, *systems[0][i].shape) for i in range(4)
    )
    batched = steady_state_kalman(A, C, Q, R)
    assert batched.gain.shape == (3, 2, 4, 2)
    for i in range(3):
        for j in range(2):
            one = steady_state_kalman(A[i, j], C[i, j], Q[i, j], R[i, j])
            torch.testing.assert_close(batched.pred_cov[i, j], one.pred_cov, rtol=0, atol=GAIN_ATOL)
            torch.testing.assert_close(batched.gain[i, j], one.gain, rtol=0, atol=GAIN_ATOL)


def test_scalar_random_walk_closed_form():
    # x_{k+1} = x_k + w, y = x + v: Sigma = (q + sqrt(q^2 + 4 q r)) / 2, K = Sigma / (Sigma + r)
    q, r = 0.3, 2.0
    res = steady_state_kalman(t([[1.0]]), t([[1.0]]), t([[q]]), t([[r]]))
    sigma = (q + np.sqrt(q * q + 4 * q * r)) / 2
    assert float(res.pred_cov) == pytest.approx(sigma, rel=SCIPY_RTOL)
    assert float(res.gain) == pytest.approx(sigma / (sigma + r), rel=SCIPY_RTOL)
    assert float(res.filt_cov) == pytest.approx(sigma * r / (sigma + r), rel=SCIPY_RTOL)
    assert float(res.innov_cov) == pytest.approx(sigma + r, rel=SCIPY_RTOL)


def dmc_model(integrating, N=20):
    Gu = [[FOPDT(2.0, 6.0, 2.5), FOPDT(-1.0, 3.0, 0.7)], [FOPDT(1.5, 4.0, 1.2), FOPDT(0.8, 2.0, 0)]]
    Gv = [[FOPDT(0.5, 5.0, 1.0)], [FOPDT(-0.7, 3.0, 0.0)]]
    for j, integ in enumerate(integrating):
        if integ:
            Gu[j] = [IPDT(0.1, 3.0, 1.5), IPDT(-0.05, 2.0, 0.4)]
            Gv[j] = [IPDT(0.02, 2.0, 0.0)]
    return StepResponseModel.from_transfer_functions(Gu, Gv, dt=1.0, horizon=N)


LAYOUTS = {"stable": (False, False), "integrating": (True, True), "mixed": (False, True)}


@pytest.mark.parametrize("layout", list(LAYOUTS.values()), ids=list(LAYOUTS))
@pytest.mark.parametrize("qY", [0.5, 0.01])
def test_dmc_realisation_dare_and_gain_match_scipy(layout, qY):
    r = realize(dmc_model(layout))
    A, H = r.A.numpy(), r.H.numpy()
    n, ny = A.shape[0], H.shape[0]
    Q, R = qY * np.eye(n), np.eye(ny)
    ref = scipy_filter_dare(A, H, Q, R)
    K_ref = ref @ H.T @ np.linalg.inv(H @ ref @ H.T + R)
    res = steady_state_kalman(r.A, r.H, t(Q), t(R))
    scale = np.abs(ref).max()
    np.testing.assert_allclose(res.pred_cov.numpy(), ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL * scale)
    np.testing.assert_allclose(res.gain.numpy(), K_ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL)
    # the per-CV decoupled solve used by the predictor gives the same gain
    K_blocks = steady_gain(r, t(Q), t(R))
    torch.testing.assert_close(K_blocks, res.gain, rtol=0, atol=GAIN_ATOL)


def test_full_and_decoupled_paths_agree_with_correlated_measurement_noise():
    r = realize(dmc_model((False, True)))
    n = r.state_dim
    Qy = t([[1.0, 0.3], [0.3, 0.5]])  # not diagonal: the full DARE is solved
    K = steady_gain(r, 0.2 * torch.eye(n, dtype=D), Qy)
    ref = scipy_filter_dare(r.A.numpy(), r.H.numpy(), 0.2 * np.eye(n), Qy.numpy())
    H = r.H.numpy()
    K_ref = ref @ H.T @ np.linalg.inv(H @ ref @ H.T + Qy.numpy())
    np.testing.assert_allclose(K.numpy(), K_ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL)


def remark1_system(integrating, N=15):
    """The paper's remark 1 / Lee & Xiao (2000) eq. (19): the prediction vector without y(k|k), H = 0."""
    L = N + 2 if integrating else N + 1
    M = torch.diag(torch.ones(L - 1, dtype=D), 1)
    if integrating:
        M[-1, -2], M[-1, -1] = -1.0, 2.0
    else:
        M[-1, -1] = 1.0
    M = M[1:, 1:]  # drop the y(k|k) block
    return M, torch.zeros(1, M.shape[0], dtype=D)


@pytest.mark.parametrize("integrating", [False, True], ids=["stable", "integrating"])
def test_remark1_H_zero_raises(integrating):
    M, H0 = remark1_system(integrating)
    n = M.shape[0]
    with pytest.raises(NotDetectableError, match=r"not detectable.*eigenvalue 1"):
        solve_dare(M, H0, 0.5 * torch.eye(n, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(NotDetectableError, match="not detectable"):
        steady_state_kalman(M, H0, 0.5 * torch.eye(n, dtype=D), torch.eye(1, dtype=D))


def test_our_realisation_with_H_zeroed_raises():
    r = realize(dmc_model((False, True)))
    with pytest.raises(NotDetectableError, match="not detectable"):
        steady_gain(
            r._replace(H=torch.zeros_like(r.H)),
            0.5 * torch.eye(r.state_dim, dtype=D),
            torch.eye(2, dtype=D),
        )


def test_undetectable_unstable_mode_raises_but_stable_unobserved_mode_is_fine():
    A = t([[1.2, 0.0], [0.0, 0.5]])
    Q, R = torch.eye(2, dtype=D), torch.eye(1, dtype=D)
    with pytest.raises(NotDetectableError, match=r"eigenvalue 1\.2"):
        solve_dare(A, t([[0.0, 1.0]]), Q, R)
    A2 = t([[0.5, 0.0], [0.0, 1.2]])  # the unobserved mode (0.5) is stable: detectable
    got = solve_dare(A2, t([[0.0, 1.0]]), Q, R).numpy()
    ref = scipy_filter_dare(A2.numpy(), np.array([[0.0, 1.0]]), np.eye(2), np.eye(1))
    np.testing.assert_allclose(got, ref, rtol=SCIPY_RTOL, atol=SCIPY_RTOL * np.abs(ref).max())


def test_not_stabilisable_raises():
    # a random walk with no process noise: the unit mode is never excited
    A = t([[1.0, 0.0], [0.0, 0.3]])
    with pytest.raises(NotDetectableError, match="not stabilisable"):
        solve_dare(A, t([[1.0, 1.0]]), t([[0.0, 0.0], [0.0, 1.0]]), torch.eye(1, dtype=D))


def test_batch_index_in_message():
    A = torch.stack([torch.eye(1, dtype=D), 1.1 * torch.eye(1, dtype=D)])
    C = torch.stack([torch.ones(1, 1, dtype=D), torch.zeros(1, 1, dtype=D)])
    with pytest.raises(NotDetectableError, match="batch index 1"):
        check_detectable(A, C)


def test_bad_inputs_name_the_argument():
    I2 = torch.eye(2, dtype=D)
    with pytest.raises(ShapeError, match=r"C: expected shape \(\.\.\., m, 2\)"):
        solve_dare(I2, torch.ones(1, 3, dtype=D), I2, torch.eye(1, dtype=D))
    with pytest.raises(ShapeError, match="Q: expected a square matrix"):
        solve_dare(I2, torch.ones(1, 2, dtype=D), torch.eye(3, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="R must be positive definite"):
        solve_dare(I2, torch.ones(1, 2, dtype=D), I2, torch.zeros(1, 1, dtype=D))
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        solve_dare(I2, torch.ones(1, 2, dtype=D), -I2, torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="A contains non-finite"):
        solve_dare(I2 * float("nan"), torch.ones(1, 2, dtype=D), I2, torch.eye(1, dtype=D))
    with pytest.raises(InputError, match=r"A must be a torch\.Tensor"):
        solve_dare(np.eye(2), torch.ones(1, 2, dtype=D), I2, torch.eye(1, dtype=D))


#: Relative accuracy the DARE solution must reach on a large, ill-conditioned plant (issue 24 item
#: 7): scipy's generalised-Schur answer alone has a relative residual of 2.6e-9 and a gain error of
#: 7e-8 on the 306-state realisation below; after the Newton refinement step 2e-16 and 1.2e-11.
LARGE_PLANT_RTOL = 1e-10


def doubling_dare(A, C, Q, R, iterations=50):
    """Filter-form DARE by the structure-preserving doubling algorithm (an independent reference:
    quadratic convergence, no Schur decomposition)."""
    Ak, G, H = A.T.copy(), C.T @ np.linalg.solve(R, C), Q.copy()
    eye = np.eye(A.shape[0])
    for _ in range(iterations):
        W = np.linalg.inv(eye + G @ H)
        Ak, G, H_new = Ak @ W @ Ak, G + Ak @ W @ G @ Ak.T, H + Ak.T @ H @ W @ Ak
        G, H_new = 0.5 * (G + G.T), 0.5 * (H_new + H_new.T)
        done = np.abs(H_new - H).max() <= 1e-15 * np.abs(H_new).max()
        H = H_new
        if done:
            break
    return H


def test_large_plant_dare_is_refined_to_full_accuracy():
    # the paper's section 3.2 plant: three integrating CVs, N = 100, a 306-state realisation; a
    # correlated measurement noise makes the full (not the per-CV) DARE the one solved
    Gu, Gv = integrating_fractionator()
    model = StepResponseModel.from_transfer_functions(
        Gu, Gv, dt=1.0, horizon=100, integrating=[True, True, True]
    )
    r = realize(model)
    A, H = r.A.numpy(), r.H.numpy()
    n = A.shape[0]
    assert n == 306
    Q = 0.5 * np.eye(n)
    R = np.array([[1.0, 0.3, 0.1], [0.3, 1.0, 0.3], [0.1, 0.3, 1.0]])
    res = steady_state_kalman(r.A, r.H, t(Q), t(R))
    S, K = res.pred_cov.numpy(), res.gain.numpy()
    assert residual(A, H, Q, R, S) < LARGE_PLANT_RTOL
    ref = doubling_dare(A, H, Q, R)
    K_ref = ref @ H.T @ np.linalg.inv(H @ ref @ H.T + R)
    assert np.abs(K - K_ref).max() / np.abs(K_ref).max() < LARGE_PLANT_RTOL
