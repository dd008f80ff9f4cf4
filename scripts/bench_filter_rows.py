"""bench_filter's linear n = 8, batch 256 CKF rows, timed many times, for any checkout.

``bench_filter.py`` times these rows only ``max(3, repeats // 2)`` times, and the
``compile="loop"`` row is bimodal on this machine (runs of one process spread from 0.09 s to
0.17 s), so a before/after ratio from three timings flips between runs. This script times the
same rows (the same problem and runner, imported from the checkout given by ``--root``: its
package and its ``scripts/bench_filter.py``) ``--repeats`` times each and reports the median,
minimum and maximum. Run it on two checkouts in turn, a few rounds each, to compare:

    for i in 1 2; do
      for c in ../before .; do python scripts/bench_filter_rows.py --root $c --out out/rows/$i-$(basename $c); done
    done

Prints a table and writes ``rows.json``.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROWS = {"eager": False, "step": "step", "loop": "loop"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--rows", default="eager,step,loop", help="comma-separated: eager,step,loop")
    ap.add_argument("--repeats", type=int, default=60)
    ap.add_argument("--out", type=Path, default=Path("out/bench_filter_rows"))
    args = ap.parse_args(argv)
    root = args.root.resolve()
    # the checkout's package and its bench_filter (this script's helpers from this folder)
    sys.path[:0] = [str(root), str(root / "scripts")]
    import torch

    torch.set_num_threads(1)
    bf = importlib.import_module("bench_filter")
    here = str(Path(__file__).resolve().parent)
    sys.path.append(here)
    from _common import environment, table, write_json

    lin = bf.linear_problem(8, 4, 256)
    x0, P0 = torch.zeros(8, dtype=torch.float64), torch.eye(8, dtype=torch.float64)
    rows: list[dict[str, Any]] = []
    for tag in args.rows.split(","):
        run, first = bf.torchfilt_runner(
            lin["y"], compile=ROWS[tag], model=lin["model"], x0=x0, P0=P0, path="cubature"
        )
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            run()
            times.append(time.perf_counter() - t0)
        rows.append(
            {
                "name": f"torchfilt CKF, linear n=8, {tag}",
                "batch": 256,
                "seconds_per_run": statistics.median(times),
                "min_s": min(times),
                "max_s": max(times),
                "first_call_s": first,
            }
        )
    print(f"checkout {root}; {args.repeats} timed runs per row, 1 thread, float64")
    body = [
        [r["name"], r["seconds_per_run"], r["min_s"], r["max_s"], r["first_call_s"]] for r in rows
    ]
    print(table(["row", "median s", "min s", "max s", "first call s"], body))
    write_json(
        args.out / "rows.json",
        {
            "root": str(root),
            "package": str(Path(bf.torchfilt.__file__).parent),
            "repeats": args.repeats,
            "rows": rows,
            "environment": environment(),
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
