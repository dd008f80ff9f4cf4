"""The Kalman runners (sequential, fast, Riccati) against each other and against the independent
NumPy reference, and the one Gaussian log-likelihood term against scipy."""

import numpy as np
import pytest
import scipy.stats
import torch
from conftest import random_spd

from torchfilt.numerics import gaussian_log_prob

TOL = 1e-10


def _logpdf(e, S, o):
    if not o.any():
        return 0.0
    return scipy.stats.multivariate_normal(np.zeros(int(o.sum())), S[np.ix_(o, o)]).logpdf(e[o])


@pytest.mark.parametrize("library", [False, True])
@pytest.mark.parametrize("layout", ["per_residual", "shared", "per_step_shared"])
def test_gaussian_log_prob_matches_scipy(layout, library):
    """log N(e; 0, S) over the observed components (the others: a unit row and column in the
    factor and a zero residual), for one factor per residual and for factors shared by the batch
    (solved as columns of one solve)."""
    rng = np.random.default_rng(11)
    T, B, m = 4, 70, 3
    lead = {"per_residual": (T, B), "shared": (), "per_step_shared": (T, 1)}[layout]
    count = int(np.prod(lead)) if lead else 1
    S = np.stack([random_spd(rng, m) for _ in range(count)]).reshape(*lead, m, m)
    e = rng.standard_normal((T, B, m))
    Sfull = np.broadcast_to(S, (T, B, m, m))
    want = np.array(
        [[_logpdf(e[t, b], Sfull[t, b], np.ones(m, bool)) for b in range(B)] for t in range(T)]
    )
    got = gaussian_log_prob(
        torch.tensor(e), torch.linalg.cholesky(torch.tensor(S)), library=library
    )
    np.testing.assert_allclose(got.numpy(), want, rtol=TOL, atol=TOL)
    # missing components: masked factor per residual and the observed count
    obs = rng.random((T, B, m)) > 0.3
    want = np.array(
        [[_logpdf(e[t, b], Sfull[t, b], obs[t, b]) for b in range(B)] for t in range(T)]
    )
    Sm = Sfull * (obs[..., :, None] * obs[..., None, :]) + np.eye(m) * (1.0 - obs)[..., None, :]
    L = torch.linalg.cholesky(torch.tensor(Sm))
    got = gaussian_log_prob(torch.tensor(e * obs), L, torch.tensor(obs).sum(-1), library=library)
    np.testing.assert_allclose(got.numpy(), want, rtol=TOL, atol=TOL)
