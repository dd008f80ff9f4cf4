"""Recordings and datasets: CSV/NPZ time series with a JSON manifest, validated at load time.

A *recording* is one time series: a time column and named channels, each a ``state`` (ground truth
or reference, when the log has it), an ``input`` or a ``measurement`` (NaN = not observed). A
*dataset* is a manifest plus recordings, split into train/validation/test by recording.
See ``data/FORMAT.md`` for the file format.
"""

from torchfilt.io.atomic import atomic_write, atomic_write_bytes, atomic_write_text, sha256_file
from torchfilt.io.dataset import Dataset, load_dataset
from torchfilt.io.errors import DataError
from torchfilt.io.manifest import ROLES, Channel, Manifest, RecordingEntry
from torchfilt.io.recording import Recording, read_recording, write_recording

__all__ = [
    "ROLES",
    "Channel",
    "DataError",
    "Dataset",
    "Manifest",
    "Recording",
    "RecordingEntry",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "load_dataset",
    "read_recording",
    "sha256_file",
    "write_recording",
]
