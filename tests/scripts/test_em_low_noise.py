"""``scripts/em_low_noise.py`` on a simulated, nearly noise-free log (the real logs are not
shipped): its three fits run from the bench's GP start, EM's trace never drops, and every row
reports what the diagnosis reads. Slow (about 30 s: the bench's linear EM and L-BFGS start,
then three GP fits)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from script_support import load_script

pytestmark = pytest.mark.slow

ROWS = ("plain", "R at the boundary (sd 1e-09)", "noise floored (sd >= 0.001)")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    data = tmp_path_factory.mktemp("logs")
    rng = np.random.default_rng(3)
    A = np.array([[1.6, -0.72], [1.0, 0.0]])  # poles 0.8 +- 0.28i
    u, x, y = rng.standard_normal(240), np.zeros(2), np.empty(240)
    for k in range(240):
        y[k] = 0.5 * x[0] + 0.3 * x[1] + 1e-4 * rng.standard_normal()
        x = A @ x + np.array([1.0, 0.0]) * u[k] + 1e-3 * rng.standard_normal(2)
    (data / "robot-arm.csv").write_text(
        "u,y\n" + "".join(f"{a},{b}\n" for a, b in zip(u, y, strict=True))
    )
    out = tmp_path_factory.mktemp("out")
    args = ["--data", str(data), "--out", str(out), "--order", "2", "--block-rows", "6"]
    args += ["--inducing", "4", "--iterations", "3", "--short", "2"]
    assert load_script("em_low_noise").main(args) == 0
    return json.loads((out / "results.json").read_text())


def test_three_fits_from_the_bench_start(results):
    assert tuple(results["rows"]) == ROWS
    lin = results["linear"]
    best = "EM + L-BFGS" if lin["lbfgs_log_likelihood"] > lin["em_log_likelihood"] else "EM"
    assert lin["start"] == best
    starts = [r["initial_log_likelihood"] for r in results["rows"].values()]
    assert all(math.isfinite(s) for s in starts) and len(set(starts)) == 3


def test_plain_em_never_drops_and_reports_every_parameter_group(results):
    plain = results["rows"]["plain"]
    trace = [plain["initial_log_likelihood"], *plain["log_likelihood_trace"]]
    assert len(trace) == plain["iterations"] + 1 <= 4
    assert all(b >= a for a, b in itertools.pairwise(trace))
    assert plain["log_likelihood"] == trace[-1]
    assert plain["last_gain"] == pytest.approx(trace[-1] - trace[-2])
    groups = set(plain["moved"])
    assert {"transition.noise_param.raw_diag", "measurement.noise_param.raw_diag"} <= groups
    assert any(k.startswith("transition.base.") for k in groups)
    assert all(v >= 0 for v in plain["moved"].values())


def test_every_row_has_its_figures(results):
    for name, r in results["rows"].items():
        assert math.isfinite(r["rmse"]) and 0.0 <= r["coverage95"] <= 1.0, name
        assert len(r["noise_sd"]["transition"]) == 2 and len(r["noise_sd"]["measurement"]) == 1
        assert all(s > 0 for s in r["noise_sd"]["transition"] + r["noise_sd"]["measurement"])
        assert r["jitter_warnings"] >= 0 and r["seconds"] > 0
