"""The gradient M-step's objective ``Q(theta)``, whose parameter-free part (the cubature points of
the smoothed pairs) is computed once per M-step, against the cubature expectation written out in
numpy and scipy (float64): third-degree spherical-radial points of every smoothed pair and every
smoothed state, a missing measurement and a padded step left out."""

import numpy as np
import scipy.stats
import torch

from torchfilt.cubature import SphericalRadialRule
from torchfilt.filters import CKF
from torchfilt.systems import reaction
from torchfilt.training.em_steps import _expected_loglik, _pair_points, smoothed_pairs

D = torch.float64


def _points(mean, cov):
    n = mean.shape[0]
    L = np.linalg.cholesky(0.5 * (cov + cov.T))
    unit = np.sqrt(n) * np.concatenate([np.eye(n), -np.eye(n)])
    return mean + unit @ L.T  # (2n, n), weights 1 / (2n)


def _reference(sp, y, valid, Q, R, measurement=True):
    pm, pc, m, c, cc = (v.numpy() for v in sp)
    B, T, n = m.shape
    q = 0.0
    for b in range(B):
        for t in range(T):
            if not valid[b, t]:
                continue
            mean2 = np.concatenate([pm[b, t], m[b, t]])
            cov2 = np.block([[pc[b, t], cc[b, t]], [cc[b, t].T, c[b, t]]])
            pts = _points(mean2, cov2)
            fx = reaction.transition(torch.tensor(pts[:, :n])).numpy()
            lp = [
                scipy.stats.multivariate_normal.logpdf(pts[i, n:], fx[i], Q) for i in range(4 * n)
            ]
            q += np.mean(lp)
            if measurement and np.isfinite(y[b, t]).all():
                p1 = _points(m[b, t], c[b, t])
                hx = p1.sum(-1, keepdims=True)
                lp1 = [
                    scipy.stats.multivariate_normal.logpdf(y[b, t], hx[i], R) for i in range(2 * n)
                ]
                q += np.mean(lp1)
    return q


def test_expected_loglik_from_the_points_matches_the_cubature_expectation():
    sim = reaction.simulate_truth(2, steps=12, seed=2)
    y = sim.measurements.clone()
    y[0, 5] = float("nan")  # a missing measurement: no measurement term at that step
    model = reaction.model()
    x0, P0 = reaction.prior_mean(), reaction.prior_cov()
    with torch.no_grad():
        res = CKF(model).filter(y, x0=x0, P0=P0)
        sp = smoothed_pairs(res, x0, P0)
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[1, -1] = False  # a padded step: no transition
    y[1, -1] = float("nan")
    rule = SphericalRadialRule()
    pts = _pair_points(2, sp, y, None, rule, True, valid)
    q = float(_expected_loglik(model, pts, y, None, rule, True, valid))
    Q = np.diag(reaction.Q_DIAG)
    R = np.array([[reaction.R_VAR]])
    ref = _reference(sp, y.numpy(), valid.numpy(), Q, R)
    assert abs(q - ref) <= 1e-10 * abs(ref)
    # from the smoothed pairs directly: the same value
    assert float(_expected_loglik(model, sp, y, None, rule, True, valid)) == q
    # without the measurement term
    q0 = float(_expected_loglik(model, _pair_points(2, sp, y, None, rule, False, valid), y, None,
                                rule, False, valid))  # fmt: skip
    ref0 = _reference(sp, y.numpy(), valid.numpy(), Q, R, measurement=False)
    assert abs(q0 - ref0) <= 1e-10 * abs(ref0)
    assert abs(ref0 - ref) > 1.0  # the measurement term counts


def test_expected_loglik_every_step_observed_shares_one_noise_factor():
    """All observed and no per-point variance: ``Q`` and ``R`` are each factored once for all
    points; the value equals the cubature expectation written out."""
    sim = reaction.simulate_truth(2, steps=10, seed=5)
    y = sim.measurements
    model = reaction.model()
    x0, P0 = reaction.prior_mean(), reaction.prior_cov()
    with torch.no_grad():
        res = CKF(model).filter(y, x0=x0, P0=P0)
        sp = smoothed_pairs(res, x0, P0)
    valid = torch.ones(2, 10, dtype=torch.bool)
    rule = SphericalRadialRule()
    pts = _pair_points(2, sp, y, None, rule, True, valid)
    assert pts.all_seen
    q = float(_expected_loglik(model, pts, y, None, rule, True, valid))
    ref = _reference(sp, y.numpy(), valid.numpy(), np.diag(reaction.Q_DIAG), [[reaction.R_VAR]])
    assert abs(q - ref) <= 1e-10 * abs(ref)
