"""Hypothesis suites over OpenLoopPredictor (issue 12): run / update against the recursion written
out in NumPy, with missing (non-finite) measurements; bad gains, states and shapes refused; and over
the multi-priority steady-state target calculation (issue 24): TargetRow fields, bounds and inputs
with NaN / inf / out-of-range values are refused naming the field, and every answer is checked
against the hard constraints, the rows' violations and an independent LP for the first priority.
See tests/fuzz_support.py for the contract."""

from __future__ import annotations

import clarabel
import numpy as np
import pytest
import scipy.sparse as sp
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.dmc import (
    FOPDT,
    IPDT,
    MultiPriorityTarget,
    OpenLoopPredictor,
    StepResponseModel,
    TargetRow,
)
from torchfilt.exceptions import InputError

D = torch.float64
#: the same linear recursion evaluated in a different order (float64), relative to its scale
EXACT_RTOL = 1e-9


def _reference(pred: OpenLoopPredictor, y, du, dv, x0) -> tuple[np.ndarray, np.ndarray]:
    r = pred.realization
    A, B, Bv, H, K = (t.numpy() for t in (r.A, r.B, r.Bv, r.H, pred.gain))
    x = x0.copy()
    xs, es = [], []
    for k in range(y.shape[0]):
        xp = A @ x + B @ du[k] + Bv @ dv[k]
        e = y[k] - H @ xp
        ok = np.isfinite(y[k])
        x = xp + K[:, ok] @ e[ok]
        xs.append(x)
        es.append(np.where(ok, e, np.nan))
    return np.array(xs), np.array(es)


def check_predictor(data: st.DataObject) -> None:
    ny = data.draw(st.integers(1, 2), label="ny")
    nu = data.draw(st.integers(1, 2), label="nu")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    Gu = []
    for _ in range(ny):
        row = []
        for _ in range(nu):
            K = float(rng.uniform(-2, 2))
            if rng.uniform() < 0.3:
                row.append(IPDT(0.2 * K, float(rng.uniform(0, 2))))
            else:
                row.append(FOPDT(K, float(rng.uniform(0.5, 5)), float(rng.uniform(0, 2))))
        Gu.append(row)
    Gv = [[FOPDT(float(rng.uniform(-1, 1)), 2.0, 0.0)] for _ in range(ny)]
    N = data.draw(st.integers(3, 12), label="horizon")
    model = StepResponseModel.from_transfer_functions(Gu, Gv, dt=1.0, horizon=N)
    how = data.draw(st.sampled_from(["kalman", "kalman", "classical", "gain"]), label="how")
    bad_param = data.draw(st.sampled_from([None, None, None, "nan", "inf", "negative"]))
    if how == "kalman":
        qY = (
            0.3
            if bad_param is None
            else {"nan": np.nan, "inf": np.inf, "negative": -1.0}[bad_param]
        )
        pred, _ = attempt("OpenLoopPredictor", OpenLoopPredictor, model, Q_Y=qY, Q_y=1.0)
    elif how == "classical":
        h = (
            1.0
            if bad_param is None
            else {"nan": np.nan, "inf": np.inf, "negative": -1.0}[bad_param]
        )
        pred, _ = attempt("OpenLoopPredictor.classical", OpenLoopPredictor.classical, model, h)
    else:
        n = OpenLoopPredictor.classical(model).state_dim
        K = torch.tensor(rng.uniform(0, 0.5, (n, ny)), dtype=D)
        if bad_param in ("nan", "inf"):
            K[0, 0] = float(bad_param)
        pred, _ = attempt("OpenLoopPredictor(gain=)", OpenLoopPredictor, model, gain=K)
    if isinstance(pred, Refused):
        assert bad_param is not None, pred
        return
    assert bad_param in (None, "negative"), f"a {bad_param} parameter was accepted"
    T = data.draw(st.integers(0, 8), label="T")
    y = rng.standard_normal((T, ny)) * 10.0 ** rng.uniform(-2, 3)
    fill = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]), label="fill")
    y[rng.uniform(size=y.shape) < data.draw(st.sampled_from([0.0, 0.3, 1.0]))] = fill
    du = rng.standard_normal((T, nu))
    dv = rng.standard_normal((T, 1))
    x0 = pred.initial_state(float(rng.uniform(-3, 3))).numpy()
    bad_x0 = data.draw(st.sampled_from([None, None, "nan", "shape"]), label="bad x0")
    if bad_x0 == "nan":
        x0[0] = np.nan
    elif bad_x0 == "shape":
        x0 = np.zeros(x0.shape[0] + 1)
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    y_dtype = data.draw(
        st.sampled_from(
            [D, D, D, D, torch.float32, torch.float16, torch.bfloat16, torch.complex128]
        ),
        label="y dtype",
    )
    if y_dtype != D:
        yd = torch.tensor(y, dtype=y_dtype)
        out, _ = attempt("OpenLoopPredictor.run (dtype)", pred.run, yd, t(du), t(dv))
        if y_dtype == torch.float32:
            # converted to the model's dtype: the same recursion on the float32-rounded data
            if not isinstance(out, Refused):
                assert T > 0
                xr, _ = _reference(pred, yd.double().numpy(), du, dv, pred.initial_state().numpy())
                sc = max(1.0, np.abs(xr).max())
                np.testing.assert_allclose(out.states.numpy(), xr, rtol=0, atol=EXACT_RTOL * sc)
            else:
                assert T == 0, out
        else:
            assert isinstance(out, Refused) and isinstance(out.error, InputError), out
    run, _ = attempt("OpenLoopPredictor.run", pred.run, t(y), t(du), t(dv), x0=t(x0))
    if isinstance(run, Refused):
        assert T == 0 or bad_x0 is not None, run
        assert isinstance(run.error, InputError)
        return
    assert T > 0 and bad_x0 is None, "an empty recording or a bad x0 was accepted"
    xs, es = _reference(pred, y, du, dv, x0)
    scale = max(1.0, np.abs(xs).max())
    np.testing.assert_allclose(run.states.numpy(), xs, rtol=0, atol=EXACT_RTOL * scale)
    np.testing.assert_array_equal(np.isnan(run.innovations.numpy()), np.isnan(es))
    assert torch.isfinite(run.predictions).all()
    # the online path agrees with the offline run
    pred.reset(t(x0))
    for k in range(T):
        out, _ = attempt("OpenLoopPredictor.update", pred.update, t(y[k]), t(du[k]), t(dv[k]))
        assert not isinstance(out, Refused), out
    np.testing.assert_allclose(pred.state.numpy(), xs[-1], rtol=0, atol=EXACT_RTOL * scale)


test_fuzz_predictor, test_fuzz_predictor_long = property_tests(check_predictor, short=6, long=400)


# ------------------------------------------------------------------------------------------ SSTC
#: The answer's hard constraints and first-priority cost hold to this (the LP vertex, the economic
#: QP's interior point and the later stages' relaxation margins, relative to 1 + |value|).
SSTC_TOL = 1e-6
#: A value that is never valid for a numeric field of a row, drawn with the valid ones.
_BAD_NUMBERS = [float("nan"), float("inf"), float("-inf")]


#: Where one invalid value is put (or nowhere: about half the cases are valid throughout).
_SITES = [
    *[None] * 16,
    "value",
    "concern",
    "priority",
    "kind",
    "weights",
    "u_min",
    "u_max",
    "y_min",
    "y_max",
    "du_ss_max",
    "cost",
    "J_min",
    "economic_weight",
    "y_ss",
    "u_prev",
]


def _maybe_bad(data, label, good, bad, inject: bool):
    """``(value, is_bad)``: a draw of ``bad`` where ``inject``, else of ``good``."""
    if inject:
        return data.draw(st.sampled_from(bad), label=label), True
    return data.draw(good, label=label), False


def _draw_row(data, k: int, ny: int, nu: int, site: str | None, expect: list[str]):
    """One soft row (built as a TargetRow, a plain tuple, or a TargetRow edited by _replace), with
    the invalid value of ``site`` if any; the message substrings that would name it go into
    ``expect``."""
    via = data.draw(st.sampled_from(["TargetRow", "TargetRow", "tuple", "_replace"]), label="via")
    names = {"TargetRow": ("TargetRow", f"rows[{k}]")}.get(via, (f"rows[{k}]",))
    kind = data.draw(st.sampled_from(["ideal", "lower", "upper"]), label="kind")
    if site == "kind":
        kind = data.draw(st.sampled_from(["hold", "hold", "minimum", 3]), label="bad kind")
        expect += [f"{n}.kind" for n in names]
    if kind == "hold":  # a valid TargetRow kind, but not one the SSTC takes
        expect.append(f"rows[{k}].kind")
    which = "lin" if site == "weights" else data.draw(st.sampled_from(["y", "u", "lin"]))
    if which == "lin":
        w = [data.draw(st.floats(-2, 2), label="weight") for _ in range(ny + nu)]
        bad = data.draw(st.sampled_from(["nan", "length"])) if site == "weights" else None
        if bad == "nan":
            w[0] = float("nan")
            expect += [f"{n}.variable" for n in names]
        elif bad == "length":
            w.append(1.0)
            expect.append(f"rows[{k}]")
        variable = ("lin", w)
    else:
        variable = (which, data.draw(st.integers(0, (ny if which == "y" else nu) - 1)))
    value, bad_v = _maybe_bad(data, "value", st.floats(-3, 3), _BAD_NUMBERS, site == "value")
    concern, bad_c = _maybe_bad(
        data, "concern", st.floats(0.05, 5), [*_BAD_NUMBERS, 0.0, -1.0], site == "concern"
    )
    priority, bad_p = _maybe_bad(
        data, "priority", st.integers(1, 3), [*_BAD_NUMBERS, 0, -1, 1.5, True], site == "priority"
    )
    for field, bad in (("value", bad_v), ("concern", bad_c), ("priority", bad_p)):
        if bad:  # 0 / -1 / 1.5 pass the TargetRow check and are the target's to refuse
            expect += [f"{n}.{field}" for n in (*names, f"rows[{k}]")]
    fields = (variable, kind, value, concern, priority)
    if via == "tuple":
        return fields
    if via == "_replace":  # _replace bypasses TargetRow's check: the target must catch it
        base = TargetRow(("y", 0), "ideal", 0.0, 1.0, 1)
        return base._replace(
            variable=variable, kind=kind, value=value, concern=concern, priority=priority
        )
    out, _ = attempt("TargetRow", TargetRow, *fields)
    return out


def _row_values(rows, F: np.ndarray, g: np.ndarray, du: np.ndarray) -> np.ndarray:
    """Each row's violation at ``du`` (rows are ``f = F du + g``)."""
    f = F @ du + g
    out = []
    for r, fr in zip(rows, f, strict=True):
        if r.kind == "lower":
            out.append(max(r.value - fr, 0.0))
        elif r.kind == "upper":
            out.append(max(fr - r.value, 0.0))
        else:
            out.append(abs(fr - r.value))
    return np.array(out)


def _first_priority_reference(rows, F, g, lo, hi, G, y0, y_lim, p: int) -> float:
    """min sum eps_r / e_r over the rows of priority ``p`` subject to the hard constraints, by
    Clarabel (an interior-point method; the SSTC solves its LP stages with HiGHS)."""
    sel = [i for i, r in enumerate(rows) if r.priority == p]
    nu, ns = F.shape[1], len(sel)
    A, b = [], []
    for i, r in enumerate(rows[k] for k in sel):
        signs = (-1.0, 1.0) if r.kind == "ideal" else ((-1.0,) if r.kind == "lower" else (1.0,))
        for sign in signs:  # sign (F du + g - v) <= eps
            row = np.zeros(nu + ns)
            row[:nu], row[nu + i] = sign * F[sel[i]], -1.0
            A.append(row)
            b.append(sign * (r.value - g[sel[i]]))
    for j in range(nu + ns):
        bounds = (lo[j], hi[j]) if j < nu else (0.0, np.inf)
        for sign, v in ((-1.0, -bounds[0]), (1.0, bounds[1])):
            if np.isfinite(v):
                row = np.zeros(nu + ns)
                row[j] = sign
                A.append(row)
                b.append(v)
    for j, (ymin, ymax) in enumerate(y_lim):
        for sign, v in ((1.0, ymax - y0[j]), (-1.0, y0[j] - ymin)):
            if np.isfinite(v):
                row = np.zeros(nu + ns)
                row[:nu] = sign * G[j]
                A.append(row)
                b.append(v)
    c = np.concatenate([np.zeros(nu), [1.0 / rows[k].concern for k in sel]])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(
        sp.csc_matrix((nu + ns, nu + ns)),
        c,
        sp.csc_matrix(np.array(A)),
        np.array(b),
        [clarabel.NonnegativeConeT(len(b))],
        settings,
    )
    sol = solver.solve()
    assert sol.status == clarabel.SolverStatus.Solved, sol.status
    return float(c @ np.asarray(sol.x))


def _draw_bounds(data, y0: np.ndarray, up: np.ndarray, site: str | None, expect: list[str]) -> dict:
    """Bounds that keep ``du = 0`` feasible (so a refusal of valid input is a bug), but for the
    invalid one at ``site``."""
    ny, nu = y0.size, up.size
    kw: dict = {}
    for name, centre, sign in (
        ("u_min", up, -1.0),
        ("u_max", up, 1.0),
        ("y_min", y0, -1.0),
        ("y_max", y0, 1.0),
    ):
        none_ok = name.startswith("y")
        wrong = [float("nan"), -sign * float("inf")]
        gap, bad = _maybe_bad(data, name, st.floats(0.05, 2.0), wrong, site == name)
        if bad:
            expect.append(name)
            kw[name] = gap
        elif none_ok and data.draw(st.booleans(), label=f"{name} none"):
            kw[name] = None
        else:
            kw[name] = torch.tensor(centre + sign * gap, dtype=D)
    dmax, bad = _maybe_bad(
        data, "du_ss_max", st.floats(0.05, 1.0), [float("nan"), -1.0], site == "du_ss_max"
    )
    if bad:
        expect.append("du_ss_max")
    kw["du_ss_max"] = None if not bad and data.draw(st.booleans(), label="no du max") else dmax
    h = [data.draw(st.floats(-2, 2), label="cost") for _ in range(nu)]
    if site == "cost":
        h[0] = data.draw(st.sampled_from(_BAD_NUMBERS))
        expect.append("cost")
    kw["cost"] = h
    kw["minimum_move"] = [i for i in range(nu) if data.draw(st.booleans(), label="mm")]
    kw["J_min"], bad = _maybe_bad(data, "J_min", st.floats(-1, 0), _BAD_NUMBERS, site == "J_min")
    if bad:
        expect.append("J_min")
    kw["economic_weight"], bad = _maybe_bad(
        data, "w_J", st.floats(0, 2), [*_BAD_NUMBERS, -1.0], site == "economic_weight"
    )
    if bad:
        expect.append("economic_weight")
    del ny
    return kw


def _check_answer(res, rows, sstc, y0, up, kw) -> None:
    """The answer against its definition, computed here in NumPy."""
    G = sstc.G
    du, y, u = res.du.numpy(), res.y.numpy(), res.u.numpy()
    assert np.isfinite(du).all() and np.isfinite(y).all() and np.isfinite(u).all()
    np.testing.assert_allclose(u, up + du, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, y0 + G @ du, rtol=0, atol=1e-12 * (1 + np.abs(y).max()))
    tol = SSTC_TOL * (1 + np.abs(np.concatenate([y, u])).max())
    assert (u >= sstc.u_min - tol).all() and (u <= sstc.u_max + tol).all(), (u, kw)
    assert (np.abs(du) <= sstc.du_max + tol).all(), (du, kw)
    assert (y >= sstc.y_min - tol).all() and (y <= sstc.y_max + tol).all(), (y, kw)
    ny, nu = y0.size, up.size
    a = np.zeros((len(rows), ny + nu))
    for i, r in enumerate(rows):
        name, idx = r.variable
        if name == "lin":
            a[i] = idx
        else:
            a[i, idx if name == "y" else ny + idx] = 1.0
    F, g = a[:, :ny] @ G + a[:, ny:], a[:, :ny] @ y0 + a[:, ny:] @ up
    viol = _row_values(rows, F, g, du)
    np.testing.assert_allclose(res.relaxation.numpy(), viol, rtol=0, atol=1e-9 * (1 + viol.max()))
    levels = sorted({int(r.priority) for r in rows})
    if len(levels) > 1:  # the first LP stage is optimal, and later stages keep its answer
        lo = np.maximum(sstc.u_min - up, -sstc.du_max)
        hi = np.minimum(sstc.u_max - up, sstc.du_max)
        y_lim = list(zip(sstc.y_min, sstc.y_max, strict=True))
        ref = _first_priority_reference(rows, F, g, lo, hi, G, y0, y_lim, levels[0])
        top = [i for i, r in enumerate(rows) if r.priority == levels[0]]
        got = float(sum(viol[i] / rows[i].concern for i in top))
        assert float(res.stage_costs[0]) == pytest.approx(ref, abs=SSTC_TOL * (1 + ref))
        assert got <= ref + 10 * SSTC_TOL * (1 + ref), (got, ref)


def check_sstc(data: st.DataObject) -> None:
    ny = data.draw(st.integers(1, 2), label="ny")
    nu = data.draw(st.integers(1, 2), label="nu")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    G = rng.uniform(-2, 2, (ny, nu))
    model = StepResponseModel.from_arrays(torch.tensor(np.repeat(G[None], 4, axis=0)))
    y0, up = rng.uniform(-1, 1, ny), rng.uniform(-1, 1, nu)
    expect: list[str] = []
    site = data.draw(st.sampled_from(_SITES), label="invalid")
    n_rows = data.draw(st.integers(1, 4), label="rows")
    at = data.draw(st.integers(0, n_rows - 1), label="invalid row")
    rows = []
    for k in range(n_rows):
        row = _draw_row(data, k, ny, nu, site if k == at else None, expect)
        if isinstance(row, Refused):
            assert any(e in str(row.error) for e in expect), (row, expect)
            return
        rows.append(row)
    kw = _draw_bounds(data, y0, up, site, expect)
    sstc, _ = attempt("MultiPriorityTarget", MultiPriorityTarget, model, rows, **kw)
    y_in, u_in = torch.tensor(y0), torch.tensor(up)
    if not isinstance(sstc, Refused):
        if site in ("y_ss", "u_prev"):
            expect.append(site)
            (y_in if site == "y_ss" else u_in)[0] = data.draw(st.sampled_from(_BAD_NUMBERS))
        res, _ = attempt("MultiPriorityTarget.solve", sstc.solve, y_in, u_in)
    else:
        res = sstc
    if isinstance(res, Refused):
        assert isinstance(res.error, InputError), res
        assert any(e in str(res.error) for e in expect), (res, expect)
        return
    assert not expect, f"accepted although {expect} should have been refused"
    _check_answer(res, [TargetRow(*r) for r in rows], sstc, y0, up, kw)


test_fuzz_sstc, test_fuzz_sstc_long = property_tests(check_sstc, short=80, long=400)


def teardown_module() -> None:
    print_stats()
