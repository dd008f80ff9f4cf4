"""The GP benchmark script runs end to end on a small size and writes its JSON (slow)."""

from __future__ import annotations

import json

import pytest
import torch
from script_support import load_script


@pytest.mark.slow
def test_bench_gp_filter_small(tmp_path):
    mod = load_script("bench_gp_filter")
    threads = torch.get_num_threads()
    try:
        mod.main(
            [
                "--sizes",
                "200",
                "--threads",
                "1",
                "--repeats",
                "1",
                "--full-iters",
                "1",
                "--no-sparse",
                "--no-compile",
                "--out",
                str(tmp_path),
            ]
        )
    finally:
        torch.set_num_threads(threads)
    res = json.loads((tmp_path / "results.json").read_text())
    (size,) = res["sizes"]
    assert size["S"] == 200 and size["chosen"] is not None
    forms = {f["form"]: f for f in size["forms"]}
    assert forms["frozen exact"]["var_err_max_f"] == 0.0
    assert all(g["step_ms"] > 0 for g in size["gpytorch"])
    assert res["gpu"].startswith("not measured") or torch.cuda.is_available()
