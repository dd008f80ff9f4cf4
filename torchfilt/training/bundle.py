"""Model bundles: one file holding a trained state-space model and where it came from.

A bundle is a ``torch.save`` file of plain tensors, dicts, lists, strings and numbers (no pickled
code), so it is loaded with ``torch.load(weights_only=True)``: a bundle can never run code, and a
tampered or foreign file is refused with a clear error. It holds, for each side of the model,
either a GP's state (training data or inducing points, hyperparameters, standardisation
statistics, options) or a reference to a built-in analytic model; the channel names and units;
the sample time; a default filter prior; the dataset fingerprint; the resolved recipe; validation
figures; and a schema version.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import BundleError, InputError
from torchfilt.io import Channel, atomic_write
from torchfilt.models import CalibratedModel, ConditionalModel, StateSpaceModel
from torchfilt.systems import get_system

__all__ = [
    "BUNDLE_SCHEMA",
    "BundleError",
    "ModelSpec",
    "build_side",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "save_bundle",
]

#: Schema identifier stored in every bundle.
BUNDLE_SCHEMA = "torchfilt.bundle/1"
_REQUIRED = ("schema", "transition", "measurement", "channels", "sample_time", "prior")


@dataclass
class ModelSpec:
    """A state-space model plus what is needed to run it on recordings.

    Attributes:
        model: the model.
        states, measurements, inputs: channel ``(name, unit)`` pairs, in model order.
        sample_time: time between steps the model was built for.
        prior_mean: default prior mean ``(n,)`` (state at the first row of a recording).
        prior_cov: default prior covariance ``(n, n)``.
        source: where the model came from (bundle path or ``system:NAME``).
        info: extra description (training data fingerprint, options, ...).
    """

    model: StateSpaceModel
    states: list[tuple[str, str]]
    measurements: list[tuple[str, str]]
    inputs: list[tuple[str, str]]
    sample_time: float
    prior_mean: Tensor
    prior_cov: Tensor
    source: str
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def channels(self) -> tuple[Channel, ...]:
        return (
            *(Channel(n, "state", u) for n, u in self.states),
            *(Channel(n, "input", u) for n, u in self.inputs),
            *(Channel(n, "measurement", u) for n, u in self.measurements),
        )

    @classmethod
    def from_system(cls, name: str) -> ModelSpec:
        """The built-in analytic model ``name`` (see :data:`torchfilt.systems.SYSTEMS`)."""
        sysspec = get_system(name)
        return cls(
            model=sysspec.model(),
            states=list(sysspec.states),
            measurements=list(sysspec.measurements),
            inputs=list(sysspec.inputs),
            sample_time=sysspec.sample_time,
            prior_mean=sysspec.prior_mean(),
            prior_cov=sysspec.prior_cov(),
            source=f"system:{name}",
            info={"description": sysspec.description},
        )


def nominal_model(spec: dict[str, Any]) -> Any:
    """A GP prior mean from its recipe/bundle description ``{system = NAME, **parameters}``."""
    params = {k: float(v) for k, v in spec.items() if k != "system"}
    return get_system(str(spec["system"])).nominal_transition(**params)


def build_side(entry: dict[str, Any], role: str) -> ConditionalModel:
    """Rebuild one side (``"transition"`` or ``"measurement"``) of a model from its bundle entry."""
    kind = entry.get("kind")
    if kind == "system":
        model = get_system(str(entry["system"])).model()
        return model.transition if role == "transition" else model.measurement
    if kind == "gp":
        from torchfilt.models.gp import GPMeasurement, GPTransition  # heavy import (gpytorch)

        cls = GPTransition if role == "transition" else GPMeasurement
        pm = entry.get("prior_mean")
        return cls.from_state(entry["state"], prior_mean=None if pm is None else nominal_model(pm))
    raise BundleError(f"unknown {role} kind {kind!r} (expected 'gp' or 'system')")


def apply_calibration(side: ConditionalModel, entry: dict[str, Any] | None) -> ConditionalModel:
    """Wrap a side in a :class:`~torchfilt.models.CalibratedModel` with its stored variance scales
    and floor ``{"scale": [...], "floor": [...]}`` (``None``: the side as it is)."""
    if not entry:
        return side
    try:
        cal = CalibratedModel(
            side,
            scale=entry["scale"],
            floor=entry["floor"],
            min_scale=float(entry.get("min_scale", 0.0)),
        )
    except (InputError, KeyError) as e:
        raise BundleError(f"invalid calibration entry ({e})") from None
    cal.requires_grad_(False)
    return cal


def save_bundle(path: str | Path, bundle: dict[str, Any]) -> Path:
    """Write a bundle atomically (temporary file + rename)."""
    bundle = {"schema": BUNDLE_SCHEMA, **bundle}
    missing = [k for k in _REQUIRED if k not in bundle]
    if missing:
        raise ValueError(f"bundle is missing {missing}")
    return atomic_write(path, lambda fh: torch.save(bundle, fh))


def load_bundle(path: str | Path) -> dict[str, Any]:
    """Load and check a bundle without running any code from it.

    Raises:
        FileNotFoundError: no such file.
        BundleError: the file is corrupted, is not a torchfilt bundle, or contains pickled Python
            objects other than plain data (a tampered or foreign file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model bundle not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        detail = next((ln.strip() for ln in str(e).splitlines() if "Unsupported global" in ln), "")
        raise BundleError(
            f"{path}: refused: the file contains Python objects that are not plain data, so it is "
            f"not a torchfilt bundle (tampered or foreign file; loading it could run code). {detail}"
        ) from None
    except Exception as e:  # corrupt zip, truncated file, not a torch file at all
        raise BundleError(
            f"{path}: not a readable torchfilt model bundle ({type(e).__name__}: {e})"
        ) from None
    if not isinstance(obj, dict) or obj.get("schema") != BUNDLE_SCHEMA:
        found = obj.get("schema") if isinstance(obj, dict) else type(obj).__name__
        raise BundleError(
            f"{path}: not a torchfilt model bundle (expected schema {BUNDLE_SCHEMA!r}, found {found!r})"
        )
    missing = [k for k in _REQUIRED if k not in obj]
    if missing:
        raise BundleError(f"{path}: incomplete bundle, missing {missing}")
    return obj


def load_model_spec(path: str | Path) -> ModelSpec:
    """A bundle's model with its channels, sample time and default prior."""
    b = load_bundle(path)
    try:
        cal = b.get("calibration") or {}
        model = StateSpaceModel(
            apply_calibration(build_side(b["transition"], "transition"), cal.get("transition")),
            apply_calibration(build_side(b["measurement"], "measurement"), cal.get("measurement")),
        )
    except (KeyError, TypeError) as e:
        raise BundleError(f"{path}: malformed model entry ({type(e).__name__}: {e})") from None
    ch = b["channels"]
    return ModelSpec(
        model=model,
        states=[tuple(c) for c in ch["states"]],  # type: ignore[misc]
        measurements=[tuple(c) for c in ch["measurements"]],  # type: ignore[misc]
        inputs=[tuple(c) for c in ch.get("inputs", [])],  # type: ignore[misc]
        sample_time=float(b["sample_time"]),
        prior_mean=b["prior"]["mean"],
        prior_cov=b["prior"]["cov"],
        source=str(path),
        info={
            k: b[k]
            for k in ("name", "dataset", "calibration", "validation", "recipe", "created")
            if b.get(k) is not None
        },
    )


def load_model(path: str | Path) -> StateSpaceModel:
    """The state-space model in a bundle, ready for :class:`~torchfilt.CKF`."""
    return load_model_spec(path).model
