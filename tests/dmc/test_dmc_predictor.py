"""The open-loop prediction module: equals a converged time-varying Kalman filter, reproduces the
step-response superposition, the classical DMC correction, the paper's observer test, and batches."""

import numpy as np
import pytest
import torch
from reference import kalman_filter

from torchfilt import CKF, LinearGaussianModel
from torchfilt.dmc import (
    FOPDT,
    IPDT,
    OpenLoopPredictor,
    StepResponseModel,
    integrating_fractionator,
)
from torchfilt.exceptions import ShapeError

D = torch.float64
#: Agreement between two exact evaluations of the same linear recursion (different op order).
EXACT_TOL = 1e-10
#: Steady-state filter vs a time-varying KF started far away, after the gains have converged.
CONVERGED_TOL = 1e-8
#: The paper's section-3.2 requirement on the noise-free observer error at k = 1000.
OBSERVER_TOL = 1e-8


def mixed_model(N=15, dt=1.0):
    Gu = [
        [FOPDT(2.0, 4.0, 1.5), FOPDT(-1.0, 2.0, 0.6)],
        [IPDT(0.2, 2.0, 1.2), IPDT(-0.1, 1.0, 0.0)],
        [FOPDT(1.0, 3.0, 0.0), FOPDT(0.5, 1.0, 2.3)],
    ]
    Gv = [[FOPDT(0.5, 3.0, 0.5)], [IPDT(0.05, 2.0, 0.0)], [FOPDT(-0.4, 2.0, 1.0)]]
    return StepResponseModel.from_transfer_functions(Gu, Gv, dt=dt, horizon=N)


def random_inputs(seed, T, model, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    y = scale * torch.randn(T, model.ny, generator=g, dtype=D)
    du = torch.randn(T, model.nu, generator=g, dtype=D)
    dv = torch.randn(T, model.nv, generator=g, dtype=D)
    return y, du, dv


@pytest.mark.parametrize("reference", ["numpy_kf", "ckf"])
def test_equals_converged_time_varying_kalman_filter(reference):
    model = mixed_model(N=8)
    pred = OpenLoopPredictor(model, Q_Y=0.3, Q_y=torch.tensor([1.0, 0.5, 2.0], dtype=D))
    r = pred.realization
    T, late = 120, 100  # the filters agree to ~1e-12 from k ~ 100 on (closed-loop radius 0.77)
    y, du, dv = random_inputs(0, T, model)
    x0 = torch.zeros(r.state_dim, dtype=D)
    P0 = 10.0 * torch.eye(r.state_dim, dtype=D)
    Bfull = torch.cat([r.B, r.Bv], dim=1)
    u = torch.cat([du, dv], dim=1)  # row k: [du(k-1), dv(k)]
    if reference == "numpy_kf":
        ms, _, _, Pps, _ = kalman_filter(
            r.A.numpy(),
            r.H.numpy(),
            pred.Q_Y.numpy(),
            pred.Q_y.numpy(),
            y.numpy(),
            x0.numpy(),
            P0.numpy(),
            Bfull.numpy(),
            u.numpy(),
        )
        means, Pp_last = torch.tensor(ms), torch.tensor(Pps[-1])
    else:
        lgm = LinearGaussianModel(r.A, r.H, pred.Q_Y, pred.Q_y, B=Bfull)
        res = CKF(lgm).filter(y, u, x0=x0, P0=P0)
        means, Pp_last = res.mean, res.predicted_cov[-1]
    ours = pred.run(y, du, dv, x0=x0)
    # the time-varying gain has converged to the steady-state gain ...
    K_tv = Pp_last @ r.H.mT @ torch.linalg.inv(r.H @ Pp_last @ r.H.mT + pred.Q_y)
    torch.testing.assert_close(K_tv, pred.gain, rtol=0, atol=CONVERGED_TOL)
    # ... and so have the predictions
    tv_pred = pred.predictions(means)
    torch.testing.assert_close(ours.predictions[late:], tv_pred[late:], rtol=0, atol=CONVERGED_TOL)
    # early on they differ (the comparison can fail)
    assert (ours.predictions[:5] - tv_pred[:5]).abs().max() > 1e-3


def truth_output(model, du, dv, k):
    """y(k) = sum_{j<k} S_{k-j} du(j) + sum_{j<k} S^v_{k-j} dv(j) (eq. (1); S_0 = 0)."""
    Su = model.coefficients(k + 1, "u").numpy()
    Sv = model.coefficients(k + 1, "v").numpy()
    out = np.zeros(model.ny)
    for j in range(k):
        out += Su[k - j - 1] @ du[j] + Sv[k - j - 1] @ dv[j]
    return out


def superposition(model, du, dv, k, p_max):
    """Free response y(k+p|k), p = 1..p_max, from eq. (1): sum of step responses of the past moves."""
    Su = model.coefficients(k + p_max + 1, "u").numpy()
    Sv = model.coefficients(k + p_max + 1, "v").numpy()
    out = np.zeros((p_max, model.ny))
    for p in range(1, p_max + 1):
        for j in range(k):  # du(j), j <= k-1
            out[p - 1] += Su[k + p - j - 1] @ du[j]
        for j in range(k + 1):  # dv(j), j <= k
            out[p - 1] += Sv[k + p - j - 1] @ dv[j]
    return out


@pytest.mark.parametrize("gain", ["kalman", "classical"])
def test_predictions_are_the_step_response_superposition(gain):
    model = mixed_model(N=12)
    pred = (
        OpenLoopPredictor(model, 0.5, 1.0)
        if gain == "kalman"
        else OpenLoopPredictor.classical(model)
    )
    T = 40
    _, du_seq, dv_seq = random_inputs(1, T, model)  # du(j), dv(j) for j = 0..T-1
    # the noise-free truth: y(k) = sum_j S_{k-j} du(j) + sum_j S^v_{k-j} dv(j)
    y = torch.tensor(
        np.stack([truth_output(model, du_seq.numpy(), dv_seq.numpy(), k) for k in range(T)])
    )
    # row k of the run: y(k), du(k-1), dv(k)
    du_in = torch.cat([torch.zeros(1, model.nu, dtype=D), du_seq[:-1]])
    run = pred.run(y, du_in, dv_seq)
    torch.testing.assert_close(run.innovations, torch.zeros_like(y), rtol=0, atol=EXACT_TOL)
    for k in (0, 7, 25, T - 1):
        ref = superposition(model, du_seq.numpy(), dv_seq.numpy(), k, model.horizon)
        np.testing.assert_allclose(run.predictions[k].numpy(), ref, rtol=0, atol=EXACT_TOL)


def classical_dmc_reference(model, y, du_in, dv):
    """Hand-written classical DMC prediction: shift the corrected prediction vector, h = 1."""
    N = model.horizon
    Su = model.coefficients(N + 2, "u").numpy()
    Sv = model.coefficients(N + 2, "v").numpy()
    integ = model.integrating.numpy()
    out = []
    Y = np.zeros((N + 2, model.ny))  # y(k-1+i|k-1), i = 0..N+1
    for k in range(y.shape[0]):
        Y1 = Y.copy()
        Y1[1:] += Su[: N + 1] @ du_in[k]  # y(k-1+i) gets S_i du(k-1)
        e = y[k] - Y1[1]
        Y1 += e  # output correction with h = 1
        new = np.empty_like(Y)
        new[:-1] = Y1[1:]
        # last element: hold (stable) or extrapolate the slope (integrating)
        new[-1] = np.where(integ, 2 * Y1[-1] - Y1[-2], Y1[-1])
        new[1:] += Sv[: N + 1] @ dv[k]
        Y = new
        out.append(Y[1 : N + 1].copy())
    return np.stack(out)


def test_classical_predictor_equals_hand_written_dmc():
    model = mixed_model(N=10)
    y, du, dv = random_inputs(2, 30, model)
    run = OpenLoopPredictor.classical(model).run(y, du, dv)
    ref = classical_dmc_reference(model, y.numpy(), du.numpy(), dv.numpy())
    np.testing.assert_allclose(run.predictions.numpy(), ref, rtol=0, atol=EXACT_TOL)
    # h = 1 makes y(k|k) the measurement itself
    torch.testing.assert_close(OpenLoopPredictor.classical(model).current(run.states), y)


def paper_observer(T_end=1000, noise=None):
    """Section 3.2: truth starts at 0, the estimate at all 5s; u = [0.5, 0.3, -0.5] from k = 0."""
    Gu, Gv = integrating_fractionator()
    model = StepResponseModel.from_transfer_functions(
        Gu, Gv, dt=1.0, horizon=100, integrating=[True, True, True]
    )
    pred = OpenLoopPredictor(model, Q_Y=0.01, Q_y=1.0)
    r = pred.realization
    K = T_end + 1
    du = torch.zeros(K, 3, dtype=D)
    du[0] = torch.tensor([0.5, 0.3, -0.5], dtype=D)  # u(-1) = 0
    v = torch.zeros(K, 2, dtype=D)
    v[48:498] = torch.tensor([-5.0, 5.0], dtype=D)
    v[498:] = torch.tensor([5.0, -5.0], dtype=D)
    dv = torch.diff(v, dim=0, prepend=torch.zeros(1, 2, dtype=D))
    X = [torch.zeros(r.state_dim, dtype=D)]
    for k in range(1, K):
        X.append(r.A @ X[-1] + r.B @ du[k - 1] + r.Bv @ dv[k])
    X = torch.stack(X)
    y = X @ r.H.mT
    if noise is not None:
        y = y + noise
    x0 = torch.full((r.state_dim,), 5.0, dtype=D)
    run = pred.run(y[1:], du[:-1], dv[1:], x0=x0)  # X(0|0) = 5, then k = 1..T_end
    Xhat = torch.cat([x0[None], run.states])
    return X, Xhat, y


def test_paper_noise_free_observer_error_converges():
    X, Xhat, _ = paper_observer()
    err = (X - Xhat).norm(dim=-1)
    assert err[0] > 50.0  # starts far away
    assert err[1000] < OBSERVER_TOL
    assert err[200:].max() < OBSERVER_TOL * err[0]


def test_online_update_equals_offline_run_and_batch_equals_loop():
    model = mixed_model(N=8)
    pred = OpenLoopPredictor(model, 0.5, 1.0)
    ys, dus, dvs = zip(*(random_inputs(s, 12, model) for s in range(4)), strict=True)
    y, du, dv = torch.stack(ys).reshape(2, 2, 12, 3), torch.stack(dus), torch.stack(dvs)
    batched = pred.run(y, du.reshape(2, 2, 12, 2), dv.reshape(2, 2, 12, 1))
    assert batched.predictions.shape == (2, 2, 12, 8, 3)
    for b in range(4):
        one = pred.run(ys[b], dus[b], dvs[b])
        torch.testing.assert_close(
            batched.states.reshape(4, 12, -1)[b], one.states, rtol=0, atol=EXACT_TOL
        )
        pred.reset()
        for k in range(12):
            out = pred.update(ys[b][k], dus[b][k], dvs[b][k])
        torch.testing.assert_close(out, one.predictions[-1], rtol=0, atol=EXACT_TOL)
        torch.testing.assert_close(pred.state, one.states[-1], rtol=0, atol=EXACT_TOL)


def test_missing_measurement_skips_the_correction():
    model = mixed_model(N=8)
    pred = OpenLoopPredictor(model, 0.5, 1.0)
    y, du, dv = random_inputs(5, 6, model)
    y[3, 1] = float("nan")
    run = pred.run(y, du, dv)
    r = pred.realization
    prior = r.A @ run.states[2] + r.B @ du[3] + r.Bv @ dv[3]
    eps = y[3] - r.H @ prior
    eps[1] = 0.0
    torch.testing.assert_close(run.states[3], prior + pred.gain @ eps, rtol=0, atol=EXACT_TOL)
    assert torch.isnan(run.innovations[3, 1]) and torch.isfinite(run.states).all()


def test_bad_inputs_name_the_argument():
    model = mixed_model(N=5)
    pred = OpenLoopPredictor(model, 0.5, 1.0)
    n = pred.state_dim
    with pytest.raises(ShapeError, match=r"y: expected shape \(3,\)"):
        pred.update(torch.zeros(2, dtype=D))
    with pytest.raises(ShapeError, match=r"du: expected shape \(\.\.\., nu\) with nu = 2"):
        pred.update(torch.zeros(3, dtype=D), torch.zeros(3, dtype=D))
    with pytest.raises(ShapeError, match=r"dv: expected shape \(\.\.\., nv\) with nv = 1"):
        pred.update(torch.zeros(3, dtype=D), None, torch.zeros(2, dtype=D))
    with pytest.raises(ShapeError, match="du: has 4 samples but y has 5"):
        pred.run(torch.zeros(5, 3, dtype=D), torch.zeros(4, 2, dtype=D))
    with pytest.raises(ValueError, match="du contains non-finite"):
        pred.run(torch.zeros(5, 3, dtype=D), torch.full((5, 2), float("nan"), dtype=D))
    with pytest.raises(ShapeError, match=rf"x0: expected shape \(\.\.\., n\) with n = {n}"):
        pred.run(torch.zeros(5, 3, dtype=D), x0=torch.zeros(n + 1, dtype=D))
    with pytest.raises(ShapeError, match=rf"Q_Y: expected a scalar, \({n},\) or"):
        OpenLoopPredictor(model, torch.ones(3, dtype=D), 1.0)
    with pytest.raises(ShapeError, match=r"Q_y: expected a scalar, \(3,\) or"):
        OpenLoopPredictor(model, 0.5, torch.ones(2, 2, dtype=D))
    with pytest.raises(ValueError, match="give the covariances Q_Y and Q_y"):
        OpenLoopPredictor(model)
    with pytest.raises(ValueError, match="either gain or the covariances"):
        OpenLoopPredictor(model, 0.5, 1.0, gain=torch.zeros(n, 3, dtype=D))
    with pytest.raises(ShapeError, match=rf"gain: expected shape \({n}, 3\)"):
        OpenLoopPredictor(model, gain=torch.zeros(n, 2, dtype=D))
    with pytest.raises(ValueError, match="Q_Y is not symmetric"):
        OpenLoopPredictor(model, torch.triu(torch.ones(n, n, dtype=D)), 1.0)
