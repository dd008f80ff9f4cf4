"""A sensor known up to its gain and offset (AffineSensor), the gauge it leaves, and learning
such a sensor's calibration and the physics constants from measurements alone.

References: the closed form ``scale * g(x) + bias``; the simulation's true constants (re-entry:
``gamma``, radar gain 1 and offset 0, ``R``); 2A -> B's true rate constant.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from torch import nn

import torchfilt
from torchfilt.exceptions import GaugeError, InputError
from torchfilt.models import (
    AffineSensor,
    DiagonalCovariance,
    FunctionModel,
    InducingTransition,
    LinearModel,
    ScalarCovariance,
    StateSpaceModel,
)
from torchfilt.optim import OptimizerOptions
from torchfilt.systems import reaction, reentry
from torchfilt.training import check_gauge, fit_likelihood, fit_measurement_only

DT = torch.float64


def test_affine_sensor_is_gain_times_map_plus_offset():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 5, 2, generator=g, dtype=DT)

    def base(x: torch.Tensor) -> torch.Tensor:
        return torch.stack([x[..., 0] ** 2, torch.sin(x[..., 1]), x.sum(-1)], -1)

    h = AffineSensor(base, out_dim=3, channels=[0, 2], scale=[2.0, -0.5], bias=[1.0, 3.0])
    p = h.predict(x)
    want = base(x) * torch.tensor([2.0, 1.0, -0.5], dtype=DT) + torch.tensor([1.0, 0, 3.0])
    torch.testing.assert_close(p.mean, want, rtol=0, atol=1e-14)
    assert torch.allclose(h.scale, torch.tensor([2.0, -0.5], dtype=DT))
    # a per-point variance of the base scales by the gain squared; its noise is kept
    inner = InducingTransition(2, torch.randn(3, 2, generator=g, dtype=DT), outputscale=0.3)
    lin = AffineSensor(inner, channels=[1], scale=3.0, bias=-1.0)
    pi, pl = inner.predict(x), lin.predict(x)
    assert pi.var is not None and pl.var is not None
    torch.testing.assert_close(pl.var, pi.var * torch.tensor([1.0, 9.0], dtype=DT))
    torch.testing.assert_close(pl.mean, pi.mean * torch.tensor([1.0, 3.0]) - torch.tensor([0, 1.0]))
    noisy = LinearModel(torch.eye(2, dtype=DT), torch.eye(2, dtype=DT))
    assert AffineSensor(noisy).noise_cov() is not None
    torch.testing.assert_close(AffineSensor(noisy).noise_cov(), noisy.noise_cov())
    with pytest.raises(InputError, match="channels"):
        AffineSensor(base, out_dim=3, channels=[3])
    with pytest.raises(InputError, match="out_dim"):
        AffineSensor(base)
    with pytest.raises(InputError, match="scale"):
        AffineSensor(base, out_dim=3, scale=0.0)


def _radar_model(scale: float = 1.005, bias: float = 500.0, gamma: float = 3e-5):
    class Drag(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.log_gamma = nn.Parameter(torch.tensor(math.log(gamma), dtype=DT))

        def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
            return reentry.transition(x, gamma=self.log_gamma.exp())

    f = FunctionModel(
        Drag(), DiagonalCovariance(torch.tensor([1e2, 1e2, 1e-10], dtype=DT)), name="transition"
    )
    h = AffineSensor(reentry.measurement, out_dim=1, scale=scale, bias=bias)
    return StateSpaceModel(f, h, R=ScalarCovariance(torch.tensor(4e4, dtype=DT), 1))


def test_gauge_accepts_a_learned_gain_and_offset_only_on_a_nonlinear_map():
    # the radar range is a hyperbola in the altitude: its gain and offset may be learned
    assert check_gauge(_radar_model(), [0]) == [0]
    # an affine known map: x -> a x + c absorbs a learned gain and offset
    H = torch.tensor([[1.0, 0.0]], dtype=DT)
    h = AffineSensor(LinearModel(H, torch.eye(1, dtype=DT)), scale=1.0, bias=0.0)
    model = StateSpaceModel(
        InducingTransition(2, 0, dtype=DT), h, Q=DiagonalCovariance(torch.ones(2, dtype=DT))
    )
    with pytest.raises(GaugeError, match=r"channel 0 .*affine in the state"):
        check_gauge(model, [0])
    # frozen, the same sensor is a known map again
    h.log_scale.requires_grad_(False)
    h.bias.requires_grad_(False)
    assert check_gauge(model, [0]) == [0]


@pytest.fixture(scope="module")
def radar():
    return reentry.simulate_truth(4, seed=11)


@pytest.mark.slow
def test_radar_gain_offset_and_drag_constant_from_ranges_alone(radar):
    """From 4 recordings of range alone: the drag constant, the radar's gain and offset and R
    come back near the simulation's (several minutes: 30 L-BFGS iterations)."""
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT), reentry.prior_cov()
    model = _radar_model()
    fit = fit_measurement_only(
        model,
        radar.measurements,
        x0=x0,
        P0=P0,
        known_channels=[0],
        method="likelihood",
        iterations=30,
        optimizer=OptimizerOptions("lbfgs", lr=0.01),
        noise_scale="none",  # all four recordings fit: none held out to scale Q
    )
    h = model.measurement.base
    gamma = float(model.transition._fn.log_gamma.detach().exp())
    assert abs(gamma / reentry.GAMMA - 1) < 0.01
    assert abs(float(h.scale.detach()) - 1) < 1e-3 and abs(float(h.bias.detach())) < 100.0
    assert 0.5 < float(model.measurement.noise_cov().detach()[0, 0]) / reentry.R_VAR < 2.0
    # far better than the miscalibrated start on the same recordings
    start = _radar_model()
    with torch.no_grad():
        ll0 = float(
            torchfilt.CKF(start).filter(radar.measurements, x0=x0, P0=P0).log_likelihood.sum()
        )
    assert fit.log_likelihood > ll0 + 200


def test_lbfgs_step_out_of_the_finite_region_is_retried_not_a_crash(radar):
    """The default first L-BFGS step on these scales (a gain gradient 1e5 times the offset's)
    leaves the finite region; torch's strong-Wolfe search then raised an IndexError from
    inside torch. Now the step is retried from the last good point with a fresh history."""
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT), reentry.prior_cov()
    crash = _radar_model()
    with torch.no_grad():
        ll0 = float(
            torchfilt.CKF(crash).filter(radar.measurements, x0=x0, P0=P0).log_likelihood.sum()
        )
    res = fit_likelihood(crash, radar.measurements, x0=x0, P0=P0, iterations=2)
    assert math.isfinite(res.log_likelihood) and res.log_likelihood >= ll0
    assert all(bool(torch.isfinite(p).all()) for p in crash.parameters())


def test_em_m_step_falls_back_to_the_maps_when_the_noise_step_lowers_the_likelihood():
    """2A -> B from total pressure, the rate constant learned inside a physics model: the joint
    M-step raises Q (a wrong model's smoothed states look noisy) and lowers the filter
    likelihood; the maps-only step does not, and EM goes on to the true rate constant."""

    class Kinetics(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.log_k1 = nn.Parameter(torch.tensor(math.log(0.08), dtype=DT))

        def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
            return reaction.transition(x, k1=self.log_k1.exp())

    kin = Kinetics()
    model = StateSpaceModel(
        kin,
        reaction.measurement,
        Q=ScalarCovariance(torch.tensor(1e-3, dtype=DT), 2),
        R=ScalarCovariance(torch.tensor(0.05, dtype=DT), 1),
    )
    train = reaction.simulate_truth(8, start="paper", seed=1)
    x0, P0 = reaction.prior_mean("paper", DT), reaction.prior_cov(DT)
    fit = fit_measurement_only(
        model,
        train.measurements,
        x0=x0,
        P0=P0,
        known_channels=[0],
        method="em",
        iterations=40,
    )
    lls = [h["log_likelihood"] for h in fit.history]
    assert all(b >= a for a, b in itertools.pairwise(lls))
    assert fit.iterations > 5
    assert abs(float(kin.log_k1.detach().exp()) / reaction.K1 - 1) < 0.1


def test_em_m_step_uses_partly_observed_steps():
    """Two sensors that never report at the same step (as Plaza2's beacons): the M-step's
    measurement term is the density of the observed components, so EM learns R. Before, only
    fully observed steps counted, and R stayed at its start."""
    A = torch.tensor([[0.9, 0.2], [-0.2, 0.8]], dtype=DT)
    truth = torchfilt.LinearGaussianModel(
        A,
        torch.eye(2, dtype=DT),
        0.05 * torch.eye(2, dtype=DT),
        torch.diag(torch.tensor([0.2, 0.5], dtype=DT)),
    )
    x0, P0 = torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)
    sim = torchfilt.simulate(
        truth, 200, x0, batch_shape=(4,), generator=torch.Generator().manual_seed(3)
    )
    y = sim.measurements.clone()
    y[:, 0::2, 0] = math.nan
    y[:, 1::2, 1] = math.nan  # never both at once
    model = StateSpaceModel(
        lambda x, u=None: x @ A.mT,
        lambda x, u=None: x,
        Q=ScalarCovariance(torch.tensor(0.05, dtype=DT), 2),
        R=DiagonalCovariance(torch.ones(2, dtype=DT)),
    )
    fit = fit_measurement_only(
        model, y, x0=x0, P0=P0, known_channels=[0, 1], method="em", iterations=15
    )
    R = model.measurement.noise_cov().detach().diagonal()
    assert fit.log_likelihood > fit.history[0]["log_likelihood"]
    torch.testing.assert_close(R, torch.tensor([0.2, 0.5], dtype=DT), rtol=0.35, atol=0)
