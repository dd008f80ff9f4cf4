"""The online API (init / predict / update, one measurement at a time) equals the whole-recording
filter, for every form, with missing components, inputs, batches and time-varying noise."""

import math

import pytest
import torch
from linear_support import make_problem, t64

from torchfilt import CKF, ConstrainedCKF, LinearGaussianModel
from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models import TimeVarying
from torchfilt.systems import reaction, reentry

#: online and whole-recording runs do the same arithmetic; float64 agreement (issue 13)
ONLINE_TOL = 1e-12


def run_online(filt, y, u, x0, P0, mask=None):
    state = filt.init(x0, P0)
    means, covs, ll = [], [], 0.0
    for t in range(y.shape[-2]):
        state = filt.predict(state, None if u is None else u[..., t, :])
        state, info = filt.update(
            state,
            y[..., t, :],
            None if u is None else u[..., t, :],
            mask=None if mask is None else mask[..., t, :],
        )
        means.append(state.mean)
        covs.append(state.cov)
        ll = ll + info.log_likelihood
    return torch.stack(means, -2), torch.stack(covs, -3), ll


def assert_same(online, res):
    mean, cov, ll = online
    torch.testing.assert_close(mean, res.mean, rtol=ONLINE_TOL, atol=ONLINE_TOL)
    torch.testing.assert_close(cov, res.cov, rtol=ONLINE_TOL, atol=ONLINE_TOL)
    torch.testing.assert_close(ll, res.log_likelihood, rtol=ONLINE_TOL, atol=ONLINE_TOL)


@pytest.mark.parametrize(
    "opts",
    [{}, {"sqrt": True}, {"redraw": False}, {"sqrt": True, "redraw": False}],
    ids=["plain", "sqrt", "no-redraw", "sqrt-no-redraw"],
)
def test_online_equals_filter_linear_with_inputs_and_missing(opts):
    p = make_problem(5, T=20)
    Qt = torch.stack([t64(p["Q"]) * (1 + 0.1 * k) for k in range(20)])
    model = LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), TimeVarying(Qt), t64(p["R"]), B=t64(p["B"])
    )
    filt = CKF(model, **opts)
    y, u = t64(p["y"]), t64(p["u"])
    mask = torch.rand(y.shape, generator=torch.Generator().manual_seed(1)) > 0.2
    res = filt.filter(y, u, x0=t64(p["m0"]), P0=t64(p["P0"]), mask=mask)
    assert_same(run_online(filt, y, u, t64(p["m0"]), t64(p["P0"]), mask), res)


@pytest.mark.parametrize("batch", [(4,), (2, 3)])
def test_online_batched_nonlinear_equals_filter(batch):
    sim = reentry.simulate_truth(math.prod(batch), seed=2, steps=10)
    y = sim.measurements.reshape(*batch, *sim.measurements.shape[1:]).clone()
    y[..., 4, :] = float("nan")
    filt = CKF(reentry.model())
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float64), reentry.prior_cov()
    res = filt.filter(y, x0=x0, P0=P0)
    # filter() expands the prior to the batch; so does the online user here
    assert_same(run_online(filt, y, None, x0.expand(*batch, 3), P0), res)
    # an unbatched prior is broadcast by the first batched measurement (same up to op order)
    mean, _, _ = run_online(filt, y, None, x0, P0)
    torch.testing.assert_close(mean, res.mean, rtol=1e-10, atol=0)


def test_online_constrained_equals_filter():
    sim = reaction.simulate_truth(runs=3, seed=0)
    y = sim.measurements[:, :12]
    filt = ConstrainedCKF(reaction.model(), lower=[0.0, 0.0], upper=[100.0, 100.0])
    x0, P0 = reaction.prior_mean(), reaction.prior_cov()
    res = filt.filter(y, x0=x0, P0=P0)
    assert_same(run_online(filt, y, None, x0, P0), res)


def test_online_errors():
    p = make_problem(0)
    filt = CKF(LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"])))
    state = filt.init(t64(p["m0"]), t64(p["P0"]))
    with pytest.raises(InputError, match="update needs a predicted state"):
        filt.update(state, t64(p["y"][0]))
    with pytest.raises(InputError, match="state: predict needs the FilterState"):
        filt.predict((state.mean, state.cov))  # type: ignore[arg-type]
    state = filt.predict(state)
    with pytest.raises(ShapeError, match=r"y: expected shape \(\.\.\., 2\)"):
        filt.update(state, torch.zeros(3, dtype=torch.float64))
    with pytest.raises(ShapeError, match="x0"):
        filt.init(torch.zeros(4, dtype=torch.float64), t64(p["P0"]))
    # an all-missing measurement leaves the prediction as it is
    post, info = filt.update(state, torch.full((2,), float("nan"), dtype=torch.float64))
    torch.testing.assert_close(post.mean, state.mean, rtol=0, atol=0)
    assert float(info.log_likelihood) == 0.0
