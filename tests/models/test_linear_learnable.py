"""LinearGaussianModel.learnable(): a copy to fit by gradient, checked against the textbook Kalman
filter of tests/reference.py, and EM finished by L-BFGS."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from linear_support import make_problem, t64
from reference import kalman_filter
from torch import nn

from torchfilt.exceptions import InputError
from torchfilt.filters import kalman_filter as kalman_filter_tf
from torchfilt.models import CholeskyCovariance, LinearGaussianModel
from torchfilt.training import fit_em, fit_likelihood


def _model(p, **kw):
    return LinearGaussianModel(
        t64(p["A"]), t64(p["H"]), t64(p["Q"]), t64(p["R"]), B=t64(p["B"]), **kw
    )


def test_learnable_copy_filters_as_the_original():
    p = make_problem(11, T=40)
    y, u = t64(p["y"]), t64(p["u"])
    x0, P0 = t64(p["m0"]), t64(p["P0"])
    lin = _model(p)
    copy = lin.learnable()
    assert isinstance(copy.A, nn.Parameter) and isinstance(copy.B, nn.Parameter)
    assert not isinstance(copy.H, nn.Parameter)
    assert any(isinstance(m, CholeskyCovariance) for m in copy.transition.modules())
    want = kalman_filter(p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], p["B"], p["u"])
    got = kalman_filter_tf(copy, y, u, x0=x0, P0=P0)
    assert float(got.log_likelihood.detach()) == pytest.approx(want[-1], rel=1e-10)
    np.testing.assert_allclose(got.mean.detach().numpy(), want[0], rtol=1e-9, atol=1e-10)
    kept = lin.learnable(fixed=("A", "Q", "H"))
    assert not isinstance(kept.A, nn.Parameter) and isinstance(kept.H, torch.Tensor)
    assert not any(isinstance(m, CholeskyCovariance) for m in kept.transition.modules())
    assert any(isinstance(m, CholeskyCovariance) for m in kept.measurement.modules())
    kept.A.add_(1.0)  # a copy: the original is untouched
    assert torch.equal(lin.A, t64(p["A"]))
    with pytest.raises(InputError, match="fixed"):
        lin.learnable(fixed=("C",))


def test_a_singular_noise_gets_a_positive_definite_start():
    p = make_problem(12, T=10)
    Q = t64(p["Q"])
    v = torch.linalg.eigh(Q).eigenvectors[:, :1]
    singular = Q - (v.mT @ Q @ v) * (v @ v.mT)  # one zero eigenvalue
    lin = LinearGaussianModel(t64(p["A"]), t64(p["H"]), singular, t64(p["R"]))
    Qc = lin.learnable().transition.noise_cov()
    assert torch.linalg.eigvalsh(Qc).min() > 0
    torch.testing.assert_close(Qc, singular, rtol=0, atol=1e-10)


def test_em_finished_by_lbfgs_climbs_to_a_stationary_point():
    """EM's last model, made learnable and fitted by L-BFGS: the likelihood does not drop, the
    fit's figure is the reference filter's at the returned model, and the gradient there is
    small."""
    p = make_problem(13, n=2, m=2, nu=1, T=200, missing=0.0)
    y, u = t64(p["y"]), t64(p["u"])
    x0, P0 = t64(p["m0"]), t64(p["P0"])
    start = LinearGaussianModel(
        t64(p["A"]) * 0.8, t64(p["H"]), t64(p["Q"]) * 2, t64(p["R"]) * 2, B=t64(p["B"])
    )
    em = fit_em(start, y, u, x0=x0, P0=P0, known_channels=[0, 1], iterations=5)
    lin = em.model.learnable()
    lf = fit_likelihood(lin, y, u, x0=x0, P0=P0, optimizer="lbfgs")
    assert lf.stopped == "converged"
    assert lf.log_likelihood >= em.log_likelihood - 1e-8
    Q, R = lin.transition.noise_cov().detach(), lin.measurement.noise_cov().detach()
    ref = kalman_filter(
        lin.A.detach().numpy(), p["H"], Q.numpy(), R.numpy(), p["y"], p["m0"], p["P0"],
        lin.B.detach().numpy(), p["u"],
    )  # fmt: skip
    assert lf.log_likelihood == pytest.approx(ref[-1], rel=1e-9)
    ll = kalman_filter_tf(lin, y, u, x0=x0, P0=P0).log_likelihood.sum()  # at the optimum
    grads = torch.autograd.grad(ll, [q for q in lin.parameters() if q.requires_grad])
    assert max(float(g.abs().max()) for g in grads if g.numel()) < 1e-3
