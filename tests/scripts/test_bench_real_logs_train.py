"""``scripts/bench_real_logs_train.py``: the dataset it writes (row 0 the prior's time, the input
of row ``k`` driving the step to row ``k + 1``) read back by ``load_dataset`` as the stage reads
it, and the script end to end on a simulated stable system (the real logs are not shipped)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from script_support import load_script
from test_bench_real_logs import simulated_log_args  # the simulated log of its sibling

from torchfilt.io import load_dataset


@pytest.fixture(scope="module")
def brt():
    return load_script("bench_real_logs_train")


def test_the_dataset_reads_back_as_the_stage_fits_it(brt, tmp_path):
    """The stage fits ``measurements[1:]`` with ``inputs[:-1]``: exactly the Python ``(y, u)``
    of the training part (``u[t]`` drives the step ``y[t]`` updates), every digit kept."""
    g = torch.Generator().manual_seed(0)
    parts = tuple(torch.randn(1, T, 1, generator=g, dtype=torch.float64) for T in (40, 40, 25, 25))
    brt.write_dataset(tmp_path / "data", 3, parts)
    ds = load_dataset(tmp_path / "data", require_finite=("input",), optional=("state",))
    assert ds.state_dim == 3 and ds.input_dim == 1
    for split, (u, y) in (("train", parts[:2]), ("test", parts[2:])):
        (rec,) = ds.split(split)
        assert torch.equal(rec.measurements[1:].to(torch.float64), y[0])
        assert bool(torch.isnan(rec.measurements[0]).all())  # the prior's time: no reading
        assert torch.equal(rec.inputs[:-1].to(torch.float64), u[0])


@pytest.mark.slow
def test_main_on_a_simulated_log(brt, tmp_path):
    out, args = simulated_log_args(tmp_path)
    assert brt.main([*args, "--noise", "1e-2"]) == 0
    rows = json.loads((out / "bench_real_logs_train.json").read_text())["logs"]["robot-arm"]
    assert set(rows) == {"N4SID (nfoursid)", "train, R = 0.01"}
    row = rows["train, R = 0.01"]
    assert row["stopped"] in ("converged", "iterations", "no improvement")
    assert 1 <= row["iterations"] <= row["budget"] == 30
    # the stage's start was chosen among the candidates, and the log says how the run went
    assert any(c.get("chosen") for c in row["start"])
    assert any("transition: learning from measurements alone" in line for line in row["log"])
    # noise 5% of the output's scale: a learned model free-runs it far below its spread (1)
    assert math.isfinite(row["rmse"]) and row["rmse"] < 0.3, row
    assert 0.8 <= row["coverage95"] <= 1.0, row
