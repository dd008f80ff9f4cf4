"""The cubature RTS smoother (gains solved for all steps at once, then the backward recursion)
against the textbook recursion written out in numpy, step by step, on a nonlinear model's CKF
result (float64)."""

import numpy as np
import torch

from torchfilt.filters import CKF, rts_smooth
from torchfilt.systems import reaction

D = torch.float64


def _reference(res):
    m, P = res.mean.numpy(), res.cov.numpy()
    mp, Pp, C = res.predicted_mean.numpy(), res.predicted_cov.numpy(), res.cross_cov.numpy()
    B, T, n = m.shape
    ms, Ps, G = m.copy(), P.copy(), np.zeros((B, T - 1, n, n))
    for b in range(B):
        for t in range(T - 2, -1, -1):
            g = np.linalg.solve(Pp[b, t + 1], C[b, t + 1].T).T
            ms[b, t] = m[b, t] + g @ (ms[b, t + 1] - mp[b, t + 1])
            S = P[b, t] + g @ (Ps[b, t + 1] - Pp[b, t + 1]) @ g.T
            Ps[b, t] = 0.5 * (S + S.T)
            G[b, t] = g
    return ms, Ps, G


def test_rts_smooth_matches_the_stepwise_recursion():
    sim = reaction.simulate_truth(3, steps=30, seed=4)
    res = CKF(reaction.model()).filter(
        sim.measurements, x0=reaction.prior_mean(), P0=reaction.prior_cov()
    )
    sm = rts_smooth(res)
    ms, Ps, G = _reference(res)
    scale = np.abs(Ps).max()
    np.testing.assert_allclose(sm.mean.numpy(), ms, rtol=0, atol=1e-10 * np.abs(ms).max())
    np.testing.assert_allclose(sm.cov.numpy(), Ps, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(sm.gain.numpy(), G, rtol=0, atol=1e-10 * np.abs(G).max())
    # the last step is the filter's
    assert torch.equal(sm.mean[:, -1], res.mean[:, -1])


def test_rts_smooth_of_one_step_is_the_filter_result():
    sim = reaction.simulate_truth(2, steps=1, seed=1)
    res = CKF(reaction.model()).filter(
        sim.measurements, x0=reaction.prior_mean(), P0=reaction.prior_cov()
    )
    sm = rts_smooth(res)
    assert torch.equal(sm.mean, res.mean) and torch.equal(sm.cov, res.cov)
    assert sm.gain.shape == (2, 0, 2, 2)
    sm.mean.add_(1.0)  # a copy: the filter result is untouched
    assert not torch.equal(sm.mean, res.mean)


def test_kalman_smoother_of_a_converged_time_invariant_model_matches_the_recursion():
    """The exact smoother's shared-covariance pass (gains that repeat once the filter has
    converged, their backward mean recursion a doubling scan) against the stepwise recursion."""
    from torchfilt.filters import kalman_filter, kalman_smoother
    from torchfilt.models import LinearGaussianModel

    g = torch.Generator().manual_seed(3)
    n, m, B, T = 4, 2, 5, 400
    A = torch.randn(n, n, generator=g, dtype=D)
    A = 0.9 * A / torch.linalg.eigvals(A).abs().max()
    H = torch.randn(m, n, generator=g, dtype=D)
    model = LinearGaussianModel(A, H, 0.1 * torch.eye(n, dtype=D), 0.2 * torch.eye(m, dtype=D))
    y = torch.randn(B, T, m, generator=g, dtype=D)
    x0, P0 = torch.zeros(n, dtype=D), torch.eye(n, dtype=D)
    sm = kalman_smoother(model, y, x0=x0, P0=P0)
    ms, Ps, G = _reference(kalman_filter(model, y, x0=x0, P0=P0))
    np.testing.assert_allclose(sm.mean.numpy(), ms, rtol=0, atol=1e-10 * np.abs(ms).max())
    np.testing.assert_allclose(sm.cov.numpy(), Ps, rtol=0, atol=1e-10 * np.abs(Ps).max())
    np.testing.assert_allclose(sm.gain.numpy(), G, rtol=0, atol=1e-10 * np.abs(G).max())
