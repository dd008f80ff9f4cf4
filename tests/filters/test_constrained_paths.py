"""The constrained CKF's own step runs through every path: smooth(), compile=True and the online
API; graphed() refuses clearly instead of capturing the plain CKF's step."""

import pytest
import torch
from linear_support import make_problem, t64

from torchfilt import CKF, ConstrainedCKF, LinearGaussianModel
from torchfilt.exceptions import ModelError
from torchfilt.systems import reaction

#: compiled kernels reorder floating-point operations (as in tests/filters/test_compile.py)
COMPILE_RTOL = 1e-9
#: the CCKF with no bound in reach equals the CKF up to op order (tests/filters/test_cckf.py)
SAME_FILTER = 1e-9


def test_smooth_equals_ckf_smoother_without_bounds_in_reach():
    p = make_problem(7, T=12, missing=0.0)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]))
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y = t64(p["y"])
    y[3] = float("nan")
    ref = CKF(model).smooth(y, **kw)
    got = ConstrainedCKF(model, -1e6, 1e6, covariance="corrected").smooth(y, **kw)
    torch.testing.assert_close(got.mean, ref.mean, rtol=SAME_FILTER, atol=SAME_FILTER)
    torch.testing.assert_close(got.cov, ref.cov, rtol=SAME_FILTER, atol=SAME_FILTER)


def test_smooth_keeps_the_bounds():
    sim = reaction.simulate_truth(runs=4, seed=0)
    filt = ConstrainedCKF(reaction.model(), lower=[0.0, 0.0], upper=[100.0, 100.0])
    kw = dict(x0=reaction.prior_mean(), P0=reaction.prior_cov())
    sm = filt.smooth(sim.measurements, **kw)
    assert (sm.mean >= 0).all() and (sm.mean <= 100).all()
    torch.testing.assert_close(sm.filtered.mean, filt.filter(sim.measurements, **kw).mean)


def test_graphed_refuses():
    filt = ConstrainedCKF(reaction.model(), lower=[0.0, 0.0], upper=[100.0, 100.0])
    y = reaction.simulate_truth(runs=1, seed=0).measurements
    with pytest.raises(ModelError, match="cannot be captured into a CUDA graph"):
        filt.graphed(y, x0=reaction.prior_mean(), P0=reaction.prior_cov())


@pytest.mark.slow
def test_compiled_constrained_equals_eager():
    sim = reaction.simulate_truth(runs=2, seed=1)
    y = sim.measurements[:, :8].clone()
    y[:, 3] = float("nan")
    kw = dict(x0=reaction.prior_mean(), P0=reaction.prior_cov())
    eager = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0])
    compiled = ConstrainedCKF(reaction.model(), [0.0, 0.0], [100.0, 100.0], compile=True)
    want, want_info = eager.filter_with_info(y, **kw)
    got, got_info = compiled.filter_with_info(y, **kw)
    assert got.numerics.execution == "compiled-step"
    torch.testing.assert_close(got.mean, want.mean, rtol=COMPILE_RTOL, atol=1e-12)
    torch.testing.assert_close(got.cov, want.cov, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=COMPILE_RTOL, atol=0)
    assert torch.equal(got_info.solver_status, want_info.solver_status)
