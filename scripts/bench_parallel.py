"""Parallel-in-time (associative scan) against sequential Kalman filtering + RTS smoothing, one
long sequence, CPU, 1 thread, float64; dynamax's sequential and parallel smoothers as peers.

For each ``T`` and ``n`` (m = n / 2) the script times torchfilt's ``kalman_smoother`` sequential
and with ``parallel=True`` (filter + smoother together) and, with ``--jax-python``, dynamax's
jitted ``lgssm_smoother`` and ``parallel_lgssm_smoother`` in the same run; the parallel means are
compared with the sequential ones (``max_diff``). ``speedup`` is sequential time over parallel
time. No GPU rows: run it on a GPU machine with ``--device cuda`` for those.

    python scripts/bench_parallel.py --out out/bench_parallel --jax-python /work/wt/jaxenv/bin/python
    python scripts/bench_parallel.py --steps 10000 100000      # T = 10^5 as well (slow on a CPU)
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json
from bench_linear import dynamax_peer, problem

import torchfilt
from torchfilt.filters import kalman_smoother


def _smooth(model: Any, y: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor, parallel: bool):
    out = kalman_smoother(model, y, x0=x0, P0=P0, parallel=parallel).mean
    if y.device.type == "cuda":
        torch.cuda.synchronize()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, nargs="*", default=[10_000])
    ap.add_argument("--dims", type=int, nargs="*", default=[4, 20])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jax-python", default=None, help="python of a venv with dynamax")
    ap.add_argument("--cpu", type=int, default=0, help="core to pin to")
    ap.add_argument("--out", type=Path, default=Path("out/bench_parallel"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    dev = torch.device(args.device)
    rows: list[dict[str, Any]] = []
    peers = ""
    with torch.no_grad():
        for T in args.steps:
            for n in args.dims:
                m = max(n // 2, 1)
                p = problem(n, m, T, 1)
                t = lambda a: torch.tensor(a, dtype=torch.float64, device=dev)  # noqa: E731
                model = torchfilt.LinearGaussianModel(t(p["A"]), t(p["H"]), t(p["Q"]), t(p["R"]))
                y = t(p["y"])

                x0, P0 = t(p["m0"]), t(p["P0"])
                run = functools.partial(_smooth, model, y, x0, P0)
                seq = timeit(functools.partial(run, False), args.repeats)
                par = timeit(functools.partial(run, True), args.repeats)
                diff = float((run(True) - run(False)).abs().max())
                row: dict[str, Any] = {"T": T, "n": n, "m": m, "device": str(dev)}
                row.update(sequential_s=seq, parallel_s=par, speedup=seq / par, max_diff=diff)
                dseq, _, peers = dynamax_peer(args.jax_python, p, "smoother", args.repeats)
                dpar, _, _ = dynamax_peer(args.jax_python, p, "parallel_smoother", args.repeats)
                row["dynamax_sequential_s"], row["dynamax_parallel_s"] = dseq, dpar
                row["dynamax_speedup"] = None if dseq is None or dpar is None else dseq / dpar
                rows.append(row)
                print(f"done T {T} n {n}", file=sys.stderr)
    print(f"filter + RTS smoother, batch 1, float64, 1 thread, {dev}; peers: {peers}")
    headers = ["T", "n", "sequential s", "parallel s", "speed-up", "max diff"]
    headers += ["dynamax seq s", "dynamax par s", "dynamax speed-up"]
    body = [
        [r["T"], r["n"], r["sequential_s"], r["parallel_s"], r["speedup"], r["max_diff"],
         r["dynamax_sequential_s"], r["dynamax_parallel_s"], r["dynamax_speedup"]]
        for r in rows
    ]  # fmt: skip
    print(table(headers, body))
    write_json(
        args.out / "bench_parallel.json",
        {"rows": rows, "peers": peers, "environment": environment(), "gpu_rows": "not measured"},
    )
    print(f"wrote {args.out / 'bench_parallel.json'}")


if __name__ == "__main__":
    main()
