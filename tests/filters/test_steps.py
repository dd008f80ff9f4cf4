"""The pure steps: predict/update compose into the filter, equal a Kalman step on a linear model;
mask exactness; the square-root form's definiteness check; the settings a result reports."""

import warnings

import numpy as np
import pytest
import torch
from conftest import REF_ATOL, REF_RTOL, TIGHT
from linear_support import make_problem, t64
from reference import kalman_filter

import torchfilt
from torchfilt import CKF, LinearGaussianModel, settings
from torchfilt.exceptions import DivergenceWarning, ShapeError
from torchfilt.filters import Belief, FilterResult, predict, update
from torchfilt.filters.steps import lost_definiteness
from torchfilt.settings import NumericsPath


def linear(p):
    return LinearGaussianModel(t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]))


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_steps_equal_kalman_reference(sqrt):
    """predict then update, called by hand, equal the textbook Kalman filter step by step."""
    p = make_problem(3)
    model = linear(p)
    rule = torchfilt.cubature.SphericalRadialRule(3)
    ms, Ps, mps, Pps, _ = kalman_filter(
        p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], B=p["B"], u=p["u"]
    )
    belief = Belief(t64(p["m0"]), t64(p["P0"]), torch.linalg.cholesky(t64(p["P0"])))
    for t in range(p["y"].shape[0]):
        pred, cache = predict(belief, model, t64(p["u"][t]), rule, sqrt=sqrt)
        np.testing.assert_allclose(pred.mean.numpy(), mps[t], rtol=REF_RTOL, atol=REF_ATOL)
        np.testing.assert_allclose(pred.cov.numpy(), Pps[t], rtol=REF_RTOL, atol=REF_ATOL)
        belief, stats = update(pred, t64(p["y"][t]), None, model, rule, sqrt=sqrt, cache=cache)
        np.testing.assert_allclose(belief.mean.numpy(), ms[t], rtol=REF_RTOL, atol=REF_ATOL)
        np.testing.assert_allclose(belief.cov.numpy(), Ps[t], rtol=REF_RTOL, atol=REF_ATOL)
        assert stats.innovation.isnan().tolist() == (~np.isfinite(p["y"][t])).tolist()


def test_result_is_built_by_field_name_and_reports_its_path():
    p = make_problem(0)
    res = CKF(linear(p)).filter(
        t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
    )
    assert isinstance(res, FilterResult)
    assert res.numerics == NumericsPath("eager", "library", "jitter")
    batch = t64(p["y"]).expand(64, *p["y"].shape)
    res64 = CKF(linear(p)).filter(
        batch, t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
    )
    assert res64.numerics.small_kernels == "unrolled"  # "auto" resolved once for the run
    with settings.small_matrix_kernels("library"):
        lib = CKF(linear(p)).filter(
            batch, t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
        )
    assert lib.numerics.small_kernels == "library"
    # the two kernels agree to round-off
    torch.testing.assert_close(lib.mean, res64.mean, rtol=TIGHT, atol=TIGHT)
    with settings.sync_free():
        sf = CKF(linear(p)).filter(
            t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="cubature"
        )
    assert sf.numerics.on_failure == "nan"
    torch.testing.assert_close(sf.mean, res.mean, rtol=TIGHT, atol=TIGHT)
    assert settings.current_small_matrix_kernels() == "auto" and not settings.is_sync_free()


def test_settings_reject_unknown_mode():
    with pytest.raises(torchfilt.InputError, match="small_matrix_kernels: mode must be"):
        with settings.small_matrix_kernels("fast"):  # type: ignore[arg-type]
            pass


def test_mask_must_match_y_exactly():
    """A mask may add batch dims, but never stretch y over time or components (issue 12)."""
    model = LinearGaussianModel(
        torch.eye(5, dtype=torch.float64),
        torch.eye(1, 5, dtype=torch.float64),
        torch.eye(5, dtype=torch.float64),
        torch.eye(1, dtype=torch.float64),
    )
    kw = dict(x0=torch.zeros(5, dtype=torch.float64), P0=torch.eye(5, dtype=torch.float64))
    y = torch.zeros(1, 1, dtype=torch.float64)
    with pytest.raises(ShapeError, match=r"mask: shape \(3, 7, 5\) does not match y \(1, 1\)"):
        CKF(model).filter(y, mask=torch.ones(3, 7, 5, dtype=torch.bool), **kw)
    # batch dims are fine: 3 sequences of the same 1-step recording
    res = CKF(model).filter(y, mask=torch.ones(3, 1, 1, dtype=torch.bool), **kw)
    assert res.mean.shape == (3, 1, 5)


def poorly_observable(dtype):
    """Two constant states of which only the sum is measured, very precisely, from a wide prior."""
    A = torch.eye(2, dtype=dtype)
    H = torch.tensor([[1.0, 1.0]], dtype=dtype)
    model = LinearGaussianModel(
        A, H, torch.zeros(2, 2, dtype=dtype), 1e-8 * torch.eye(1, dtype=dtype)
    )
    gen = torch.Generator().manual_seed(0)
    t = torch.arange(60, dtype=torch.float64)[:, None]
    y = (0.3 * t + 1e-4 * torch.randn(60, 1, generator=gen, dtype=torch.float64)).to(dtype)
    return model, y, torch.zeros(2, dtype=dtype), 1e6 * torch.eye(2, dtype=dtype)


def test_sqrt_filter_reports_lost_definiteness():
    """Regression (issue 12): the float32 square-root filter lost definiteness here silently."""
    model, y, x0, P0 = poorly_observable(torch.float32)
    with pytest.warns(DivergenceWarning, match="non-finite estimates"):
        res = CKF(model, sqrt=True).filter(y, x0=x0, P0=P0, path="cubature")
    assert not torch.isfinite(res.mean[-1]).all()
    # in float64 the same problem is resolved: no warning, finite estimates
    model64, y64, x064, P064 = poorly_observable(torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ok = CKF(model64, sqrt=True).filter(y64, x0=x064, P0=P064, path="cubature")
    assert torch.isfinite(ok.mean).all()


def test_lost_definiteness_criterion():
    eye = torch.eye(3, dtype=torch.float64)
    good = torch.linalg.cholesky(torch.tensor([[4.0, 1, 0], [1, 3, 1], [0, 1, 2]]).double())
    zero = good.clone()
    zero[2, 2] = 0.0
    neg = good.clone()
    neg[1, 1] = -0.5
    ill = eye.clone()
    ill[1, 0] = 1.0
    ill[1, 1] = 1e-17  # row 1 is row 0 to within round-off
    flags = lost_definiteness(torch.stack([good, zero, neg, ill, 1e-200 * eye]))
    assert flags.tolist() == [False, True, True, True, False]  # scale-invariant
