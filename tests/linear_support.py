"""A random linear-Gaussian problem with inputs and missing data, shared by the filter tests."""

import numpy as np
import torch
from conftest import random_spd


def make_problem(seed, n=3, m=2, nu=1, T=15, missing=0.2):
    """Matrices, prior, inputs and measurements (NaN where missing; step 3 all missing)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.95 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    B = rng.standard_normal((n, nu))
    Q = random_spd(rng, n, 0.3)
    R = random_spd(rng, m, 0.5)
    m0 = rng.standard_normal(n)
    P0 = random_spd(rng, n, 2.0)
    u = rng.standard_normal((T, nu))
    x = rng.multivariate_normal(m0, P0)
    ys = []
    for t in range(T):
        x = A @ x + B @ u[t] + rng.multivariate_normal(np.zeros(n), Q)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(m), R))
    y = np.array(ys)
    y[rng.random(y.shape) < missing] = np.nan
    y[3] = np.nan  # one step with nothing observed
    return dict(A=A, H=H, B=B, Q=Q, R=R, m0=m0, P0=P0, u=u, y=y)


def t64(a):
    return torch.tensor(a, dtype=torch.float64)
