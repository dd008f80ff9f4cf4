"""The bundle benchmark script runs end to end on a tiny bundle and writes its JSON (slow)."""

from __future__ import annotations

import json

import pytest
import torch
from run_support import tiny_bundle
from script_support import load_script


@pytest.mark.slow
def test_bench_bundle_small(tmp_path):
    bundle = tiny_bundle(tmp_path / "b")
    mod = load_script("bench_bundle")
    threads = torch.get_num_threads()
    try:
        args = ["--quickstart", str(bundle), "--large", str(bundle), "--large-exact", str(bundle)]
        args += ["--repeats", "1"]
        assert mod.main([*args, "--out", str(tmp_path / "out")]) == 0
    finally:
        torch.set_num_threads(threads)
    res = json.loads((tmp_path / "out" / "bench_bundle.json").read_text())["results"]
    assert [r["bundle"] for r in res] == ["quick start", "5000 points, auto", "5000 points, exact"]
    for r in res:
        assert r["cold_s"] > 0 and r["warm_s"] > 0 and r["refit_s"] > 0
        assert min(r["training_points"].values()) > 0
