"""Synthetic datasets from built-in systems (the engine of ``torchfilt simulate``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchfilt.io.manifest import Channel, Manifest, RecordingEntry
from torchfilt.io.recording import Recording, write_recording
from torchfilt.systems import get_system, simulate

__all__ = ["simulate_dataset"]


def simulate_dataset(
    system: str,
    out: str | Path,
    *,
    recordings: int = 10,
    steps: int | None = None,
    seed: int = 0,
    splits: tuple[float, float, float] = (0.7, 0.15, 0.15),
    fmt: str = ".csv",
    missing: float = 0.0,
) -> Manifest:
    """Simulate recordings of a built-in system and write them with a manifest.

    Each recording starts from the system's initial-state distribution; states (ground truth) and
    measurements are written, measurements thinned at random with probability ``missing``.
    Recordings with non-finite states are re-drawn.

    Args:
        system: a name from :data:`torchfilt.systems.SYSTEMS`.
        out: output folder (created).
        recordings: number of recordings.
        steps: steps per recording (default: the system's).
        seed: random seed; the same seed gives the same files.
        splits: fractions for train, validation and test (by recording).
        fmt: ``".csv"`` or ``".npz"``.
        missing: probability that a measurement is not observed.

    Returns:
        The manifest written to ``out/manifest.json``.
    """
    spec = get_system(system)
    if recordings < 1:
        raise ValueError(f"recordings must be >= 1, got {recordings}")
    if not 0.0 <= missing < 1.0:
        raise ValueError(f"missing must be in [0, 1), got {missing}")
    if len(splits) != 3 or any(s < 0 for s in splits) or sum(splits) <= 0:
        raise ValueError(f"splits must be three non-negative fractions, got {splits}")
    if fmt not in (".csv", ".npz"):
        raise ValueError(f"fmt must be '.csv' or '.npz', got {fmt!r}")
    steps = spec.steps if steps is None else steps
    out = Path(out)
    gen = torch.Generator().manual_seed(seed)
    model = spec.model()
    xs, ys = [], []
    have = 0
    for _ in range(100):
        x0 = spec.initial(recordings, gen)
        sim = simulate(model, steps, x0, generator=gen)
        ok = torch.isfinite(sim.states).all(-1).all(-1) & torch.isfinite(sim.measurements).all(
            -1
        ).all(-1)
        xs.append(torch.cat([sim.initial[ok, None], sim.states[ok]], 1))
        ys.append(sim.measurements[ok])
        have += int(ok.sum())
        if have >= recordings:
            break
    else:
        raise RuntimeError(f"{system}: could not draw {recordings} finite recordings")
    X = torch.cat(xs)[:recordings]
    Y = torch.cat(ys)[:recordings]
    if missing > 0:
        drop = torch.rand(Y.shape, generator=gen, dtype=Y.dtype) < missing
        Y = Y.masked_fill(drop, float("nan"))
    channels = (
        *(Channel(n, "state", u) for n, u in spec.states),
        *(Channel(n, "measurement", u) for n, u in spec.measurements),
    )
    n_train = round(splits[0] / sum(splits) * recordings)
    n_val = round(splits[1] / sum(splits) * recordings)
    entries = []
    t = np.arange(steps + 1) * spec.sample_time
    for r in range(recordings):
        # row 0 is the initial state, not yet measured
        y = np.concatenate([np.full((1, Y.shape[-1]), np.nan), Y[r].numpy()])
        cols = {c.name: X[r, :, i].numpy() for i, c in enumerate(channels[: X.shape[-1]])}
        cols.update({c.name: y[:, j] for j, c in enumerate(channels[X.shape[-1] :])})
        rec = Recording.from_arrays(t, channels, cols)
        name = f"rec_{r:03d}{fmt}"
        write_recording(rec, out / name)
        split = "train" if r < n_train else "validation" if r < n_train + n_val else "test"
        entries.append(RecordingEntry(name, split))
    manifest = Manifest(
        name=system,
        sample_time=spec.sample_time,
        channels=channels,
        recordings=tuple(entries),
        time_column="time",
        time_unit=spec.time_unit,
        description=spec.description,
        extra={
            "generator": {
                "command": "torchfilt simulate",
                "system": system,
                "seed": seed,
                "steps": steps,
                "missing": missing,
            }
        },
    )
    manifest.save(out / "manifest.json")
    return manifest
