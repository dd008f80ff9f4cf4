"""Seconds and log-likelihood after each iteration of ``fit_measurement_only`` (defaults) from
the robot-arm GP start of ``scripts/bench_real_logs.py`` (rebuilt by ``em_low_noise.gp_start``).

Run from a checkout: ``PYTHONPATH=. python scripts/results/cpu-2026-12-05-ecm/trace_robot_arm.py
--data DIR --out OUT.json [--iterations 30] [--accelerate]``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # scripts/
from em_low_noise import gp_start

from torchfilt.training import fit_measurement_only


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--accelerate", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    start = gp_start("robot-arm", args.data, 4, 20, 16)
    y, u, x0, P0 = start["fit"]
    trace: list[tuple[float, float]] = []
    t0 = time.perf_counter()

    def record(state: object) -> None:
        trace.append((round(time.perf_counter() - t0, 1), state.log_likelihood))  # type: ignore[attr-defined]
        print(trace[-1], flush=True)

    fit = fit_measurement_only(
        start["gp"], y, u, x0=x0, P0=P0, known_channels=[0], iterations=args.iterations,
        accelerate=True if args.accelerate else None, callback=record,
    )  # fmt: skip
    print("stopped:", fit.stopped)
    args.out.write_text(json.dumps(trace))


if __name__ == "__main__":
    main()
