"""Filter throughput on the re-entry problem: torchfilt's CKF against filterpy (and dynamax if present).

Re-entry, analytic model, RK4 with 10 sub-steps per 1 s step, T = 60, float64 on the CPU. filterpy
gets its fastest form: dynamics written with plain Python floats. Everything is timed in the same
run; each figure is the median of ``--repeats`` timed runs after a warm-up (compile time is
reported separately). Prints a table and writes ``results.json``.

    python scripts/bench_filter.py --out out/bench_filter
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.systems import reentry

T = reentry.STEPS


def timeit(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn`` over ``repeats`` runs, after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


# --------------------------------------------------------------------------- filterpy
def filterpy_runner(y: np.ndarray) -> Callable[[], None]:
    """filterpy's CubatureKalmanFilter with the dynamics in plain Python floats."""
    from filterpy.kalman import CubatureKalmanFilter

    gamma, M, H = reentry.GAMMA, reentry.RADAR_M, reentry.RADAR_H
    sub = reentry.SUBSTEPS

    def fx(x: np.ndarray, dt: float) -> np.ndarray:
        x1, x2, x3 = float(x[0]), float(x[1]), float(x[2])
        h = dt / sub
        for _ in range(sub):
            k1a, k1v = -x2, -math.exp(-gamma * x1) * x2 * x2 * x3
            a, v = x1 + 0.5 * h * k1a, x2 + 0.5 * h * k1v
            k2a, k2v = -v, -math.exp(-gamma * a) * v * v * x3
            a, v = x1 + 0.5 * h * k2a, x2 + 0.5 * h * k2v
            k3a, k3v = -v, -math.exp(-gamma * a) * v * v * x3
            a, v = x1 + h * k3a, x2 + h * k3v
            k4a, k4v = -v, -math.exp(-gamma * a) * v * v * x3
            x1 += h / 6.0 * (k1a + 2 * k2a + 2 * k3a + k4a)
            x2 += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        return np.array([x1, x2, x3])

    def hx(x: np.ndarray) -> np.ndarray:
        d = float(x[0]) - H
        return np.array([math.sqrt(M * M + d * d)])

    def run() -> None:
        ckf = CubatureKalmanFilter(3, 1, reentry.DT, hx, fx)
        ckf.x = np.array(reentry.PRIOR_MEAN)
        ckf.P = np.diag(reentry.PRIOR_COV_DIAG)
        ckf.Q = np.zeros((3, 3))
        ckf.R = np.array([[reentry.R_VAR]])
        for t in range(y.shape[0]):
            ckf.predict()
            ckf.update(y[t])

    return run


# --------------------------------------------------------------------------- torchfilt
def torchfilt_runner(
    y: torch.Tensor, *, compile: bool, sqrt: bool = False
) -> tuple[Callable[[], None], float]:
    """A closure filtering ``y`` with torchfilt, and the time its first call took."""
    dtype, device = y.dtype, y.device
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=dtype, device=device)
    P0 = reentry.prior_cov(dtype).to(device)
    filt = torchfilt.CKF(reentry.model(dtype=dtype).to(device), sqrt=sqrt, compile=compile)

    def run() -> None:
        with torch.inference_mode(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torchfilt.NumericsWarning)
            filt.filter(y, x0=x0, P0=P0)
            if device.type == "cuda":
                torch.cuda.synchronize()

    t0 = time.perf_counter()
    run()
    return run, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_filter"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--gpu-batch", type=int, default=10_000)
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile rows")
    ap.add_argument("--cckf", action="store_true", help="also run the constrained-CKF benchmark")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    sim = reentry.simulate_truth(max(args.batch, 1), seed=0)
    y1 = sim.measurements[:1]
    yB = sim.measurements[: args.batch]
    rows: list[dict[str, Any]] = []

    def record(
        name: str, device: str, batch: int, seconds: float, first: float | None = None
    ) -> None:
        rows.append(
            {
                "name": name,
                "device": device,
                "batch": batch,
                "seconds_per_run": seconds,
                "us_per_step": seconds / T * 1e6,
                "sequence_steps_per_s": batch * T / seconds,
                "first_call_s": first,
            }
        )
        print(f"  {name:<42} {batch * T / seconds:12.4g} seq-steps/s", flush=True)

    print(f"Re-entry CKF, T = {T}, float64, {args.threads} CPU threads")
    fp = filterpy_runner(y1[0].numpy())
    record("filterpy CKF (Python-float dynamics)", "cpu", 1, timeit(fp, args.repeats))
    variants = [(False, "eager")] + ([] if args.no_compile else [(True, "torch.compile")])
    for compile_, tag in variants:
        run, first = torchfilt_runner(y1, compile=compile_)
        record(f"torchfilt CKF, {tag}", "cpu", 1, timeit(run, args.repeats), first)
    for compile_, tag in variants:
        run, first = torchfilt_runner(yB, compile=compile_)
        record(
            f"torchfilt CKF, {tag}",
            "cpu",
            args.batch,
            timeit(run, max(2, args.repeats // 2)),
            first,
        )

    gpu: dict[str, Any] = {}
    if torch.cuda.is_available():
        yg = reentry.simulate_truth(args.gpu_batch, seed=0, dtype=torch.float32).measurements.cuda()
        for compile_, tag in variants:
            run, first = torchfilt_runner(yg, compile=compile_)
            record(f"torchfilt CKF float32, {tag}", "cuda", args.gpu_batch, timeit(run, 3), first)
    else:
        gpu["note"] = "not measured: no CUDA device on this machine"
        print("  GPU rows: not measured (no CUDA device)")

    dynamax = "installed" if importlib.util.find_spec("dynamax") else "not installed"

    cckf: dict[str, Any] | None = None
    if args.cckf:
        from bench_cckf import run_cckf_benchmark  # type: ignore[import-not-found]

        cckf = run_cckf_benchmark(repeats=max(3, args.repeats))

    fp_rate = rows[0]["sequence_steps_per_s"]
    for r in rows:
        r["ratio_to_filterpy"] = r["sequence_steps_per_s"] / fp_rate
    print()
    print(
        table(
            [
                "implementation",
                "device",
                "batch",
                "us/step",
                "seq-steps/s",
                "x filterpy",
                "first call s",
            ],
            [
                [
                    r["name"],
                    r["device"],
                    r["batch"],
                    r["us_per_step"],
                    r["sequence_steps_per_s"],
                    r["ratio_to_filterpy"],
                    "" if r["first_call_s"] is None else r["first_call_s"],
                ]
                for r in rows
            ],
        )
    )
    payload = {
        "benchmark": "reentry CKF throughput",
        "steps": T,
        "substeps": reentry.SUBSTEPS,
        "dtype": "float64 (CPU), float32 (GPU)",
        "rows": rows,
        "gpu": gpu,
        "dynamax": dynamax,
        "cckf": cckf,
        "environment": environment(),
    }
    write_json(args.out / "results.json", payload)
    print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
