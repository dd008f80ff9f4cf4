"""The E-step of a linear EM fit is the exact Kalman smoother: its smoothed pairs equal the dense
joint posterior, and a fit's parameters equal a closed-form EM written in numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from torchfilt.cubature import SphericalRadialRule
from torchfilt.models import LinearGaussianModel
from torchfilt.optim import StoppingOptions
from torchfilt.training import fit_em
from torchfilt.training.em_steps import _EMProblem, _linear_start
from torchfilt.training.likelihood import _recordings

f64 = torch.float64


def _system(rng, n=3, m=2, nu=1):
    A = rng.standard_normal((n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    B = rng.standard_normal((n, nu))
    W = rng.standard_normal((n, n))
    Q = 0.2 * W @ W.T + 0.1 * np.eye(n)
    V = rng.standard_normal((m, m))
    R = 0.2 * V @ V.T + 0.2 * np.eye(m)
    return A, H, B, Q, R


def _simulate(rng, A, H, B, Q, R, x0, P0, u):
    n, m = A.shape[0], H.shape[0]
    x = rng.multivariate_normal(x0, P0)
    ys = []
    for t in range(u.shape[0]):
        x = A @ x + B @ u[t] + rng.multivariate_normal(np.zeros(n), Q)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(m), R))
    return np.array(ys)


def _joint_prior(A, H, B, Q, R, x0, P0, u):
    """The joint Gaussian prior of ``x_{-1}, ..., x_{T-1}`` (mean, covariance) and the stacked
    measurement matrix ``G`` (``y = G x + v``), by dense linear algebra."""
    n, m, T = A.shape[0], H.shape[0], u.shape[0]
    N = n * (T + 1)
    # x = F x + c + e (block lower bidiagonal), so x = (I - F)^{-1} (c + e)
    F, c, Sig_e = np.zeros((N, N)), np.zeros(N), np.zeros((N, N))
    c[:n], Sig_e[:n, :n] = x0, P0
    G = np.zeros((m * T, N))
    for t in range(T):
        i = n * (t + 1)
        F[i : i + n, i - n : i] = A
        c[i : i + n] = B @ u[t]
        Sig_e[i : i + n, i : i + n] = Q
        G[m * t : m * (t + 1), i : i + n] = H
    L = np.linalg.inv(np.eye(N) - F)
    return L @ c, L @ Sig_e @ L.T, G


def test_exact_e_step_equals_dense_posterior_with_lag_one_covariances():
    rng = np.random.default_rng(3)
    A, H, B, Q, R = _system(rng)
    n, T = 3, 7
    x0, P0 = rng.standard_normal(n), np.eye(n)
    u = rng.standard_normal((2, T, 1))
    y = np.stack([_simulate(rng, A, H, B, Q, R, x0, P0, u[i]) for i in range(2)])
    model = LinearGaussianModel(*map(torch.tensor, (A, H, Q, R, B)))
    # the E-step at the true parameters, compared with the dense posterior
    recs = _recordings(
        model, torch.tensor(y), torch.tensor(u), torch.tensor(x0), torch.tensor(P0), f64
    )
    valid = torch.ones(2, T, dtype=torch.bool)
    lin = _linear_start(model, f64, [0])
    em = _EMProblem(model, lin, [], recs, valid, [0], SphericalRadialRule(), None, True, 1, 0)
    ll, sp = em.e_step()
    want = 0.0
    for i in range(2):
        mu0, Sig0, G = _joint_prior(A, H, B, Q, R, x0, P0, u[i])
        S = G @ Sig0 @ G.T + np.kron(np.eye(T), R)
        K = Sig0 @ G.T @ np.linalg.inv(S)
        mu, Sig = mu0 + K @ (y[i].reshape(-1) - G @ mu0), Sig0 - K @ G @ Sig0
        want += multivariate_normal(G @ mu0, S).logpdf(y[i].reshape(-1))
        for t in range(T):
            a, b = slice(n * t, n * (t + 1)), slice(n * (t + 1), n * (t + 2))
            np.testing.assert_allclose(sp.prev_mean[i, t].numpy(), mu[a], atol=1e-10)
            np.testing.assert_allclose(sp.mean[i, t].numpy(), mu[b], atol=1e-10)
            np.testing.assert_allclose(sp.prev_cov[i, t].numpy(), Sig[a, a], atol=1e-10)
            np.testing.assert_allclose(sp.cov[i, t].numpy(), Sig[b, b], atol=1e-10)
            # the lag-one covariance Cov(x_{t-1}, x_t | y) = J_{t-1} P^s_t
            np.testing.assert_allclose(sp.cross_cov[i, t].numpy(), Sig[a, b], atol=1e-10)
    # the log-likelihood of the exact filter: the dense marginal density of y
    assert abs(ll - want) < 1e-9


def _np_rts(A, H, B, Q, R, x0, P0, u, y):
    """Kalman filter and RTS smoother over ``x_{-1}, ..., x_{T-1}`` (numpy), with the lag-one
    covariances ``J_{t-1} P^s_t``."""
    T = y.shape[0]
    ms, Ps, mps, Pps = [x0], [P0], [None], [None]
    for t in range(T):
        mp, Pp = A @ ms[-1] + B @ u[t], A @ Ps[-1] @ A.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        ms.append(mp + K @ (y[t] - H @ mp))
        Ps.append(Pp - K @ S @ K.T)
        mps.append(mp)
        Pps.append(Pp)
    msm, Psm, lag = [None] * (T + 1), [None] * (T + 1), [None] * (T + 1)
    msm[T], Psm[T] = ms[T], Ps[T]
    for k in range(T - 1, -1, -1):
        J = Ps[k] @ A.T @ np.linalg.inv(Pps[k + 1])
        msm[k] = ms[k] + J @ (msm[k + 1] - mps[k + 1])
        Psm[k] = Ps[k] + J @ (Psm[k + 1] - Pps[k + 1]) @ J.T
        lag[k + 1] = J @ Psm[k + 1]  # Cov(x_{k-1}, x_k | y) in the shifted index
    return np.array(msm), np.array(Psm), np.array(lag[1:])


def _np_em(A, H, B, Q, R, x0, P0, u, y, known, iterations, fixed=()):
    """Closed-form EM (Shumway & Stoffer) in numpy over several recordings; the blocks in
    ``fixed`` keep their values and the free ones take their closed form given them."""
    n = A.shape[0]
    for _ in range(iterations):
        Sxx = Spp = Sxp = Spu = Suu = Sxu = Syy = Sxy = 0.0
        N = 0
        for i in range(y.shape[0]):
            m, P, C = _np_rts(A, H, B, Q, R, x0, P0, u[i], y[i])
            for t in range(y.shape[1]):
                xp, xc = m[t], m[t + 1]
                Exx = P[t + 1] + np.outer(xc, xc)
                Sxx = Sxx + Exx
                Spp = Spp + P[t] + np.outer(xp, xp)
                Sxp = Sxp + C[t].T + np.outer(xc, xp)
                Spu = Spu + np.outer(xp, u[i][t])
                Suu = Suu + np.outer(u[i][t], u[i][t])
                Sxu = Sxu + np.outer(xc, u[i][t])
                Sxy = Sxy + np.outer(xc, y[i][t])
                Syy = Syy + np.outer(y[i][t], y[i][t])
                N += 1
        Szz = np.block([[Spp, Spu], [Spu.T, Suu]])
        Sxz = np.hstack([Sxp, Sxu])
        AB = Sxz @ np.linalg.inv(Szz)
        if "A" in fixed and "B" in fixed:
            AB = np.hstack([A, B])
        elif "A" in fixed:
            AB = np.hstack([A, (Sxu - A @ Spu) @ np.linalg.inv(Suu)])
        elif "B" in fixed:
            AB = np.hstack([(Sxp - B @ Spu.T) @ np.linalg.inv(Spp), B])
        if "Q" not in fixed:
            Q = (Sxx - AB @ Sxz.T - Sxz @ AB.T + AB @ Szz @ AB.T) / N
        A, B = AB[:, :n], AB[:, n:]
        if "H" not in fixed:
            H = H.copy()
            unknown = [j for j in range(H.shape[0]) if j not in known]
            H[unknown] = (np.linalg.solve(Sxx, Sxy[:, unknown])).T
        if "R" not in fixed:
            R = (Syy - H @ Sxy - Sxy.T @ H.T + H @ Sxx @ H.T) / N
    return A, H, B, Q, R


def _em_problem(seed: int = 11):
    """A 3-state, 2-output model with an input, 3 recordings x 60 steps simulated from it, and a
    start away from the truth (the known channel 0 of ``H`` kept): ``(A, H, B, Q, R)`` of the
    start, ``x0``, ``P0``, ``u``, ``y`` (numpy)."""
    rng = np.random.default_rng(seed)
    A, H, B, Q, R = _system(rng)
    n, T, reps = 3, 60, 3
    x0, P0 = np.zeros(n), np.eye(n)
    u = rng.standard_normal((reps, T, 1))
    y = np.stack([_simulate(rng, A, H, B, Q, R, x0, P0, u[i]) for i in range(reps)])
    # start away from the truth
    A1, H1, B1 = 0.8 * A, H + 0.2, B * 0.5
    H1[0] = H[0]  # the known channel
    return (A1, H1, B1, 2 * Q, 0.5 * R), x0, P0, u, y


def _fit_em(theta, x0, P0, u, y, iterations, **kw):
    """``fit_em`` from the start ``theta = (A, H, B, Q, R)`` of :func:`_em_problem`, channel 0
    known, for exactly ``iterations`` iterations."""
    A1, H1, B1, Q1, R1 = theta
    return fit_em(
        LinearGaussianModel(*map(torch.tensor, (A1, H1, Q1, R1, B1))),
        torch.tensor(y),
        torch.tensor(u),
        x0=torch.tensor(x0),
        P0=torch.tensor(P0),
        known_channels=[0],
        iterations=iterations,
        stopping=StoppingOptions(tol=0.0, rtol=0.0),
        **kw,
    )


@pytest.mark.parametrize(
    ("iterations", "fixed"),
    [(1, ()), (6, ()), (3, ("A",)), (3, ("B", "R")), (3, ("Q", "H")), (2, ("A", "B"))],
)
def test_linear_em_equals_numpy_closed_form_em(iterations, fixed):
    theta, x0, P0, u, y = _em_problem()
    A1, H1, B1, Q1, R1 = theta
    # plain EM steps, as the reference (SQUAREM: test_em_accel.py)
    fit = _fit_em(theta, x0, P0, u, y, iterations, fixed=fixed, accelerate=False)
    assert fit.iterations == iterations
    want = _np_em(A1, H1, B1, Q1, R1, x0, P0, u, y, [0], iterations, fixed)
    got = fit.model
    for name, w in zip("AHBQR", want, strict=True):
        g = {
            "A": got.A,
            "H": got.H,
            "B": got.B,
            "Q": got.transition.noise_cov(),
            "R": got.measurement.noise_cov(),
        }[name]
        np.testing.assert_allclose(g.numpy(), w, atol=1e-10, rtol=0, err_msg=name)


def test_linear_e_step_is_the_exact_smoother_and_equals_the_cubature_one(monkeypatch):
    """Ragged recordings and missing components: the exact E-step equals the former CKF + generic
    RTS E-step (exact too for a linear model), and it never calls the generic smoother."""
    rng = np.random.default_rng(5)
    A, H, B, Q, R = _system(rng)
    n = 3
    x0, P0 = np.zeros(n), np.eye(n)
    u = [rng.standard_normal((T, 1)) for T in (40, 25)]
    y = [_simulate(rng, A, H, B, Q, R, x0, P0, ui) for ui in u]
    y[0][rng.random(y[0].shape) < 0.2] = np.nan
    model = LinearGaussianModel(*map(torch.tensor, (A, H, Q, R, B)))
    recs = _recordings(
        model, [torch.tensor(v) for v in y], [torch.tensor(v) for v in u], torch.tensor(x0),
        torch.tensor(P0), f64,
    )  # fmt: skip
    valid = torch.arange(40).unsqueeze(0) < torch.tensor(recs.lengths).unsqueeze(-1)
    lin = _linear_start(model, f64, [0])
    em = _EMProblem(model, lin, [], recs, valid, [0], SphericalRadialRule(), None, True, 1, 0)
    old = _EMProblem(model, None, [], recs, valid, [0], SphericalRadialRule(), None, True, 1, 0)
    ll_old, sp_old = old.e_step()

    def refuse(*_args, **_kw):
        raise AssertionError("the linear E-step called the generic rts_smooth")

    monkeypatch.setattr("torchfilt.training.em_steps.rts_smooth", refuse)
    ll, sp = em.e_step()
    assert abs(ll - ll_old) < 1e-9
    for a, b in zip(sp, sp_old, strict=True):
        np.testing.assert_allclose(a[valid].numpy(), b[valid].numpy(), atol=1e-10)
