"""Quick start: learn a re-entering vehicle's dynamics and radar from a log, then track it.

1. trains GP models of the transition and of the radar range on the shipped log
   ``data/reentry`` (recipe ``trainers/reentry.toml``: the same as ``torchfilt train``);
2. filters and smooths the held-out paper-scenario recordings with the learned models (the same as
   ``torchfilt filter --smooth --plot``);
3. compares with the logged truth (``torchfilt evaluate``) and writes a figure per recording.

    python scripts/quickstart.py --out out/quickstart
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import torchfilt
from torchfilt.io import load_dataset

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/quickstart"))
    ap.add_argument("--recipe", type=Path, default=ROOT / "trainers" / "reentry.toml")
    args = ap.parse_args(argv)
    run, est = args.out / "run", args.out / "filter"
    if run.exists():  # our own previous output: start afresh
        shutil.rmtree(run)
    t0 = time.perf_counter()
    print(f"1/3 training the transition and measurement GPs ({args.recipe.name}) ...", flush=True)
    bundle = torchfilt.train_recipe(args.recipe, run, progress=sys.stderr.isatty())
    print(f"    model bundle: {bundle} ({time.perf_counter() - t0:.0f} s)")
    test = load_dataset(ROOT / "data" / "reentry", splits=("test",))
    recs = [r.path for r in test.recordings if r.path is not None]
    print(
        f"2/3 filtering and smoothing {len(recs)} held-out recordings with the learned models ..."
    )
    # est/ is this script's own output of an earlier run: replace it
    summary = torchfilt.pipeline.filter_recordings(
        bundle, recs, est, smooth=True, plot=True, force=True
    )
    print("3/3 comparing with the logged truth ...")
    for which in ("filtered", "smoothed"):
        ev = torchfilt.pipeline.evaluate_outputs(est, which=which, force=True)
        p = ev["pooled"]
        rm = ", ".join(f"{s} {v:.4g}" for s, v in zip(ev["states"], p["rmse"], strict=True))
        print(
            f"    {which:>8}: RMSE {rm}; mean NEES {p['nees']:.3g} (consistent: {p['nees_expected']})"
        )
    figs = [e["plot"] for e in summary["recordings"]]
    print(
        f"wrote {len(figs)} figures to {est}/ (e.g. {est / figs[0]}) in {time.perf_counter() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
