"""The Van der Pol case of ``scripts/reproduce_measurement_only.py`` (``_oscillator_case.py``):
its evaluation against numpy and closed forms, its simulation against its stated noise, and a
tiny end-to-end run (a raised ``FitError`` is a row, not a crash)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from script_support import load_script

from torchfilt.exceptions import FitError


@pytest.fixture(scope="module")
def oc():
    return load_script("_oscillator_case")


def test_metrics_match_numpy(oc):
    g = torch.Generator().manual_seed(0)
    R, T, n = 4, 7, 2
    x = torch.randn(R, T, n, generator=g, dtype=torch.float64)
    mean = x + 0.3 * torch.randn(R, T, n, generator=g, dtype=torch.float64)
    A = torch.randn(R, T, n, n, generator=g, dtype=torch.float64)
    cov = A @ A.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    ll = torch.randn(R, generator=g, dtype=torch.float64)
    mean[2, 3, 0] = float("nan")  # run 2 is left out
    out = oc.metrics(mean, cov, x, ll, burn=3)
    keep = [0, 1, 3]
    e = (mean.numpy() - x.numpy())[keep]
    P = cov.numpy()[keep]
    nees = np.einsum("rti,rti->rt", e, np.linalg.solve(P, e[..., None])[..., 0])
    assert out["finite_runs"] == 3
    assert out["rmse"] == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-12)
    assert out["rmse_per_state"] == pytest.approx(np.sqrt(np.mean(e**2, axis=(0, 1))), rel=1e-12)
    assert out["nees"] == pytest.approx(nees.mean(), rel=1e-10)
    assert out["rmse_after_burn"] == pytest.approx(np.sqrt(np.mean(e[:, 3:] ** 2)), rel=1e-12)
    assert out["nees_after_burn"] == pytest.approx(nees[:, 3:].mean(), rel=1e-10)
    assert out["nees_median"] == pytest.approx(np.median(nees), rel=1e-10)
    assert out["log_predictive_density"] == pytest.approx(ll.numpy()[keep].sum() / (3 * T))


def test_nees_band_closed_form(oc):
    # chi-square with 2 degrees of freedom is exponential with mean 2: ppf(p) = -2 log(1 - p)
    lo, hi = oc.nees_band(2, 1)
    assert lo == pytest.approx(-2 * math.log(0.975), rel=1e-10)
    assert hi == pytest.approx(-2 * math.log(0.025), rel=1e-10)
    lo, hi = oc.nees_band(2, 4000)  # a mean of many: about 2 +- 1.96 sqrt(2 * 2 / 4000)
    assert lo == pytest.approx(2 - 1.96 * math.sqrt(1e-3), abs=2e-3)
    assert hi == pytest.approx(2 + 1.96 * math.sqrt(1e-3), abs=2e-3)


def test_simulation_has_the_stated_noise(oc):
    sim = oc.simulate(4, 500, seed=3)
    w = sim.states[:, 1:] - oc.vdp_step(sim.states[:, :-1])
    v = sim.measurements - oc.sensor(sim.states)
    assert w.reshape(-1, 2).std(0).numpy() == pytest.approx([oc.Q_STD] * 2, rel=0.05)
    assert v.reshape(-1, 2).var(0).numpy() == pytest.approx(oc.R.diagonal().numpy(), rel=0.1)


def test_tiny_case_runs_and_reports_a_fit_error(oc, monkeypatch):
    out = oc.oscillator_case(30, 2, 0, state_iterations=3, iterations=1)
    rows = out["rows"]
    assert math.isfinite(rows["true model"]["nees"])
    ref = rows[oc.STATE_ROW]["rmse"]
    for row in rows.values():
        assert row["rmse_ratio_to_state_trained"] == pytest.approx(row["rmse"] / ref)
    for m in ("em", "likelihood"):
        t = out["targets"][m]
        assert t["met"] == (t["rmse_ratio"] <= 1.5 and 1 <= t["nees"] <= 4)
    assert "/ with states" in oc.oscillator_table(out)

    def fail(*args, **kwargs):
        raise FitError("fit_em: iteration 1, M-step: broken", fit="fit_em", step="iteration 1")

    monkeypatch.setattr(oc.torchfilt, "fit_measurement_only", fail)
    test = oc.simulate(1, 10, seed=1)
    row, record = oc.measurement_only_row("em", test.measurements[0], test, 0, 1)
    assert record["step"] == "iteration 1" and "broken" in row["raised"]
    rows["GP, measurement only (em)"] = row
    assert oc.verdict(rows, "em") == {"raised": row["raised"], "met": False}


def test_methods_choose_the_fits(oc):
    out = oc.oscillator_case(30, 2, 0, state_iterations=3, iterations=1, methods=("em",))
    assert set(out["targets"]) == {"em"}
    assert "GP, measurement only (em)" in out["rows"]
    assert "GP, measurement only (likelihood)" not in out["rows"]
    with pytest.raises(ValueError, match="methods"):
        oc.oscillator_case(30, 2, 0, state_iterations=3, iterations=1, methods=("newton",))
