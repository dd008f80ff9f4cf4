"""Learning from measurements alone: EM with the cubature RTS smoother and direct likelihood
maximisation, against statsmodels' ARMA MLE on a linear-Gaussian system (float64, seeded).

The system has n = 2 states and m = 1 measurement with a known H = [1, 0] (the gauge). Its output
is an ARMA(2, 2) process, so statsmodels' exact MLE of SARIMAX(2, 0, 2) is an independent
reference for the invariants of the learned model: the eigenvalues of A are the inverse AR roots,
and the output spectrum ``H (zI - A)^{-1} Q (z^{-1} I - A^T)^{-1} H^T + R`` equals the ARMA
spectrum ``s2 |theta(z)|^2 / |phi(z)|^2`` on the unit circle. A, Q themselves are identified only
up to the similarity transforms that keep H (m < n), so they are not compared entry by entry.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from statsmodels.tsa.statespace.sarimax import SARIMAX

import torchfilt
from torchfilt.exceptions import GaugeError, InputError
from torchfilt.models import (
    CholeskyCovariance,
    InducingTransition,
    LinearGaussianModel,
    LinearModel,
    StateSpaceModel,
)
from torchfilt.optim import CheckpointOptions, OptimizerOptions, StoppingOptions, WindowOptions
from torchfilt.training import check_gauge, fit_em, fit_measurement_only

DT = torch.float64
A_TRUE = torch.tensor([[0.8, 0.4], [-0.4, 0.6]], dtype=DT)
H = torch.tensor([[1.0, 0.0]], dtype=DT)
Q_TRUE = torch.tensor([[0.2, 0.05], [0.05, 0.3]], dtype=DT)
R_TRUE = torch.tensor([[0.05]], dtype=DT)
A_INIT = torch.tensor([[0.5, 0.2], [-0.1, 0.4]], dtype=DT)
X0, P0 = torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)
T = 400
#: |eig(A) - inverse AR roots of the reference MLE| (same data; the two fits differ by the
#: prior of the first state and, for the likelihood method, by the windows' burn-in)
EIG_TOL = 0.05
#: relative error of the output spectrum on a frequency grid
SPECTRUM_RTOL = 0.15
#: log-likelihood gap to the reference MLE (nats; the prior conventions differ)
LL_TOL = 3.0


def simulate(T: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    LQ, LR = torch.linalg.cholesky(Q_TRUE), torch.linalg.cholesky(R_TRUE)
    x = torch.zeros(2, dtype=DT)
    ys = []
    for _ in range(T):
        x = A_TRUE @ x + LQ @ torch.randn(2, generator=g, dtype=DT)
        ys.append(H @ x + LR @ torch.randn(1, generator=g, dtype=DT))
    return torch.stack(ys)


@pytest.fixture(scope="module")
def data() -> torch.Tensor:
    return simulate(T, seed=3)


@pytest.fixture(scope="module")
def reference(data: torch.Tensor):
    res = SARIMAX(data.numpy()[:, 0], order=(2, 0, 2), trend="n").fit(disp=False)
    return res


OMEGA = np.linspace(0.05, math.pi, 40)


def ss_spectrum(A: torch.Tensor, Q: torch.Tensor, R: torch.Tensor) -> np.ndarray:
    A_, Q_, R_, H_ = (t.detach().numpy() for t in (A, Q, R, H))
    out = []
    for w in OMEGA:
        G = H_ @ np.linalg.inv(np.exp(1j * w) * np.eye(2) - A_)
        out.append((G @ Q_ @ G.conj().T).real[0, 0] + R_[0, 0])
    return np.array(out)


def arma_spectrum(res) -> np.ndarray:
    ar, ma, s2 = res.arparams, res.maparams, res.params[-1]
    z = np.exp(-1j * OMEGA)
    phi = 1 - ar[0] * z - ar[1] * z**2
    theta = 1 + ma[0] * z + ma[1] * z**2
    return s2 * np.abs(theta) ** 2 / np.abs(phi) ** 2


def check_invariants(A, Q, R, reference) -> None:
    eig = np.sort_complex(torch.linalg.eigvals(A.detach()).numpy())
    ref = np.sort_complex(1.0 / reference.arroots)
    assert np.abs(eig - ref).max() < EIG_TOL, (eig, ref)
    spec, ref_spec = ss_spectrum(A, Q, R), arma_spectrum(reference)
    assert np.abs(spec / ref_spec - 1).max() < SPECTRUM_RTOL


def initial_linear() -> LinearGaussianModel:
    return LinearGaussianModel(A_INIT, H, 0.3 * torch.eye(2, dtype=DT), torch.eye(1, dtype=DT))


def learnable_linear() -> StateSpaceModel:
    """The likelihood method's model: an InducingTransition without inducing points (the linear
    part alone), learnable Q, a known H and a learnable R."""
    f = InducingTransition(2, 0, linear=A_INIT)
    f.bias.requires_grad_(False)
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))


@pytest.fixture(scope="module")
def em_fit(data):
    return fit_em(
        initial_linear(),
        data,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=100,
        stopping=StoppingOptions(tol=1e-9),
    )


def test_em_recovers_linear_system(em_fit, reference):
    m = em_fit.model
    assert isinstance(m, LinearGaussianModel)
    check_invariants(m.A, m.transition.noise_cov(), m.measurement.noise_cov(), reference)
    assert abs(em_fit.log_likelihood - reference.llf) < LL_TOL
    assert torch.equal(m.H, H)  # the gauge is kept


def test_em_log_likelihood_never_decreases(em_fit):
    ll = np.array([em_fit.initial_log_likelihood] + [h["log_likelihood"] for h in em_fit.history])
    assert len(ll) > 20 and ll[-1] == em_fit.log_likelihood
    # exact EM on a linear-Gaussian model: monotone up to round-off
    assert (np.diff(ll) >= -1e-8 * np.abs(ll[1:])).all()
    assert ll[-1] > ll[0] + 50


@pytest.mark.slow
def test_likelihood_method_recovers_linear_system(data, reference):
    model = learnable_linear()
    fit = fit_measurement_only(
        model,
        data,
        x0=X0,
        P0=P0,
        known_channels=[0],
        method="likelihood",
        iterations=12,
        windows=WindowOptions(window=50, burn_in=10),
        noise_scale="none",  # the reference MLE is of all the data: none held out
    )
    f = model.transition.base
    assert isinstance(f, InducingTransition)
    Q = model.transition.noise_cov()
    R = model.measurement.noise_cov()
    check_invariants(f.linear, Q, R, reference)
    full = torchfilt.CKF(model).filter(data, x0=X0, P0=P0).log_likelihood
    assert abs(float(full.detach()) - reference.llf) < LL_TOL
    assert fit.method == "likelihood" and fit.known_channels == [0]


def test_likelihood_method_moves_towards_the_mle(data, reference):
    """The fast twin of the slow recovery test: three L-BFGS iterations raise the likelihood and
    bring eig(A) closer to the reference MLE's."""
    model = learnable_linear()
    ref = np.sort_complex(1.0 / reference.arroots)

    def gap() -> float:
        eig = np.sort_complex(torch.linalg.eigvals(model.transition.base.linear.detach()).numpy())
        return float(np.abs(eig - ref).max())

    before = gap()
    fit = fit_measurement_only(
        model,
        data[:150],
        x0=X0,
        P0=P0,
        known_channels=[0],
        method="likelihood",
        iterations=3,
        windows=WindowOptions(window=50, burn_in=10),
    )
    assert fit.log_likelihood > fit.detail.initial_log_likelihood + 20
    assert gap() < 0.5 * before


def test_em_gp_transition_improves_likelihood(data):
    """The gradient M-step (any model): a GP transition with inducing points, from the same
    start, raises the likelihood monotonically (generalised EM)."""
    f = InducingTransition(2, 6, linear=A_INIT, outputscale=0.01, lengthscale=1.0)
    f.init_inducing(torch.randn(50, 2, generator=torch.Generator().manual_seed(1), dtype=DT))
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    model = StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))
    fit = fit_em(model, data[:150], x0=X0, P0=P0, known_channels=[0], iterations=8)
    ll = np.array([fit.initial_log_likelihood] + [r["log_likelihood"] for r in fit.history])
    # the E-step is exact only for a linear model; here the step is safeguarded
    assert (np.diff(ll) >= 0).all()
    assert ll[-1] > ll[0] + 10


def test_em_reproducible_and_resume_equals_uninterrupted(data, tmp_path):
    y = data[:200]
    full = fit_em(
        initial_linear(),
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=12,
        stopping=StoppingOptions(tol=0),
    )
    again = fit_em(
        initial_linear(),
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=12,
        stopping=StoppingOptions(tol=0),
    )
    assert again.log_likelihood == full.log_likelihood
    ck = tmp_path / "em.pt"
    part = fit_em(
        initial_linear(),
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=5,
        checkpoint=ck,
        stopping=StoppingOptions(tol=0),
    )
    assert part.iterations == 5
    resumed = fit_em(
        initial_linear(),
        y,
        x0=X0,
        P0=P0,
        known_channels=[0],
        iterations=12,
        stopping=StoppingOptions(tol=0),
        checkpoint=CheckpointOptions(ck, resume=True),
    )
    assert resumed.iterations == 12
    assert resumed.log_likelihood == full.log_likelihood
    assert torch.equal(resumed.model.A, full.model.A)
    assert [h["log_likelihood"] for h in resumed.history] == [
        h["log_likelihood"] for h in full.history
    ]


def test_likelihood_method_resume_equals_uninterrupted(data, tmp_path):
    y = data[:120]

    def run(iterations: int, **kw):
        torch.manual_seed(0)
        model = learnable_linear()
        fit_measurement_only(
            model,
            y,
            x0=X0,
            P0=P0,
            known_channels=[0],
            method="likelihood",
            optimizer="adam",
            iterations=iterations,
            **kw,
            windows=WindowOptions(window=40, burn_in=5),
        )
        return torch.cat([p.detach().reshape(-1) for p in model.parameters()])

    full = run(10)
    assert torch.equal(run(10), full)  # reproducible
    ck = tmp_path / "lik.pt"
    run(4, checkpoint=CheckpointOptions(ck, every=2))
    assert torch.equal(run(10, checkpoint=CheckpointOptions(ck, every=2, resume=True)), full)


def test_no_gauge_refused(data):
    with pytest.raises(GaugeError, match="known_channels"):
        fit_em(initial_linear(), data, x0=X0, P0=P0, known_channels=None)
    with pytest.raises(GaugeError, match="known_channels"):
        fit_measurement_only(
            learnable_linear(), data, x0=X0, P0=P0, known_channels=[], method="likelihood"
        )
    # a "known" channel whose map is learned is no gauge
    f = InducingTransition(2, 0)
    scale = torch.nn.Parameter(torch.ones(1, dtype=DT))
    model = StateSpaceModel(
        f, lambda x, u: scale * x[..., :1], Q=0.1 * torch.eye(2, dtype=DT), R=R_TRUE
    )
    model.measurement.register_parameter("scale", scale)
    with pytest.raises(GaugeError, match=r"measurement\.scale"):
        check_gauge(model, [0])
    scale.requires_grad_(False)
    assert check_gauge(model, [0]) == [0]
    with pytest.raises(InputError, match="known_channels"):
        check_gauge(model, [3])
    assert issubclass(GaugeError, torchfilt.TorchfiltError)
    blind = LinearGaussianModel(A_INIT, torch.zeros(1, 2, dtype=DT), P0, R_TRUE)
    with pytest.raises(GaugeError, match="all zero"):
        fit_em(blind, data, x0=X0, P0=P0, known_channels=[0])


def test_inducing_transition_is_the_gp_conditional():
    g = torch.Generator().manual_seed(5)
    Z = torch.randn(5, 3, generator=g, dtype=DT)  # n = 2 states, nu = 1 input
    f = InducingTransition(2, Z, input_dim=1, lengthscale=0.7, outputscale=0.3, floor=1e-4)
    with torch.no_grad():
        f.inducing_outputs.copy_(torch.randn(2, 5, generator=g, dtype=DT))
    x, u = Z[:, :2].unsqueeze(0), Z[:, 2:].unsqueeze(0)
    pred = f.predict(x, u)
    assert pred.mean.shape == (1, 5, 2) and pred.var is not None
    # at the inducing inputs: the linear part plus the inducing outputs, variance ~ the floor
    lin = Z @ f.linear.detach().mT
    assert torch.allclose(pred.mean[0] - lin, f.inducing_outputs.detach().mT, atol=1e-4)
    assert torch.allclose(pred.var, torch.full_like(pred.var, 1e-4), atol=1e-5)
    # far away: the linear part alone and the prior variance
    far = f.predict(torch.full((1, 1, 2), 50.0, dtype=DT), torch.zeros(1, 1, 1, dtype=DT))
    assert torch.allclose(far.mean[0, 0], torch.full((2,), 50.0, dtype=DT))
    assert torch.allclose(far.var, torch.full_like(far.var, 0.3 + 1e-4))
    # a nominal model sits under it; W then starts at zero
    g2 = InducingTransition(2, 0, nominal=lambda x, u: 0.5 * x)
    assert torch.equal(g2.predict(x).mean, 0.5 * x)
    with pytest.raises(InputError, match="u"):
        f.predict(x)
    with pytest.raises(InputError, match="inducing"):
        InducingTransition(2, Z[:, :2], input_dim=1)


def test_em_gp_resume_equals_uninterrupted(data, tmp_path):
    def model() -> StateSpaceModel:
        f = InducingTransition(2, 4, linear=A_INIT, outputscale=0.01)
        f.init_inducing(torch.randn(40, 2, generator=torch.Generator().manual_seed(2), dtype=DT))
        h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
        return StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))

    y, kw = (
        data[:80],
        dict(
            x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=0.0), m_step_iterations=3
        ),
    )
    full = fit_em(model(), y, iterations=4, **kw)
    ck = tmp_path / "em_gp.pt"
    fit_em(model(), y, iterations=2, checkpoint=ck, **kw)
    resumed = fit_em(model(), y, iterations=4, **kw, checkpoint=CheckpointOptions(ck, resume=True))
    assert resumed.log_likelihood == full.log_likelihood
    assert [h["log_likelihood"] for h in resumed.history] == [
        h["log_likelihood"] for h in full.history
    ]
    with pytest.raises(torchfilt.exceptions.RunError, match="another fit"):
        fit_em(model(), y[:60], iterations=4, **kw, checkpoint=CheckpointOptions(ck, resume=True))


def test_em_with_inputs_recovers_B_under_the_full_gauge():
    """H = I known pins every coordinate, so A, B, Q, R themselves are identified."""
    g = torch.Generator().manual_seed(7)
    B = torch.tensor([[0.5], [-0.3]], dtype=DT)
    eye = torch.eye(2, dtype=DT)
    truth = LinearGaussianModel(A_TRUE, eye, Q_TRUE, 0.05 * eye, B=B)
    u = torch.randn(8, 100, 1, generator=g, dtype=DT)
    y = torchfilt.simulate(truth, 100, X0, u=u, batch_shape=(8,), generator=g).measurements
    start = LinearGaussianModel(A_INIT, eye, 0.3 * eye, eye, B=torch.zeros(2, 1, dtype=DT))
    # plain EM's 80 iterations. The maximum likelihood of these 800 steps itself has R[1, 1]
    # near 0.007 (accelerated EM reaches it: -1345.05 against -1345.86 where plain EM stops),
    # so the truth's R is recovered on the way there, not at the optimum
    fit = fit_em(start, y, u, x0=X0, P0=P0, known_channels=[0, 1], iterations=80, accelerate=False)
    m = fit.model
    assert isinstance(m, LinearGaussianModel) and m.B is not None
    assert torch.allclose(m.A, A_TRUE, atol=0.1)
    assert torch.allclose(m.B, B, atol=0.1)
    assert torch.allclose(m.measurement.noise_cov(), 0.05 * eye, atol=0.03)
    # the GP path takes the same inputs
    f = InducingTransition(
        2, 4, input_dim=1, linear=torch.cat([A_INIT, torch.zeros(2, 1, dtype=DT)], -1)
    )
    f.init_inducing(
        torch.randn(40, 2, generator=g, dtype=DT), torch.randn(40, 1, generator=g, dtype=DT)
    )
    h = LinearModel(eye, CholeskyCovariance(eye), name="measurement")
    gp = StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * eye))
    gfit = fit_em(gp, y[:4], u[:4], x0=X0, P0=P0, known_channels=[0, 1], iterations=3)
    assert gfit.log_likelihood > gfit.initial_log_likelihood + 10


def test_gp_transition_starts_from_an_identified_linear_model(em_fit, data):
    """Initialisation from a linear model identified from the data (EM), then EM on the GP."""
    lin = em_fit.model
    assert isinstance(lin, LinearGaussianModel)
    with torch.no_grad():
        sm = torchfilt.filters.rts_smooth(torchfilt.CKF(lin).filter(data, x0=X0, P0=P0))
    f = InducingTransition.from_linear(lin.A, inducing=5, states=sm.mean, outputscale=1e-3)
    assert torch.equal(f.linear.detach(), lin.A)
    x = sm.mean[:10].unsqueeze(0)
    assert torch.allclose(f.predict(x).mean, x @ lin.A.mT)  # the residual starts at zero
    with pytest.raises(InputError, match="states"):
        InducingTransition.from_linear(lin.A, inducing=5)
    with pytest.raises(InputError, match="B"):
        InducingTransition.from_linear(lin.A, torch.zeros(3, 1, dtype=DT))
    g = InducingTransition.from_linear(lin.A, torch.ones(2, 1, dtype=DT))
    assert g.input_dim == 1


def test_likelihood_method_learns_inducing_inputs_and_outputs(data):
    """Gradients reach the inducing inputs and outputs through the batched filter."""
    f = InducingTransition(2, 4, linear=A_INIT, outputscale=0.05)
    f.init_inducing(torch.randn(40, 2, generator=torch.Generator().manual_seed(4), dtype=DT))
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    model = StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))
    Z0, U0 = f.inducing_inputs.detach().clone(), f.inducing_outputs.detach().clone()
    fit = fit_measurement_only(
        model,
        data[:120],
        x0=X0,
        P0=P0,
        known_channels=[0],
        method="likelihood",
        iterations=15,
        optimizer=OptimizerOptions("adam", lr=0.02),
        windows=WindowOptions(window=40, burn_in=5),
    )
    assert fit.log_likelihood > fit.detail.initial_log_likelihood
    assert not torch.equal(f.inducing_inputs.detach(), Z0)
    assert not torch.equal(f.inducing_outputs.detach(), U0)


def test_em_resume_of_a_converged_fit_stays_converged(data, tmp_path):
    y, ck = data[:150], tmp_path / "em_conv.pt"
    kw = dict(x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=1e-3))
    full = fit_em(initial_linear(), y, iterations=200, **kw)
    assert full.stopped == "converged" and full.iterations < 200
    fit_em(initial_linear(), y, iterations=200, **kw, checkpoint=CheckpointOptions(ck, every=50))
    again = fit_em(
        initial_linear(), y, iterations=200, **kw, checkpoint=CheckpointOptions(ck, resume=True)
    )
    assert again.stopped == "converged" and again.iterations == full.iterations
    assert again.log_likelihood == full.log_likelihood


def test_compile_reaches_both_methods_and_bad_values_are_refused(data, monkeypatch):
    import torchfilt.training.measurement_only as mo

    seen = {}

    def fake_em(*args, **kwargs):
        seen["em"] = kwargs["compile"]
        raise RuntimeError("stop")

    def fake_likelihood(*args, **kwargs):
        seen["likelihood"] = kwargs["compile"]
        raise RuntimeError("stop")

    monkeypatch.setattr(mo, "fit_em", fake_em)
    monkeypatch.setattr(mo, "_fit_likelihood", fake_likelihood)
    cases = [("em", True, "loop"), ("em", "step", "step"), ("em", False, False)]
    cases += [("likelihood", "loop", True), ("likelihood", True, True)]
    cases += [("likelihood", False, False)]
    for method, given, expected in cases:
        with pytest.raises(RuntimeError, match="stop"):
            fit_measurement_only(
                learnable_linear(), data, x0=X0, P0=P0, known_channels=[0], method=method,
                compile=given,
            )  # fmt: skip
        assert seen[method] == expected, (method, given)
    for bad in ("fast", 1, None):
        with pytest.raises(InputError, match="compile"):
            fit_measurement_only(
                learnable_linear(), data, x0=X0, P0=P0, known_channels=[0], compile=bad
            )


@pytest.mark.slow
def test_compiled_likelihood_fit_equals_the_eager_one(data):
    fits = []
    for compile in (False, True):
        fit = fit_measurement_only(
            learnable_linear(), data[:80], x0=X0, P0=P0, known_channels=[0],
            method="likelihood", iterations=2, compile=compile,
        )  # fmt: skip
        fits.append(fit)
    assert fits[1].detail.iterations == fits[0].detail.iterations == 2
    assert fits[1].log_likelihood == pytest.approx(fits[0].log_likelihood, rel=1e-8)
    for a, b in zip(fits[0].model.parameters(), fits[1].model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)


def _gp_model(seed: int = 1, inducing: int = 6) -> StateSpaceModel:
    f = InducingTransition(2, inducing, linear=A_INIT, outputscale=0.01, lengthscale=1.0)
    f.init_inducing(torch.randn(50, 2, generator=torch.Generator().manual_seed(seed), dtype=DT))
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))


def test_accelerated_gradient_em_starts_as_two_plain_steps(data):
    """SQUAREM over the gradient M-step: its first cycle (the bound on the steplength is 1) is
    exactly two plain iterations, and no cycle lowers the likelihood."""
    y = data[:150]
    kw = dict(x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=0.0, rtol=0.0))
    fast = fit_em(_gp_model(), y, iterations=3, accelerate=True, **kw)
    ll = np.array([fast.initial_log_likelihood] + [r["log_likelihood"] for r in fast.history])
    assert (np.diff(ll) >= 0).all()
    assert int(fast.history[-1]["e_steps"]) > 2 * 3  # an extrapolation was tried
    plain = fit_em(_gp_model(), y, iterations=2, accelerate=False, **kw)
    assert fast.history[0]["log_likelihood"] == plain.history[1]["log_likelihood"]


@pytest.mark.slow
def test_accelerated_gradient_em_climbs_further_than_plain(data):
    """For the same number of M-steps the accelerated fit ends higher than plain EM (here it
    lags in the first cycles and leads in the tail, where plain EM slows down)."""
    y = data[:150]
    kw = dict(x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=0.0, rtol=0.0))
    fast = fit_em(_gp_model(), y, iterations=10, accelerate=True, **kw)
    ll = np.array([fast.initial_log_likelihood] + [r["log_likelihood"] for r in fast.history])
    assert (np.diff(ll) >= 0).all()
    # M-steps and extrapolations (each with its filter): more than two per cycle
    m_steps = int(fast.history[-1]["e_steps"])
    assert m_steps > 2 * 10
    plain = fit_em(_gp_model(), y, iterations=m_steps, accelerate=False, **kw)
    assert fast.log_likelihood > plain.log_likelihood


def test_accelerated_gradient_em_resume_equals_uninterrupted(data, tmp_path):
    y = data[:80]
    kw = dict(
        x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=0.0, rtol=0.0),
        m_step_iterations=3, accelerate=True,
    )  # fmt: skip
    full = fit_em(_gp_model(2, 4), y, iterations=4, **kw)
    ck = tmp_path / "em_gp_accel.pt"
    fit_em(_gp_model(2, 4), y, iterations=2, checkpoint=ck, **kw)
    resumed = fit_em(
        _gp_model(2, 4), y, iterations=4, checkpoint=CheckpointOptions(ck, resume=True), **kw
    )
    assert [h["log_likelihood"] for h in resumed.history] == [
        h["log_likelihood"] for h in full.history
    ]
    assert resumed.history[-1]["e_steps"] == full.history[-1]["e_steps"]


def test_accelerate_is_of_em_alone(data):
    with pytest.raises(InputError, match="accelerate"):
        fit_measurement_only(
            learnable_linear(), data[:50], x0=X0, P0=P0, known_channels=[0],
            method="likelihood", accelerate=True,
        )  # fmt: skip
