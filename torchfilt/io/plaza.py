"""Loader for the CMU "Plaza" range-only robot data sets shipped in the gtsam wheel.

Djugash & Singh's Plaza runs: a wheeled robot with ground-truth pose (GPS-RTK), wheel odometry and
ranges to 4 surveyed radio beacons that arrive irregularly, one beacon at a time. gtsam ships them
as ``gtsam/Data/Plaza{1,2}_.mat`` with arrays ``GT`` (time, x, y, heading), ``DR`` (time, distance
and heading increments of the odometry), ``TD`` (time, sensor, beacon id, range) and ``TL``
(beacon id, x, y).

Facts of the data a model has to respect (checked in ``tests/io/test_plaza.py``):

- the robot travels along ``heading + pi``: the ground-truth heading points backwards;
- the odometry distance is unsigned: where the robot backs up (twice in the last 8 s of Plaza2) it
  still reads positive;
- against the ground truth the odometry is biased: the true heading change is ~1.015 times the
  odometry's plus ~7e-4 rad per 0.1 s step (dead reckoning drifts by ~0.4 rad a minute), and
  the ranges read ~7 % long (``r ~ 1.07 d``, residual sd ~0.57 m, white).

This loader is optional: it needs ``gtsam`` (for the files) and ``scipy`` (``loadmat``), installed
by the ``plaza`` or ``dev`` extras.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfilt.exceptions import InputError, MissingDependencyError, MissingFileError
from torchfilt.io.manifest import Channel
from torchfilt.io.recording import Recording

__all__ = ["PlazaData", "load_plaza", "plaza_path"]


@dataclass
class PlazaData:
    """A Plaza run on a regular time grid.

    Attributes:
        recording: states ``x, y, heading`` (ground truth, heading unwrapped), inputs
            ``odo_distance, odo_heading`` (odometry increments from row ``k`` to ``k + 1``; the
            last row's are 0) and measurements ``range_b{id}`` per beacon (NaN when no reading
            fell in that step).
        beacons: beacon id -> surveyed position ``(x, y)`` in metres.
        readings: number of range readings in the source file.
        collisions: readings dropped because another reading of the same beacon fell in the same
            step (the first one is kept).
        source: the ``.mat`` file.
    """

    recording: Recording
    beacons: dict[int, tuple[float, float]]
    readings: int
    collisions: int
    source: Path


def plaza_path(which: int = 2) -> Path:
    """Path of ``Plaza{which}_.mat`` inside the installed gtsam package."""
    if which not in (1, 2):
        raise InputError(f"which must be 1 or 2, got {which!r}")
    spec = importlib.util.find_spec("gtsam")
    if spec is None or spec.origin is None:
        raise MissingDependencyError(
            "the Plaza data ships with the gtsam wheel: pip install gtsam (or torchfilt[plaza])"
        )
    path = Path(spec.origin).parent / "Data" / f"Plaza{which}_.mat"
    if not path.is_file():
        raise MissingFileError(
            f"{path}: not found in the installed gtsam package (reinstall it: pip install gtsam)"
        )
    return path


def load_plaza(which: int = 2, dt: float = 0.1) -> PlazaData:
    """Load a Plaza run resampled onto a regular grid of period ``dt`` seconds.

    Ground truth is interpolated linearly (heading unwrapped first); odometry increments are the
    differences of the cumulative odometry interpolated at the grid times; each range reading is
    assigned to the nearest grid time (an error of at most ``dt / 2`` in time).

    Args:
        which: Plaza run 1 or 2.
        dt: grid period in seconds.

    Returns:
        A :class:`PlazaData`.
    """
    if not dt > 0:
        raise InputError(f"dt must be positive, got {dt}")
    try:
        from scipy.io import loadmat
    except ImportError:
        raise MissingDependencyError(
            "load_plaza needs scipy: pip install scipy (or torchfilt[plaza])"
        ) from None
    path = plaza_path(which)
    d = loadmat(path)
    gt, dr, td, tl = d["GT"], d["DR"], d["TD"], d["TL"]
    t0, t1 = gt[0, 0], gt[-1, 0]
    t = t0 + dt * np.arange(int(np.floor((t1 - t0) / dt)) + 1)
    heading = np.unwrap(gt[:, 3])
    x = np.interp(t, gt[:, 0], gt[:, 1])
    y = np.interp(t, gt[:, 0], gt[:, 2])
    th = np.interp(t, gt[:, 0], heading)
    # cumulative odometry, starting at 0 at the first DR time
    cum_t = np.concatenate([[gt[0, 0]], dr[:, 0]])
    cum_d = np.concatenate([[0.0], np.cumsum(dr[:, 1])])
    cum_h = np.concatenate([[0.0], np.cumsum(dr[:, 2])])
    od = np.diff(np.interp(t, cum_t, cum_d), append=np.nan)
    oh = np.diff(np.interp(t, cum_t, cum_h), append=np.nan)
    od[-1] = oh[-1] = 0.0
    ids = [int(b) for b in tl[:, 0]]
    ranges = {b: np.full(t.shape, np.nan) for b in ids}
    collisions = 0
    k = np.rint((td[:, 0] - t0) / dt).astype(int)
    for kk, b, r in zip(k, td[:, 2].astype(int), td[:, 3], strict=True):
        if not 0 <= kk < t.size:
            continue
        if np.isnan(ranges[b][kk]):
            ranges[b][kk] = r
        else:
            collisions += 1
    channels = (
        Channel("x", "state", "m"),
        Channel("y", "state", "m"),
        Channel("heading", "state", "rad"),
        Channel("odo_distance", "input", "m"),
        Channel("odo_heading", "input", "rad"),
        *(Channel(f"range_b{b}", "measurement", "m") for b in ids),
    )
    cols = {"x": x, "y": y, "heading": th, "odo_distance": od, "odo_heading": oh}
    cols.update({f"range_b{b}": ranges[b] for b in ids})
    rec = Recording.from_arrays(t - t0, channels, cols)
    rec.path = path
    beacons = {int(b): (float(bx), float(by)) for b, bx, by in tl}
    return PlazaData(rec, beacons, int(td.shape[0]), collisions, path)
