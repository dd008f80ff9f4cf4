"""Prediction ahead (torchfilt.filters.forecast): free-run and k-step-ahead moments.

Linear models against closed-form moments computed independently in numpy float64 (matrix powers
``A^j m + sum_i A^i B u``, ``A^j P A^j' + sum_i A^i Q A^i'``, ``H x + D u``, ``H P H' + R`` from a
numpy Kalman filter of tests/reference.py); nonlinear models against the CKF's own prediction on
NaN measurements (the workaround the functions replace); coverage on data simulated from the true
model; the argument checks, by example and by hypothesis.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from fuzz_support import Refused, attempt, property_tests
from hypothesis import strategies as st
from reference import kalman_filter as np_kalman

import torchfilt
from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.filters import ConstrainedCKF, Forecast, free_run, k_step_ahead

D = torch.float64
TOL = 1e-10


def _linear(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    th = 0.3
    A = 0.95 * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    return {
        "A": A,
        "B": rng.standard_normal((2, 1)),
        "H": rng.standard_normal((2, 2)),
        "D": rng.standard_normal((2, 1)),
        "Q": np.array([[0.2, 0.05], [0.05, 0.1]]),
        "R": np.array([[0.3, 0.0], [0.0, 0.5]]),
        "x0": np.array([1.0, -0.5]),
        "P0": np.array([[0.5, 0.1], [0.1, 0.4]]),
    }


def _model(p: dict[str, np.ndarray]) -> LinearGaussianModel:
    t = {k: torch.tensor(v, dtype=D) for k, v in p.items()}
    return LinearGaussianModel(A=t["A"], H=t["H"], Q=t["Q"], R=t["R"], B=t["B"], D=t["D"])


def _data(T: int, batch: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    y = rng.standard_normal((batch, T, 2))
    y[:, 3, 0] = np.nan  # missing components and a missing step
    y[:, 7, :] = np.nan
    u = rng.standard_normal((batch, T, 1))
    return y, u


def _ahead(p: dict[str, np.ndarray], m: np.ndarray, P: np.ndarray, u: np.ndarray, s: int, j: int):
    """Moments of x_s and y_s, ``j`` closed-form prediction steps from (m, P) about x_{s-j}."""
    A, B, Q = p["A"], p["B"], p["Q"]
    Aj = np.linalg.matrix_power(A, j)
    mean = Aj @ m + sum(np.linalg.matrix_power(A, i) @ B @ u[s - i] for i in range(j))
    cov = Aj @ P @ Aj.T + sum(
        np.linalg.matrix_power(A, i) @ Q @ np.linalg.matrix_power(A, i).T for i in range(j)
    )
    y_mean = p["H"] @ mean + p["D"] @ u[s]
    y_free = p["H"] @ cov @ p["H"].T
    return mean, cov, y_mean, y_free + p["R"], y_free


def _filtered(p: dict[str, np.ndarray], y: np.ndarray, u: np.ndarray):
    # tests/reference.py's filter has no feed-through: subtract D u from the measurements
    yd = y - u @ p["D"].T
    ms, Ps, *_ = np_kalman(p["A"], p["H"], p["Q"], p["R"], yd, p["x0"], p["P0"], B=p["B"], u=u)
    return ms, Ps


def _reference(p, y, u, origin_of):
    """Closed-form moments of every step ``s``, predicted from the filtered belief at
    ``origin_of(s)`` (``-1``: the prior)."""
    ms, Ps = _filtered(p, y, u)
    out = [[] for _ in range(5)]
    for s in range(y.shape[0]):
        o = origin_of(s)
        m, P = (p["x0"], p["P0"]) if o < 0 else (ms[o], Ps[o])
        for acc, v in zip(out, _ahead(p, m, P, u, s, s - o), strict=True):
            acc.append(v)
    return [np.array(v) for v in out]


def _check(res: Forecast, ref: list[np.ndarray]) -> None:
    for got, want in zip(res, ref, strict=True):
        np.testing.assert_allclose(got.numpy(), want, rtol=TOL, atol=TOL)


def _args(p):
    return {"x0": torch.tensor(p["x0"], dtype=D), "P0": torch.tensor(p["P0"], dtype=D)}


@pytest.mark.parametrize("path", ["auto", "cubature"])
@pytest.mark.parametrize("k", [0, 1, 3, 25])
def test_k_step_ahead_equals_closed_form(path: str, k: int) -> None:
    p = _linear()
    y, u = _data(T=20, batch=3)
    res = k_step_ahead(
        _model(p), torch.tensor(y), torch.tensor(u), horizon=k, path=path, **_args(p)
    )  # type: ignore[arg-type]
    assert res.mean.shape == (3, 20, 2) and res.output_cov.shape == (3, 20, 2, 2)
    for b in range(3):
        ref = _reference(p, y[b], u[b], lambda s: max(s - k, -1))
        _check(Forecast(*(f[b] for f in res)), ref)


@pytest.mark.parametrize("path", ["auto", "cubature"])
@pytest.mark.parametrize("burn_in", [0, 1, 8, 20])
def test_free_run_equals_closed_form(path: str, burn_in: int) -> None:
    p = _linear()
    y, u = _data(T=20, batch=2)
    res = free_run(
        _model(p), torch.tensor(y), torch.tensor(u), burn_in=burn_in, path=path, **_args(p)
    )  # type: ignore[arg-type]
    for b in range(2):
        ref = _reference(p, y[b], u[b], lambda s: s if s < burn_in else burn_in - 1)
        _check(Forecast(*(f[b] for f in res)), ref)


def test_free_run_ignores_measurements_after_burn_in() -> None:
    p = _linear()
    y, u = _data(T=15, batch=1)
    y2 = y.copy()
    y2[:, 6:] += 100.0
    a = free_run(_model(p), torch.tensor(y), torch.tensor(u), burn_in=6, **_args(p))
    b = free_run(_model(p), torch.tensor(y2), torch.tensor(u), burn_in=6, **_args(p))
    for x, z in zip(a, b, strict=True):
        torch.testing.assert_close(x, z, rtol=0, atol=0)


def _nonlinear() -> StateSpaceModel:
    def f(x, u):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 + 0.1 * x2, x2 - 0.1 * torch.sin(x1) + 0.1 * u[..., 0]], -1)

    def h(x, u):
        return torch.stack([torch.sin(x[..., 0]) + 0.5 * u[..., 0], x[..., 0] * x[..., 1]], -1)

    return StateSpaceModel(f, h, Q=0.01 * torch.eye(2, dtype=D), R=0.1 * torch.eye(2, dtype=D))


def _nl_data(T: int = 12, batch: int = 2):
    g = torch.Generator().manual_seed(3)
    y = torch.randn(batch, T, 2, generator=g, dtype=D)
    y[:, 2, 1] = math.nan
    u = torch.randn(batch, T, 1, generator=g, dtype=D)
    return y, u, {"x0": torch.tensor([0.3, -0.2], dtype=D), "P0": 0.2 * torch.eye(2, dtype=D)}


def test_nonlinear_free_run_equals_ckf_on_nan_measurements() -> None:
    model = _nonlinear()
    y, u, prior = _nl_data()
    burn_in = 5
    ckf = CKF(model)
    res = ckf.free_run(y, u, burn_in=burn_in, **prior)
    y_nan = y.clone()
    y_nan[:, burn_in:] = math.nan
    old = ckf.filter(y_nan, u, **prior)
    torch.testing.assert_close(res.mean, old.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.cov, old.cov, rtol=1e-12, atol=1e-12)
    after = slice(burn_in, None)
    torch.testing.assert_close(res.output_mean[:, after], old.measurement_mean[:, after])
    torch.testing.assert_close(res.output_cov[:, after], old.innovation_cov[:, after])
    R = 0.1 * torch.eye(2, dtype=D)
    torch.testing.assert_close(res.output_cov_noise_free, res.output_cov - R)


@pytest.mark.parametrize("k", [1, 2, 4])
def test_nonlinear_k_step_equals_ckf_on_nan_measurements(k: int) -> None:
    model = _nonlinear()
    y, u, prior = _nl_data()
    T = y.shape[-2]
    ckf = CKF(model)
    res = ckf.k_step_ahead(y, u, horizon=k, **prior)
    for s in range(T):
        y_nan = y.clone()
        y_nan[:, max(s - k + 1, 0) :] = math.nan  # measurements up to s - k only
        old = ckf.filter(y_nan, u, **prior)
        torch.testing.assert_close(res.mean[:, s], old.predicted_mean[:, s], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(res.cov[:, s], old.predicted_cov[:, s], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(res.output_mean[:, s], old.measurement_mean[:, s])
        torch.testing.assert_close(res.output_cov[:, s], old.innovation_cov[:, s])


@pytest.mark.parametrize("model", ["linear", "nonlinear"])
def test_k0_is_filtered_and_k1_is_the_filters_prediction(model: str) -> None:
    if model == "linear":
        p = _linear()
        mdl: StateSpaceModel = _model(p)
        yn, un = _data(T=15, batch=2)
        y, u, prior = torch.tensor(yn), torch.tensor(un), _args(p)
    else:
        mdl = _nonlinear()
        y, u, prior = _nl_data()
    ckf = CKF(mdl)
    filt = ckf.filter(y, u, **prior)
    k0 = ckf.k_step_ahead(y, u, horizon=0, **prior)
    torch.testing.assert_close(k0.mean, filt.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(k0.cov, filt.cov, rtol=1e-12, atol=1e-12)
    if model == "linear":  # the filtered belief mapped through the output map
        H, Dm = torch.tensor(p["H"]), torch.tensor(p["D"])
        want = filt.mean @ H.mT + u @ Dm.mT
        torch.testing.assert_close(k0.output_mean, want, rtol=1e-12, atol=1e-12)
        want_cov = H @ filt.cov @ H.mT + torch.tensor(p["R"])
        torch.testing.assert_close(k0.output_cov, want_cov, rtol=1e-12, atol=1e-12)
    k1 = ckf.k_step_ahead(y, u, horizon=1, **prior)
    torch.testing.assert_close(k1.mean, filt.predicted_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(k1.cov, filt.predicted_cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(k1.output_mean, filt.measurement_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(k1.output_cov, filt.innovation_cov, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("path", ["kalman", "cubature"])
def test_time_varying_noise_is_read_at_the_predicted_step(path: str) -> None:
    """Per-step Q and R: the free run equals the filter on NaN measurements after the burn-in,
    which reads Q_t and R_t at step t."""
    p = _linear()
    T = 12
    scale = torch.linspace(0.2, 3.0, T, dtype=D)[:, None, None]
    t = {k: torch.tensor(v, dtype=D) for k, v in p.items()}
    model = LinearGaussianModel(
        A=t["A"],
        H=t["H"],
        Q=torchfilt.models.TimeVarying(scale * t["Q"]),
        R=torchfilt.models.TimeVarying(scale.flip(0) * t["R"]),
        B=t["B"],
        D=t["D"],
    )
    yn, un = _data(T=T, batch=2)
    y, u = torch.tensor(yn), torch.tensor(un)
    ckf = CKF(model)
    res = ckf.free_run(y, u, burn_in=4, path=path, **_args(p))
    y_nan = y.clone()
    y_nan[:, 4:] = math.nan
    old = ckf.filter(y_nan, u, path=path, **_args(p))
    torch.testing.assert_close(res.cov, old.cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.output_cov[:, 4:], old.innovation_cov[:, 4:])
    ahead = ckf.k_step_ahead(y, u, horizon=1, path=path, **_args(p))
    full = ckf.filter(y, u, path=path, **_args(p))
    torch.testing.assert_close(ahead.cov, full.predicted_cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ahead.output_cov, full.innovation_cov, rtol=1e-12, atol=1e-12)


def test_mask_is_missing_data() -> None:
    p = _linear()
    yn, un = _data(T=10, batch=2)
    y, u = torch.tensor(yn), torch.tensor(un)
    mask = torch.ones(10, 2, dtype=torch.bool)
    mask[5, 1] = False
    mask[6] = False
    y_nan = y.clone()
    y_nan[..., ~mask] = math.nan
    for kw in ({"horizon": 2}, {"horizon": 0}):
        a = k_step_ahead(_model(p), y, u, mask=mask, **kw, **_args(p))
        b = k_step_ahead(_model(p), y_nan, u, **kw, **_args(p))
        for x, z in zip(a, b, strict=True):
            torch.testing.assert_close(x, z, rtol=0, atol=0)
    a = free_run(_model(p), y, u, mask=mask, burn_in=8, **_args(p))
    b = free_run(_model(p), y_nan, u, burn_in=8, **_args(p))
    for x, z in zip(a, b, strict=True):
        torch.testing.assert_close(x, z, rtol=0, atol=0)


def test_batched_model_and_prior() -> None:
    """A model whose matrices carry a batch dimension, with a batched prior, matches per-batch
    runs."""
    p = _linear()
    scales = torch.tensor([0.5, 0.9, 1.0], dtype=D)
    A = torch.tensor(p["A"]) * scales[:, None, None]
    t = {k: torch.tensor(v, dtype=D) for k, v in p.items()}
    model = LinearGaussianModel(A=A, H=t["H"], Q=t["Q"], R=t["R"], B=t["B"], D=t["D"])
    yn, un = _data(T=10, batch=3)
    y, u = torch.tensor(yn), torch.tensor(un)
    x0 = t["x0"] * torch.arange(1, 4, dtype=D)[:, None]
    for fn, kw in ((k_step_ahead, {"horizon": 2}), (free_run, {"burn_in": 4})):
        for path in ("auto", "cubature"):
            res = fn(model, y, u, x0=x0, P0=t["P0"], path=path, **kw)  # type: ignore[operator]
            for b in range(3):
                one = LinearGaussianModel(A=A[b], H=t["H"], Q=t["Q"], R=t["R"], B=t["B"], D=t["D"])
                ref = fn(one, y[b], u[b], x0=x0[b], P0=t["P0"], **kw)  # type: ignore[operator]
                for got, want in zip(res, ref, strict=True):
                    torch.testing.assert_close(got[b], want, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("what", ["k_step", "free_run"])
def test_coverage_of_output_band_on_true_model(what: str) -> None:
    """95% bands of the output from the true model hold about 95% of simulated measurements."""
    p = _linear(seed=4)
    model = _model(p)
    g = torch.Generator().manual_seed(11)
    B, T = 400, 40
    u = torch.randn(B, T, 1, generator=g, dtype=D)
    sim = torchfilt.systems.simulate(
        model,
        T,
        torch.tensor(p["x0"]),
        P0=torch.tensor(p["P0"]),
        u=u,
        batch_shape=(B,),
        generator=g,
    )
    y = sim.measurements
    if what == "k_step":
        res = k_step_ahead(model, y, u, horizon=3, **_args(p))
    else:  # the steps after the burn-in (before it, the band is conditioned on y_t itself)
        res = Forecast(*(f[:, 10:] for f in free_run(model, y, u, burn_in=10, **_args(p))))
        y = y[:, 10:]
    z = (y - res.output_mean) / res.output_cov.diagonal(dim1=-2, dim2=-1).sqrt()
    inside = float((z.abs() <= 1.959964).to(D).mean())
    assert 0.94 < inside < 0.96, inside
    # the noise-free band is narrower by the measurement noise: it holds 2 Phi(1.96 r) - 1 of
    # them, r = sqrt(noise-free variance / variance)
    free = res.output_cov_noise_free.diagonal(dim1=-2, dim2=-1)
    zf = (y - res.output_mean) / free.sqrt()
    r = (free / res.output_cov.diagonal(dim1=-2, dim2=-1)).sqrt()
    expected = float((2 * torch.special.ndtr(1.959964 * r) - 1).mean())
    assert expected < 0.945
    assert abs(float((zf.abs() <= 1.959964).to(D).mean()) - expected) < 0.01


# ---------------------------------------------------------------------------------- errors
def _small():
    p = _linear()
    y, u = _data(T=10, batch=1)
    return _model(p), torch.tensor(y), torch.tensor(u), _args(p)


@pytest.mark.parametrize(
    ("kw", "err", "name"),
    [
        ({"horizon": -1}, InputError, "horizon"),
        ({"horizon": 1.5}, InputTypeError, "horizon"),
        ({"horizon": True}, InputTypeError, "horizon"),
        ({"horizon": None}, InputTypeError, "horizon"),
    ],
)
def test_k_step_argument_errors(kw, err, name) -> None:
    model, y, u, prior = _small()
    with pytest.raises(err, match=name):
        k_step_ahead(model, y, u, **prior, **kw)


@pytest.mark.parametrize(
    ("kw", "err", "name"),
    [
        ({"burn_in": -1}, InputError, "burn_in"),
        ({"burn_in": 11}, InputError, "burn_in"),
        ({"burn_in": 2.0}, InputTypeError, "burn_in"),
    ],
)
def test_free_run_argument_errors(kw, err, name) -> None:
    model, y, u, prior = _small()
    with pytest.raises(err, match=name):
        free_run(model, y, u, **prior, **kw)


@pytest.mark.parametrize("fn", ["k", "free"])
def test_shape_and_model_errors(fn: str) -> None:
    model, y, u, prior = _small()

    def call(*args, **kw):
        if fn == "k":
            return k_step_ahead(*args, horizon=1, **kw)
        return free_run(*args, burn_in=2, **kw)

    with pytest.raises(ShapeError, match="y"):
        call(model, y[..., :1], u, **prior)
    with pytest.raises(ShapeError, match="u"):
        call(model, y, u[..., :3, :], **prior)
    with pytest.raises(ShapeError, match="u"):
        call(model, y, torch.cat([u, u], -1), **prior)
    with pytest.raises(InputError, match="u"):
        call(model, y, None, **prior)
    with pytest.raises(ShapeError, match="x0"):
        call(model, y, u, x0=torch.zeros(3, dtype=D), P0=prior["P0"])
    with pytest.raises(ShapeError, match="y"):
        call(model, y[..., :0, :], u[..., :0, :], **prior)
    with pytest.raises(ModelError, match="kalman"):
        call(_nonlinear(), y, u, path="kalman", **prior)


def test_constrained_filter_is_refused() -> None:
    model, y, u, prior = _small()
    cckf = ConstrainedCKF(
        model, lower=torch.full((2,), -10.0, dtype=D), upper=torch.full((2,), 10.0, dtype=D)
    )
    with pytest.raises(ModelError, match="ConstrainedCKF"):
        cckf.k_step_ahead(y, u, horizon=1, **prior)
    with pytest.raises(ModelError, match="ConstrainedCKF"):
        cckf.free_run(y, u, burn_in=1, **prior)


# ---------------------------------------------------------------------------------- fuzz
_COUNTS = st.one_of(
    st.integers(-3, 12),
    st.floats(-2.0, 12.0),
    st.just(math.nan),
    st.none(),
    st.booleans(),
    st.just(np.int64(2)),
)


def _fuzz(data: st.DataObject) -> None:
    p = _linear()
    T = data.draw(st.integers(1, 8), "T")
    batch = data.draw(st.sampled_from([(), (2,)]), "batch")
    m = data.draw(st.sampled_from([2, 2, 1]), "m")
    nu = data.draw(st.sampled_from([1, 1, 2, None]), "nu")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 99), "seed"))
    y = torch.randn(*batch, T, m, generator=g, dtype=D)
    u = None if nu is None else torch.randn(*batch, T, nu, generator=g, dtype=D)
    count = data.draw(_COUNTS, "count")
    which = data.draw(st.sampled_from(["k", "free"]), "fn")
    path = data.draw(st.sampled_from(["auto", "cubature"]), "path")
    model = _model(p)
    if which == "k":
        out, _ = attempt(
            "k_step_ahead", k_step_ahead, model, y, u, horizon=count, path=path, **_args(p)
        )
    else:
        out, _ = attempt("free_run", free_run, model, y, u, burn_in=count, path=path, **_args(p))
    valid_count = (
        not isinstance(count, (bool, float))
        and count is not None
        and 0 <= int(count)
        and (which == "k" or int(count) <= T)
    )
    valid = valid_count and m == 2 and nu == 1
    if not valid:
        assert isinstance(out, Refused), (count, m, nu, out)
        return
    assert isinstance(out, Forecast), out
    assert out.mean.shape == (*batch, T, 2) and out.cov.shape == (*batch, T, 2, 2)
    assert out.output_mean.shape == (*batch, T, 2)
    assert out.output_cov.shape == (*batch, T, 2, 2)
    assert bool(torch.isfinite(out.output_cov).all())
    evals = torch.linalg.eigvalsh(out.output_cov)
    assert bool((evals > 0).all())


test_fuzz_forecast_arguments, test_fuzz_forecast_arguments_long = property_tests(
    _fuzz, short=40, long=600
)


@pytest.mark.parametrize("path", ["auto", "cubature"])
def test_differentiable_in_the_model_parameters(path: str) -> None:
    """The forecast moments are differentiable (gradcheck against finite differences)."""
    p = _linear()
    t = {k: torch.tensor(v, dtype=D) for k, v in p.items()}
    yn, un = _data(T=9, batch=1)
    y, u = torch.tensor(yn), torch.tensor(un)

    def fn(a: torch.Tensor) -> tuple[torch.Tensor, ...]:
        model = LinearGaussianModel(A=a * t["A"], H=t["H"], Q=t["Q"], R=t["R"], B=t["B"], D=t["D"])
        ahead = k_step_ahead(model, y, u, horizon=2, path=path, **_args(p))
        sim = free_run(model, y, u, burn_in=3, path=path, **_args(p))
        return ahead.output_mean, ahead.output_cov, sim.output_mean, sim.cov

    a = torch.tensor(0.9, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (a,))
