"""The data-parallel benchmark script runs end to end on a tiny size and writes its JSON (slow)."""

from __future__ import annotations

import json

import pytest
import torch
from script_support import load_script


@pytest.mark.slow
def test_bench_dataparallel_small(tmp_path):
    mod = load_script("bench_dataparallel")
    threads = torch.get_num_threads()
    try:
        mod.main(["--recordings", "4", "--steps", "40", "--iterations", "2", "--gp-iterations",
                  "1", "--out", str(tmp_path)])  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    res = json.loads((tmp_path / "bench_dataparallel.json").read_text())
    assert len(res["rows"]) == 9
    assert all(r["s_per_iteration"] > 0 for r in res["rows"])
    assert all(r["rel_diff_to_1_process"] < 1e-9 for r in res["rows"])
