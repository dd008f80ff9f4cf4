"""A fleet of reactors filtered through Ray: how the nominal model's error spreads over the units.

Simulates ``--units`` recordings (default 10^4) of the built-in gas-phase reaction 2A -> B
(``torchfilt.systems.reaction``), each unit with its own rate constant ``k1`` (log-normal around
the nominal 0.16 with ``--spread`` log-sd: manufacturing spread), then filters every recording with
the *nominal* model (``system:reaction``) through ``filter_recordings_ray`` on a local Ray
instance, and writes into ``--out``:

- ``data/unit_NNNNN.csv``: the recordings (seeded; reused when already there);
- ``filtered/``: the per-unit estimates and ``filter_summary.json`` (a re-run resumes);
- ``fleet_summary.json`` and ``fleet_summary.md``: quantiles across the fleet of the per-unit
  RMSE, NEES and 95% coverage, overall and by how far the unit's ``k1`` is from nominal;
- ``fleet_errors.png``: the distribution of the per-unit errors, and error against ``k1``.

    python scripts/fleet_example.py --out out/fleet
    python scripts/fleet_example.py --units 500 --out out/fleet-small     # a quick look
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import table, write_json

from torchfilt.io import Channel, Recording, atomic_write_text, write_recording
from torchfilt.models import StateSpaceModel
from torchfilt.pipeline import filter_recordings_ray
from torchfilt.systems import get_system, reaction, simulate

matplotlib.use("Agg")


def simulate_fleet(
    root: Path, units: int, steps: int, spread: float, seed: int
) -> tuple[list[Path], np.ndarray]:
    """Write one recording per unit; returns the paths and each unit's ``k1``."""
    gen = torch.Generator().manual_seed(seed)
    k1 = reaction.K1 * torch.exp(spread * torch.randn(units, 1, generator=gen, dtype=torch.float64))
    spec = get_system("reaction")
    nominal = spec.model()
    model = StateSpaceModel(
        functools.partial(reaction.transition, k1=k1),
        reaction.measurement,
        Q=nominal.transition.noise_cov(),
        R=nominal.measurement.noise_cov(),
    )
    x0 = spec.initial(units, gen)
    sim = simulate(model, steps, x0, generator=gen)
    X = torch.cat([sim.initial[:, None], sim.states], 1).numpy()
    Y = sim.measurements.numpy()
    t = np.arange(steps + 1) * spec.sample_time
    channels = (
        *(Channel(n, "state", u) for n, u in spec.states),
        *(Channel(n, "measurement", u) for n, u in spec.measurements),
    )
    paths = []
    for r in range(units):
        y = np.concatenate([[np.nan], Y[r, :, 0]])
        cols = {"PA": X[r, :, 0], "PB": X[r, :, 1], "pressure": y}
        path = root / f"unit_{r:05d}.csv"
        write_recording(Recording.from_arrays(t, channels, cols), path)
        paths.append(path)
    np.save(root / "k1.npy", k1[:, 0].numpy())
    return paths, k1[:, 0].numpy()


def _quantiles(v: np.ndarray) -> dict[str, float]:
    q = np.quantile(v, [0.05, 0.5, 0.95])
    return {"p5": float(q[0]), "median": float(q[1]), "p95": float(q[2]), "mean": float(v.mean())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--spread", type=float, default=0.25, help="log-sd of k1 across the fleet")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray instance")
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--out", type=Path, default=Path("out/fleet"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    timings: dict[str, float] = {}
    data = args.out / "data"
    t0 = time.perf_counter()
    stamp = data / "fleet.json"
    want = {"units": args.units, "steps": args.steps, "spread": args.spread, "seed": args.seed}
    if stamp.is_file() and json.loads(stamp.read_text()) == want:
        paths = [data / f"unit_{r:05d}.csv" for r in range(args.units)]
        k1 = np.load(data / "k1.npy")
    else:
        paths, k1 = simulate_fleet(data, args.units, args.steps, args.spread, args.seed)
        atomic_write_text(stamp, json.dumps(want) + "\n")
    timings["simulate_and_write_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    res = filter_recordings_ray(
        "system:reaction",
        paths,
        args.out / "filtered",
        workers=args.workers,
        batch_size=args.batch_size,
    )
    timings["filter_ray_s"] = time.perf_counter() - t0
    d = res["distributed"]

    met = [e["filtered_metrics"] for e in res["recordings"]]
    rmse = np.array([m["rmse"] for m in met])  # (units, 2)
    nees = np.array([m["nees"] for m in met])
    cov = np.array([m["coverage95"] for m in met])
    dev = np.abs(np.log(k1 / reaction.K1))
    bins = [0.0, 0.1, 0.25, 0.5, np.inf]
    by_dev = []
    for lo, hi in itertools.pairwise(bins):
        sel = (dev >= lo) & (dev < hi)
        if not sel.any():
            continue
        by_dev.append(
            {
                "abs_log_k1_ratio": f"[{lo:g}, {hi:g})",
                "units": int(sel.sum()),
                "rmse_PA_median": float(np.median(rmse[sel, 0])),
                "rmse_PB_median": float(np.median(rmse[sel, 1])),
                "nees_median": float(np.median(nees[sel])),
                "coverage95_PA_mean": float(cov[sel, 0].mean()),
            }
        )
    summary: dict[str, Any] = {
        "system": "reaction (2A -> B), filtered with the nominal k1 = 0.16",
        "units": args.units,
        "steps": args.steps,
        "k1_log_sd": args.spread,
        "workers": args.workers,
        "batch_size": args.batch_size,
        "timings": timings,
        "recordings_per_s": args.units / timings["filter_ray_s"],
        "ray": {k: d[k] for k in ("filtered", "complete_before", "tasks")},
        "fleet": {
            "rmse_PA": _quantiles(rmse[:, 0]),
            "rmse_PB": _quantiles(rmse[:, 1]),
            "nees": _quantiles(nees),
            "coverage95_PA": _quantiles(cov[:, 0]),
            "coverage95_PB": _quantiles(cov[:, 1]),
        },
        "by_k1_deviation": by_dev,
    }
    write_json(args.out / "fleet_summary.json", summary)
    rows = [[k, *v.values()] for k, v in summary["fleet"].items()]
    t1 = table(["metric (per unit)", "p5", "median", "p95", "mean"], rows)
    t2 = table(
        ["|log k1/k1_nom|", "units", "RMSE PA med", "RMSE PB med", "NEES med", "cov95 PA"],
        [list(r.values()) for r in by_dev],
    )
    head = (
        f"{args.units} units, T = {args.steps}, k1 log-sd {args.spread}; filtered through Ray "
        f"({args.workers} workers, batch {args.batch_size}) in {timings['filter_ray_s']:.1f} s "
        f"({summary['recordings_per_s']:.0f} recordings/s; {d['filtered']} filtered now, "
        f"{d['complete_before']} already complete)"
    )
    text = f"{head}\n\n{t1}\n\n{t2}\n"
    atomic_write_text(args.out / "fleet_summary.md", text)
    print(text)
    _figure(args.out / "fleet_errors.png", rmse, nees, k1)
    return 0


def _figure(path: Path, rmse: np.ndarray, nees: np.ndarray, k1: np.ndarray) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for i, name in enumerate(["PA", "PB"]):
        ax[0].hist(rmse[:, i], bins=60, histtype="step", label=f"{name} [atm]")
    ax[0].set(xlabel="per-unit RMSE", ylabel="units", title="filter error across the fleet")
    ax[0].legend()
    ax[1].hist(np.clip(nees, 0, 20), bins=60, color="C2")
    ax[1].axvline(2.0, color="k", ls="--", lw=1, label="expected (n = 2)")
    ax[1].set(xlabel="per-unit mean NEES (clipped at 20)", title="consistency")
    ax[1].legend()
    ax[2].scatter(k1 / reaction.K1, rmse[:, 0], s=2, alpha=0.3)
    ax[2].set(xscale="log", xlabel="unit k1 / nominal k1", ylabel="RMSE PA [atm]")
    ax[2].set_title("error against the unit's parameter")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
