"""Hypothesis suite over OpenLoopPredictor (issue 12): run / update against the recursion written
out in NumPy, with missing (non-finite) measurements; bad gains, states and shapes refused. See
tests/fuzz_support.py for the contract."""

from __future__ import annotations

import numpy as np
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.dmc import FOPDT, IPDT, OpenLoopPredictor, StepResponseModel
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


def teardown_module() -> None:
    print_stats()
