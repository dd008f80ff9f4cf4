"""The errors of ``--ray`` that need no Ray session open in this process (tests/pipeline/test_distributed.py
keeps one open for its whole module, which ``--ray ADDRESS`` would then reuse)."""

from __future__ import annotations

import socket
import time

from torchfilt.cli import main
from torchfilt.io.synth import simulate_dataset

SYSTEM = "system:pendulum"


def test_unreachable_cluster_is_one_line_and_writes_nothing(tmp_path, capsys):
    simulate_dataset("pendulum", tmp_path / "data", recordings=1, steps=10, seed=0)
    recordings = sorted((tmp_path / "data").glob("*.csv"))
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "o"
    argv = ["filter", str(recordings[0]), "--model", SYSTEM, "--out", str(out)]
    t0 = time.perf_counter()
    assert main([*argv, "--ray", f"127.0.0.1:{port}"]) == 2
    assert time.perf_counter() - t0 < 30
    err = capsys.readouterr().err
    assert f"--ray 127.0.0.1:{port}: no Ray cluster answers there" in err
    assert not out.exists()
