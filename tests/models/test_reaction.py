"""The 2A -> B system: the discretisation follows the ODE (with the paper's typo fixed)."""

import pytest
import torch

from torchfilt.systems import reaction

D = torch.float64
#: Euler's local error over one step of 0.1 s at PA <= 10: |x''| dt^2 / 2 with x'' = 8 k1^2 PA^3
EULER_ATOL = 0.5 * 8 * reaction.K1**2 * 10.0**3 * reaction.DT**2


def test_euler_step_follows_the_ode():
    x = torch.tensor([[10.0, 1.0], [3.0, 1.0], [0.1, 4.5]], dtype=D)
    nxt = reaction.transition(x)
    # conservation: PA + 2 PB is invariant (2 A -> B), which the printed eq. (31) violates
    assert torch.allclose(
        nxt[..., 0] + 2 * nxt[..., 1], x[..., 0] + 2 * x[..., 1], rtol=0, atol=1e-12
    )
    # the exact ODE solution PA(t) = PA0 / (1 + 2 k1 PA0 t) one sample later
    exact = x[..., 0] / (1 + 2 * reaction.K1 * x[..., 0] * reaction.DT)
    assert torch.allclose(nxt[..., 0], exact, rtol=0, atol=EULER_ATOL)
    assert float((nxt[0, 0] - exact[0]).abs()) > 0  # it is Euler, not the exact flow


def test_measurement_and_model():
    m = reaction.model()
    assert m.state_dim == 2 and m.obs_dim == 1
    x = torch.tensor([2.0, 3.0], dtype=D)
    assert float(reaction.measurement(x)) == 5.0
    assert torch.allclose(
        m.transition.noise_cov(), torch.diag(torch.tensor(reaction.Q_DIAG, dtype=D))
    )
    assert float(m.measurement.noise_cov()) == reaction.R_VAR


def test_starts_and_simulation():
    assert reaction.prior_mean("hr").tolist() == [0.1, 4.5]
    assert reaction.true_x0("paper").tolist() == [10.0, 1.0]
    a = reaction.simulate_truth(5, start="hr", steps=20, seed=3)
    b = reaction.simulate_truth(5, start="hr", steps=20, seed=3)
    c = reaction.simulate_truth(5, start="hr", steps=20, seed=4)
    assert a.states.shape == (5, 20, 2) and a.measurements.shape == (5, 20, 1)
    assert torch.equal(a.measurements, b.measurements)
    assert not torch.equal(a.measurements, c.measurements)
    with pytest.raises(ValueError, match="start must be one of"):
        reaction.prior_mean("rawlings")
