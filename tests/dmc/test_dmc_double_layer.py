"""The dynamic layer's CV constraints (against scipy on the penalty form) and the double-layered DMC
closed loop of the paper's section 3.1 (hard limits held throughout)."""

import numpy as np
import pytest
import scipy.optimize
import torch
from script_support import load_script

from torchfilt.dmc import (
    FOPDT,
    DMCController,
    OpenLoopPredictor,
    SampledPlant,
    StepResponseModel,
    run_closed_loop,
    shell_fractionator,
)

D = torch.float64
#: Agreement with scipy's SLSQP (ftol 1e-14) on the penalty form of the soft constraints.
SLSQP_TOL = 1e-5
#: Constraint satisfaction of a QP solution (Clarabel at QP_TOL).
FEAS_TOL = 1e-8

GU = [[FOPDT(2.0, 5.0, 1.5), FOPDT(-0.8, 3.0, 0.4)], [FOPDT(1.0, 4.0, 0.0), FOPDT(1.5, 2.0, 2.2)]]
#: The same with every channel into y1 delayed by 1.5 samples (nothing reaches y1(k+1)).
GU_DELAYED = [
    [FOPDT(2.0, 5.0, 1.5), FOPDT(-0.8, 3.0, 1.5)],
    [FOPDT(1.0, 4.0, 0.0), FOPDT(1.5, 2.0, 2.2)],
]


def predict_outputs(model, free, du, P):
    """y(k+i|k) = y^ol(k+i|k) + sum_j S_{i-j} du(k+j), by explicit loops."""
    S = model.coefficients(P, "u").numpy()
    y = free[:P].copy()
    for i in range(1, P + 1):
        for j in range(min(i, du.shape[0])):
            y[i - 1] += S[i - j - 1] @ du[j]
    return y


def test_soft_cv_bounds_match_scipy_on_the_penalty_form():
    model = StepResponseModel.from_transfer_functions(GU, dt=1.0, horizon=30)
    P, M = 8, 3
    Q, Lam, W = np.array([1.0, 0.5]), np.array([0.5, 0.8]), np.array([0.3, 0.3])
    q_lo, q_hi = np.array([2.0, 1.0]), np.array([4.0, 3.0])
    z_lo, z_hi, y_hi = -0.2, 0.25, 0.42
    rng = np.random.default_rng(3)
    free = 0.3 + 0.05 * np.cumsum(rng.standard_normal((30, 2)), axis=0)
    u_prev, yt, ut = np.array([0.1, -0.1]), np.array([0.9, -0.4]), np.array([0.2, 0.0])
    ctrl = DMCController(
        model,
        P,
        M,
        Q=torch.tensor(Q),
        Lambda=torch.tensor(Lam),
        W=torch.tensor(W),
        u_min=-1.0,
        u_max=1.0,
        du_max=0.5,
        y_max=y_hi,
        z_min=z_lo,
        z_max=z_hi,
        q_lower=torch.tensor(q_lo),
        q_upper=torch.tensor(q_hi),
    )
    plan = ctrl.plan(torch.tensor(free), torch.tensor(u_prev), torch.tensor(yt), torch.tensor(ut))

    def cost(x):
        du = x.reshape(M, 2)
        y = predict_outputs(model, free, du, P)
        u_end = u_prev + du.sum(0)
        return (
            (((y - yt) ** 2) * Q).sum()
            + ((du**2) * Lam).sum()
            + (((u_end - ut) ** 2) * W).sum()
            + ((np.maximum(z_lo - y, 0.0) ** 2) * q_lo).sum()
            + ((np.maximum(y - z_hi, 0.0) ** 2) * q_hi).sum()
        )

    cum = np.kron(np.tril(np.ones((M, M))), np.eye(2))
    ref = scipy.optimize.minimize(
        cost,
        np.zeros(2 * M),
        method="SLSQP",
        bounds=[(-0.5, 0.5)] * (2 * M),
        constraints=[
            {"type": "ineq", "fun": lambda x: 1.0 - (u_prev.repeat(M) + cum @ x)},
            {"type": "ineq", "fun": lambda x: (u_prev.repeat(M) + cum @ x) + 1.0},
            {
                "type": "ineq",
                "fun": lambda x: y_hi - predict_outputs(model, free, x.reshape(M, 2), P).ravel(),
            },
        ],
        options={"ftol": 1e-14, "maxiter": 1000},
    )
    assert ref.success
    np.testing.assert_allclose(plan.du.numpy().ravel(), ref.x, atol=SLSQP_TOL)
    y = plan.y.numpy()
    assert y.max() <= y_hi + FEAS_TOL
    assert y.max() > z_hi  # the soft upper bound is violated (the target is above it) ...
    assert np.isclose(y.max(), y_hi, atol=1e-6)  # ... up to the hard limit, which is active


def test_unavoidable_hard_cv_violation_is_minimised_not_fatal():
    # within the dead time (1.5 samples on y1) no move acts: free predictions above y_max there
    model = StepResponseModel.from_transfer_functions(GU_DELAYED, dt=1.0, horizon=30)
    free = np.full((30, 2), 0.0)
    free[:, 0] = 0.8
    ctrl = DMCController(model, 6, 2, u_min=-1.0, u_max=1.0, du_max=0.5, y_min=-0.7, y_max=0.7)
    plan = ctrl.plan(torch.tensor(free), torch.zeros(2, dtype=D))
    y = plan.y.numpy()
    np.testing.assert_allclose(y[0, 0], 0.8, atol=FEAS_TOL)  # y1(k+1): no move reaches it
    assert y[3:, 0].max() <= 0.7 + FEAS_TOL  # from k+4 on the limit holds again


def test_fractionator_double_layer_holds_every_hard_limit():
    mod = load_script("reproduce_dmc")
    Gu, Gv = shell_fractionator()
    steps = 250
    model = StepResponseModel.from_transfer_functions(Gu, Gv, dt=4.0, horizon=100)
    plant = SampledPlant(Gu, Gv, dt=4.0, steps=steps, output_scale=0.9)
    v = torch.zeros(steps, 2, dtype=D)
    v[64:79] = torch.tensor([0.2, 0.1], dtype=D)
    v[122:] = torch.tensor([1.0, -1.0], dtype=D)
    sstc, ctrl = mod.double_layer(model)
    rec = mod.RecordingTarget(sstc)
    res = run_closed_loop(plant, OpenLoopPredictor(model, Q_Y=0.5, Q_y=1.0), ctrl, rec, v)
    assert float(res.u.abs().max()) <= 0.5 + FEAS_TOL
    assert float(res.du.abs().max()) <= 0.1 + FEAS_TOL
    assert float(res.y.abs().max()) <= mod.CV_HARD
    # the steady-state targets respect the hard limits too, and move by at most du_ss_max
    assert float(res.y_target.abs().max()) <= mod.CV_HARD + FEAS_TOL
    assert float(res.u_target.abs().max()) <= 0.5 + FEAS_TOL
    u_prev = torch.cat([torch.zeros(1, 3, dtype=D), res.u[:-1]])
    assert float((res.u_target - u_prev).abs().max()) <= 0.1 + FEAS_TOL
    # the two highest priorities are met once the loop has settled (y2 >= -0.5, y3 <= 0.5,
    # u3 <= 0.55; then y2 = -0.3)
    assert all(float(r.stage_costs[0]) < FEAS_TOL for r in rec.log[60:])
    assert float(res.y_target[60:, 1].sub(-0.3).abs().max()) < 1e-6


@pytest.mark.slow
def test_double_layer_reproduction_script(tmp_path):
    mod = load_script("reproduce_dmc")
    out = mod.main(["--double-layer", "--out", str(tmp_path), "--steps-31", "250"])
    r = out["section_3_1_double_layer"]
    for name in ("kf", "classical"):
        assert r["max_abs_y"][name] <= mod.CV_HARD
        assert r["max_abs_u"][name] <= 0.5 + FEAS_TOL and r["max_abs_du"][name] <= 0.1 + FEAS_TOL
        assert len(r["steady_states"][name]) == 3
    assert 0.0 < r["max_abs_cv_difference"] < 0.1 * r["cv_range"]  # "practically coincide"
    assert (tmp_path / "results_double_layer.json").stat().st_size > 0
    assert all((tmp_path / f).stat().st_size > 0 for f in out["figures"])
