"""Regenerate the datasets shipped under ``data/`` (fixed seeds: the files are reproducible).

- ``data/reentry``: radar tracking of a re-entering vehicle. Train and validation recordings are
  trajectories from :func:`torchfilt.systems.reentry.record_training_data` (initial states drawn
  from the filter's prior, propagated with the true dynamics, implausible steps cut); the test
  recordings are the paper's scenario (true x0 = [3e5, 2e4, 1e-3]) with radar noise, row 0
  unmeasured (it is the filter prior's time).
- ``data/reaction``: the gas-phase reaction 2A -> B (``torchfilt simulate reaction``).

    python scripts/make_data.py            # writes data/reentry and data/reaction
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import torch

from torchfilt.io import Channel, Manifest, Recording, RecordingEntry, write_recording
from torchfilt.io.synth import simulate_dataset
from torchfilt.systems import reentry

ROOT = Path(__file__).resolve().parents[1] / "data"

REENTRY_CHANNELS = (
    Channel("altitude", "state", "ft"),
    Channel("velocity", "state", "ft/s"),
    Channel("ballistic", "state", ""),
    Channel("range", "measurement", "ft"),
)


def _write(out: Path, name: str, states: torch.Tensor, meas: torch.Tensor, dt: float) -> None:
    t = np.arange(states.shape[0]) * dt
    cols = {c.name: states[:, i].numpy() for i, c in enumerate(REENTRY_CHANNELS[:3])}
    cols["range"] = meas[:, 0].numpy()
    write_recording(Recording.from_arrays(t, REENTRY_CHANNELS, cols), out / name)


def make_reentry(out: Path, *, pairs: int, validation: int, test: int, seed: int) -> Manifest:
    """Training/validation trajectories from the recorder and paper-scenario test recordings."""
    rec = reentry.record_training_data(pairs, seed=seed)
    entries = []
    n = len(rec.states)
    n_val = max(1, round(validation * n))
    for i, (x, y) in enumerate(zip(rec.states, rec.measurements, strict=True)):
        if x.shape[0] < 2:
            continue
        name = f"traj_{i:03d}.csv"
        _write(out, name, x, y, reentry.DT)
        entries.append(RecordingEntry(name, "validation" if i >= n - n_val else "train"))
    sim = reentry.simulate_truth(test, seed=seed + 1)
    for i in range(test):
        x = torch.cat([sim.initial[i][None], sim.states[i]])
        y = torch.cat([torch.full((1, 1), float("nan"), dtype=x.dtype), sim.measurements[i]])
        name = f"scenario_{i:02d}.csv"
        _write(out, name, x, y, reentry.DT)
        entries.append(RecordingEntry(name, "test"))
    manifest = Manifest(
        name="reentry",
        sample_time=reentry.DT,
        channels=REENTRY_CHANNELS,
        recordings=tuple(entries),
        description=(
            "Radar tracking of a re-entering vehicle (Athans et al. 1968; Wei & Song 2013). "
            "train/validation: trajectories from initial states drawn from the filter prior "
            "(reentry.record_training_data); test: the paper's scenario, row 0 unmeasured."
        ),
        extra={
            "generator": {
                "script": "scripts/make_data.py",
                "seed": seed,
                "pairs": pairs,
                "rejected": rec.rejected,
            }
        },
    )
    manifest.save(out / "manifest.json")
    return manifest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=ROOT)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for name in ("reentry", "reaction"):
        if (args.out / name).exists():
            shutil.rmtree(args.out / name)
    m = make_reentry(args.out / "reentry", pairs=2000, validation=0.15, test=5, seed=args.seed)
    counts = {s: sum(r.split == s for r in m.recordings) for s in ("train", "validation", "test")}
    print(f"data/reentry: {counts}")
    m = simulate_dataset("reaction", args.out / "reaction", recordings=30, seed=args.seed)
    counts = {s: sum(r.split == s for r in m.recordings) for s in ("train", "validation", "test")}
    print(f"data/reaction: {counts}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
