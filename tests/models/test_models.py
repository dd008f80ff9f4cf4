import pytest
import torch

from torchfilt import LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import InputError
from torchfilt.models import ConditionalModel, FunctionModel, Prediction, TimeVarying


def test_linear_model_moves_with_to():
    m = LinearGaussianModel(torch.eye(2), torch.ones(1, 2), torch.eye(2), torch.eye(1))
    m64 = m.to(torch.float64)
    assert m64.A.dtype == torch.float64 and m64.transition.noise_cov().dtype == torch.float64


def test_one_and_two_argument_callables():
    f1 = FunctionModel(lambda x: 2 * x, torch.eye(2))
    f2 = FunctionModel(lambda x, u: x + u, torch.eye(2))
    x = torch.ones(3, 2)
    assert torch.equal(f1.predict(x).mean, 2 * x)
    assert torch.equal(f2.predict(x, torch.ones(3, 2)).mean, 2 * x)


def test_time_varying_noise_indexing():
    tv = TimeVarying(torch.stack([torch.eye(2) * k for k in range(1, 4)]))
    assert tv.steps == 3 and torch.equal(tv(2), 3 * torch.eye(2))
    with pytest.raises(InputError, match="3 steps"):
        tv(3)
    with pytest.raises(ValueError, match="TimeVarying values"):
        TimeVarying(torch.eye(2))


class Learned(ConditionalModel):
    """A stand-in for a GP: mean 0.5 x, per-point variance 0.1."""

    out_dim = 2
    in_dim = 2

    def predict(self, x, u=None):
        return Prediction(0.5 * x, var=torch.full_like(x, 0.1))


def test_model_object_with_extra_noise():
    m = StateSpaceModel(Learned(), lambda x: x[..., :1], Q=0.2 * torch.eye(2), R=torch.eye(1))
    assert m.state_dim == 2 and m.obs_dim == 1
    assert torch.allclose(m.transition.noise_cov(), 0.2 * torch.eye(2))
    assert torch.equal(m.transition.predict(torch.ones(3, 2)).var, torch.full((3, 2), 0.1))


def test_per_point_variance_enters_predicted_cov():
    """Law of total variance: P^- = spread + mean point variance + Q."""
    from torchfilt import CKF

    m = StateSpaceModel(Learned(), lambda x: x[..., :1], Q=0.2 * torch.eye(2), R=torch.eye(1))
    x0, P0 = torch.zeros(2), torch.eye(2)
    res = CKF(m).filter(torch.full((1, 1), float("nan")), x0=x0, P0=P0)
    assert torch.allclose(res.predicted_cov[0], 0.25 * P0 + 0.1 * torch.eye(2) + 0.2 * torch.eye(2))


def test_linear_model_keeps_an_nn_parameter_a_parameter():
    """A matrix passed as an nn.Parameter is fitted (in model.parameters()); a plain tensor is a
    buffer. It used to become a buffer either way, so the fits silently left it unchanged."""
    from torch import nn

    from torchfilt.models import LinearGaussianModel
    from torchfilt.optim import StoppingOptions
    from torchfilt.training import fit_likelihood

    g = torch.Generator().manual_seed(0)
    A = nn.Parameter(torch.tensor([[0.5]], dtype=torch.float64))
    model = LinearGaussianModel(
        A,
        torch.eye(1, dtype=torch.float64),
        0.1 * torch.eye(1, dtype=torch.float64),
        0.1 * torch.eye(1, dtype=torch.float64),
    )
    assert any(p is A for p in model.parameters())
    assert "transition.C" not in dict(model.named_buffers())
    plain = LinearGaussianModel(torch.tensor([[0.5]]), torch.eye(1), torch.eye(1), torch.eye(1))
    assert list(plain.parameters()) == [] and "transition.C" in dict(plain.named_buffers())
    # data from a = 0.9: the fit moves the parameter towards it
    x, ys = torch.zeros(8, dtype=torch.float64), []
    for _ in range(200):
        x = 0.9 * x + 0.3 * torch.randn(8, generator=g, dtype=torch.float64)
        ys.append(x + 0.3 * torch.randn(8, generator=g, dtype=torch.float64))
    y = torch.stack(ys, -1).unsqueeze(-1)
    fit_likelihood(
        model,
        y,
        x0=torch.zeros(1, dtype=torch.float64),
        P0=torch.eye(1, dtype=torch.float64),
        iterations=30,
        optimizer="lbfgs",
        stopping=StoppingOptions(rtol=0.0),
    )
    assert abs(float(model.A.detach()) - 0.9) < 0.1
