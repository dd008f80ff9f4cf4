"""The multi-priority steady-state target calculation: priority order on hand-built cases with known
answers, the hard-constraint error, and the economic stage against a brute-force solve."""

import itertools

import numpy as np
import pytest
import torch

from torchfilt.dmc import FOPDT, MultiPriorityTarget, StepResponseModel, TargetRow
from torchfilt.exceptions import ConvergenceWarning, InfeasibleError, InputError, ShapeError

D = torch.float64
R = TargetRow
#: Known answers of the LP stages (HiGHS returns vertices; the economic QP's interior point and its
#: regulariser move them by less than this).
EXACT_TOL = 1e-6
#: The paper's economics reach J_min exactly, where (J - J_min)^2 is flat: the interior-point
#: minimiser is determined to about the square root of the QP tolerance (1e-8; measured 1.1e-5).
J_MIN_TOL = 1e-4
#: Brute-force grid spacing of the economic test (a 2-D move box of width 0.4).
GRID = 401
#: How much worse the grid optimum may be than the exact one (never better): the objective is
#: smooth at the optimum, so about its curvature times the squared spacing (measured: <= 3.1e-6).
GRID_SLACK = 1e-4


def gain_model(G):
    """A stable model whose step response equals the gain ``G`` from the first sample on."""
    G = np.asarray(G, dtype=np.float64)
    Su = np.repeat(G[None], 5, axis=0)
    return StepResponseModel.from_arrays(torch.tensor(Su))


def solve(model, rows, y0, u_prev, **kw):
    kw.setdefault("u_min", -10.0)
    kw.setdefault("u_max", 10.0)
    sstc = MultiPriorityTarget(model, rows, **kw)
    return sstc.solve(torch.tensor(y0, dtype=D), torch.tensor(u_prev, dtype=D))


@pytest.mark.parametrize("limit_first", [True, False])
def test_higher_priority_wins(limit_first):
    m = gain_model([[2.0]])
    p_lim, p_ideal = (1, 2) if limit_first else (2, 1)
    rows = [R(("y", 0), "upper", 0.2, 1.0, p_lim), R(("y", 0), "ideal", 0.5, 1.0, p_ideal)]
    # a third, lowest level so that both rows above are LP stages
    rows.append(R(("u", 0), "ideal", 0.0, 1.0, 3))
    res = solve(m, rows, [0.0], [0.0])
    want = 0.2 if limit_first else 0.5
    assert float(res.y[0]) == pytest.approx(want, abs=EXACT_TOL)
    assert float(res.u[0]) == pytest.approx(want / 2.0, abs=EXACT_TOL)
    relaxed = 1 if limit_first else 0  # the lower-priority row carries the conflict of 0.3
    assert float(res.relaxation[relaxed]) == pytest.approx(0.3, abs=EXACT_TOL)
    assert float(res.relaxation[1 - relaxed]) == pytest.approx(0.0, abs=EXACT_TOL)


@pytest.mark.parametrize(("e_low", "e_high", "want"), [(0.1, 1.0, 0.4), (1.0, 0.1, 0.2)])
def test_equal_concern_errors_within_a_priority(e_low, e_high, want):
    # y >= 0.4 and y <= 0.2 at one priority: the row with the larger equal-concern error gives way
    m = gain_model([[1.0]])
    rows = [
        R(("y", 0), "lower", 0.4, e_low, 1),
        R(("y", 0), "upper", 0.2, e_high, 1),
        R(("u", 0), "ideal", 0.0, 1.0, 2),
    ]
    res = solve(m, rows, [0.0], [0.0])
    assert float(res.y[0]) == pytest.approx(want, abs=EXACT_TOL)
    assert float(res.stage_costs[0]) == pytest.approx(0.2 / max(e_low, e_high), abs=EXACT_TOL)


def test_hard_limits_first_then_priorities_on_the_remaining_freedom():
    G = np.array([[1.0, 2.0], [3.0, -1.0]])
    m = gain_model(G)
    y0, up = np.array([0.1, -0.2]), np.array([0.05, 0.0])
    # priority 1 wants y1 = 10, out of reach: the move box |du| <= 0.1 (hard) makes y1 as large as
    # possible at the vertex du = 0.1 sign(G[0]); nothing is left for priority 2
    rows = [R(("y", 0), "ideal", 10.0, 1.0, 1), R(("y", 1), "ideal", 0.0, 1.0, 2)]
    rows.append(R(("u", 1), "ideal", -5.0, 1.0, 3))
    res = solve(m, rows, y0, up, du_ss_max=0.1)
    du = 0.1 * np.sign(G[0])
    np.testing.assert_allclose(res.du.numpy(), du, atol=EXACT_TOL)
    np.testing.assert_allclose(res.y.numpy(), y0 + G @ du, atol=EXACT_TOL)
    assert any(a.startswith("hard |du1_ss|") for a in res.active)
    # with y1 reachable, priority 1 is met exactly and priority 2 uses the one freedom left
    rows[0] = R(("y", 0), "ideal", 0.2, 1.0, 1)
    res = solve(m, rows, y0, up, du_ss_max=0.1)
    assert float(res.y[0]) == pytest.approx(0.2, abs=EXACT_TOL)
    # two ideal values, two MVs: the unique solution of G du = target - y0 (inside the box)
    du = np.linalg.solve(G, np.array([0.2, 0.0]) - y0)
    assert np.abs(du).max() < 0.1
    np.testing.assert_allclose(res.du.numpy(), du, atol=EXACT_TOL)
    assert float(res.relaxation[2]) > 1.0  # the lowest priority gets nothing


def test_hard_cv_limit_beats_every_soft_row():
    m = gain_model([[1.0, 1.0]])
    rows = [R(("y", 0), "ideal", 0.9, 0.01, 1), R(("u", 0), "ideal", 0.0, 1.0, 2)]
    res = solve(m, rows, [0.0], [0.0, 0.0], y_max=0.5, du_ss_max=1.0)
    assert float(res.y[0]) == pytest.approx(0.5, abs=EXACT_TOL)
    assert "hard y1 upper 0.5" in res.active


def test_infeasible_hard_constraints_raise():
    m = gain_model([[1.0, 0.5]])
    rows = [R(("y", 0), "ideal", 0.0, 1.0, 1)]
    # y1 can reach only [-0.15, 0.15] within |du| <= 0.1 from y0 = 0
    with pytest.raises(InfeasibleError, match=r"y1_ss can only reach \[-0.15, 0.15\]"):
        solve(m, rows, [0.0], [0.0, 0.0], du_ss_max=0.1, y_min=0.5, y_max=0.7)
    # u(k-1) further outside the MV range than one move can recover
    with pytest.raises(InfeasibleError, match=r"u2\(k-1\) = 0.8"):
        solve(m, rows, [0.0], [0.0, 0.8], u_min=-0.5, u_max=0.5, du_ss_max=0.1)
    # a clear TorchfiltError, not a crash, and soft conflicts never raise
    res = solve(m, [*rows, R(("y", 0), "ideal", 1.0, 1.0, 1)], [0.0], [0.0, 0.0], du_ss_max=0.1)
    assert float(res.stage_costs.sum()) > 0.0


def test_bad_arguments():
    m = gain_model([[1.0]])
    with pytest.raises(InputError, match="kind must be ideal, lower or upper"):
        MultiPriorityTarget(m, [R(("y", 0), "hold", 0.0, 1.0, 1)], u_min=-1, u_max=1)
    with pytest.raises(InputError, match="concern must be positive"):
        MultiPriorityTarget(m, [R(("y", 0), "ideal", 0.0, 0.0, 1)], u_min=-1, u_max=1)
    with pytest.raises(InputError, match="minimum_move"):
        MultiPriorityTarget(
            m, [R(("y", 0), "ideal", 0.0, 1.0, 1)], u_min=-1, u_max=1, minimum_move=[3]
        )
    with pytest.raises(InputError, match="stable CVs only"):
        integ = StepResponseModel.from_arrays(torch.ones(5, 1, 1, dtype=D), integrating=[True])
        MultiPriorityTarget(integ, [R(("y", 0), "ideal", 0.0, 1.0, 1)], u_min=-1, u_max=1)
    sstc = MultiPriorityTarget(m, [R(("y", 0), "ideal", 0.0, 1.0, 1)], u_min=-1, u_max=1)
    with pytest.raises(ShapeError, match=r"y_ss: expected shape \(1,\)"):
        sstc.solve(torch.zeros(2, dtype=D), torch.zeros(1, dtype=D))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
@pytest.mark.parametrize("field", ["value", "concern", "priority"])
def test_non_finite_row_fields_are_refused_naming_the_field(field, bad):
    # issue 24: a NaN value reached scipy's linprog ("Invalid input for linprog")
    m = gain_model([[1.0]])
    good = R(("y", 0), "ideal", 0.0, 1.0, 1)
    with pytest.raises(InputError, match=rf"TargetRow\.{field} must be finite"):
        R(**{**good._asdict(), field: bad})
    # rows that bypass the constructor (_replace, a plain tuple) are checked by the target
    for row in (good._replace(**{field: bad}), tuple(good._replace(**{field: bad}))):
        with pytest.raises(InputError, match=rf"rows\[1\]\.{field} must be finite"):
            MultiPriorityTarget(m, [good, row], u_min=-1, u_max=1)


def test_non_finite_bounds_weights_and_inputs_are_refused():
    m = gain_model([[1.0, 2.0]])
    rows = [R(("y", 0), "ideal", 0.0, 1.0, 1)]
    nan, inf = float("nan"), float("inf")
    cases = [
        ({"u_min": inf}, "u_min must be finite or -inf"),
        ({"u_max": -inf}, "u_max must be finite or \\+inf"),
        ({"u_min": nan}, "u_min contains NaN"),
        ({"y_max": nan}, "y_max contains NaN"),
        ({"du_ss_max": nan}, "du_ss_max contains NaN"),
        ({"cost": [1.0, inf]}, "cost must be finite"),
        ({"J_min": nan}, "J_min must be finite"),
        ({"economic_weight": inf}, "economic_weight must be finite"),
        ({"minimum_move": [0.5]}, "minimum_move"),
    ]
    for kw, match in cases:
        with pytest.raises(InputError, match=match):
            MultiPriorityTarget(m, rows, **{"u_min": -1.0, "u_max": 1.0, **kw})
    with pytest.raises(
        InputError, match=r"TargetRow\.variable: the linear weights must be a finite"
    ):
        R(("lin", [1.0, nan, 0.0]), "ideal", 0.0, 1.0, 1)
    sstc = MultiPriorityTarget(m, rows, u_min=-1.0, u_max=1.0)
    with pytest.raises(InputError, match="y_ss must be finite"):
        sstc.solve(torch.tensor([nan], dtype=D), torch.zeros(2, dtype=D))
    with pytest.raises(InputError, match="u_prev must be finite"):
        sstc.solve(torch.zeros(1, dtype=D), torch.tensor([0.0, inf], dtype=D))


def test_paper_economics_reach_j_min():
    # h = [-2, 1, 2], u2 minimum-move, |du_ss| <= 0.1 and nothing else binding: J_min = -0.4 is
    # reached at du = [0.1, 0, -0.1]
    m = StepResponseModel.from_transfer_functions(
        [[FOPDT(1.0, 5.0, 0.0), FOPDT(0.5, 5.0, 0.0), FOPDT(0.2, 5.0, 0.0)]], dt=1.0, horizon=60
    )
    rows = [R(("y", 0), "upper", 5.0, 1.0, 1), R(("y", 0), "lower", -5.0, 1.0, 2)]
    res = solve(
        m,
        rows,
        [0.0],
        [0.0, 0.0, 0.0],
        u_min=-0.5,
        u_max=0.5,
        du_ss_max=0.1,
        cost=[-2.0, 1.0, 2.0],
        minimum_move=[1],
        J_min=-0.4,
    )
    np.testing.assert_allclose(res.du.numpy(), [0.1, 0.0, -0.1], atol=J_MIN_TOL)
    assert res.economic == pytest.approx(-0.4, abs=J_MIN_TOL)


def brute_force_objective(G, y0, up, rows_p1, rows_low, h, mm, J_min, box):
    """min over a grid of du of (J - J_min)^2 + sum_low (eps / e)^2, subject to the priority-1 rows
    (satisfiable here, so their relaxations are zero) and the box."""
    axes = [np.linspace(-box, box, GRID)] * 2
    du = np.array(list(itertools.product(*axes)))  # (GRID^2, 2)
    y = y0 + du @ G.T
    u = up + du
    vals = np.concatenate([y, u], axis=1)
    ok = np.ones(len(du), dtype=bool)
    for r in rows_p1:
        col = r.variable[1] + (0 if r.variable[0] == "y" else 2)
        ok &= vals[:, col] <= r.value if r.kind == "upper" else vals[:, col] >= r.value
    J = sum(h[i] * (np.abs(du[:, i]) if i in mm else du[:, i]) for i in range(2))
    obj = (J - J_min) ** 2
    for r in rows_low:
        col = r.variable[1] + (0 if r.variable[0] == "y" else 2)
        x = vals[:, col]
        if r.kind == "ideal":
            e = np.abs(x - r.value)
        elif r.kind == "upper":
            e = np.maximum(x - r.value, 0.0)
        else:
            e = np.maximum(r.value - x, 0.0)
        obj = obj + (e / r.concern) ** 2
    return float(obj[ok].min())


@pytest.mark.parametrize("case", range(3))
def test_economic_stage_matches_brute_force(case):
    rng = np.random.default_rng(case)
    G = rng.uniform(0.5, 2.0, (2, 2)) * np.array([[1.0, -1.0], [1.0, 1.0]])
    y0 = rng.uniform(-0.2, 0.2, 2)
    up = rng.uniform(-0.1, 0.1, 2)
    h = rng.uniform(-2.0, 2.0, 2)
    mm = [1] if case != 1 else []
    rows_p1 = [
        R(("y", 0), "upper", float(y0[0] + 0.15), 0.2, 1),
        R(("y", 1), "lower", -0.4, 0.2, 1),
    ]
    rows_low = [
        R(("y", 1), "ideal", float(y0[1] + 0.1), 0.25, 2),
        R(("u", 0), "upper", 0.0, 0.5, 2),
    ]
    box = 0.2
    sstc = MultiPriorityTarget(
        gain_model(G),
        rows_p1 + rows_low,
        u_min=-10.0,
        u_max=10.0,
        du_ss_max=box,
        cost=h,
        minimum_move=mm,
        J_min=-1.0,
    )
    res = sstc.solve(torch.tensor(y0), torch.tensor(up))
    assert float(res.stage_costs[0]) == pytest.approx(0.0, abs=EXACT_TOL)  # priority 1 is met
    du = res.du.numpy()
    J = sum(h[i] * (abs(du[i]) if i in mm else du[i]) for i in range(2))
    assert res.economic == pytest.approx(J, abs=EXACT_TOL)
    ours = (J + 1.0) ** 2
    y = y0 + G @ du
    vals = np.concatenate([y, up + du])
    for r in rows_low:
        col = r.variable[1] + (0 if r.variable[0] == "y" else 2)
        x = vals[col]
        e = abs(x - r.value) if r.kind == "ideal" else max(x - r.value, 0.0)
        ours += (e / r.concern) ** 2
    brute = brute_force_objective(G, y0, up, rows_p1, rows_low, h, mm, -1.0, box)
    assert ours <= brute + EXACT_TOL  # the exact optimum is never worse than a grid point
    assert brute - ours <= GRID_SLACK  # and the grid gets close to it


@pytest.mark.parametrize("levels", [2, 1])
def test_a_failed_economic_qp_falls_back_to_the_feasibility_answer(monkeypatch, levels):
    import torchfilt.dmc.sstc as sstc_module

    m = gain_model([[2.0]])
    rows = [R(("y", 0), "upper", 0.2, 1.0, 1), R(("y", 0), "ideal", 0.5, 1.0, levels)]

    def failing(G, c, A, b, **kw):
        return np.zeros(G.shape[0]), np.zeros(A.shape[0]), False, 200

    monkeypatch.setattr(sstc_module, "solve_one", failing)
    with pytest.warns(ConvergenceWarning, match="economic QP did not converge"):
        res = solve(m, rows, [0.0], [0.0], y_min=-0.7, y_max=0.7)
    if levels == 2:  # the answer of the priority-1 LP: its row holds
        assert float(res.y[0]) <= 0.2 + EXACT_TOL
    assert -0.7 - EXACT_TOL <= float(res.y[0]) <= 0.7 + EXACT_TOL  # hard limits hold either way
