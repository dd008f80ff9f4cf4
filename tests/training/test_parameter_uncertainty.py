"""Parameter uncertainty: the Laplace posterior of a fit and the filter that carries it.

References are a plain numpy Kalman filter written here: its log-likelihood's finite-difference
Hessian and scores for :func:`parameter_posterior`, and the Kalman filter of the explicitly
augmented linear system for :class:`UncertainParameters`.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from fuzz_support import Refused, attempt, property_tests
from hypothesis import strategies as st
from torch import nn

import torchfilt
from torchfilt.exceptions import InputError, ModelError, ShapeError
from torchfilt.models import DiagonalCovariance, FunctionModel, StateSpaceModel

D = torch.float64
A = np.array([[0.9, 0.2], [-0.1, 0.8]])
B = np.array([[0.5], [0.1]])
H = np.array([[1.0, 0.0]])
Q = np.diag([0.05, 0.02])
RV = 0.1


class Drift(nn.Module):
    """``x' = a A x + B u + c`` with a scalar gain ``a`` and an offset ``c`` ``(2,)``."""

    def __init__(self) -> None:
        super().__init__()
        self.a = nn.Parameter(torch.tensor(1.0, dtype=D))
        self.c = nn.Parameter(torch.tensor([0.1, -0.2], dtype=D))
        self.register_buffer("A", torch.tensor(A))
        self.register_buffer("B", torch.tensor(B))

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.a * x @ self.A.mT + u @ self.B.mT + self.c


class Biased(nn.Module):
    """``y = x_1 + b``."""

    def __init__(self) -> None:
        super().__init__()
        self.b = nn.Parameter(torch.tensor([0.3], dtype=D))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x[..., :1] + self.b


def make_model() -> StateSpaceModel:
    f = FunctionModel(Drift(), torch.tensor(Q), name="transition")
    h = FunctionModel(Biased(), torch.tensor([[RV]], dtype=D), name="measurement")
    return StateSpaceModel(f, h)


def data(runs: int, T: int = 40, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    model = make_model()
    u = torch.randn(runs, T, 1, generator=gen, dtype=D)
    x0, P0 = torch.zeros(2, dtype=D), 0.5 * torch.eye(2, dtype=D)
    sim = torchfilt.simulate(model, T, x0, u=u, batch_shape=(runs,), generator=gen)
    return sim.measurements, u, x0, P0


def np_kalman(y, u, x0, P0, Af, Bf, Hf, Qf, Rf, cf=None, bf=None):
    """Per-recording log-likelihood, means and covariances of the closed-form Kalman filter."""
    n = Af.shape[0]
    cf = np.zeros(n) if cf is None else cf
    bf = np.zeros(Hf.shape[0]) if bf is None else bf
    lls, means, covs = [], [], []
    for r in range(y.shape[0]):
        x, P, ll, ms, cs = x0.copy(), P0.copy(), 0.0, [], []
        for k in range(y.shape[1]):
            x = Af @ x + Bf @ u[r, k] + cf
            P = Af @ P @ Af.T + Qf
            S = Hf @ P @ Hf.T + Rf
            e = y[r, k] - (Hf @ x + bf)
            K = P @ Hf.T @ np.linalg.inv(S)
            x = x + K @ e
            P = P - K @ S @ K.T
            ll += -0.5 * (e @ np.linalg.solve(S, e) + np.log(np.linalg.det(2 * np.pi * S)))
            ms.append(x.copy())
            cs.append(P.copy())
        lls.append(ll)
        means.append(ms)
        covs.append(cs)
    return np.array(lls), np.array(means), np.array(covs)


def np_loglik(theta, y, u, x0, P0):
    a, c, b = theta[0], theta[1:3], theta[3:4]
    ll, _, _ = np_kalman(y, u, x0, P0, a * A, B, H, Q, np.array([[RV]]), c, b)
    return ll


NAMES = ["transition._fn.a", "transition._fn.c", "measurement._fn.b"]
THETA = np.array([1.0, 0.1, -0.2, 0.3])


def np_hessian_and_scores(y, u, x0, P0, eps=1e-4):
    p = THETA.size
    args = (y.numpy(), u.numpy(), x0.numpy(), P0.numpy())

    def grad(t):
        g = np.zeros((y.shape[0], p))
        for i in range(p):
            e = np.zeros(p)
            e[i] = eps
            g[:, i] = (np_loglik(t + e, *args) - np_loglik(t - e, *args)) / (2 * eps)
        return g

    Hm = np.zeros((p, p))
    for i in range(p):
        e = np.zeros(p)
        e[i] = eps
        Hm[i] = -(grad(THETA + e).sum(0) - grad(THETA - e).sum(0)) / (2 * eps)
    return 0.5 * (Hm + Hm.T), -grad(THETA)


def test_posterior_equals_the_closed_form_kalman_hessian_and_sandwich() -> None:
    y, u, x0, P0 = data(12, seed=1)
    Hm, scores = np_hessian_and_scores(y, u, x0, P0)
    Hinv = np.linalg.inv(Hm)
    post = torchfilt.parameter_posterior(make_model(), y, u, x0=x0, P0=P0, parameters=NAMES)
    assert post.names == tuple(NAMES)
    np.testing.assert_allclose(post.mean.numpy(), THETA, rtol=0, atol=1e-15)
    # finite differences: ~1e-8 of the largest entry
    np.testing.assert_allclose(post.cov.numpy(), Hinv, rtol=1e-5, atol=1e-6 * abs(Hinv).max())
    sand = torchfilt.parameter_posterior(
        make_model(), y, u, x0=x0, P0=P0, parameters=NAMES, covariance="sandwich"
    )
    S = 12 / (12 - 4) * Hinv @ scores.T @ scores @ Hinv  # HC1: R / (R - p)
    np.testing.assert_allclose(sand.cov.numpy(), S, rtol=1e-5, atol=1e-6 * abs(S).max())
    # the default picks the maps' parameters (the noises are buffers here)
    default = torchfilt.parameter_posterior(make_model(), y, u, x0=x0, P0=P0)
    assert default.names == tuple(NAMES)


def test_uncertain_parameters_equal_the_augmented_linear_kalman_filter() -> None:
    y, u, x0, P0 = data(3, seed=2)
    model = make_model()
    rng = np.random.default_rng(3)
    G = rng.standard_normal((3, 3))
    C = np.diag([0.04, 0.09, 0.01]) + 0.01 * G @ G.T  # over (c1, c2, b), correlated
    mean = np.array([0.05, -0.1, 0.25])
    post = torchfilt.models.ParameterPosterior(
        ("transition._fn.c", "measurement._fn.b"), torch.tensor(mean), torch.tensor(C)
    )
    aug = torchfilt.UncertainParameters(model, post)
    assert aug.state_dim == 5 and aug.base_state_dim == 2
    z0, Pz0 = aug.prior(x0, P0)
    with torch.no_grad():
        res = torchfilt.CKF(aug).filter(y, u, x0=z0, P0=Pz0)
    # reference: [x; c; b] as a linear system
    Aa = np.zeros((5, 5))
    Aa[:2, :2], Aa[:2, 2:4], Aa[2:, 2:] = A, np.eye(2), np.eye(3)
    Ba = np.vstack([B, np.zeros((3, 1))])
    Ha = np.array([[1.0, 0.0, 0.0, 0.0, 1.0]])
    Qa = np.zeros((5, 5))
    Qa[:2, :2] = Q
    ll, means, covs = np_kalman(
        y.numpy(), u.numpy(), z0.numpy(), Pz0.numpy(), Aa, Ba, Ha, Qa, np.array([[RV]])
    )
    np.testing.assert_allclose(res.mean.numpy(), means, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.cov.numpy(), covs, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.log_likelihood.numpy(), ll, rtol=1e-10)
    mx, Px = aug.state_marginal(res.mean, res.cov)
    mt, Pt = aug.parameter_marginal(res.mean, res.cov)
    assert mx.shape == (3, 40, 2) and Px.shape == (3, 40, 2, 2)
    assert mt.shape == (3, 40, 3) and Pt.shape == (3, 40, 3, 3)
    # the base model is untouched and the smoother runs on the augmented model too
    assert float(model.transition._fn.c.detach()[0]) == pytest.approx(0.1)
    with torch.no_grad():
        sm = torchfilt.CKF(aug).smooth(y, u, x0=z0, P0=Pz0)
    assert torch.isfinite(sm.mean).all()


def test_refusals() -> None:
    y, u, x0, P0 = data(3, seed=4)
    model = make_model()
    with pytest.raises(InputError, match=r"'transition\._fn\.zz' is not a parameter"):
        torchfilt.parameter_posterior(model, y, u, x0=x0, P0=P0, parameters=["transition._fn.zz"])
    with pytest.raises(InputError, match=r"sandwich.*more recordings than parameter values"):
        torchfilt.parameter_posterior(model, y, u, x0=x0, P0=P0, covariance="sandwich")
    with pytest.raises(InputError, match="covariance must be"):
        torchfilt.parameter_posterior(model, y, u, x0=x0, P0=P0, covariance="fisher")  # type: ignore[arg-type]
    # a learnable noise is not a map parameter
    f = FunctionModel(Drift(), DiagonalCovariance(torch.tensor([0.05, 0.02], dtype=D)))
    noisy = StateSpaceModel(f, FunctionModel(Biased(), torch.tensor([[RV]], dtype=D)))
    with pytest.raises(InputError, match="noise covariance"):
        torchfilt.parameter_posterior(
            noisy, y, u, x0=x0, P0=P0, parameters=["transition.noise_param.raw"]
        )
    post = torchfilt.models.ParameterPosterior(
        ("measurement._fn.b",), torch.zeros(1, dtype=D), torch.eye(1, dtype=D)
    )
    with pytest.raises(InputError, match="noise covariance's parameter"):
        torchfilt.UncertainParameters(
            noisy,
            torchfilt.models.ParameterPosterior(
                ("transition.noise_param.raw",), torch.zeros(2, dtype=D), torch.eye(2, dtype=D)
            ),
        )
    with pytest.raises(ShapeError, match=r"mean must be \(1,\)"):
        torchfilt.UncertainParameters(model, post._replace(mean=torch.zeros(2, dtype=D)))
    with pytest.raises(ShapeError, match="x0, P0"):
        torchfilt.UncertainParameters(model, post).prior(torch.zeros(3, dtype=D), P0)


class Unused(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.k = nn.Parameter(torch.tensor(1.0, dtype=D))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x[..., :1] + 0.0 * self.k


class ItemMap(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.k = nn.Parameter(torch.tensor(1.0, dtype=D))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x[..., :1] * float(self.k.item())


def test_a_flat_direction_and_a_map_vmap_cannot_run_are_named() -> None:
    y, u, x0, P0 = data(3, seed=5)
    f = FunctionModel(Drift(), torch.tensor(Q), name="transition")
    flat = StateSpaceModel(
        f, FunctionModel(Unused(), torch.tensor([[RV]], dtype=D), name="measurement")
    )
    with pytest.raises(ModelError, match=r"measurement\._fn\.k"):
        torchfilt.parameter_posterior(flat, y, u, x0=x0, P0=P0)
    bad = StateSpaceModel(
        FunctionModel(Drift(), torch.tensor(Q)),
        FunctionModel(ItemMap(), torch.tensor([[RV]], dtype=D)),
    )
    post = torchfilt.models.ParameterPosterior(
        ("measurement._fn.k",), torch.ones(1, dtype=D), torch.eye(1, dtype=D)
    )
    aug = torchfilt.UncertainParameters(bad, post)
    z0, Pz0 = aug.prior(x0, P0)
    with pytest.raises(ModelError, match="vmap"):
        torchfilt.CKF(aug).filter(y, u, x0=z0, P0=Pz0)


# ----------------------------------------------------------------------------------- fuzz
POOL = ["transition._fn.c", "measurement._fn.b", "transition._fn.a", "transition._fn.zz", "b"]


SIZES = {"transition._fn.c": 2, "measurement._fn.b": 1, "transition._fn.a": 1}


def _fuzz_case(draw: st.DataObject) -> None:
    seed = draw.draw(st.integers(0, 2**32 - 1), label="seed")
    rng = np.random.default_rng(seed)
    if draw.draw(st.booleans(), label="valid names"):
        pool = st.sampled_from(sorted(SIZES))
        names = draw.draw(st.lists(pool, min_size=1, max_size=3, unique=True), label="names")
    else:
        names = draw.draw(st.lists(st.sampled_from(POOL), max_size=3), label="names")
    if draw.draw(st.booleans(), label="sizes agree"):
        p = sum(SIZES.get(k, 1) for k in names)
    else:
        p = draw.draw(st.integers(0, 5), label="p")
    kind = draw.draw(st.sampled_from(["spd", "spd", "nan", "asym", "indefinite"]), label="cov")
    G = rng.standard_normal((p, p))
    C = 0.01 * (G @ G.T + np.eye(p))
    if kind == "nan" and p:
        C[0, 0] = np.nan
    elif kind == "asym" and p > 1:
        C[0, 1] += 0.5
    elif kind == "indefinite" and p:
        C[0, 0] = -1.0
    mean = rng.standard_normal(p) * 0.1
    post = torchfilt.models.ParameterPosterior(tuple(names), torch.tensor(mean), torch.tensor(C))
    T = draw.draw(st.integers(1, 5), label="T")
    y, u, x0, P0 = data(2, T=T, seed=seed % 1000)
    x0 = x0[: draw.draw(st.sampled_from([2, 2, 2, 1]), label="x0 size")]

    def run():
        aug = torchfilt.UncertainParameters(make_model(), post)
        z0, Pz0 = aug.prior(x0, P0)
        with torch.no_grad():
            return aug, torchfilt.CKF(aug).filter(y, u, x0=z0, P0=Pz0)

    out, _ = attempt("UncertainParameters", run)
    if isinstance(out, Refused):
        return
    # a valid case: the explicitly augmented linear Kalman filter (a, c, b as named)
    aug, res = out
    assert kind == "spd" or p == 0 or (kind == "asym" and p == 1)
    assert res.mean.shape == (2, T, 2 + p)
    z0, Pz0 = aug.prior(x0, P0)
    n = 2 + p
    Aa, Ba, Ha = np.zeros((n, n)), np.zeros((n, 1)), np.zeros((1, n))
    Aa[:2, :2], Ba[:2], Ha[0, 0] = A, B, 1.0
    Aa[2:, 2:] = np.eye(p)
    k = 2
    a_named = "transition._fn.a" in names
    for name in names:
        if name == "transition._fn.c":
            Aa[:2, k : k + 2] = np.eye(2)
            k += 2
        elif name == "measurement._fn.b":
            Ha[0, k] = 1.0
            k += 1
        else:  # the gain a: x' = a A x is bilinear in (a, x); leave such cases to the invariants
            k += 1
    Qa = np.zeros((n, n))
    Qa[:2, :2] = Q
    if a_named:
        assert torch.isfinite(res.log_likelihood).all()
        return
    cf = np.zeros(n)  # the transition offset c when it is not a state
    if "transition._fn.c" not in names:
        cf[:2] = [0.1, -0.2]
    bf = np.array([0.3]) if "measurement._fn.b" not in names else None
    ll, means, _ = np_kalman(
        y.numpy(), u.numpy(), z0.numpy(), Pz0.numpy(), Aa, Ba, Ha, Qa, np.array([[RV]]), cf, bf
    )
    np.testing.assert_allclose(res.mean.numpy(), means, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(res.log_likelihood.numpy(), ll, rtol=1e-9, atol=1e-9)


test_fuzz_uncertain_parameters, test_fuzz_uncertain_parameters_long = property_tests(
    _fuzz_case, short=25, long=400
)
