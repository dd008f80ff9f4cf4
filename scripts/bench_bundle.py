"""Model-bundle load time: with the stored predictor cache (schema 2) against refitting it.

Three bundles: the quick-start bundle (``trainers/reentry.toml`` on ``data/reentry``, as
``scripts/quickstart.py`` trains it; about 1600 training points per side, transition variance
exact, sensor low rank) and two bundles with 5000 training points per side (the reaction system,
50 simulated recordings of 100 steps, the quick-start options): one with the default
``variance = "auto"`` (low-rank roots are stored), one with ``variance = "exact"`` on both sides,
the worst case (the ``S x S`` Cholesky factors are not stored but recomputed). For each:

* **cold**: ``load_model`` in a fresh process, the first call (file read, checksum, value checks,
  GP modules, caches); ``cold, torch warm`` the same after one ``torch.broadcast_shapes`` call,
  which pays torch's one-time lazy import of sympy (about 1 s) that the filter pays anyway;
* **warm**: the median of repeated ``load_model`` calls in one process;
* **refit**: the same bundle rebuilt without its cache (what every load did before schema 2:
  choosing the variance form again), one call in the same (warm) process.

    PYTHONPATH=. python scripts/bench_bundle.py --out out/bench_bundle [--quickstart PATH]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json

from torchfilt.io.synth import simulate_dataset
from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.pipeline import load_bundle, load_model, train_recipe

ROOT = Path(__file__).resolve().parents[1]
#: Recipe of the 5000-point bundle (the quick-start recipe's options on another system).
LARGE_RECIPE = """
name = "large"
seed = 0
[dataset]
path = "{data}"
[transition]
increment = true
iterations = 60
lr = 0.05{variance}
[measurement]
iterations = 60
lr = 0.05{variance}
[train]
checkpoint_every = 60
"""

COLD = (
    "import sys, time, torch\n"
    "from torchfilt.pipeline import load_model\n"
    "if sys.argv[2] == '1':\n"
    "    torch.broadcast_shapes((2, 1), (1, 3))\n"
    "torch.set_num_threads(int(sys.argv[3]))\n"
    "t = time.perf_counter()\n"
    "load_model(sys.argv[1])\n"
    "print(time.perf_counter() - t)\n"
)


def cold(path: Path, prewarm: bool, threads: int, repeats: int) -> float:
    """Median over ``repeats`` fresh processes of the first ``load_model`` call."""
    env_path = str(ROOT)
    times = []
    for _ in range(repeats):
        out = subprocess.run(
            [sys.executable, "-c", COLD, str(path), "1" if prewarm else "0", str(threads)],
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"},
        )
        times.append(float(out.stdout.strip().splitlines()[-1]))
    return statistics.median(times)


def refit(path: Path) -> None:
    """Rebuild both sides without the stored cache (the pre-schema-2 load)."""
    b = load_bundle(path)
    for role, cls in (("transition", GPTransition), ("measurement", GPMeasurement)):
        cls.from_state({**b[role]["state"], "frozen": None})


def training_points(path: Path) -> dict[str, int]:
    b = load_bundle(path)
    out = {}
    for role in ("transition", "measurement"):
        sd = b[role]["state"]["state_dict"]
        out[role] = int(sd["groups.0.train_x"].shape[0])
    return out


def build_quickstart(work: Path) -> Path:
    return train_recipe(ROOT / "trainers" / "reentry.toml", work / "quickstart", progress=False)


def build_large(work: Path, variance: str) -> Path:
    data = work / "large_data"
    if not (data / "manifest.json").is_file():
        simulate_dataset("reaction", data, recordings=50, steps=100, seed=0, splits=(1.0, 0.0, 0.0))
    recipe = work / f"large_{variance}.toml"
    extra = "" if variance == "auto" else f'\nvariance = "{variance}"'
    recipe.write_text(LARGE_RECIPE.format(data=data.as_posix(), variance=extra))
    return train_recipe(recipe, work / f"large_{variance}", progress=False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_bundle"))
    ap.add_argument("--quickstart", type=Path, help="an existing quick-start model.pt")
    ap.add_argument("--large", type=Path, help="an existing 5000-point model.pt (auto)")
    ap.add_argument("--large-exact", type=Path, help="an existing 5000-point model.pt (exact)")
    ap.add_argument("--keep", type=Path, help="train the bundles here (kept) instead of a temp dir")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows: list[list[Any]] = []
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        bundles = {
            "quick start": args.quickstart or build_quickstart(work),
            "5000 points, auto": args.large or build_large(work, "auto"),
            "5000 points, exact": args.large_exact or build_large(work, "exact"),
        }
        for name, path in bundles.items():
            pts = training_points(path)
            r = {
                "bundle": name,
                "training_points": pts,
                "file_mb": path.stat().st_size / 1e6,
                "cold_s": cold(path, False, args.threads, args.repeats),
                "cold_torch_warm_s": cold(path, True, args.threads, args.repeats),
                "warm_s": timeit(lambda p=path: load_model(p), args.repeats),
                # one call: refitting a 5000-point model takes minutes on a shared machine
                "refit_s": timeit(lambda p=path: refit(p), 1, warmup=0),
            }
            results.append(r)
            rows.append(
                [
                    name,
                    f"{pts['transition']} / {pts['measurement']}",
                    r["file_mb"],
                    r["cold_s"],
                    r["cold_torch_warm_s"],
                    r["warm_s"],
                    r["refit_s"],
                ]
            )
    headers = ["bundle", "points (f / h)", "MB", "cold s", "cold, torch warm s", "warm s"]
    print(table([*headers, "refit s"], rows, fmt="{:.3g}"))
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S")
    write_json(
        args.out / "bench_bundle.json",
        {"created": stamp, "environment": environment(), "results": results},
    )
    print(f"wrote {args.out / 'bench_bundle.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
