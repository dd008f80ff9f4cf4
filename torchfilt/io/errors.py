"""The error raised for invalid recordings, manifests and datasets (defined in
:mod:`torchfilt.exceptions`, re-exported here)."""

from __future__ import annotations

from torchfilt.exceptions import DataError

__all__ = ["DataError"]
