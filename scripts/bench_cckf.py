"""Throughput of the constrained CKF against the CKF on 2A -> B (one sequence and a batch), on the CPU.

Both filters run the paper's 2A -> B setting (spec cckf.md s.4: T = 100 steps, float64, bounds
0 <= x <= 100) under ``torch.no_grad()``; every figure is the median of ``--repeats`` timed runs after
one warm-up. Throughput is counted in sequence-steps per second (batch x T / wall time); the cost
ratio is the CCKF's wall time over the CKF's for the same batch. The CCKF also reports its mean
reconciliation-solver iterations per point and step.

    python scripts/bench_cckf.py --out out/bench_cckf

``run_cckf_benchmark`` returns the same numbers as a dict, for ``scripts/bench_filter.py``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import timeit
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.filters.constrained import ConstrainedCKF
from torchfilt.systems import reaction


def _median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    fn()  # warm-up (allocations, caches)
    return statistics.median(timeit.repeat(fn, number=1, repeat=repeats))


def run_cckf_benchmark(
    batches: Sequence[int] = (1, 1000),
    *,
    steps: int = reaction.STEPS,
    repeats: int = 5,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> dict[str, Any]:
    """Time the CKF and the CCKF (paper and corrected covariance) on 2A -> B.

    Args:
        batches: numbers of sequences filtered at once (1 = a single sequence ``(T, 1)``).
        steps: sequence length ``T``.
        repeats: timed runs per measurement (the median is reported).
        seed: seed of the simulated measurements.
        dtype: floating dtype.

    Returns:
        ``{"rows": [...], "environment": {...}, ...}``; each row has ``batch``, ``filter``,
        ``seconds``, ``seq_steps_per_s``, ``cost_ratio`` (CCKF over CKF, same batch) and, for the
        CCKF, ``solver_iterations_mean``.
    """
    model = reaction.model(dtype)
    x0, P0 = reaction.prior_mean("paper", dtype), reaction.prior_cov(dtype)
    filters: dict[str, Any] = {
        "CKF": torchfilt.CKF(model),
        "CCKF (paper cov)": ConstrainedCKF(model, reaction.LOWER, reaction.UPPER),
        "CCKF (corrected cov)": ConstrainedCKF(
            model, reaction.LOWER, reaction.UPPER, covariance="corrected"
        ),
    }
    rows = []
    for batch in batches:
        sim = reaction.simulate_truth(batch, start="paper", steps=steps, seed=seed, dtype=dtype)
        y = sim.measurements[0] if batch == 1 else sim.measurements
        base = None
        for name, filt in filters.items():
            with torch.no_grad():
                seconds = _median_seconds(lambda f=filt, y=y: f.filter(y, x0=x0, P0=P0), repeats)
                row: dict[str, Any] = {"batch": batch, "filter": name, "seconds": seconds}
                if isinstance(filt, ConstrainedCKF):
                    _, info = filt.filter_with_info(y, x0=x0, P0=P0)
                    row["solver_iterations_mean"] = float(info.solver_iterations.double().mean())
            base = seconds if base is None else base
            row["seq_steps_per_s"] = batch * steps / seconds
            row["cost_ratio"] = seconds / base
            rows.append(row)
    return {
        "benchmark": "cckf_vs_ckf_2a_to_b",
        "steps": steps,
        "repeats": repeats,
        "dtype": str(dtype).removeprefix("torch."),
        "device": "cpu",
        "rows": rows,
        "environment": environment(),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 1000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--threads", type=int, default=1, help="intra-op threads (1: robust on a shared machine)"
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_cckf"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    res = run_cckf_benchmark(args.batches, repeats=args.repeats)
    headers = ["batch", "filter", "ms / run", "seq-steps / s", "cost ratio", "solver it."]
    rows = [
        [
            r["batch"],
            r["filter"],
            1e3 * r["seconds"],
            r["seq_steps_per_s"],
            r["cost_ratio"],
            r.get("solver_iterations_mean", "-"),
        ]
        for r in res["rows"]
    ]
    print(
        f"2A -> B, T = {res['steps']}, {res['dtype']}, CPU, {torch.get_num_threads()} threads; "
        f"median of {res['repeats']} runs"
    )
    print(table(headers, rows, fmt="{:.4g}"))
    write_json(args.out / "results.json", res)
    print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
