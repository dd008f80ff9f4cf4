"""scripts/reproduce_cckf.py and scripts/bench_cckf.py end to end (the full run is slow)."""

import json

import matplotlib
import pytest
from script_support import load_script

matplotlib.use("Agg")


def test_reproduction_smoke(tmp_path):
    """A few runs: the JSON has every filter and figure; the CCKF never leaves the box."""
    mod = load_script("reproduce_cckf")
    args = ["--runs", "6", "--steps", "40", "--reentry-runs", "4", "--out", str(tmp_path)]
    # the learned re-entry model, trained on the fly (tiny) since no cached bundle exists there
    args += ["--mfckf-samples", "300", "--mfckf-runs", "3", "--mfckf-dir", str(tmp_path / "mf")]
    assert mod.main(args) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    for start in ("paper", "hr"):
        rows = saved["reaction"][start]
        assert set(rows) == {"CKF"} | {
            f"CCKF {c} cov, theta {t}" for c in ("paper", "corrected") for t in ("paper", "std")
        }
        for name, m in rows.items():
            assert len(m["rmse_first20"]) == 2 and m["rmse_all"][0] > 0
            if name.startswith("CCKF"):
                assert m["outside_steps"] == 0.0 and m["solver_not_converged"] == 0
    assert saved["theta"]["chosen"] in ("paper", "std")
    assert set(saved["reentry"]["filters"]) == {
        "CKF1",
        "CKF1 + x3>=0 (paper cov)",
        "CKF1 + x3>=0 (corrected cov)",
    }
    assert saved["reentry"]["filters"]["CKF1 + x3>=0 (corrected cov)"]["x3_negative_steps"] == 0
    learned = saved["reentry_learned"]
    assert learned["runs"] == 3 and learned["training"]["reused"] is False
    assert set(learned["filters"]) == {
        f"{m}{c}"
        for m in ("CKF1", "MF-CKF (a)")
        for c in ("", " + x3>=0 (paper cov)", " + x3>=0 (corrected cov)")
    }
    for name, s in learned["filters"].items():
        if "x3>=0" in name:
            assert s["x3_negative_steps"] == 0 and s["solver_not_converged"] == 0, name
    assert (tmp_path / "mf" / "mfckf_a.pt").is_file()
    assert len(saved["figures"]) == 8
    assert all((tmp_path / f).stat().st_size > 0 for f in saved["figures"])


@pytest.mark.slow
def test_reproduction_meets_the_issue_targets(tmp_path):
    """The full 100-run reproduction: every target of issue 5 on both starts, theta default."""
    mod = load_script("reproduce_cckf")
    assert mod.main(["--out", str(tmp_path), "--reentry-runs", "200", "--skip-mfckf"]) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    for start in ("paper", "hr"):
        assert all(saved["targets"][start].values()), saved["targets"][start]
    assert saved["theta"]["chosen"] == saved["theta"]["library_default"]
    re = saved["reentry"]["filters"]["CKF1 + x3>=0 (corrected cov)"]
    assert re["failed"] == 0 and re["lost"] == 0


def test_benchmark_function_returns_rows():
    """Structure only (no timing assertions): rows per batch and filter, ratios against the CKF."""
    mod = load_script("bench_cckf")
    res = mod.run_cckf_benchmark((1, 3), steps=4, repeats=1)
    assert [(r["batch"], r["filter"]) for r in res["rows"]] == [
        (b, f) for b in (1, 3) for f in ("CKF", "CCKF (paper cov)", "CCKF (corrected cov)")
    ]
    for r in res["rows"]:
        assert r["seconds"] > 0 and r["seq_steps_per_s"] > 0
        if r["filter"] == "CKF":
            assert r["cost_ratio"] == 1.0
        else:
            assert r["solver_iterations_mean"] >= 1.0
