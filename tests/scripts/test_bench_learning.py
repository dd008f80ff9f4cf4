"""The learning benchmark script runs end to end at its --quick size without the peers and writes
its JSON (slow); its time-to-optimum rule is checked on a made-up history."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from script_support import load_script


def test_time_to_optimum_is_the_first_time_within_tolerance():
    mod = load_script("bench_learning")
    lls = np.array([-100.0, -10.0, -1.05, -1.0, np.nan, -0.95])
    elapsed = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    # best -0.95; within 0.1 nats per sequence (1 sequence): first at -1.05 (t = 2)
    assert mod.time_to_optimum(lls, elapsed, 1) == 2.0
    # 1000 sequences: within 100 nats, so from the start
    assert mod.time_to_optimum(lls, elapsed, 1000) == 0.0
    assert mod.time_to_optimum(np.array([np.nan]), np.array([0.0]), 1) is None
    # to a level given from outside (the best of all methods): first reached at t = 3, or never
    assert mod._time_to(lls, elapsed, -1.0) == 3.0
    assert mod._time_to(lls, elapsed, 0.0) is None


def test_budgets_keep_given_iterations_and_fill_the_rest():
    import argparse

    mod = load_script("bench_learning")
    full = argparse.Namespace(quick=False, repeats=5, em_iterations=None, pykalman_iterations=None)
    sizes = mod.budgets(full)
    assert sizes["lin"] == (20, 500)
    # long enough for dynamax's EM to reach the optimum (about 1400 iterations)
    assert (full.em_iterations, full.pykalman_iterations, full.lik_iterations) == (1500, 300, 6)
    given = argparse.Namespace(quick=True, repeats=5, em_iterations=7, pykalman_iterations=None)
    assert mod.budgets(given)["lin"] == (3, 30)
    assert (given.em_iterations, given.pykalman_iterations, given.repeats) == (7, 3, 1)


@pytest.mark.slow
def test_bench_learning_quick(tmp_path):
    mod = load_script("bench_learning")
    threads = torch.get_num_threads()
    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    try:
        assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    finally:
        torch.set_num_threads(threads)
        if affinity is not None:
            os.sched_setaffinity(0, affinity)
    res = json.loads((tmp_path / "bench_learning.json").read_text())
    rows = {(r["row"], r.get("method")) for r in res["rows"]}
    assert ("linear grad", None) in rows
    assert ("reentry grad", "CKF(compile=False)") in rows
    assert ("reentry grad", "CKF(compile=True)") in rows
    assert ("2A->B EM iteration", "fit_em(compile=False)") in rows
    assert ("linear time to optimum", "torchfilt fit_em (default: SQUAREM)") in rows
    assert ("linear time to optimum", "torchfilt fit_em (plain EM)") in rows
    for r in res["rows"]:
        assert r["torchfilt_s"] is None or r["torchfilt_s"] >= 0
        assert r.get("peer_s") is None  # no --jax-python: no peer ran
    assert res["quick"] is True
