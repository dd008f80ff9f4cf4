import pytest
import torch

from torchfilt import CKF, LinearGaussianModel, simulate
from torchfilt.exceptions import ShapeError
from torchfilt.systems import reentry


def test_reentry_constants_and_trajectory():
    sim = reentry.simulate_truth(2, seed=0)
    x = sim.states
    assert x.shape == (2, reentry.STEPS, 3) and sim.measurements.shape == (2, reentry.STEPS, 1)
    assert torch.equal(x[0], x[1])  # no process noise: one trajectory, new measurement noise
    assert not torch.equal(sim.measurements[0], sim.measurements[1])
    # spec: x1 ~ 2.7e4 ft at t = 60 s, and the target passes the radar altitude near t = 10 s
    assert 2.0e4 < float(x[0, -1, 0]) < 3.5e4
    crossing = int((x[0, :, 0] < reentry.RADAR_H).nonzero()[0])
    assert 8 <= crossing <= 12
    assert torch.allclose(x[0, :, 2], torch.full((60,), 1e-3, dtype=torch.float64))


def test_reentry_transition_equals_generic_rk4():
    from torchfilt.models import rk4

    gen = torch.Generator().manual_seed(0)
    x = torch.tensor(reentry.X0_TRUE, dtype=torch.float64) * (
        1 + 0.2 * torch.randn(50, 3, generator=gen, dtype=torch.float64)
    )
    want = rk4(reentry.drift, x, None, reentry.DT, reentry.SUBSTEPS)
    assert torch.allclose(reentry.transition(x), want, rtol=1e-13, atol=0)


def test_reentry_measurement_models():
    x = torch.tensor([[2e5, 0.0, 0.0]], dtype=torch.float64)
    assert float(reentry.measurement(x)) == pytest.approx((1e10 + 1e10) ** 0.5)
    assert float(reentry.measurement(x, M=reentry.RADAR_M_WRONG)) == pytest.approx(
        (9e10 + 1e10) ** 0.5
    )


def test_rk4_converges_to_exact_solution():
    """dx/dt = -x: RK4 with 10 sub-steps is accurate to ~1e-7 relative over one step."""
    from torchfilt.models import rk4

    x = torch.tensor([1.0], dtype=torch.float64)
    out = rk4(lambda x, u: -x, x, None, 1.0, 10)
    assert float(out) == pytest.approx(float(torch.exp(torch.tensor(-1.0))), rel=1e-6)


def test_simulate_is_reproducible_and_has_model_statistics():
    dtype = torch.float64
    A = torch.tensor([[0.9, 0.2], [0.0, 0.7]], dtype=dtype)
    Q = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=dtype)
    model = LinearGaussianModel(A, torch.eye(2, dtype=dtype), Q, 0.3 * torch.eye(2, dtype=dtype))
    a = simulate(
        model,
        3,
        torch.ones(2, dtype=dtype),
        batch_shape=(4,),
        generator=torch.Generator().manual_seed(1),
    )
    b = simulate(
        model,
        3,
        torch.ones(2, dtype=dtype),
        batch_shape=(4,),
        generator=torch.Generator().manual_seed(1),
    )
    assert torch.equal(a.states, b.states) and torch.equal(a.measurements, b.measurements)
    big = simulate(
        model,
        2,
        torch.ones(2, dtype=dtype),
        batch_shape=(200000,),
        generator=torch.Generator().manual_seed(2),
    )
    x2 = big.states[:, 1]
    assert torch.allclose(x2.mean(0), A @ A @ torch.ones(2, dtype=dtype), atol=5e-3)
    want_cov = A @ Q @ A.T + Q
    assert torch.allclose(torch.cov(x2.T), want_cov, atol=5e-3)


def test_simulate_argument_errors():
    model = LinearGaussianModel(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2))
    with pytest.raises(ShapeError, match="x0"):
        simulate(model, 3, torch.zeros(3))


def test_reentry_ckf1_tracks():
    sim = reentry.simulate_truth(20, seed=1)
    res = CKF(reentry.model()).filter(
        sim.measurements, x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov()
    )
    err = (res.mean - sim.states)[:, 20:, :2].abs()  # after the radar-altitude pass
    assert torch.isfinite(res.mean).all()
    assert float(err.mean()) < 500.0
