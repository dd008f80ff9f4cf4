"""The exact Kalman path: equal to the CKF on linear models, to a NumPy reference and to filterpy."""

import numpy as np
import pytest
import torch
from conftest import REF_ATOL, REF_RTOL, random_spd
from linear_support import make_problem, t64
from reference import kalman_filter, rts_smoother

import torchfilt
from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import InputError, ModelError
from torchfilt.filters.kalman import FIELDS
from torchfilt.filters.kalman import kalman_filter as exact_filter
from torchfilt.models import LinearModel, LinearSystem, TimeVarying

#: the exact path and the CKF compute the same closed form in a different order of operations
EXACT_TOL = 1e-10
#: filterpy updates the covariance in Joseph form: the same value, rounded differently
FILTERPY_TOL = 1e-9


def model_of(p, **extra):
    return LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]), **extra
    )


def assert_same(a, b, what, tol=EXACT_TOL):
    assert a.shape == b.shape, what
    assert torch.allclose(a, b, rtol=tol, atol=tol, equal_nan=True), (
        f"{what}: max diff {float((a - b).nan_to_num().abs().max()):.2e}"
    )


def assert_results_equal(got, want, tol=EXACT_TOL):
    for name in FIELDS:
        a, b = getattr(got, name), getattr(want, name)
        if b.dtype == torch.bool:
            assert torch.equal(a.expand_as(b), b), name
        else:
            assert_same(a, b, name, tol)


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
@pytest.mark.parametrize("seed", [0, 1])
def test_exact_equals_ckf_filter_and_smoother(seed, sqrt):
    """Every field, with missing components (one step wholly missing) and controls."""
    p = make_problem(seed)
    filt = CKF(model_of(p), sqrt=sqrt)
    args, kw = (t64(p["y"]), t64(p["u"])), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    want = filt.smooth(*args, **kw, path="cubature")
    got = filt.smooth(*args, **kw)
    assert got.path == "kalman" and want.path == "cubature"
    assert_results_equal(got.filtered, want.filtered)
    assert_same(got.mean, want.mean, "smoothed mean")
    assert_same(got.cov, want.cov, "smoothed cov")
    assert_same(got.gain, want.gain, "smoother gain")


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_exact_equals_numpy_reference(sqrt):
    p = make_problem(2)
    ms, Ps, mps, Pps, ll = kalman_filter(
        p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], p["B"], p["u"]
    )
    msm, Psm = rts_smoother(p["A"], ms, Ps, mps, Pps)
    sm = CKF(model_of(p), sqrt=sqrt).smooth(
        t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path="kalman"
    )
    for got, want, what in (
        (sm.filtered.mean, ms, "mean"),
        (sm.filtered.cov, Ps, "cov"),
        (sm.filtered.predicted_cov, Pps, "predicted cov"),
        (sm.mean, msm, "smoothed mean"),
        (sm.cov, Psm, "smoothed cov"),
    ):
        np.testing.assert_allclose(got.numpy(), want, rtol=REF_RTOL, atol=REF_ATOL, err_msg=what)
    assert float(sm.filtered.log_likelihood) == pytest.approx(ll, rel=REF_RTOL)


@pytest.mark.parametrize("controls", [True, False], ids=["controls", "no_controls"])
def test_exact_equals_filterpy_kalman_filter(controls):
    kalman = pytest.importorskip("filterpy.kalman")
    p = make_problem(3, missing=0.0)
    if not controls:  # filterpy's rts_smoother predicts without B u: compare it on u = 0
        p["u"] = np.zeros_like(p["u"])
    p["y"][3] = p["y"][2]  # filterpy has no missing components: observe the step make_problem drops
    n, m = p["A"].shape[0], p["H"].shape[0]
    kf = kalman.KalmanFilter(dim_x=n, dim_z=m, dim_u=1)
    kf.F, kf.H, kf.B, kf.Q, kf.R = p["A"], p["H"], p["B"], p["Q"], p["R"]
    kf.x, kf.P = p["m0"].copy(), p["P0"].copy()
    means, covs, ll = [], [], 0.0
    for t in range(p["y"].shape[0]):
        kf.predict(u=p["u"][t])
        kf.update(p["y"][t])
        means.append(kf.x.copy())
        covs.append(kf.P.copy())
        ll += float(kf.log_likelihood)
    Fs = np.repeat(p["A"][None], len(means), 0)
    Qs = np.repeat(p["Q"][None], len(means), 0)
    xs, Ps, *_ = kf.rts_smoother(np.array(means), np.array(covs), Fs, Qs)
    sm = CKF(model_of(p)).smooth(t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]))
    np.testing.assert_allclose(sm.filtered.mean.numpy(), np.array(means), rtol=FILTERPY_TOL)
    np.testing.assert_allclose(
        sm.filtered.cov.numpy(), np.array(covs), rtol=FILTERPY_TOL, atol=FILTERPY_TOL
    )
    assert float(sm.filtered.log_likelihood) == pytest.approx(ll, rel=FILTERPY_TOL)
    if not controls:
        np.testing.assert_allclose(sm.mean.numpy(), xs, rtol=FILTERPY_TOL, atol=FILTERPY_TOL)
        np.testing.assert_allclose(sm.cov.numpy(), Ps, rtol=FILTERPY_TOL, atol=FILTERPY_TOL)


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_mask_feedthrough_and_time_varying_noise(sqrt):
    """A mask, a feed-through D u and time-varying Q and R: exact path = CKF."""
    p = make_problem(4, missing=0.1)
    rng = np.random.default_rng(11)
    T, m = p["y"].shape
    Qt = np.linspace(0.5, 2.0, T)[:, None, None] * p["Q"]
    Rt = np.linspace(2.0, 0.5, T)[:, None, None] * p["R"]
    D = rng.standard_normal((m, 1))
    model = LinearGaussianModel(
        t64(p["A"]),
        t64(p["H"]),
        TimeVarying(t64(Qt)),
        TimeVarying(t64(Rt)),
        B=t64(p["B"]),
        D=t64(D),
    )
    mask = torch.tensor(rng.random((T, m)) > 0.2)
    filt = CKF(model, sqrt=sqrt)
    args = (t64(p["y"]), t64(p["u"]))
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]), mask=mask)
    want = filt.smooth(*args, **kw, path="cubature")
    got = filt.smooth(*args, **kw)
    assert got.path == "kalman"
    assert_results_equal(got.filtered, want.filtered)
    assert_same(got.mean, want.mean, "smoothed mean")
    assert_same(got.cov, want.cov, "smoothed cov")


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_batched_parameters_equal_loop(sqrt):
    """A batch of models (A, Q and H batched) over a batch of sequences equals one at a time."""
    p = make_problem(5, missing=0.1)
    rng = np.random.default_rng(3)
    n, m = p["A"].shape[0], p["H"].shape[0]
    As = np.stack([p["A"] * s for s in (0.5, 1.0, 0.8)])
    Qs = np.stack([random_spd(rng, n, 0.3) for _ in range(3)])
    Hs = p["H"] + 0.1 * rng.standard_normal((3, m, n))
    model = LinearGaussianModel(t64(As), t64(Hs), t64(Qs), t64(p["R"]), B=t64(p["B"]))
    y = t64(p["y"]).expand(3, *p["y"].shape)
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    sm = CKF(model, sqrt=sqrt).smooth(y, t64(p["u"]), **kw)
    assert sm.mean.shape == (3, *p["y"].shape[:1], n)
    for i in range(3):
        one = LinearGaussianModel(t64(As[i]), t64(Hs[i]), t64(Qs[i]), t64(p["R"]), B=t64(p["B"]))
        ref = CKF(one).smooth(t64(p["y"]), t64(p["u"]), **kw, path="cubature")
        assert_same(sm.filtered.mean[i], ref.filtered.mean, f"model {i} mean")
        assert_same(sm.filtered.log_likelihood[i], ref.filtered.log_likelihood, f"model {i} ll")
        assert_same(sm.cov[i], ref.cov, f"model {i} smoothed cov")


@pytest.mark.parametrize("complete", [False, True], ids=["missing", "complete"])
@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_log_likelihood_gradients_equal_ckf(sqrt, complete):
    """d log-likelihood / d(A, Q, R) through the exact path equals it through the cubature path."""
    p = make_problem(6, missing=0.0 if complete else 0.2)
    if complete:
        p["y"][3] = p["y"][2]

    def grads(path):
        A = t64(p["A"]).requires_grad_(True)
        Lq = torch.linalg.cholesky(t64(p["Q"])).requires_grad_(True)
        R = t64(p["R"]).requires_grad_(True)
        model = LinearGaussianModel(A, t64(p["H"]), Lq @ Lq.mT, R, B=t64(p["B"]))
        res = CKF(model, sqrt=sqrt).filter(
            t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]), path=path
        )
        assert res.path == path
        return torch.autograd.grad(res.log_likelihood, (A, Lq, R))

    for name, a, b in zip("A Lq R".split(), grads("kalman"), grads("cubature"), strict=True):
        assert_same(a, b, f"d ll / d {name}")


def test_gradcheck_exact_path():
    p = make_problem(7, n=2, m=1, T=5)
    y = t64(p["y"])

    def fn(A, q, r):
        model = LinearGaussianModel(A, t64(p["H"]), q * t64(p["Q"]), r * t64(p["R"]), B=t64(p["B"]))
        sm = CKF(model).smooth(y, t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]))
        return sm.filtered.log_likelihood, sm.mean, sm.cov

    args = (
        t64(p["A"]),
        torch.tensor(1.0, dtype=torch.float64),
        torch.tensor(1.0, dtype=torch.float64),
    )
    assert torch.autograd.gradcheck(
        fn, tuple(a.requires_grad_(True) for a in args), eps=1e-6, atol=1e-6
    )


def test_path_selection():
    p = make_problem(8)
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y, u = t64(p["y"]), t64(p["u"])
    assert CKF(model_of(p)).filter(y, u, **kw).path == "kalman"
    # without re-drawn update points the CKF is not the Kalman filter: it keeps its own answer
    assert CKF(model_of(p), redraw=False).filter(y, u, **kw).path == "cubature"
    # two LinearModel maps are recognised; so is a model declaring linear_system()
    A, H = t64(p["A"]), t64(p["H"])
    pair = StateSpaceModel(LinearModel(A, t64(p["Q"]), t64(p["B"])), LinearModel(H, t64(p["R"])))
    assert CKF(pair).filter(y, u, **kw).path == "kalman"

    class Declared(StateSpaceModel):
        def linear_system(self):
            return LinearSystem(A=A, H=H, B=t64(p["B"]))

    declared = Declared(
        lambda x, u: x @ A.mT + u @ t64(p["B"]).mT,
        lambda x, u: x @ H.mT,
        Q=t64(p["Q"]),
        R=t64(p["R"]),
    )
    a = CKF(declared).filter(y, u, **kw)
    b = CKF(declared).filter(y, u, **kw, path="cubature")
    assert a.path == "kalman" and b.path == "cubature"
    assert_same(a.mean, b.mean, "declared model")
    nonlinear = StateSpaceModel(
        lambda x, u: torch.sin(x), lambda x, u: x[..., :2], Q=t64(p["Q"]), R=t64(p["R"])
    )
    assert CKF(nonlinear).filter(y, **kw).path == "cubature"
    with pytest.raises(ModelError, match="path='kalman' needs a linear-Gaussian model"):
        CKF(nonlinear).filter(y, **kw, path="kalman")
    with pytest.raises(ModelError, match="parallel=True needs a linear-Gaussian model"):
        CKF(nonlinear).smooth(y, **kw, parallel=True)
    with pytest.raises(InputError, match="path must be"):
        CKF(model_of(p)).filter(y, u, **kw, path="exact")
    with pytest.raises(InputError, match="u: the model has an input matrix"):
        exact_filter(model_of(p), y, **kw)


@pytest.mark.parametrize("grad", [False, True], ids=["no_grad", "grad"])
@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
def test_outputs_option(sqrt, grad):
    """Only the asked-for fields come back, with the values of the full run."""
    p = make_problem(9)
    q = torch.tensor(1.0, dtype=torch.float64, requires_grad=grad)
    model = LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), q * t64(p["Q"]), t64(p["R"]), B=t64(p["B"])
    )
    filt = CKF(model, sqrt=sqrt)
    args, kw = (t64(p["y"]), t64(p["u"])), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    full = filt.filter(*args, **kw)
    for outputs in (
        ("mean", "log_likelihood"),
        ("cov", "cross_cov"),
        ("innovation", "log_likelihood"),
    ):
        part = filt.filter(*args, **kw, outputs=outputs)
        for name in FIELDS:
            if name in outputs:
                assert_same(getattr(part, name), getattr(full, name), f"{outputs}: {name}")
            else:
                assert getattr(part, name).numel() == 0, name
        ckf = filt.filter(*args, **kw, outputs=outputs, path="cubature")
        assert ckf.cov.numel() == (0 if "cov" not in outputs else full.cov.numel())
    if grad:
        part = filt.filter(*args, **kw, outputs=("log_likelihood",))
        (g1,) = torch.autograd.grad(part.log_likelihood, q, retain_graph=True)
        (g2,) = torch.autograd.grad(full.log_likelihood, q)
        assert_same(g1, g2, "gradient with outputs=")
    with pytest.raises(InputError, match="outputs: unknown fields"):
        filt.filter(*args, **kw, outputs=("means",))


def test_result_path_survives_reconstruction():
    """Code that rebuilds a result field by field (pipeline.offline) keeps the class and path."""
    p = make_problem(10)
    res = CKF(model_of(p)).filter(t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]))
    again = type(res)(*res)
    assert again.path == "kalman" and isinstance(again, torchfilt.FilterResult)
    assert res._replace(mean=res.mean * 2).path == "kalman"


@pytest.mark.parametrize("grad", [False, True], ids=["no_grad", "grad"])
def test_log_likelihood_inside_the_loop(monkeypatch, grad):
    """Large batches sum the log-likelihood inside the loop: same value (and gradient)."""
    import torchfilt.filters.kalman_runners as kalman

    p = make_problem(12)
    q = torch.tensor(1.0, dtype=torch.float64, requires_grad=grad)
    model = LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), q * t64(p["Q"]), t64(p["R"]), B=t64(p["B"])
    )
    args, kw = (t64(p["y"]), t64(p["u"])), dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    want = CKF(model).filter(*args, **kw, path="cubature")
    monkeypatch.setattr(kalman, "_VECTOR_LL_BYTES", 0)
    got = CKF(model).filter(*args, **kw)
    assert_results_equal(got, want)
    if grad:
        g1 = torch.autograd.grad(got.log_likelihood, q, retain_graph=True)[0]
        g2 = torch.autograd.grad(want.log_likelihood, q)[0]
        assert_same(g1, g2, "gradient")


@pytest.mark.parametrize("doubling", [True, False], ids=["doubling", "sequential"])
@pytest.mark.parametrize("varying", [False, True], ids=["invariant", "time_varying"])
def test_shared_covariance_path(monkeypatch, varying, doubling):
    """All observed and one P0 for the batch: the covariance recursion runs once (and, for a
    time-invariant model, stops once converged); every field still equals the CKF's, whether
    the means' recursion runs step by step or as doubling scans."""
    import torchfilt.filters.kalman_runners as kalman

    monkeypatch.setattr(kalman, "_DOUBLING_WORK", float("inf") if doubling else 0)
    p = make_problem(13, T=120, missing=0.0)
    p["y"][3] = p["y"][2]
    rng = np.random.default_rng(2)
    T, m = p["y"].shape
    D = rng.standard_normal((m, 1))
    Q = (
        TimeVarying(t64(np.linspace(0.5, 2.0, T)[:, None, None] * p["Q"]))
        if varying
        else t64(p["Q"])
    )
    model = LinearGaussianModel(t64(p["A"]), t64(p["H"]), Q, t64(p["R"]), B=t64(p["B"]), D=t64(D))
    gen = torch.Generator().manual_seed(3)
    y = t64(p["y"]) + torch.randn(4, T, m, generator=gen, dtype=torch.float64)
    x0 = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    kw = dict(x0=x0, P0=t64(p["P0"]))
    want = CKF(model).filter(y, t64(p["u"]), **kw, path="cubature")
    got = CKF(model).filter(y, t64(p["u"]), **kw)
    assert got.cov.stride(0) == 0  # one covariance sequence, viewed by every batch element
    assert_results_equal(got, want)
    part = CKF(model).filter(y, t64(p["u"]), **kw, outputs=("mean", "log_likelihood"))
    assert_same(part.log_likelihood, want.log_likelihood, "outputs=")
    sm_want = CKF(model).smooth(y, t64(p["u"]), **kw, path="cubature")
    sm = CKF(model).smooth(y, t64(p["u"]), **kw)
    assert sm.cov.stride(0) == 0
    assert_same(sm.mean, sm_want.mean, "smoothed mean")
    assert_same(sm.cov, sm_want.cov, "smoothed cov")
    assert_same(sm.gain, sm_want.gain, "smoother gain")


def _per_sequence_problem(batch=5, T=150, n=3, m=2, seed=21):
    """A time-invariant model with controls, all observed, and a different ``P0`` per sequence."""
    p = make_problem(seed, n=n, m=m, T=max(T, 5), missing=0.0)
    p["y"], p["u"] = p["y"][:T], p["u"][:T]
    p["y"][3:4] = p["y"][2:3]
    rng = np.random.default_rng(seed + 1)
    D = rng.standard_normal((m, 1))
    model = model_of(p, D=t64(D))
    gen = torch.Generator().manual_seed(seed)
    y = t64(p["y"]) + torch.randn(batch, T, m, generator=gen, dtype=torch.float64)
    x0 = torch.randn(batch, n, generator=gen, dtype=torch.float64)
    scale = torch.rand(batch, 1, 1, generator=gen, dtype=torch.float64) * 4.0 + 0.25
    P0 = scale * t64(p["P0"])  # one covariance sequence per element of the batch
    return model, (y, t64(p["u"])), dict(x0=x0, P0=P0)


@pytest.mark.parametrize("tail", ["doubling", "sequential", "per_sequence_gains"], ids=lambda s: s)
def test_per_sequence_covariances_converge(monkeypatch, tail):
    """P0 per sequence and a time-invariant model: the per-sequence Riccati recursions run until
    all have converged, then the gains repeat (shared once they agree). Every field equals the
    CKF's and the per-step recursion's, whichever way the converged tail of the means runs."""
    import torchfilt.filters.kalman_runners as kalman

    model, args, kw = _per_sequence_problem()
    want = CKF(model).filter(*args, **kw, path="cubature")
    if tail == "doubling":
        monkeypatch.setattr(kalman, "_DOUBLING_WORK", float("inf"))
    else:
        monkeypatch.setattr(kalman, "_DOUBLING_WORK", 0)
    if tail == "per_sequence_gains":
        monkeypatch.setattr(kalman, "_AGREE_ULPS", -1.0)
    calls = []
    real = kalman._run_riccati

    def spy(*a, **k):
        out = real(*a, **k)
        calls.append(k["Bc"])
        return out

    monkeypatch.setattr(kalman, "_run_riccati", spy)
    got = CKF(model).filter(*args, **kw)
    assert calls == [args[0].shape[0]]  # the per-sequence Riccati runner ran
    assert got.cov.stride(0) != 0  # one covariance sequence per element
    assert_results_equal(got, want)
    part = CKF(model).filter(*args, **kw, outputs=("mean", "log_likelihood"))
    assert_same(part.mean, want.mean, "outputs= mean")
    assert_same(part.log_likelihood, want.log_likelihood, "outputs= log-likelihood")
    monkeypatch.setattr(kalman, "_covariance_batch", lambda data, steps: None)
    step_by_step = CKF(model).filter(*args, **kw)  # the per-step recursion (_run_fast)
    assert_results_equal(got, step_by_step)


@pytest.mark.parametrize("T", [1, 2, 3, 4, 5, 9])
@pytest.mark.parametrize("shared", [True, False], ids=["shared", "per_sequence"])
def test_riccati_runner_short_recordings(T, shared):
    """Recordings shorter than the convergence check, or ending right after it."""
    model, (y, u), kw = _per_sequence_problem(batch=3, T=T)
    if shared:
        kw["P0"] = kw["P0"][0]
    want = CKF(model).filter(y, u, **kw, path="cubature")
    assert_results_equal(CKF(model).filter(y, u, **kw), want)


def test_converged_tail_equals_numpy_reference():
    """A long recording of a scalar measurement (``m = 1``, the divided gain) against the NumPy
    Kalman filter of ``reference``: means, covariances and log-likelihood."""
    p = make_problem(31, n=2, m=1, T=400, missing=0.0)
    model = model_of(p)
    got = exact_filter(model, t64(p["y"]), t64(p["u"]), x0=t64(p["m0"]), P0=t64(p["P0"]))
    ms, Ps, mps, _, ll = kalman_filter(
        p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], B=p["B"], u=p["u"]
    )
    assert got.path == "kalman"
    np.testing.assert_allclose(got.mean.numpy(), ms, rtol=REF_RTOL, atol=REF_ATOL)
    np.testing.assert_allclose(got.cov.numpy(), Ps, rtol=REF_RTOL, atol=REF_ATOL)
    np.testing.assert_allclose(got.predicted_mean.numpy(), mps, rtol=REF_RTOL, atol=REF_ATOL)
    np.testing.assert_allclose(float(got.log_likelihood), ll, rtol=REF_RTOL)
