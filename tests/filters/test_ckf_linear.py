"""Every rule, plain and square-root, equals the closed-form Kalman filter and RTS smoother."""

import numpy as np
import pytest
import torch
from conftest import BATCH_SHAPES, REF_ATOL, REF_RTOL, TIGHT
from linear_support import make_problem, t64
from reference import kalman_filter, rts_smoother

from torchfilt import CKF, LinearGaussianModel
from torchfilt.cubature import GaussHermiteRule, SphericalRadialRule, UnscentedRule
from torchfilt.models import TimeVarying

RULES = {
    "cubature3": SphericalRadialRule(3),
    "cubature5": SphericalRadialRule(5),
    "unscented": UnscentedRule(alpha=1.0, beta=0.0, kappa=0.0),
    "unscented_scaled": UnscentedRule(alpha=0.5, beta=2.0, kappa=1.0),
    "gauss_hermite": GaussHermiteRule(2),
}


def assert_close(got, want, what):
    np.testing.assert_allclose(
        got.detach().numpy(), want, rtol=REF_RTOL, atol=REF_ATOL, err_msg=what
    )


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
@pytest.mark.parametrize("rule", list(RULES.values()), ids=list(RULES))
@pytest.mark.parametrize("seed", [0, 1])
def test_filter_and_smoother_equal_kalman(rule, sqrt, seed):
    p = make_problem(seed)
    ms, Ps, mps, Pps, ll = kalman_filter(
        p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], p["B"], p["u"]
    )
    msm, Psm = rts_smoother(p["A"], ms, Ps, mps, Pps)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    filt = CKF(model, rule=rule, sqrt=sqrt)
    sm = filt.smooth(t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature")
    res = sm.filtered
    assert_close(res.mean, ms, "filtered mean")
    assert_close(res.cov, Ps, "filtered cov")
    assert_close(res.predicted_mean, mps, "predicted mean")
    assert_close(res.predicted_cov, Pps, "predicted cov")
    assert float(res.log_likelihood) == pytest.approx(ll, rel=REF_RTOL)
    assert_close(sm.mean, msm, "smoothed mean")
    assert_close(sm.cov, Psm, "smoothed cov")
    assert not res.observed[3].any() and torch.isnan(res.innovation[3]).all()


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_mask_equals_nan(sqrt):
    p = make_problem(2, missing=0.0)
    rng = np.random.default_rng(5)
    mask = rng.random(p["y"].shape) > 0.3
    y_nan = p["y"].copy()
    y_nan[~mask] = np.nan
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    filt = CKF(model, sqrt=sqrt)
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    a = filt.filter(t64(p["y"]), t64(p["u"]), mask=torch.tensor(mask), **kw, path="cubature")
    b = filt.filter(t64(y_nan), t64(p["u"]), **kw, path="cubature")
    assert torch.allclose(a.mean, b.mean, rtol=TIGHT, atol=0)
    assert torch.allclose(a.log_likelihood, b.log_likelihood, rtol=TIGHT)
    ms, *_, ll = kalman_filter(
        p["A"], p["H"], p["Q"], p["R"], y_nan, p["m0"], p["P0"], p["B"], p["u"]
    )
    assert_close(a.mean, ms, "masked mean")
    assert float(a.log_likelihood) == pytest.approx(ll, rel=REF_RTOL)


def test_time_varying_noise_equals_kalman():
    p = make_problem(3, missing=0.0)
    T = p["y"].shape[0]
    scales = np.linspace(0.5, 2.0, T)
    Qt = scales[:, None, None] * p["Q"]
    model = LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), TimeVarying(t64(Qt)), t64(p["R"]), B=t64(p["B"])
    )
    res = CKF(model).filter(
        t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
    )
    ms, Ps, *_ = kalman_filter(p["A"], p["H"], Qt, p["R"], p["y"], p["m0"], p["P0"], p["B"], p["u"])
    assert_close(res.mean, ms, "mean")
    assert_close(res.cov, Ps, "cov")


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_batched_equals_loop(batch, sqrt):
    p = make_problem(4, missing=0.1)
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    filt = CKF(model, sqrt=sqrt)
    gen = torch.Generator().manual_seed(7)
    y = t64(p["y"]) + torch.randn(*batch, *p["y"].shape, generator=gen, dtype=torch.float64)
    x0 = torch.randn(*batch, 3, generator=gen, dtype=torch.float64)
    sm = filt.smooth(y, t64(p["u"]), x0=x0, P0=t64(p["P0"]), path="cubature")
    assert sm.mean.shape == (*batch, 15, 3) and sm.filtered.log_likelihood.shape == batch
    for idx in np.ndindex(*batch):
        one = filt.smooth(y[idx], t64(p["u"]), x0=x0[idx], P0=t64(p["P0"]), path="cubature")
        assert torch.allclose(sm.filtered.mean[idx], one.filtered.mean, rtol=TIGHT, atol=1e-12)
        assert torch.allclose(sm.filtered.cov[idx], one.filtered.cov, rtol=TIGHT, atol=1e-12)
        assert torch.allclose(sm.mean[idx], one.mean, rtol=TIGHT, atol=1e-12)
        assert torch.allclose(
            sm.filtered.log_likelihood[idx], one.filtered.log_likelihood, rtol=TIGHT
        )


def test_batch_of_models_via_noise_batch():
    """Q with a batch dimension filters one sequence under several models at once."""
    p = make_problem(5, missing=0.0)
    Qs = torch.stack([t64(p["Q"]) * s for s in (0.5, 1.0, 2.0)])
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), Qs, t64(p["R"]), B=t64(p["B"]))
    res = CKF(model).filter(
        t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
    )
    assert res.mean.shape == (3, 15, 3)
    for i, s in enumerate((0.5, 1.0, 2.0)):
        ms, *_ = kalman_filter(
            p["A"], p["H"], p["Q"] * s, p["R"], p["y"], p["m0"], p["P0"], p["B"], p["u"]
        )
        assert_close(res.mean[i], ms, f"model {i}")


def test_float32_runs_and_is_close_to_float64():
    p = make_problem(6, missing=0.0)
    model64 = LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))
    r64 = CKF(model64).filter(
        t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
    )
    f32 = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    r32 = CKF(model64).filter(
        f32(p["y"]), f32(p["u"]), x0=f32(p["m0"]), P0=f32(p["P0"]), path="cubature"
    )
    assert r32.mean.dtype == torch.float32
    assert torch.allclose(r32.mean.double(), r64.mean, rtol=1e-4, atol=1e-4)
