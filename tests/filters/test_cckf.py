"""The constrained CKF: against the CKF without bounds, a point-by-point SciPy reference with
bounds, the 2A -> B system, missing data, batching, gradients, per-point model variances, errors."""

import numpy as np
import pytest
import torch
from conftest import BATCH_SHAPES, REF_ATOL, REF_RTOL, TIGHT, random_spd
from reference import cckf_linear_ref

from torchfilt import CKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import ConvergenceWarning, ShapeError
from torchfilt.filters.constrained import ConstrainedCKF
from torchfilt.models import ConditionalModel, Prediction
from torchfilt.numerics import SolverStatus
from torchfilt.systems import reaction

D = torch.float64
#: the box-QP reference (BVLS) and the projected Gauss-Newton solver agree to round-off; errors
#: grow mildly through the recursion
QP_REF_ATOL = 1e-9
#: float32 vs float64 filtering of the same data
F32_ATOL = 2e-3


def t(a):
    return torch.tensor(a, dtype=D)


def linear_problem(seed, n=3, m=2, T=8):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    Q = random_spd(rng, n, 0.2)
    R = random_spd(rng, m, 0.3)
    m0 = rng.uniform(-0.3, 0.3, n)
    P0 = random_spd(rng, n, 1.0)
    x = rng.multivariate_normal(m0, P0)
    xs, ys = [], []
    for _ in range(T):
        x = A @ x + rng.multivariate_normal(np.zeros(n), Q)
        xs.append(x)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(m), R))
    return dict(A=A, H=H, Q=Q, R=R, m0=m0, P0=P0, y=np.array(ys), x=np.array(xs))


def lgm(p):
    return LinearGaussianModel(t(p["A"]), t(p["H"]), t(p["Q"]), t(p["R"]))


# ------------------------------------------------------------------- no bounds: exactly the CKF
@pytest.mark.parametrize("seed", [0, 1])
def test_unbounded_corrected_equals_ckf(seed):
    p = linear_problem(seed)
    y = t(p["y"])
    y[2, 0] = float("nan")
    y[5] = float("nan")
    kw = dict(x0=t(p["m0"]), P0=t(p["P0"]))
    ckf = CKF(lgm(p)).filter(y, **kw)
    inf = float("inf")
    cckf = ConstrainedCKF(lgm(p), -inf, inf, covariance="corrected").filter(y, **kw)
    for name in ("mean", "cov", "predicted_mean", "predicted_cov", "measurement_mean"):
        a, b = getattr(cckf, name), getattr(ckf, name)
        assert torch.allclose(a, b, rtol=REF_RTOL, atol=REF_ATOL), name
    assert torch.allclose(cckf.innovation_cov, ckf.innovation_cov, rtol=REF_RTOL, atol=REF_ATOL)
    assert torch.allclose(cckf.log_likelihood, ckf.log_likelihood, rtol=REF_RTOL)
    assert torch.equal(torch.isnan(cckf.innovation), torch.isnan(ckf.innovation))


def test_unbounded_paper_covariance_lacks_KRK():
    """One step: the paper's P+ is (I - KH) P- (I - KH)^T, the corrected one adds K R K^T."""
    p = linear_problem(2, T=1)
    kw = dict(x0=t(p["m0"]), P0=t(p["P0"]))
    ckf = CKF(lgm(p)).filter(t(p["y"]), **kw)
    paper = ConstrainedCKF(lgm(p), None, None, covariance="paper").filter(t(p["y"]), **kw)
    Pm = ckf.predicted_cov[0].numpy()
    S = p["H"] @ Pm @ p["H"].T + p["R"]
    K = Pm @ p["H"].T @ np.linalg.inv(S)
    IKH = np.eye(3) - K @ p["H"]
    assert torch.allclose(paper.mean, ckf.mean, rtol=REF_RTOL, atol=REF_ATOL)
    np.testing.assert_allclose(paper.cov[0].numpy(), IKH @ Pm @ IKH.T, rtol=REF_RTOL, atol=REF_ATOL)
    np.testing.assert_allclose(
        (ckf.cov[0] - paper.cov[0]).numpy(), K @ p["R"] @ K.T, rtol=REF_RTOL, atol=REF_ATOL
    )


# --------------------------------------------------------- bounds active: the SciPy reference
@pytest.mark.parametrize("covariance", ["paper", "corrected"])
@pytest.mark.parametrize("theta", ["paper", "std"])
@pytest.mark.parametrize("seed", [3, 4])
def test_linear_with_bounds_equals_box_qp_reference(covariance, theta, seed):
    """Points, weights, projection and every reconciliation (a box QP, solved by SciPy's BVLS)."""
    p = linear_problem(seed)
    # a box that holds the true trajectory and the prior mean but cuts the cubature points
    # (sqrt(3) prior standard deviations out); one side of two components is unbounded
    margin = 0.15
    lo = np.minimum(p["x"].min(0), p["m0"]) - margin
    hi = np.maximum(p["x"].max(0), p["m0"]) + margin
    lo[1], hi[2] = -np.inf, np.inf
    ms, Ps = cckf_linear_ref(
        p["A"], p["H"], p["Q"], p["R"], p["y"], p["m0"], p["P0"], lo, hi, covariance, theta
    )
    filt = ConstrainedCKF(lgm(p), t(lo), t(hi), covariance=covariance, theta=theta)
    res, info = filt.filter_with_info(t(p["y"]), x0=t(p["m0"]), P0=t(p["P0"]))
    assert bool((info.solver_status > 0).all())
    np.testing.assert_allclose(res.mean.numpy(), ms, atol=QP_REF_ATOL, rtol=0)
    np.testing.assert_allclose(res.cov.numpy(), Ps, atol=QP_REF_ATOL, rtol=0)
    assert bool((res.mean.numpy() <= hi).all() and (res.mean.numpy() >= lo).all())
    # the bounds did act: some reconciliations needed more than the one unconstrained step
    assert bool((info.solver_iterations > 1).any()), "bounds must be active"


# ------------------------------------------------------------------------- the 2A -> B system
@pytest.mark.parametrize("start", ["paper", "hr"])
def test_reaction_estimates_stay_in_the_box(start):
    sim = reaction.simulate_truth(8, start=start, steps=30, seed=1)
    kw = dict(x0=reaction.prior_mean(start), P0=reaction.prior_cov())
    filt = ConstrainedCKF(reaction.model(), reaction.LOWER, reaction.UPPER)
    res, info = filt.filter_with_info(sim.measurements, **kw)
    lo, hi = t(reaction.LOWER), t(reaction.UPPER)
    for est in (res.mean, res.predicted_mean):
        assert bool(((est >= lo) & (est <= hi)).all())
    assert torch.isfinite(res.cov).all() and bool((info.solver_status > 0).all())
    assert info.solver_iterations.shape == (8, 30, 4) and info.projected.shape == (8, 30)
    if start == "hr":  # the unconstrained CKF does leave the box here (what the CCKF is for)
        ckf = CKF(reaction.model()).filter(sim.measurements, **kw)
        assert bool((ckf.mean < 0).any())


# ------------------------------------------------------------------------------ missing data
def test_fully_missing_step_skips_the_update():
    p = linear_problem(5, T=4)
    y = t(p["y"])
    y[2] = float("nan")
    filt = ConstrainedCKF(lgm(p), t([-0.3, -0.3, -0.3]), t([0.3, 0.3, 0.3]))
    res = filt.filter(y, x0=t(p["m0"]).clamp(-0.3, 0.3), P0=t(p["P0"]))
    assert torch.equal(res.mean[2], res.predicted_mean[2])
    assert torch.equal(res.cov[2], res.predicted_cov[2])


def test_always_missing_component_equals_model_without_it():
    """A second sensor that never reports changes nothing (partial update uses observed rows)."""
    p = linear_problem(6, m=2)
    box = (t([-0.4, -0.4, -0.4]), t([0.4, 0.4, 0.4]))
    y = t(p["y"])
    y[:, 1] = float("nan")
    kw = dict(x0=t(p["m0"]).clamp(-0.4, 0.4), P0=t(p["P0"]))
    both = ConstrainedCKF(lgm(p), *box, covariance="corrected").filter(y, **kw)
    one = LinearGaussianModel(t(p["A"]), t(p["H"][:1]), t(p["Q"]), t(p["R"][:1, :1]))
    ref = ConstrainedCKF(one, *box, covariance="corrected").filter(y[:, :1], **kw)
    assert torch.allclose(both.mean, ref.mean, rtol=0, atol=QP_REF_ATOL)
    assert torch.allclose(both.cov, ref.cov, rtol=0, atol=QP_REF_ATOL)
    assert torch.allclose(both.log_likelihood, ref.log_likelihood, rtol=TIGHT)


def test_mask_equals_nan():
    p = linear_problem(7)
    rng = np.random.default_rng(1)
    mask = torch.tensor(rng.random(p["y"].shape) > 0.3)
    y_nan = t(p["y"]).masked_fill(~mask, float("nan"))
    filt = ConstrainedCKF(lgm(p), -0.5, 0.5)
    kw = dict(x0=t(p["m0"]), P0=t(p["P0"]))
    a = filt.filter(t(p["y"]), mask=mask, **kw)
    b = filt.filter(y_nan, **kw)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.log_likelihood, b.log_likelihood)


# -------------------------------------------------------------------------------- batching
@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
def test_batched_equals_loop(batch):
    gen = torch.Generator().manual_seed(2)
    sim = reaction.simulate_truth(int(np.prod(batch)), start="hr", steps=12, seed=3)
    y = sim.measurements.reshape(*batch, 12, 1)
    x0 = (reaction.prior_mean("hr") + 0.1 * torch.rand(*batch, 2, dtype=D, generator=gen)).abs()
    filt = ConstrainedCKF(reaction.model(), reaction.LOWER, reaction.UPPER, covariance="corrected")
    res = filt.filter(y, x0=x0, P0=reaction.prior_cov())
    assert res.mean.shape == (*batch, 12, 2) and res.log_likelihood.shape == batch
    for idx in np.ndindex(*batch):
        one = filt.filter(y[idx], x0=x0[idx], P0=reaction.prior_cov())
        assert torch.allclose(res.mean[idx], one.mean, rtol=TIGHT, atol=1e-12)
        assert torch.allclose(res.cov[idx], one.cov, rtol=TIGHT, atol=1e-12)
        assert torch.allclose(res.log_likelihood[idx], one.log_likelihood, rtol=TIGHT)


def test_batched_bounds():
    """Bounds of shape (B, n) filter B sequences under B different boxes."""
    p = linear_problem(8)
    lo = t([[-0.2, -0.2, -0.2], [-1.0, -1.0, -1.0]])
    filt = ConstrainedCKF(lgm(p), lo, 1.0)
    res = filt.filter(t(p["y"]), x0=torch.zeros(3, dtype=D), P0=t(p["P0"]))
    assert res.mean.shape == (2, 8, 3)
    for i in range(2):
        one = ConstrainedCKF(lgm(p), lo[i], 1.0).filter(
            t(p["y"]), x0=torch.zeros(3, dtype=D), P0=t(p["P0"])
        )
        assert torch.allclose(res.mean[i], one.mean, rtol=TIGHT, atol=1e-12)


def test_float32():
    sim = reaction.simulate_truth(3, start="hr", steps=20, seed=4)
    kw = dict(x0=reaction.prior_mean("hr"), P0=reaction.prior_cov())
    filt = ConstrainedCKF(reaction.model(), reaction.LOWER, reaction.UPPER)
    r64 = filt.filter(sim.measurements, **kw)
    kw32 = {k: v.float() for k, v in kw.items()}
    r32 = filt.filter(sim.measurements.float(), **kw32)
    assert r32.mean.dtype == torch.float32 and bool((r32.mean >= 0).all())
    assert torch.allclose(r32.mean.double(), r64.mean, atol=F32_ATOL, rtol=0)


# ------------------------------------------------------------------------------- gradients
def test_gradcheck_with_active_bounds():
    p = linear_problem(9, T=3)
    lo, hi = t([-0.3, -0.3, -0.3]), t([0.3, 0.3, 0.3])
    y = t(p["y"]).requires_grad_()
    x0 = t(p["m0"]).clamp(-0.25, 0.25).requires_grad_()

    def fn(y, x0):
        res = ConstrainedCKF(lgm(p), lo, hi, covariance="corrected", tol=1e-12).filter(
            y, x0=x0, P0=t(p["P0"])
        )
        return res.mean, res.cov, res.log_likelihood

    mean = fn(y, x0)[0].detach()
    assert bool(((mean == lo) | (mean == hi)).any()), "the check needs an active bound"
    assert torch.autograd.gradcheck(fn, (y, x0), eps=1e-6, atol=1e-5, fast_mode=True)


# ------------------------------------------------- learned models: per-point model variances
class VarianceModel(ConditionalModel):
    """Linear mean ``x C^T`` with a per-point variance ``a + b x_0^2`` (a stand-in for a GP)."""

    def __init__(self, C, a, b):
        super().__init__()
        self.C, self.a, self.b = C, a, b
        self.out_dim, self.in_dim = C.shape[0], C.shape[1]

    def predict(self, x, u=None):
        var = (self.a + self.b * x[..., :1] ** 2).expand(*x.shape[:-1], self.out_dim)
        return Prediction(x @ self.C.mT, var=var)


def test_per_point_measurement_variance_enters_each_reconciliation():
    """R_i = R + V_h(X_i) in each point's NDDR and R + sum w_i V_h(X_i) in P_zz (SciPy reference)."""
    p = linear_problem(10, m=1)
    a, b = 0.05, 0.4
    lo, hi = np.array([-0.3, -np.inf, -0.3]), np.array([0.3, 0.4, np.inf])
    h = VarianceModel(t(p["H"]), a, b)
    model = StateSpaceModel(lambda x: x @ t(p["A"]).mT, h, Q=t(p["Q"]), R=t(p["R"]))
    filt = ConstrainedCKF(model, t(lo), t(hi), covariance="corrected")
    res = filt.filter(t(p["y"]), x0=t(p["m0"]), P0=t(p["P0"]))
    ms, Ps = cckf_linear_ref(
        p["A"],
        p["H"],
        p["Q"],
        p["R"],
        p["y"],
        p["m0"],
        p["P0"],
        lo,
        hi,
        "corrected",
        R_point=lambda x: a + b * x[0] ** 2,
    )
    np.testing.assert_allclose(res.mean.numpy(), ms, atol=QP_REF_ATOL, rtol=0)
    np.testing.assert_allclose(res.cov.numpy(), Ps, atol=QP_REF_ATOL, rtol=0)


def test_constant_model_variances_equal_extra_noise():
    """A model reporting a constant variance V is the CKF with Q + V and R + V (no bounds)."""
    p = linear_problem(11, m=1)
    vq, vr = 0.07, 0.2
    f = VarianceModel(t(p["A"]), vq, 0.0)
    h = VarianceModel(t(p["H"]), vr, 0.0)
    learned = StateSpaceModel(f, h, Q=t(p["Q"]), R=t(p["R"]))
    plain = LinearGaussianModel(
        t(p["A"]), t(p["H"]), t(p["Q"]) + vq * torch.eye(3, dtype=D), t(p["R"]) + vr
    )
    kw = dict(x0=t(p["m0"]), P0=t(p["P0"]))
    a = ConstrainedCKF(learned, None, None, covariance="corrected").filter(t(p["y"]), **kw)
    b = CKF(plain).filter(t(p["y"]), **kw)
    assert torch.allclose(a.mean, b.mean, rtol=REF_RTOL, atol=REF_ATOL)
    assert torch.allclose(a.cov, b.cov, rtol=REF_RTOL, atol=REF_ATOL)


def test_point_variance_at_the_mean():
    """point_variance="mean": one variance, at the (projected) mean, for every point: with a
    variance that does not depend on x it equals "total"; with one that does, it differs."""
    p = linear_problem(14, m=1)
    box = (t([-1.0, -1.0, -1.0]), t([1.0, 1.0, 1.0]))
    kw = dict(x0=t(p["m0"]), P0=t(p["P0"]))
    res = {}
    for b in (0.0, 0.5):
        h = VarianceModel(t(p["H"]), 0.1, b)
        model = StateSpaceModel(lambda x: x @ t(p["A"]).mT, h, Q=t(p["Q"]), R=t(p["R"]))
        for mode in ("total", "mean"):
            filt = ConstrainedCKF(model, *box, covariance="corrected", point_variance=mode)
            res[b, mode] = filt.filter(t(p["y"]), **kw)
    assert torch.allclose(res[0.0, "mean"].mean, res[0.0, "total"].mean, rtol=0, atol=TIGHT)
    assert not torch.allclose(res[0.5, "mean"].mean, res[0.5, "total"].mean, rtol=0, atol=1e-6)


def test_per_point_transition_variance_in_the_prediction():
    """P- = spread + sum_i omega_i V_f(X_i) + Q, with the constrained weights."""
    from torchfilt.cubature import constrained_points
    from torchfilt.numerics import Box

    p = linear_problem(12, m=1, T=1)
    f = VarianceModel(t(p["A"]), 0.01, 0.5)
    model = StateSpaceModel(f, lambda x: x @ t(p["H"]).mT, Q=t(p["Q"]), R=t(p["R"]))
    box = Box(t([-0.5, -0.5, -0.5]), t([0.5, 0.5, 0.5]))
    x0 = t(p["m0"]).clamp(-0.5, 0.5)
    res = ConstrainedCKF(model, box.lower, box.upper).filter(t(p["y"]), x0=x0, P0=t(p["P0"]))
    cp = constrained_points(x0, torch.linalg.cholesky(t(p["P0"])), box)
    Xs = cp.points @ t(p["A"]).mT
    m = cp.weights @ Xs
    Dv = Xs - m
    V = (cp.weights * (0.01 + 0.5 * cp.points[:, 0] ** 2)).sum()
    want = Dv.mT @ (Dv * cp.weights[:, None]) + V * torch.eye(3, dtype=D) + t(p["Q"])
    assert torch.allclose(res.predicted_cov[0], want, rtol=REF_RTOL, atol=REF_ATOL)


# ------------------------------------------------------------------ solver reporting, errors
def test_nonconvergence_warns_once_with_counts():
    h = lambda x: torch.sin(3 * x[..., :1]) + x[..., 1:] ** 3  # noqa: E731
    model = StateSpaceModel(lambda x: x, h, Q=0.01 * torch.eye(2, dtype=D), R=t([[0.01]]))
    filt = ConstrainedCKF(model, -1.0, 1.0, max_iter=1)
    y = t([[0.9], [-0.5], [0.3]])
    with pytest.warns(ConvergenceWarning, match="reconciliation problems did not converge"):
        _, info = filt.filter_with_info(y, x0=t([0.1, 0.1]), P0=torch.eye(2, dtype=D))
    assert bool((info.solver_status == SolverStatus.MAX_ITER).any())
    assert int(info.solver_iterations.max()) == 1


@pytest.fixture
def small():
    p = linear_problem(13, T=3)
    return lgm(p), t(p["y"]), t(p["P0"])


def test_lower_above_upper(small):
    model, _, _ = small
    with pytest.raises(ValueError, match="lower > upper at index"):
        ConstrainedCKF(model, t([0.0, 1.0, 0.0]), t([1.0, 0.5, 1.0]))


def test_wrong_bound_shape(small):
    model, _, _ = small
    with pytest.raises(ShapeError, match=r"lower: expected shape \(\.\.\., n\) with n = 3"):
        ConstrainedCKF(model, t([0.0, 0.0]), 1.0)


def test_bounds_batch_must_broadcast(small):
    model, y, P0 = small
    filt = ConstrainedCKF(model, torch.zeros(4, 3, dtype=D) - 1, 1.0)
    with pytest.raises(ShapeError, match=r"lower/upper: batch shape \(4,\)"):
        filt.filter(y.expand(3, 3, 2), x0=torch.zeros(3, dtype=D), P0=P0)


def test_x0_outside_the_box(small):
    model, y, P0 = small
    filt = ConstrainedCKF(model, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"x0 lies outside the box at index \[1\]"):
        filt.filter(y, x0=t([0.5, -0.1, 0.5]), P0=P0)


def test_bad_options(small):
    model, y, P0 = small
    with pytest.raises(ValueError, match="covariance must be"):
        ConstrainedCKF(model, 0.0, 1.0, covariance="joseph")
    with pytest.raises(ValueError, match="theta must be"):
        ConstrainedCKF(model, 0.0, 1.0, theta="sd")
    # smooth() exists now (issue 13): its means respect the bounds (tests/filters/test_constrained_paths.py)
    sm = ConstrainedCKF(model, 0.0, 1.0).smooth(y, x0=torch.zeros(3, dtype=D) + 0.5, P0=P0)
    assert ((sm.mean >= 0.0) & (sm.mean <= 1.0)).all()


def test_measurement_noise_must_be_positive_definite():
    model = StateSpaceModel(
        lambda x: x,
        lambda x: x[..., :1],
        Q=0.1 * torch.eye(2, dtype=D),
        R=torch.zeros(1, 1, dtype=D),
    )
    filt = ConstrainedCKF(model, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"R \(plus .*\) is not positive definite"):
        filt.filter(t([[0.5]]), x0=t([0.5, 0.5]), P0=torch.eye(2, dtype=D))
