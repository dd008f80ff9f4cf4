"""Synthetic datasets from built-in systems (the engine of ``torchfilt simulate``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchfilt.exceptions import InputError
from torchfilt.io.atomic import check_new_outputs, output_dir
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
    force: bool = False,
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
        force: replace a dataset already in ``out`` (its manifest and recordings, including
            recordings the new manifest does not list). Without it, an existing manifest or
            recording file in ``out`` is an error and nothing is written.

    Returns:
        The manifest written to ``out/manifest.json``.

    Raises:
        InputError: an invalid option (``steps < 1``, ``recordings < 1``, ...).
        OutputError: ``out`` holds a dataset (without ``force``), is a file, or is read-only.
    """
    spec = get_system(system)
    if isinstance(recordings, bool) or not isinstance(recordings, int) or recordings < 1:
        raise InputError(f"recordings must be an integer >= 1, got {recordings!r}")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise InputError(f"steps must be an integer >= 1, got {steps!r}")
    if not 0.0 <= missing < 1.0:
        raise InputError(f"missing must be in [0, 1), got {missing}")
    if len(splits) != 3 or any(not s >= 0 for s in splits) or not sum(splits) > 0:
        raise InputError(f"splits must be three non-negative fractions, got {splits}")
    if fmt not in (".csv", ".npz"):
        raise InputError(f"fmt must be '.csv' or '.npz', got {fmt!r}")
    steps = spec.steps if steps is None else steps
    out = Path(out)
    names = [f"rec_{r:03d}{fmt}" for r in range(recordings)]
    mpath = out / "manifest.json"
    check_new_outputs([mpath, *(out / n for n in names)], force=force)
    old = _listed_files(mpath) if force else []
    output_dir(out)
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
        raise InputError(f"{system}: could not draw {recordings} finite recordings")
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
        name = names[r]
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
    manifest.save(mpath)
    for f in old:  # --force: the replaced dataset's recordings that the new one does not list
        if f not in names and (out / f).is_file():
            (out / f).unlink()
    return manifest


def _listed_files(mpath: Path) -> list[str]:
    """The recording files an existing manifest lists (plain names inside its folder only)."""
    try:
        old = Manifest.load(mpath)
    except Exception:
        return []
    return [r.file for r in old.recordings if Path(r.file).name == r.file]
