"""A dataset: a manifest plus its recordings, with splits, fingerprints and channel statistics."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchfilt.exceptions import InputError
from torchfilt.io.atomic import sha256_file
from torchfilt.io.errors import DataError
from torchfilt.io.manifest import SPLITS, Manifest
from torchfilt.io.recording import Recording, read_recording

__all__ = ["MANIFEST_NAME", "Dataset", "load_dataset"]

#: File name of the manifest inside a dataset folder.
MANIFEST_NAME = "manifest.json"
#: Splits whose recordings must have finite states and inputs (they are used for training;
#: states only when the training reads them: see ``load_dataset(require_finite=)``).
TRAINING_SPLITS = ("train", "validation")


@dataclass
class Dataset:
    """A loaded and validated dataset.

    Attributes:
        root: folder of the manifest (recording paths are relative to it).
        manifest: the manifest.
        recordings: the recordings, in manifest order.
        splits: split name of each recording.
        manifest_path: path of the manifest file.
    """

    root: Path
    manifest: Manifest
    recordings: list[Recording]
    splits: list[str]
    manifest_path: Path

    def split(self, name: str) -> list[Recording]:
        """The recordings of one split.

        Args:
            name: ``"train"``, ``"validation"`` or ``"test"``.

        Returns:
            The split's recordings, in manifest order.

        Raises:
            InputError: ``name`` is not a split.
        """
        if name not in SPLITS:
            raise InputError(f"split must be one of {SPLITS}, got {name!r}")
        return [r for r, s in zip(self.recordings, self.splits, strict=True) if s == name]

    @property
    def state_dim(self) -> int:
        """The number of state channels."""
        return len(self.manifest.names("state"))

    @property
    def input_dim(self) -> int:
        """The number of input channels."""
        return len(self.manifest.names("input"))

    @property
    def obs_dim(self) -> int:
        """The number of measurement channels."""
        return len(self.manifest.names("measurement"))

    def fingerprint(self) -> dict[str, Any]:
        """SHA-256 of every file, row counts, the split, and one hash over all of it."""
        files = {}
        for entry, rec in zip(self.manifest.recordings, self.recordings, strict=True):
            assert rec.path is not None
            files[entry.file] = {
                "sha256": sha256_file(rec.path),
                "rows": len(rec),
                "split": entry.split,
            }
        manifest_sha = sha256_file(self.manifest_path)
        h = hashlib.sha256(manifest_sha.encode())
        for name in sorted(files):
            h.update(f"{name}:{files[name]['sha256']}:{files[name]['split']}".encode())
        return {"dataset_sha256": h.hexdigest(), "manifest_sha256": manifest_sha, "files": files}

    def statistics(self, split: str | None = "train") -> dict[str, dict[str, float]]:
        """Per-channel count, missing count, mean, std, min and max over a split (or all)."""
        recs = self.recordings if split is None else self.split(split)
        out: dict[str, dict[str, float]] = {}
        names = [self.manifest.time_column, *(c.name for c in self.manifest.channels)]
        for j, name in enumerate(names):
            vals = (
                np.concatenate([r.time if j == 0 else r.data[:, j - 1] for r in recs])
                if recs
                else np.zeros(0)
            )
            ok = vals[np.isfinite(vals)]
            out[name] = {
                "count": int(vals.size),
                "missing": int(vals.size - ok.size),
                "mean": float(ok.mean()) if ok.size else float("nan"),
                "std": float(ok.std()) if ok.size else float("nan"),
                "min": float(ok.min()) if ok.size else float("nan"),
                "max": float(ok.max()) if ok.size else float("nan"),
            }
        return out

    def log(self) -> dict[str, Any]:
        """The dataset log a training run stores: manifest, fingerprint, split and statistics."""
        return {
            "manifest": str(self.manifest_path),
            "name": self.manifest.name,
            "fingerprint": self.fingerprint(),
            "split": {s: [r.name for r in self.split(s)] for s in SPLITS},
            "statistics": {s: self.statistics(s) for s in SPLITS if self.split(s)},
        }

    def check_dims(
        self,
        *,
        state_dim: int | None = None,
        obs_dim: int | None = None,
        input_dim: int | None = None,
    ) -> None:
        """Check that the dataset's channels fit a model's dimensions.

        Args:
            state_dim: the model's state dimension ``n`` (``None``: not checked).
            obs_dim: its measurement dimension ``m`` (``None``: not checked).
            input_dim: its input dimension ``nu`` (``None``: not checked).

        Raises:
            DataError: a dimension that is not the number of channels of its role.
        """
        for what, want, have, role in (
            ("states", state_dim, self.state_dim, "state"),
            ("measurements", obs_dim, self.obs_dim, "measurement"),
            ("inputs", input_dim, self.input_dim, "input"),
        ):
            if want is not None and want != have:
                raise DataError(
                    f"the model has {want} {what} but the manifest declares {have} {role} channels "
                    f"{self.manifest.names(role)}",
                    path=self.manifest_path,
                )


def load_dataset(
    path: str | Path,
    *,
    require_finite: Sequence[str] = ("state", "input"),
    splits: Sequence[str] | None = None,
    optional: Sequence[str] = (),
) -> Dataset:
    """Load a dataset from its manifest file or its folder, validating every recording.

    Args:
        path: ``manifest.json`` or the folder holding it.
        require_finite: roles that may not be NaN in the training and validation splits.
        splits: load only these splits (default: all).
        optional: roles whose columns may be absent from a recording (read as all-NaN), e.g.
            ``("state",)`` for a recipe with ``states = "none"`` (learning from measurements
            alone), which also leaves ``"state"`` out of ``require_finite``.

    Returns:
        The dataset.

    Raises:
        DataError: for an invalid manifest or recording (the message names file, column and row).
    """
    path = Path(path)
    mpath = path / MANIFEST_NAME if path.is_dir() else path
    manifest = Manifest.load(mpath)
    if not manifest.recordings:
        raise DataError("the manifest lists no recordings", path=mpath)
    recs, spl = [], []
    for entry in manifest.recordings:
        if splits is not None and entry.split not in splits:
            continue
        finite = tuple(require_finite) if entry.split in TRAINING_SPLITS else ()
        recs.append(
            read_recording(
                mpath.parent / entry.file, manifest, require_finite=finite, optional=optional
            )
        )
        spl.append(entry.split)
    if splits is not None:
        manifest = Manifest(
            **{
                **manifest.__dict__,
                "recordings": tuple(e for e in manifest.recordings if e.split in splits),
            }
        )
    return Dataset(mpath.parent, manifest, recs, spl, mpath)
