"""Bad input gives a clear error naming the argument, or a documented result."""

import warnings

import pytest
import torch

import torchfilt
from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import ShapeError
from torchfilt.systems import reentry

D = torch.float64


@pytest.fixture
def model():
    return LinearGaussianModel(
        torch.eye(2, dtype=D),
        torch.ones(1, 2, dtype=D),
        0.1 * torch.eye(2, dtype=D),
        torch.eye(1, dtype=D),
    )


@pytest.fixture
def kw():
    return dict(x0=torch.zeros(2, dtype=D), P0=torch.eye(2, dtype=D))


def test_y_wrong_last_dim(model, kw):
    with pytest.raises(ShapeError, match=r"y: expected shape \(\.\.\., T, m\) with m = 1"):
        CKF(model).filter(torch.zeros(5, 2, dtype=D), **kw)


def test_y_one_dimensional(model, kw):
    with pytest.raises(ShapeError, match="y: expected"):
        CKF(model).filter(torch.zeros(5, dtype=D), **kw)


def test_y_not_a_tensor(model, kw):
    with pytest.raises(TypeError, match=r"y must be a torch\.Tensor"):
        CKF(model).filter([[1.0]], **kw)


def test_x0_wrong_shape(model):
    with pytest.raises(ShapeError, match=r"x0: expected shape \(\.\.\., n\) with n = 2"):
        CKF(model).filter(
            torch.zeros(5, 1, dtype=D), x0=torch.zeros(3, dtype=D), P0=torch.eye(2, dtype=D)
        )


def test_P0_wrong_shape(model):
    with pytest.raises(ShapeError, match="P0: expected shape"):
        CKF(model).filter(
            torch.zeros(5, 1, dtype=D), x0=torch.zeros(2, dtype=D), P0=torch.eye(3, dtype=D)
        )


def test_mismatched_batch_shapes(model):
    with pytest.raises(ShapeError, match=r"batch shapes do not broadcast: y \(4,\), x0 \(3,\)"):
        CKF(model).filter(
            torch.zeros(4, 5, 1, dtype=D), x0=torch.zeros(3, 2, dtype=D), P0=torch.eye(2, dtype=D)
        )


def test_non_psd_P0(model):
    P0 = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=D)
    with pytest.raises(ValueError, match="P0 is not positive semi-definite"):
        CKF(model).filter(torch.zeros(5, 1, dtype=D), x0=torch.zeros(2, dtype=D), P0=P0)


def test_non_symmetric_P0(model):
    P0 = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D)
    with pytest.raises(ValueError, match="P0 is not symmetric"):
        CKF(model).filter(torch.zeros(5, 1, dtype=D), x0=torch.zeros(2, dtype=D), P0=P0)


def test_nan_x0(model):
    with pytest.raises(ValueError, match="x0 contains non-finite"):
        CKF(model).filter(
            torch.zeros(5, 1, dtype=D),
            x0=torch.tensor([0.0, float("nan")], dtype=D),
            P0=torch.eye(2, dtype=D),
        )


def test_u_wrong_length_and_nan(kw):
    m = LinearGaussianModel(
        torch.eye(2, dtype=D),
        torch.ones(1, 2, dtype=D),
        torch.eye(2, dtype=D),
        torch.eye(1, dtype=D),
        B=torch.ones(2, 1, dtype=D),
    )
    with pytest.raises(ShapeError, match=r"u: expected shape \(\.\.\., T, nu\) with T = 5"):
        CKF(m).filter(torch.zeros(5, 1, dtype=D), torch.zeros(4, 1, dtype=D), **kw)
    u = torch.zeros(5, 1, dtype=D)
    u[2] = float("nan")
    with pytest.raises(ValueError, match="u contains non-finite"):
        CKF(m).filter(torch.zeros(5, 1, dtype=D), u, **kw)
    with pytest.raises(ValueError, match="pass the inputs u"):
        CKF(m).filter(torch.zeros(5, 1, dtype=D), **kw)


def test_mask_errors(model, kw):
    y = torch.zeros(5, 1, dtype=D)
    with pytest.raises(TypeError, match="mask must be a bool tensor"):
        CKF(model).filter(y, mask=torch.ones(5, 1), **kw)
    with pytest.raises(ShapeError, match="mask: shape"):
        CKF(model).filter(y, mask=torch.ones(4, 1, dtype=torch.bool), **kw)


def test_all_nan_is_pure_prediction(model, kw):
    y = torch.full((6, 1), float("nan"), dtype=D)
    res = CKF(model).filter(y, **kw)
    assert torch.equal(res.mean, res.predicted_mean)
    assert torch.equal(res.cov, res.predicted_cov)
    assert float(res.log_likelihood) == 0.0
    assert torch.isnan(res.innovation).all() and not res.observed.any()
    # covariance grows by Q each step
    assert torch.allclose(res.cov[-1], torch.eye(2, dtype=D) * (1 + 0.1 * 6))


def test_model_returning_wrong_shape(kw):
    m = StateSpaceModel(
        lambda x, u: torch.cat([x, x], -1),
        lambda x, u: x[..., :1],
        Q=torch.eye(2, dtype=D),
        R=torch.eye(1, dtype=D),
    )
    with pytest.raises(
        torchfilt.exceptions.ModelError, match=r"transition returned shape \(4, 4\)"
    ):
        CKF(m).filter(torch.zeros(3, 1, dtype=D), **kw)


def test_model_returning_non_tensor(kw):
    m = StateSpaceModel(
        lambda x: x.numpy(), lambda x: x[..., :1], Q=torch.eye(2, dtype=D), R=torch.eye(1, dtype=D)
    )
    with pytest.raises(torchfilt.exceptions.ModelError, match="transition returned ndarray"):
        CKF(m).filter(torch.zeros(3, 1, dtype=D), **kw)


def test_state_space_model_argument_errors():
    with pytest.raises(ValueError, match="Q is required when transition is a callable"):
        StateSpaceModel(lambda x: x, lambda x: x, R=torch.eye(1))
    with pytest.raises(
        ShapeError, match=r"Q: expected a covariance of shape \(\.\.\., d, d\), got \(2, 3\)"
    ):
        StateSpaceModel(lambda x: x, lambda x: x, Q=torch.ones(2, 3), R=torch.eye(1))
    with pytest.raises(ValueError, match="R is not symmetric"):
        StateSpaceModel(
            lambda x: x, lambda x: x, Q=torch.eye(2), R=torch.tensor([[1.0, 1.0], [0.0, 1.0]])
        )
    with pytest.raises(ValueError, match="non-finite"):
        StateSpaceModel(lambda x: x, lambda x: x, Q=torch.eye(2) * float("nan"), R=torch.eye(1))
    with pytest.raises(ShapeError, match="H: expected shape"):
        LinearGaussianModel(torch.eye(2), torch.ones(1, 3), torch.eye(2), torch.eye(1))
    with pytest.raises(TypeError, match="model must be a StateSpaceModel"):
        CKF(object())


def test_diverging_sequence_is_isolated(kw):
    """A sequence whose model output is non-finite becomes NaN; the others are unaffected."""

    def f(x, u):
        return torch.where(x[..., :1] > 50.0, torch.full_like(x, float("nan")), x)

    m = StateSpaceModel(
        f, lambda x: x[..., :1], Q=0.01 * torch.eye(2, dtype=D), R=torch.eye(1, dtype=D)
    )
    y = torch.zeros(2, 4, 1, dtype=D)
    y[1] = 100.0
    x0 = torch.tensor([[0.0, 0.0], [100.0, 0.0]], dtype=D)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.exceptions.CholeskyJitterWarning)
        with pytest.warns(torchfilt.DivergenceWarning, match="1 of 2 sequences"):
            res = CKF(m).filter(y, x0=x0, P0=torch.eye(2, dtype=D))
    assert torch.isfinite(res.mean[0]).all()
    assert torch.isnan(res.mean[1]).all()


def test_non_psd_noise_is_rejected():
    Q = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=D)  # eigenvalues 3 and -1
    with pytest.raises(ValueError, match="Q is not positive semi-definite"):
        StateSpaceModel(lambda x: x, lambda x: x[..., :1], Q=Q, R=torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="R is not positive semi-definite"):
        LinearGaussianModel(torch.eye(2), torch.ones(1, 2), torch.eye(2), -torch.eye(1))
    bad = torchfilt.models.TimeVarying(torch.stack([torch.eye(2, dtype=D), Q]))
    with pytest.raises(ValueError, match="Q is not positive semi-definite"):
        LinearGaussianModel(
            torch.eye(2, dtype=D), torch.ones(1, 2, dtype=D), bad, torch.eye(1, dtype=D)
        )


def test_graphed_needs_cuda():
    """A CUDA graph of a CPU run is a clear error that points to compile=True."""
    sim = reentry.simulate_truth(2, seed=0)
    filt = torchfilt.CKF(reentry.model())
    with pytest.raises(ValueError, match=r"CUDA device.*compile=True"):
        filt.graphed(sim.measurements, x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov())
