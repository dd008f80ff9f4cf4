"""``scripts/bench_real_logs.py``: its two log layouts, the standardisation, and the N4SID
baseline's free run, checked on a simulated stable system (the real logs are not shipped)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from script_support import load_script


@pytest.fixture(scope="module")
def brl():
    return load_script("bench_real_logs")


def _simulate(T: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """A stable second-order system driven by a random input: ``(u, y)``."""
    rng = np.random.default_rng(seed)
    A = np.array([[1.6, -0.72], [1.0, 0.0]])  # poles 0.8 +- 0.28i
    B, C = np.array([1.0, 0.0]), np.array([0.5, 0.3])
    u = rng.standard_normal(T)
    x, y = np.zeros(2), np.empty(T)
    for k in range(T):
        y[k] = C @ x + noise * rng.standard_normal()
        x = A @ x + B * u[k]
    return u, y


def simulated_log_args(folder: Path) -> tuple[Path, list[str]]:
    """A simulated stable log (450 samples, noise 5% of the output) written as
    ``folder/robot-arm.csv``, and the output folder and arguments of a bench script run on it
    (order 2)."""
    u, y = _simulate(450, 2, 0.05)
    (folder / "robot-arm.csv").write_text(
        "u,y\n" + "".join(f"{a},{b}\n" for a, b in zip(u, y, strict=True))
    )
    out = folder / "out"
    return out, ["--data", str(folder), "--out", str(out), "--logs", "robot-arm", "--order", "2"]


def test_both_layouts_and_the_training_standardisation(brl, tmp_path):
    u, y = _simulate(300, 0, 0.01)
    single = tmp_path / "one.csv"
    single.write_text("u,y\n" + "".join(f"{a},{b}\n" for a, b in zip(u, y, strict=True)))
    parts = brl.read_log(single, ("u", "y"))
    k = int(300 * brl.TRAIN_SHARE)
    assert [len(p) for p in parts] == [k, k, 300 - k, 300 - k]
    np.testing.assert_array_equal(parts[3], y[k:])
    split = tmp_path / "two.csv"
    rows = ["uEst,uVal,yEst,yVal,Ts"] + [
        f"{u[i]},{u[150 + i]},{y[i]},{y[150 + i]},{4 if i == 0 else ''}" for i in range(150)
    ]
    split.write_text("\n".join(rows) + "\n")
    u_tr, y_tr, u_te, y_te = brl.read_log(split, ("uEst", "yEst", "uVal", "yVal"))
    np.testing.assert_array_equal(y_te, y[150:])
    tu, ty, _vu, vy = brl.standardised(u_tr, y_tr, u_te, y_te)
    assert tu.shape == (1, 150, 1)
    assert float(ty.mean()) == pytest.approx(0.0, abs=1e-12)
    assert float(ty.std(unbiased=False)) == pytest.approx(1.0, rel=1e-12)
    # the held-out part uses the training part's scale, not its own
    np.testing.assert_allclose(vy.reshape(-1).numpy(), (y_te - y_tr.mean()) / y_tr.std())


def test_n4sid_baseline_free_runs_a_stable_system(brl):
    u, y = _simulate(900, 1, 0.01)
    tu, ty, vu, vy = brl.standardised(u[:600], y[:600], u[600:], y[600:])
    row = brl.n4sid_row(tu, ty, vu, vy, order=2, rows=10, burn=20)
    # the noise is 1% of the output: the free run tracks it closely, far below its spread (1)
    assert math.isfinite(row["rmse"]) and row["rmse"] < 0.1
    assert row["coverage95"] is None
    # a model of the wrong system does not: the check can fail
    bad = brl.n4sid_row(tu, ty, vu, -vy, order=2, rows=10, burn=20)
    assert bad["rmse"] > 0.5


@pytest.mark.slow
def test_main_on_a_simulated_log(brl, tmp_path):
    import json

    out, args = simulated_log_args(tmp_path)
    assert brl.main([*args, "--inducing", "4", "--block-rows", "10"]) == 0
    res = json.loads((out / "bench_real_logs.json").read_text())["logs"]["robot-arm"]["rows"]
    assert set(res) == {
        "N4SID (nfoursid)", "torchfilt subspace", "torchfilt subspace + EM",
        "torchfilt subspace + EM + L-BFGS", "torchfilt GP (measurement only)",
        "torchfilt subspace, stable=True", "torchfilt GP (measurement only, accelerate=True)",
    }  # fmt: skip
    accel, gp = (
        res["torchfilt GP (measurement only, accelerate=True)"],
        res["torchfilt GP (measurement only)"],
    )
    assert accel["e_steps"] > accel["iterations"]  # the cycles ran
    # SQUAREM never ends below plain EM's two steps per cycle; against 30 plain iterations it
    # has run more M-steps, so it must not end lower
    assert accel["log_likelihood"] >= gp["log_likelihood"] - 1e-6
    assert res["torchfilt subspace + EM + L-BFGS"]["stopped"] == "converged"
    lbfgs, em = res["torchfilt subspace + EM + L-BFGS"], res["torchfilt subspace + EM"]
    assert lbfgs["log_likelihood"] >= em["log_likelihood"] - 1e-6
    for name, row in res.items():
        assert math.isfinite(row["rmse"]) and row["rmse"] < 0.3, (name, row)
        if name.startswith("torchfilt subspace") and "EM" not in name:
            continue
        if name.startswith("torchfilt"):
            # the likelihood fits' noise covers the output (the subspace start's need not)
            assert 0.8 <= row["coverage95"] <= 1.0, (name, row)


def test_free_run_row_against_a_random_walk_in_closed_form(brl):
    """``torchfilt_row`` on a scalar random walk with no burn-in: the output's free-run variance
    at step ``t`` is ``P0 + (t + 1) q + r``, so the RMSE, the 95% coverage and the mean squared
    error over the variance follow in closed form."""
    import torch

    from torchfilt.models import LinearGaussianModel

    D = torch.float64
    q, r, p0, T = 0.3, 0.1, 2.0, 60
    one = torch.ones(1, 1, dtype=D)
    model = LinearGaussianModel(one, one, q * one, r * one, torch.zeros(1, 1, dtype=D))
    g = torch.Generator().manual_seed(4)
    y = torch.randn(1, T, 1, generator=g, dtype=D) * 2.0
    u = torch.randn(1, T, 1, generator=g, dtype=D)  # B = 0: the inputs do nothing
    row = brl.torchfilt_row(model, y, u, p0 * one, 0)
    var = p0 + (torch.arange(T, dtype=D) + 1) * q + r
    e = y[0, :, 0]
    assert row["rmse"] == pytest.approx(float(e.pow(2).mean().sqrt()), rel=1e-12)
    assert row["error_over_variance"] == pytest.approx(float((e**2 / var).mean()), rel=1e-12)
    inside = (e.abs() <= 1.959963984540054 * var.sqrt()).to(D).mean()
    assert row["coverage95"] == pytest.approx(float(inside), abs=1e-12)
