"""The DMC dynamic layer (against least squares and scipy), the target layer, and closed loops."""

import numpy as np
import pytest
import scipy.optimize
import torch

from torchfilt.dmc import (
    FOPDT,
    IPDT,
    DMCController,
    FixedTarget,
    InfeasibleError,
    OpenLoopPredictor,
    SampledPlant,
    StepResponseModel,
    TargetRow,
    WeightedTarget,
    run_closed_loop,
)
from torchfilt.exceptions import ShapeError

D = torch.float64
#: Two exact solutions of the same unconstrained least-squares problem.
LSQ_TOL = 1e-9
#: Agreement with scipy's SLSQP (ftol 1e-12).
SLSQP_TOL = 1e-6
#: Offset left at the end of a closed loop with integral action (model mismatch 0.9).
OFFSET_TOL = 1e-3
#: Constraint satisfaction of a QP solution.
FEAS_TOL = 1e-9

GU = [[FOPDT(2.0, 5.0, 1.5), FOPDT(-0.8, 3.0, 0.4)], [FOPDT(1.0, 4.0, 0.0), FOPDT(1.5, 2.0, 2.2)]]


def model_2x2(N=30):
    return StepResponseModel.from_transfer_functions(GU, dt=1.0, horizon=N)


def predict_outputs(model, free, u_prev, du, P):
    """y(k+i|k) = y^ol(k+i|k) + sum_j S_{i-j} du(k+j), by explicit loops."""
    S = model.coefficients(P, "u").numpy()
    M = du.shape[0]
    y = free[:P].copy()
    for i in range(1, P + 1):
        for j in range(min(i, M)):
            y[i - 1] += S[i - j - 1] @ du[j]
    return y


def objective(model, free, u_prev, yt, ut, du_flat, P, M, Q, Lam, W):
    du = du_flat.reshape(M, -1)
    y = predict_outputs(model, free, u_prev, du, P)
    u_end = u_prev + du.sum(0)
    return (((y - yt) ** 2) * Q).sum() + ((du**2) * Lam).sum() + (((u_end - ut) ** 2) * W).sum()


def problem(seed):
    rng = np.random.default_rng(seed)
    free = np.cumsum(0.1 * rng.standard_normal((30, 2)), axis=0) + rng.standard_normal(2)
    return free, rng.uniform(-0.2, 0.2, 2), rng.uniform(-1, 1, 2), rng.uniform(-0.3, 0.3, 2)


def test_unconstrained_plan_is_the_least_squares_solution():
    model = model_2x2()
    P, M = 12, 4
    Q, Lam, W = np.array([1.0, 2.0]), np.array([0.5, 0.3]), np.array([0.2, 0.1])
    ctrl = DMCController(
        model, P, M, Q=torch.tensor(Q), Lambda=torch.tensor(Lam), W=torch.tensor(W)
    )
    free, u_prev, yt, ut = problem(0)
    plan = ctrl.plan(torch.tensor(free), torch.tensor(u_prev), torch.tensor(yt), torch.tensor(ut))
    # the objective is a sum of squares of affine functions of du: solve it by lstsq on its Jacobian
    z0 = np.zeros(M * 2)

    def residual(z):
        du = z.reshape(M, 2)
        y = predict_outputs(model, free, u_prev, du, P)
        return np.concatenate(
            [
                ((y - yt) * np.sqrt(Q)).ravel(),
                (du * np.sqrt(Lam)).ravel(),
                (u_prev + du.sum(0) - ut) * np.sqrt(W),
            ]
        )

    J = np.stack([residual(np.eye(M * 2)[i]) - residual(z0) for i in range(M * 2)], axis=1)
    ref = np.linalg.lstsq(J, -residual(z0), rcond=None)[0]
    np.testing.assert_allclose(plan.du.numpy().ravel(), ref, rtol=0, atol=LSQ_TOL)
    np.testing.assert_allclose(
        plan.y.numpy(), predict_outputs(model, free, u_prev, ref.reshape(M, 2), P), atol=LSQ_TOL
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_constrained_plan_matches_slsqp(seed):
    model = model_2x2()
    P, M = 10, 4
    Q, Lam = np.array([1.0, 1.0]), np.array([0.1, 0.1])
    u_min, u_max, du_max = -0.3, 0.25, 0.08
    ctrl = DMCController(model, P, M, Q=1.0, Lambda=0.1, u_min=u_min, u_max=u_max, du_max=du_max)
    free, u_prev, yt, _ = problem(seed)
    yt = 3.0 * yt  # far targets: the constraints bind
    plan = ctrl.plan(torch.tensor(free), torch.tensor(u_prev), torch.tensor(yt))
    L = np.kron(np.tril(np.ones((M, M))), np.eye(2))
    ref = scipy.optimize.minimize(
        lambda z: objective(model, free, u_prev, yt, u_prev, z, P, M, Q, Lam, np.zeros(2)),
        np.zeros(2 * M),
        method="SLSQP",
        bounds=[(-du_max, du_max)] * (2 * M),
        constraints=[
            {"type": "ineq", "fun": lambda z: u_max - (np.tile(u_prev, M) + L @ z)},
            {"type": "ineq", "fun": lambda z: np.tile(u_prev, M) + L @ z - u_min},
        ],
        options={"ftol": 1e-12, "maxiter": 500},
    )
    assert ref.success
    np.testing.assert_allclose(plan.du.numpy().ravel(), ref.x, rtol=0, atol=SLSQP_TOL)
    du, u = plan.du.numpy(), plan.u.numpy()
    assert np.abs(du).max() <= du_max + FEAS_TOL
    assert u.min() >= u_min - FEAS_TOL and u.max() <= u_max + FEAS_TOL
    # the constraints are active (otherwise this would test the unconstrained case)
    assert np.isclose(np.abs(du), du_max).any() or np.isclose(u, u_max).any()


def test_batched_plan_equals_looped():
    model = model_2x2()
    ctrl = DMCController(model, 8, 3, Lambda=0.2, u_min=-0.5, u_max=0.5, du_max=0.1)
    probs = [problem(s) for s in range(3)]
    free = torch.tensor(np.stack([p[0] for p in probs]))
    up = torch.tensor(np.stack([p[1] for p in probs]))
    yt = torch.tensor(np.stack([3 * p[2] for p in probs]))
    batched = ctrl.plan(free, up, yt)
    for i in range(3):
        one = ctrl.plan(free[i], up[i], yt[i])
        torch.testing.assert_close(batched.du[i], one.du, rtol=0, atol=FEAS_TOL)


def test_infeasible_start_raises():
    ctrl = DMCController(model_2x2(), 8, 3, u_min=-0.5, u_max=0.5, du_max=0.1)
    with pytest.raises(InfeasibleError, match="further than du_max"):
        ctrl.plan(torch.zeros(8, 2, dtype=D), torch.tensor([0.9, 0.0], dtype=D))


@pytest.mark.parametrize("kind", ["kalman", "classical"])
def test_closed_loop_tracks_offset_free_with_mismatch(kind):
    """SISO FOPDT, plant gain 0.9 x model: the bias correction removes the steady-state offset."""
    G = [[FOPDT(1.5, 6.0, 2.4)]]
    model = StepResponseModel.from_transfer_functions(G, dt=1.0, horizon=40)
    K = 80
    plant = SampledPlant(G, dt=1.0, steps=K, output_scale=0.9)
    pred = (
        OpenLoopPredictor(model, 0.5, 1.0)
        if kind == "kalman"
        else OpenLoopPredictor.classical(model)
    )
    ctrl = DMCController(model, 15, 5, Lambda=0.5, u_min=-1.0, u_max=1.0, du_max=0.2)
    res = run_closed_loop(plant, pred, ctrl, FixedTarget(torch.tensor([1.0])), steps=K)
    assert abs(float(res.y[-1, 0]) - 1.0) < OFFSET_TOL
    assert float(res.u.abs().max()) <= 1.0 + FEAS_TOL
    assert float(res.du.abs().max()) <= 0.2 + FEAS_TOL
    # the plant's steady state needs u = 1 / (0.9 * 1.5): check the loop found it
    assert float(res.u[-1, 0]) == pytest.approx(1.0 / 1.35, abs=OFFSET_TOL)


def weighted_penalty(G, d, rows, u, u_prev, base, reg):
    """The WeightedTarget objective written with max(0, .)^2 penalties (no slacks)."""
    y = d + G @ u
    vals = np.concatenate([y, u])
    pmax = max(r.priority for r in rows)
    total = reg * ((u - u_prev) ** 2).sum()
    for r in rows:
        name, idx = r.variable
        x = vals[idx] if name == "y" else vals[len(y) + idx]
        w = base ** (pmax - r.priority) / r.concern**2
        if r.kind == "ideal":
            total += w * (x - r.value) ** 2
        elif r.kind == "upper":
            total += w * max(0.0, x - r.value) ** 2
        else:
            total += w * max(0.0, r.value - x) ** 2
    return total


def test_weighted_target_hits_feasible_ideals_and_matches_scipy():
    from torchfilt.dmc.target import PRIORITY_BASE, TARGET_REGULARISATION

    model = model_2x2()
    G = model.steady_gain().numpy()
    y_ss, u_prev = np.array([0.2, -0.1]), np.array([0.05, -0.02])
    d = y_ss - G @ u_prev
    # ideal values reachable within the bounds: the target hits them exactly
    rows = [TargetRow(("y", 0), "ideal", 0.3, 0.25, 1), TargetRow(("y", 1), "ideal", -0.2, 0.25, 2)]
    tgt = WeightedTarget(model, rows, u_min=-1.0, u_max=1.0)(
        torch.tensor(y_ss), torch.tensor(u_prev)
    )
    np.testing.assert_allclose(tgt.y.numpy(), [0.3, -0.2], atol=1e-5)  # up to the regulariser
    np.testing.assert_allclose(tgt.y.numpy(), d + G @ tgt.u.numpy(), atol=LSQ_TOL)
    # conflicting rows, bounds and a move limit: compare with scipy on the penalty form
    rows = [
        TargetRow(("y", 0), "upper", 0.1, 0.2, 1),
        TargetRow(("y", 0), "ideal", 0.3, 0.25, 2),
        TargetRow(("u", 1), "lower", 0.0, 0.25, 2),
        TargetRow(("y", 1), "ideal", -0.4, 0.25, 3),
    ]
    layer = WeightedTarget(model, rows, u_min=-0.5, u_max=0.5, du_ss_max=0.15)
    tgt = layer(torch.tensor(y_ss), torch.tensor(u_prev))
    ref = scipy.optimize.minimize(
        lambda u: weighted_penalty(G, d, rows, u, u_prev, PRIORITY_BASE, TARGET_REGULARISATION),
        u_prev,
        method="SLSQP",
        bounds=[(max(-0.5, p - 0.15), min(0.5, p + 0.15)) for p in u_prev],
        options={"ftol": 1e-14, "maxiter": 500},
    )
    np.testing.assert_allclose(tgt.u.numpy(), ref.x, atol=SLSQP_TOL)
    assert np.abs(tgt.u.numpy() - u_prev).max() <= 0.15 + FEAS_TOL


def test_bad_controller_and_target_arguments():
    model = model_2x2()
    with pytest.raises(ValueError, match=r"M \(control horizon\) must be an integer in 1..P = 5"):
        DMCController(model, 5, 6)
    with pytest.raises(ValueError, match=r"P \(prediction horizon\)"):
        DMCController(model, 0, 1)
    with pytest.raises(ValueError, match=r"Lambda \(move suppression\) must be positive"):
        DMCController(model, 5, 2, Lambda=0.0)
    with pytest.raises(ShapeError, match=r"Q: expected a scalar or shape \(2,\)"):
        DMCController(model, 5, 2, Q=torch.ones(3))
    with pytest.raises(ValueError, match="u_min must not exceed u_max"):
        DMCController(model, 5, 2, u_min=1.0, u_max=0.0)
    ctrl = DMCController(model, 5, 2)
    with pytest.raises(
        ShapeError, match=r"free: expected shape \(\.\.\., P', 2\) with P' >= P = 5"
    ):
        ctrl.plan(torch.zeros(4, 2, dtype=D), torch.zeros(2, dtype=D))
    with pytest.raises(ShapeError, match=r"u_prev: expected shape \(\.\.\., 2\)"):
        ctrl.plan(torch.zeros(5, 2, dtype=D), torch.zeros(3, dtype=D))
    with pytest.raises(ValueError, match="free contains non-finite"):
        ctrl.plan(torch.full((5, 2), float("nan"), dtype=D), torch.zeros(2, dtype=D))
    integ = StepResponseModel.from_transfer_functions([[IPDT(0.1, 1.0)]], dt=1.0, horizon=5)
    with pytest.raises(ValueError, match="WeightedTarget supports stable CVs only"):
        WeightedTarget(integ, [TargetRow(("y", 0), "ideal", 0.0, 1.0, 1)], u_min=-1, u_max=1)
    with pytest.raises(ValueError, match=r"rows\[0\].variable must be"):
        WeightedTarget(model, [TargetRow(("y", 5), "ideal", 0.0, 1.0, 1)], u_min=-1, u_max=1)
    with pytest.raises(ValueError, match=r"rows\[0\].concern must be positive"):
        WeightedTarget(model, [TargetRow(("y", 0), "ideal", 0.0, 0.0, 1)], u_min=-1, u_max=1)
