"""GP-learned models inside the constrained CKF (issue 5: "works with the GP-learned models too").

A small GP transition and GP measurement learned on 2A -> B run inside ``ConstrainedCKF`` from the
Haseltine & Rawlings start, where the prior's cubature points leave the box. Every per-point
reconciliation (NDDR) is rebuilt independently, from the filter's reported prediction, the
reference constrained points of ``tests/reference.py`` and the GP's own predictive mean and
variance, and solved by ``scipy.optimize.least_squares(bounds=...)``; the filter's solutions and
its update must equal them.
"""

import numpy as np
import pytest
import scipy.optimize as so
import torch
from gp_support import one_thread  # noqa: F401
from reference import constrained_points_ref

import torchfilt.filters.constrained as constrained_module
from torchfilt import GPMeasurement, GPTransition, StateSpaceModel
from torchfilt.filters.constrained import ConstrainedCKF
from torchfilt.systems import reaction, simulate
from torchfilt.systems.registry import get_system

D = torch.float64
#: training transitions of the small learned model (recordings x steps)
RECORDINGS, STEPS = 10, 25
#: filter steps checked
T = 4
#: both solvers stop near sqrt(eps) in the J^T J metric (prior standard deviations of ~1e-1 to 6)
NDDR_ATOL = 1e-6
#: the filter's points vs the point-by-point reference (round-off of the Cholesky factors)
POINT_ATOL = 1e-9
#: the filter's update (weighted mean of the reconciled points) vs the reference one
UPDATE_ATOL = 1e-6
LOWER, UPPER = np.array(reaction.LOWER), np.array(reaction.UPPER)

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def learned():
    """GP f (increment form) and GP h learned on 250 simulated 2A -> B transitions (seeded)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gen = torch.Generator().manual_seed(0)
        x0 = get_system("reaction").initial(RECORDINGS, gen)
        sim = simulate(reaction.model(), STEPS, x0, generator=gen)
        states = torch.cat([x0.unsqueeze(-2), sim.states], -2)  # (R, STEPS + 1, 2)
        opts = dict(iterations=40, progress=False, seed=0)
        f = GPTransition.fit(states, increment=True, **opts)
        h = GPMeasurement.fit(sim.states, sim.measurements, **opts)
    finally:
        torch.set_num_threads(old)
    return StateSpaceModel(f, h)


def scipy_nddr(h, X, P, z, lo, hi):
    """One reconciliation, written out: argmin over the box of
    ``|L_P^{-1} (x - X)|^2 + (z - h(x))^2 / R_X``, ``R_X`` the GP's predictive variance at ``X``."""
    Wp = np.linalg.inv(np.linalg.cholesky(P))
    pred = h.predict(torch.tensor(X, dtype=D).unsqueeze(0))
    r_sd = float(pred.var[0, 0]) ** 0.5

    def mean(x):
        return h.predict(torch.as_tensor(x, dtype=D).unsqueeze(0)).mean[0]

    def fun(x):
        return np.concatenate([Wp @ (x - X), (z - mean(x).detach().numpy()) / r_sd])

    def jac(x):
        Jh = torch.autograd.functional.jacobian(mean, torch.tensor(x, dtype=D)).numpy()
        return np.concatenate([Wp, -Jh / r_sd])

    tight = dict(xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    return so.least_squares(fun, X, jac=jac, bounds=(lo, hi), method="trf", **tight).x


def test_learned_model_in_cckf_matches_scipy_least_squares(learned, monkeypatch):
    f, h = learned.transition, learned.measurement
    assert isinstance(f, GPTransition) and isinstance(h, GPMeasurement)
    solves = []
    original = constrained_module.bounded_least_squares

    def recording(residual, x0, bounds=None, **kw):
        sol = original(residual, x0, bounds, **kw)
        solves.append((x0.detach().clone(), sol))
        return sol

    monkeypatch.setattr(constrained_module, "bounded_least_squares", recording)
    data = reaction.simulate_truth(1, start="hr", steps=T, seed=3)
    y = data.measurements[0]
    filt = ConstrainedCKF(learned, reaction.LOWER, reaction.UPPER, covariance="corrected")
    res, info = filt.filter_with_info(y, x0=reaction.prior_mean("hr"), P0=reaction.prior_cov())
    assert len(solves) == T
    assert bool((info.solver_status > 0).all())
    assert bool(torch.isfinite(res.mean).all())
    assert bool((res.mean >= 0).all())
    on_bound = 0
    for k, (points, sol) in enumerate(solves):
        m_pred = res.predicted_mean[k].numpy()
        P_pred = res.predicted_cov[k].numpy()
        X, w = constrained_points_ref(m_pred, P_pred, LOWER, UPPER)
        np.testing.assert_allclose(points.numpy(), X, atol=POINT_ATOL, rtol=0)
        ref = np.stack(
            [scipy_nddr(h, X[i], P_pred, float(y[k, 0]), LOWER, UPPER) for i in range(len(X))]
        )
        np.testing.assert_allclose(sol.x.numpy(), ref, atol=NDDR_ATOL, rtol=0)
        np.testing.assert_allclose(res.mean[k].numpy(), w @ ref, atol=UPDATE_ATOL, rtol=0)
        on_bound += int(np.isclose(ref, LOWER, atol=1e-12).any(-1).sum())
    # the bounds acted: some reconciled points sit on x >= 0, where an unconstrained solve differs
    assert on_bound > 0, "the test must exercise the bounds"
    # and the GP's per-point variance really varies (R_i is not one constant R)
    var = h.predict(solves[0][0]).var[:, 0]
    assert float(var.max() / var.min()) > 1.01
