"""CKF(redraw=False) equals filterpy's CubatureKalmanFilter step by step on the re-entry problem."""

import numpy as np
import pytest
import torch

import torchfilt
from torchfilt.systems import reentry

filterpy = pytest.importorskip("filterpy.kalman")

#: filterpy forms covariances as E[xx^T] - mm^T, which loses ~7 digits at re-entry scales
FILTERPY_RTOL = 1e-7


def run_filterpy(y):
    def fx(x, dt):
        return reentry.transition(torch.tensor(x)).numpy()

    def hx(x):
        return reentry.measurement(torch.tensor(x)).numpy()

    ckf = filterpy.CubatureKalmanFilter(3, 1, reentry.DT, hx, fx)
    ckf.x = np.array(reentry.PRIOR_MEAN)
    ckf.P = np.diag(reentry.PRIOR_COV_DIAG)
    ckf.Q = np.zeros((3, 3))
    ckf.R = np.array([[reentry.R_VAR]])
    prior, post = [], []
    for t in range(y.shape[0]):
        ckf.predict()
        prior.append((ckf.x.ravel().copy(), ckf.P.copy()))
        ckf.update(y[t].reshape(1, 1))
        post.append((ckf.x.ravel().copy(), ckf.P.copy(), float(ckf.log_likelihood)))
    return prior, post


def rel_err(a, b):
    return np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))


def test_redraw_false_equals_filterpy():
    sim = reentry.simulate_truth(1, seed=11)
    y = sim.measurements[0]
    res = torchfilt.CKF(reentry.model(), redraw=False).filter(
        y, x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov()
    )
    prior, post = run_filterpy(y.numpy())
    for t in range(y.shape[0]):
        assert rel_err(res.predicted_mean[t].numpy(), prior[t][0]) < FILTERPY_RTOL
        scale = np.abs(post[t][1]).max()
        assert np.abs(res.cov[t].numpy() - post[t][1]).max() / scale < FILTERPY_RTOL
        assert rel_err(res.mean[t].numpy(), post[t][0]) < FILTERPY_RTOL


def test_redraw_false_omits_q_from_innovation_cov():
    """On a linear model, re-drawing adds exactly H Q H^T to P_yy at the first step."""
    gen = torch.Generator().manual_seed(12)
    A = torch.randn(3, 3, generator=gen, dtype=torch.float64) * 0.5
    H = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    Q = torch.diag(torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64))
    model = torchfilt.LinearGaussianModel(A, H, Q, torch.eye(2, dtype=torch.float64))
    y = torch.randn(5, 2, generator=gen, dtype=torch.float64)
    kw = dict(x0=torch.zeros(3, dtype=torch.float64), P0=torch.eye(3, dtype=torch.float64))
    a = torchfilt.CKF(model, redraw=True).filter(y, **kw)
    b = torchfilt.CKF(model, redraw=False).filter(y, **kw)
    assert torch.allclose(a.innovation_cov[0] - b.innovation_cov[0], H @ Q @ H.T, atol=1e-12)
