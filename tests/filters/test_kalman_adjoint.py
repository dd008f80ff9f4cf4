"""The closed-form gradient of the exact filter's log-likelihood (torchfilt.filters.kalman_adjoint,
issue 27 s.2): equal to autograd through the recorded exact path for batches, missing data,
inputs, time-varying and batched matrices, Cholesky-parametrised covariances, a singular process
noise and a known initial state; second derivatives replay the recorded path."""

import numpy as np
import pytest
import torch
from conftest import random_spd
from linear_support import make_problem, t64
from torch import nn

from torchfilt import LinearGaussianModel
from torchfilt.filters import kalman_filter
from torchfilt.models import CholeskyCovariance, TimeVarying

#: the closed form and autograd compute the same derivative in a different order of operations
GRAD_RTOL = 1e-8
ADJOINT = ("log_likelihood",)
#: asking for another field keeps autograd through the recorded path (the reference)
RECORDED = ("log_likelihood", "mean")


def _both(build, leaves, y, u=None, *, x0, P0, mask=None, weights=None):
    """The weighted log-likelihood's gradients in ``leaves`` by the closed form and by autograd
    through the recorded path, and the two runs' executions."""
    out = []
    for outputs in (ADJOINT, RECORDED):
        model, x0v, P0v = build()
        res = kalman_filter(model, y, u, x0=x0v, P0=P0v, mask=mask, outputs=outputs)
        ll = res.log_likelihood
        total = (ll * weights).sum() if weights is not None else ll.sum()
        grads = torch.autograd.grad(total, leaves)
        out.append((res.numerics.execution, ll.detach(), grads))
    (ex_a, ll_a, g_a), (ex_r, ll_r, g_r) = out
    assert ex_a == "kalman-adjoint"
    assert ex_r != "kalman-adjoint"
    torch.testing.assert_close(ll_a, ll_r, rtol=1e-12, atol=1e-9)
    return g_a, g_r


def _assert_grads_equal(got, want, names):
    for a, b, name in zip(got, want, names, strict=True):
        scale = float(b.abs().max())
        err = float((a - b).abs().max())
        assert scale > 0, name
        assert err <= GRAD_RTOL * scale, f"{name}: max diff {err:.2e} of {scale:.2e}"


def _lower(rng, n, scale):
    return t64(np.linalg.cholesky(random_spd(rng, n, scale))).requires_grad_(True)


@pytest.mark.parametrize("prior", ["shared", "per-recording"])
def test_batch_with_cholesky_noises_equals_autograd(prior):
    """Complete data (the Riccati forward runner, and a long enough series for the backward
    information recursion to reach its steady state), weighted recordings, learnable ``A``,
    Cholesky-parametrised ``Q`` and ``R``, prior mean and factor of the prior covariance."""
    p = make_problem(1, T=200, missing=0.0)
    p["y"][3] = p["y"][2]  # make_problem blanks step 3
    rng = np.random.default_rng(2)
    Bsz, n = 4, 3
    y = t64(p["y"]) + 0.3 * torch.randn(Bsz, 200, 2, dtype=torch.float64,
                                        generator=torch.Generator().manual_seed(0))  # fmt: skip
    A = nn.Parameter(t64(p["A"]))
    Qc, Rc = CholeskyCovariance(t64(p["Q"])), CholeskyCovariance(t64(p["R"]))
    x0 = t64(rng.standard_normal((n,) if prior == "shared" else (Bsz, n))).requires_grad_(True)
    L0 = _lower(rng, n, 2.0)

    def build():
        return LinearGaussianModel(A, t64(p["H"]), Qc, Rc), x0, L0 @ L0.mT

    leaves = [A, *Qc.parameters(), *Rc.parameters(), x0, L0]
    weights = t64(rng.uniform(0.5, 2.0, Bsz))
    got, want = _both(build, leaves, y, x0=x0, P0=L0 @ L0.mT, weights=weights)
    _assert_grads_equal(got, want, ["A", "Q diag", "Q lower", "R diag", "R lower", "x0", "L0"])


def test_missing_data_and_inputs_equal_autograd():
    """NaN entries, whole missing steps, a mask, and inputs through learnable ``B`` and ``D``
    (the transition and measurement offsets); per-recording missing patterns (the fast forward
    runner, one covariance sequence per recording)."""
    p = make_problem(3, T=40, missing=0.25)
    rng = np.random.default_rng(4)
    Bsz, m = 3, 2
    y = t64(p["y"]).expand(Bsz, -1, -1).clone()
    y[1, 10:13] = float("nan")  # a gap in one recording only
    y[2, :, 0] = torch.where(torch.rand(40, generator=torch.Generator().manual_seed(1)) < 0.3,
                             float("nan"), y[2, :, 0])  # fmt: skip
    mask = torch.ones(Bsz, 40, m, dtype=torch.bool)
    mask[0, 20, 1] = False
    u = t64(rng.standard_normal((Bsz, 40, 1)))
    A, H = nn.Parameter(t64(p["A"])), nn.Parameter(t64(p["H"]))
    Bm, Dm = nn.Parameter(t64(p["B"])), nn.Parameter(t64(rng.standard_normal((m, 1))))
    Qc, Rc = CholeskyCovariance(t64(p["Q"])), CholeskyCovariance(t64(p["R"]))
    x0 = t64(p["m0"]).requires_grad_(True)
    P0 = t64(p["P0"])

    def build():
        return LinearGaussianModel(A, H, Qc, Rc, B=Bm, D=Dm), x0, P0

    leaves = [A, H, Bm, Dm, *Qc.parameters(), *Rc.parameters(), x0]
    got, want = _both(build, leaves, y, u, x0=x0, P0=P0, mask=mask)
    _assert_grads_equal(got, want, ["A", "H", "B", "D", "Qd", "Ql", "Rd", "Rl", "x0"])


def test_time_varying_and_batched_matrices_and_measurements_equal_autograd():
    """A per-recording ``A``, time-varying ``Q`` and ``R`` (their per-step factors learnable),
    and the measurements themselves as leaves."""
    rng = np.random.default_rng(5)
    Bsz, T, n, m = 3, 25, 2, 2
    A = t64(0.5 * rng.standard_normal((Bsz, n, n))).requires_grad_(True)
    H = t64(rng.standard_normal((m, n)))
    LQ = t64(0.3 * rng.standard_normal((T, n, n)) + 0.5 * np.eye(n)).tril().requires_grad_(True)
    LR = t64(0.2 * rng.standard_normal((T, m, m)) + 0.6 * np.eye(m)).tril().requires_grad_(True)
    y = t64(rng.standard_normal((Bsz, T, m))).requires_grad_(True)
    x0, P0 = t64(np.zeros(n)), t64(np.eye(n))

    def build():
        model = LinearGaussianModel(A, H, TimeVarying(LQ @ LQ.mT), TimeVarying(LR @ LR.mT))
        return model, x0, P0

    got, want = _both(build, [A, LQ, LR, y], y, x0=x0, P0=P0)
    _assert_grads_equal(got, want, ["A", "LQ", "LR", "y"])


def test_singular_process_noise_and_known_initial_state_equal_autograd():
    """The closed form inverts neither ``Q`` nor ``P0``: a constant state component, noise-free
    and known at the start (singular ``Q`` and ``P0``)."""
    rng = np.random.default_rng(6)
    T, n = 60, 3
    A = nn.Parameter(t64([[0.9, 0.1, 0.0], [-0.1, 0.8, 0.05], [0.0, 0.0, 1.0]]))
    H = t64(rng.standard_normal((2, n)))
    q = t64([0.2, 0.1]).requires_grad_(True)
    r = t64([0.3, 0.4]).requires_grad_(True)
    y = t64(rng.standard_normal((2, T, 2)))
    x0 = t64([0.1, -0.2, 0.5]).requires_grad_(True)
    P0 = torch.diag(t64([1.0, 0.5, 0.0]))

    def build():
        Q = torch.diag(torch.cat([q, q.new_zeros(1)]))
        return LinearGaussianModel(A, H, Q, torch.diag(r)), x0, P0

    got, want = _both(build, [A, q, r, x0], y, x0=x0, P0=P0)
    _assert_grads_equal(got, want, ["A", "q", "r", "x0"])


def test_second_derivatives_replay_the_recorded_path():
    """``create_graph=True`` (a Hessian, as parameter_posterior takes) replays autograd through
    the recorded path, so second derivatives equal autograd's."""
    p = make_problem(7, T=20, missing=0.1)
    theta = t64(np.concatenate([p["A"].ravel(), np.log(np.diag(p["Q"]))])).requires_grad_(True)
    y = t64(p["y"])

    def ll(outputs):
        A, Q = theta[:9].reshape(3, 3), torch.diag(theta[9:].exp())
        model = LinearGaussianModel(A, t64(p["H"]), Q, t64(p["R"]))
        res = kalman_filter(model, y, x0=t64(p["m0"]), P0=t64(p["P0"]), outputs=outputs)
        return res

    hessians = []
    for outputs in (ADJOINT, RECORDED):
        res = ll(outputs)
        (g,) = torch.autograd.grad(res.log_likelihood, theta, create_graph=True)
        v = t64(np.linspace(-1.0, 1.0, theta.numel()))
        (hv,) = torch.autograd.grad(g @ v, theta)
        hessians.append((res.numerics.execution, g.detach(), hv))
    (ex_a, g_a, hv_a), (ex_r, g_r, hv_r) = hessians
    assert ex_a == "kalman-adjoint" and ex_r != "kalman-adjoint"
    _assert_grads_equal([g_a, hv_a], [g_r, hv_r], ["gradient", "Hessian-vector product"])


def test_square_root_form_keeps_autograd():
    p = make_problem(8, T=10, missing=0.0)
    A = nn.Parameter(t64(p["A"]))
    model = LinearGaussianModel(A, t64(p["H"]), t64(p["Q"]), t64(p["R"]))
    res = kalman_filter(model, t64(p["y"]), x0=t64(p["m0"]), P0=t64(p["P0"]), sqrt=True,
                        outputs=ADJOINT)  # fmt: skip
    assert res.numerics.execution == "kalman-sequential"
    res.log_likelihood.backward()
    assert A.grad is not None and bool(torch.isfinite(A.grad).all())


def test_a_failed_backward_factorisation_replays_autograd(monkeypatch):
    """Where the closed form cannot factor an innovation covariance, the backward pass replays
    autograd through the recorded path: the same gradient."""
    from torchfilt.filters import kalman_adjoint

    p = make_problem(9, T=30, missing=0.2)
    A = nn.Parameter(t64(p["A"]))
    Qc = CholeskyCovariance(t64(p["Q"]))
    y, x0, P0 = t64(p["y"]), t64(p["m0"]), t64(p["P0"])

    def build():
        return LinearGaussianModel(A, t64(p["H"]), Qc, t64(p["R"])), x0, P0

    leaves = [A, *Qc.parameters()]
    _, want = _both(build, leaves, y, x0=x0, P0=P0)
    monkeypatch.setattr(kalman_adjoint, "adjoint_gradients", lambda *args: None)
    got, _ = _both(build, leaves, y, x0=x0, P0=P0)
    _assert_grads_equal(got, want, ["A", "Q diag", "Q lower"])
