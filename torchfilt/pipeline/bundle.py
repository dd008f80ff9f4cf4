"""Model bundles: one file holding a trained state-space model and where it came from.

A bundle (schema ``torchfilt.bundle/2``) is a one-line header, then a payload::

    torchfilt.bundle/2 sha256=<64 hex digits of the payload>\\n
    <payload: a torch.save file of plain tensors, dicts, lists, strings and numbers>

Loading checks, in order, and refuses the file with a one-line :class:`BundleError` naming it:

1. the header and the SHA-256 of the payload (any changed, missing or added byte is caught);
2. the payload is plain data (``torch.load(weights_only=True)``: a bundle can never run code);
3. the schema and the required entries, and the values: every model tensor finite,
   standardisation scales, lengthscales and output scales positive, noise non-negative, the prior
   covariance symmetric positive semi-definite, the sample time finite and positive, the channel
   and prior dimensions consistent;
4. the model rebuilds (a tensor whose shape was edited is named).

The payload holds, for each side of the model, either a GP's state (training data or inducing
points, hyperparameters, standardisation statistics, options, and the frozen predictor's cache, so
loading does not choose the variance form again) or a reference to a built-in analytic model; the
channel names and units; the time column's name; the sample time; a default filter prior; the
dataset fingerprint; the resolved recipe; validation figures; and the schema version.

Bundles of the earlier schema ``torchfilt.bundle/1`` (a bare ``torch.save`` file: no checksum, no
cache) still load, with an :class:`UnverifiedBundleWarning`: their values are range-checked and
the GP caches are recomputed (slow). :func:`upgrade_bundle` rewrites one as a verified, fast
bundle.
"""

from __future__ import annotations

import hashlib
import io
import math
import pickle
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import BundleError, InputError, TorchfiltWarning
from torchfilt.io import Channel, atomic_write_bytes
from torchfilt.models import (
    CalibratedModel,
    ConditionalModel,
    InducingTransition,
    StateSpaceModel,
    as_conditional,
)
from torchfilt.pipeline.entry_point import build_entry_point
from torchfilt.systems import get_system

__all__ = [
    "BUNDLE_SCHEMA",
    "LEGACY_SCHEMA",
    "BundleError",
    "ModelSpec",
    "UnverifiedBundleWarning",
    "build_side",
    "check_bundle",
    "inducing_state",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "save_bundle",
    "upgrade_bundle",
]

#: Schema identifier stored in every bundle (and in its header).
BUNDLE_SCHEMA = "torchfilt.bundle/2"
#: The schema of earlier releases (a bare torch.save file without checksum or caches).
LEGACY_SCHEMA = "torchfilt.bundle/1"
_REQUIRED = ("schema", "transition", "measurement", "channels", "sample_time", "prior")
_HEADER = re.compile(rb"^torchfilt\.bundle/(\d+) sha256=([0-9a-f]{64})\n")
#: Tensors (by state-dict key) that must be positive in a GP state.
_POSITIVE_STATE = ("input_std.scale", "target_std.scale")
#: Frozen-cache arguments that must be positive, and those that must be non-negative.
_POSITIVE_CACHE = ("in_scale", "out_scale", "lengthscale", "outputscale")
_NONNEGATIVE_CACHE = ("noise", "extra_diag")
#: Relative tolerance of the prior covariance's symmetry and positive semi-definiteness.
PRIOR_PSD_RTOL = 1e-9


class UnverifiedBundleWarning(TorchfiltWarning):
    """A bundle of the earlier schema was loaded: it has no checksum and no predictor cache."""


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
        time_column: name of the recordings' time column (the training manifest's).
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
    time_column: str = "time"

    @property
    def channels(self) -> tuple[Channel, ...]:
        """Every channel: the states, then the inputs, then the measurements."""
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


#: The tensors of an ``"inducing"`` transition entry's state (besides ``state_dim``,
#: ``input_dim`` and ``jitter``): the :class:`~torchfilt.models.InducingTransition` parameters and
#: buffer, and the process noise ``Q``.
INDUCING_TENSORS = (
    "linear",
    "bias",
    "inducing_inputs",
    "inducing_outputs",
    "log_lengthscale",
    "log_outputscale",
    "floor",
    "Q",
)


def inducing_state(side: ConditionalModel) -> dict[str, Any]:
    """The plain-data state of an :class:`~torchfilt.models.InducingTransition` side (bare, or
    with an additive process noise ``Q`` as :func:`~torchfilt.models.as_conditional` wraps it):
    ``state_dim``, ``input_dim``, ``jitter`` and the tensors of :data:`INDUCING_TENSORS`
    (detached copies; ``Q (n, n)`` zero if the side has no additive noise). The nominal model is
    not part of it (the bundle entry names it by its recipe description)."""
    base = getattr(side, "base", side)
    if not isinstance(base, InducingTransition):
        raise InputError(f"side: expected an InducingTransition, got {type(base).__name__}")
    n = base.out_dim
    with torch.no_grad():
        Q = side.noise_cov()
        Q = torch.zeros(n, n, dtype=base.linear.dtype) if Q is None else Q.detach().clone()
        out: dict[str, Any] = {
            "state_dim": n,
            "input_dim": base.input_dim,
            "jitter": base.jitter,
        }
        for name in INDUCING_TENSORS[:-1]:
            out[name] = getattr(base, name).detach().clone()
        out["Q"] = Q
    return out


def _build_inducing(entry: dict[str, Any]) -> ConditionalModel:
    st = entry["state"]
    nom = entry.get("nominal")
    f = InducingTransition(
        int(st["state_dim"]),
        st["inducing_inputs"],
        input_dim=int(st["input_dim"]),
        linear=st["linear"],
        bias=st["bias"],
        lengthscale=st["log_lengthscale"].exp(),
        outputscale=st["log_outputscale"].exp(),
        floor=st["floor"],
        jitter=float(st["jitter"]),
        nominal=None if nom is None else nominal_model(nom),
        dtype=st["linear"].dtype,
    )
    with torch.no_grad():
        f.inducing_outputs.copy_(st["inducing_outputs"])
        f.log_lengthscale.copy_(st["log_lengthscale"])
        f.log_outputscale.copy_(st["log_outputscale"])
    f.requires_grad_(False)
    return as_conditional(f, st["Q"], name="transition", noise_name="Q")


def build_side(entry: dict[str, Any], role: str) -> ConditionalModel:
    """Rebuild one side (``"transition"`` or ``"measurement"``) of a model from its bundle entry:
    a built-in system's (``kind = "system"``), a GP (``"gp"``), or an
    :class:`~torchfilt.models.InducingTransition` learned from measurements alone
    (``"inducing"``, transition only; its parameters are frozen)."""
    kind = entry.get("kind")
    if kind == "inducing" and role == "transition":
        return _build_inducing(entry)
    if kind == "entry_point" and role == "measurement":
        return build_entry_point(entry, role)
    if kind == "system":
        model = get_system(str(entry["system"])).model()
        return model.transition if role == "transition" else model.measurement
    if kind == "gp":
        from torchfilt.models.gp import GPMeasurement, GPTransition  # heavy import (gpytorch)

        cls = GPTransition if role == "transition" else GPMeasurement
        pm = entry.get("prior_mean")
        return cls.from_state(entry["state"], prior_mean=None if pm is None else nominal_model(pm))
    raise BundleError(
        f"unknown {role} kind {kind!r} (expected 'gp', 'system' or, for the transition, "
        "'inducing', for the measurement 'entry_point')"
    )


def _payload(bundle: dict[str, Any]) -> bytes:
    buf = io.BytesIO()
    torch.save(bundle, buf)
    return buf.getvalue()


def save_bundle(path: str | Path, bundle: dict[str, Any]) -> Path:
    """Write a bundle atomically: the header with the payload's SHA-256, then the payload.

    Raises:
        BundleError: the bundle is incomplete or holds invalid values (the checks of
            :func:`load_bundle`).
        OutputError: the file cannot be written.
    """
    bundle = {**bundle, "schema": BUNDLE_SCHEMA}
    missing = [k for k in _REQUIRED if k not in bundle]
    if missing:
        raise BundleError(f"{path}: bundle is missing {missing}")
    check_bundle(bundle, path)
    payload = _payload(bundle)
    header = f"{BUNDLE_SCHEMA} sha256={hashlib.sha256(payload).hexdigest()}\n".encode()
    return atomic_write_bytes(path, header + payload)


def _torch_load(data: bytes, path: Path) -> Any:
    try:
        return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        detail = next((ln.strip() for ln in str(e).splitlines() if "Unsupported global" in ln), "")
        raise BundleError(
            f"{path}: refused: the file contains Python objects that are not plain data, so it is "
            f"not a torchfilt bundle (tampered or foreign file; loading it could run code). {detail}"
        ) from None
    except Exception as e:  # corrupt zip, truncated file, not a torch file at all
        msg = " ".join(str(e).split())[:200]
        raise BundleError(
            f"{path}: not a readable torchfilt model bundle ({type(e).__name__}: {msg})"
        ) from None


def load_bundle(path: str | Path) -> dict[str, Any]:
    """Load and verify a bundle without running any code from it (see the module docstring).

    Returns:
        The bundle's payload: a dict of plain data.

    Raises:
        BundleError: no such file; a checksum that does not match (a corrupted or edited file);
            a file that is not a torchfilt bundle or holds pickled Python objects other than plain
            data; invalid values. The message names the file and what is wrong.
    """
    path = Path(path)
    if not path.is_file():
        raise BundleError(f"{path}: model bundle not found")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise BundleError(f"{path}: cannot read the model bundle ({e.strerror})") from None
    m = _HEADER.match(raw)
    legacy = m is None
    if m is not None:
        schema = f"torchfilt.bundle/{int(m.group(1))}"
        if schema != BUNDLE_SCHEMA:
            raise BundleError(
                f"{path}: bundle schema {schema} is not readable by this version of torchfilt "
                f"(it reads {BUNDLE_SCHEMA} and {LEGACY_SCHEMA})"
            )
        payload = raw[m.end() :]
        if hashlib.sha256(payload).hexdigest() != m.group(2).decode():
            raise BundleError(
                f"{path}: checksum mismatch: the file is corrupted or was edited after it was "
                "written (the payload's SHA-256 differs from the header's)"
            )
        obj = _torch_load(payload, path)
    elif raw.startswith(b"torchfilt.bundle/"):
        raise BundleError(f"{path}: damaged bundle header (its first line)")
    else:
        obj = _torch_load(raw, path)
    expected = LEGACY_SCHEMA if legacy else BUNDLE_SCHEMA
    found = obj.get("schema") if isinstance(obj, dict) else type(obj).__name__
    if legacy and found == BUNDLE_SCHEMA:
        raise BundleError(f"{path}: the checksum header of a {BUNDLE_SCHEMA} bundle is missing")
    if not isinstance(obj, dict) or found != expected:
        raise BundleError(
            f"{path}: not a torchfilt model bundle (expected schema {expected!r}, found {found!r})"
        )
    missing = [k for k in _REQUIRED if k not in obj]
    if missing:
        raise BundleError(f"{path}: incomplete bundle, missing {missing}")
    check_bundle(obj, path)
    if legacy:
        warnings.warn(
            f"{path}: a bundle of the earlier schema {LEGACY_SCHEMA} has no checksum and no "
            "predictor cache (loading refits the GP caches); rewrite it with "
            "torchfilt.pipeline.upgrade_bundle",
            UnverifiedBundleWarning,
            stacklevel=2,
        )
    return obj


# ------------------------------------------------------------------------------ value checks
def _walk(obj: Any, where: str) -> Iterator[tuple[str, Tensor | float]]:
    """Every tensor and float inside ``obj``, with where it is."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, f"{where}.{k}")
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            yield from _walk(v, f"{where}[{i}]")
    elif isinstance(obj, Tensor | float):
        yield where, obj


def _bad(path: str | Path, where: str, what: str) -> BundleError:
    return BundleError(f"{path}: invalid value in {where}: {what}")


def _check_inducing(entry: dict[str, Any], role: str, path: str | Path, n: int) -> None:
    """Shapes, finiteness and ranges of an ``"inducing"`` entry (``n``: the bundle's states)."""
    if role != "transition":
        raise BundleError(f"{path}: malformed {role} entry (kind 'inducing' is a transition)")
    st = entry.get("state")
    if not isinstance(st, dict):
        raise BundleError(f"{path}: malformed {role} entry (no inducing state)")
    where = f"{role}.state"
    for key in ("state_dim", "input_dim"):
        v = st.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise _bad(path, f"{where}.{key}", f"must be a non-negative integer, got {v!r}")
    if st["state_dim"] != n:
        raise _bad(path, f"{where}.state_dim", f"{st['state_dim']} does not match {n} states")
    jit = st.get("jitter")
    if isinstance(jit, bool) or not isinstance(jit, int | float) or not 0 <= jit < math.inf:
        raise _bad(path, f"{where}.jitter", f"must be finite and non-negative, got {jit!r}")
    D = n + int(st["input_dim"])
    Z = st.get("inducing_inputs")
    M = int(Z.shape[0]) if isinstance(Z, Tensor) and Z.dim() == 2 else -1
    shapes = {
        "linear": (n, D),
        "bias": (n,),
        "inducing_inputs": (M, D),
        "inducing_outputs": (n, M),
        "log_lengthscale": (D,),
        "log_outputscale": (n,),
        "floor": (n,),
        "Q": (n, n),
    }
    for key, shape in shapes.items():
        v = st.get(key)
        if not isinstance(v, Tensor) or not v.is_floating_point():
            raise _bad(path, f"{where}.{key}", "missing or not a floating tensor")
        if M < 0 or tuple(v.shape) != shape:
            raise _bad(path, f"{where}.{key}", f"shape {tuple(v.shape)}, expected {shape}")
        if not bool(torch.isfinite(v).all()):
            raise _bad(path, f"{where}.{key}", "not finite")
    if not bool((st["floor"] >= 0).all()):
        raise _bad(path, f"{where}.floor", "must be non-negative")
    Q = st["Q"].double()
    tol = PRIOR_PSD_RTOL * float(Q.abs().max()) if n else 0.0
    if n and (float((Q - Q.mT).abs().max()) > tol or float(torch.linalg.eigvalsh(Q).min()) < -tol):
        raise _bad(path, f"{where}.Q", "not symmetric positive semi-definite")
    nom = entry.get("nominal")
    if nom is not None and (not isinstance(nom, dict) or not isinstance(nom.get("system"), str)):
        raise _bad(path, f"{role}.nominal", "must be a table with 'system' or None")


def _check_entry_point(entry: dict[str, Any], role: str, path: str | Path) -> None:
    """An entry-point side: a measurement, with its entry point, dimensions, a finite positive
    definite ``R`` (or none) and the module file's SHA-256 (checked when it is built)."""
    if role != "measurement" or not isinstance(entry.get("entry_point"), str):
        raise _bad(path, f"{role}.entry_point", "must be the measurement's entry point string")
    if not all(isinstance(entry.get(k), int) for k in ("state_dim", "obs_dim")):
        raise _bad(path, role, "entry point without its state_dim and obs_dim")
    R = entry.get("R")
    if R is not None and (
        not isinstance(R, Tensor)
        or not bool(torch.isfinite(R).all())
        or float(torch.linalg.eigvalsh(R.double()).min()) <= 0
    ):
        raise _bad(path, f"{role}.R", "must be a finite positive definite matrix")


def _check_side(entry: Any, role: str, path: str | Path, n: int = -1) -> None:
    kinds = ("gp", "system", "inducing", "entry_point")
    if not isinstance(entry, dict) or entry.get("kind") not in kinds:
        raise BundleError(
            f"{path}: malformed {role} entry (expected kind 'gp', 'system', 'inducing' or "
            "'entry_point')"
        )
    if entry["kind"] == "system":
        return
    if entry["kind"] == "entry_point":
        _check_entry_point(entry, role, path)
        return
    if entry["kind"] == "inducing":
        _check_inducing(entry, role, path, n)
        return
    state = entry.get("state")
    if not isinstance(state, dict) or not isinstance(state.get("state_dict"), dict):
        raise BundleError(f"{path}: malformed {role} entry (no GP state)")
    for where, v in _walk(state, f"{role}.state"):
        if isinstance(v, Tensor) and not v.is_floating_point():
            continue
        t = torch.as_tensor(v)
        if where.endswith(("_constraint.upper_bound", "_constraint.lower_bound")):
            if bool(t.isnan().any()):  # an unbounded constraint is +-inf
                raise _bad(path, where, "NaN")
            continue
        if not bool(torch.isfinite(t).all()):
            raise _bad(path, where, "not finite")
    sd = state["state_dict"]
    for key in _POSITIVE_STATE:
        v = sd.get(key)
        if isinstance(v, Tensor) and not bool((v > 0).all()):
            raise _bad(path, f"{role}.state.state_dict.{key}", "a scale must be positive")
    frozen = state.get("frozen")
    blocks = frozen.get("blocks", []) if isinstance(frozen, dict) else []
    for i, blk in enumerate(blocks):
        args = blk.get("args", {}) if isinstance(blk, dict) else {}
        for key in (*_POSITIVE_CACHE, *_NONNEGATIVE_CACHE):
            arg = args.get(key)
            positive = key in _POSITIVE_CACHE
            if isinstance(arg, Tensor) and not bool((arg > 0 if positive else arg >= 0).all()):
                raise _bad(
                    path,
                    f"{role}.state.frozen.blocks[{i}].{key}",
                    "must be positive" if positive else "must be non-negative",
                )


def check_bundle(b: dict[str, Any], path: str | Path) -> None:
    """Range-check a bundle's values (see the module docstring).

    Raises:
        BundleError: naming the file and the offending entry.
    """
    ch = b["channels"]
    try:
        n = len(ch["states"])
        ok = all(
            len(c) == 2 and all(isinstance(x, str) for x in c)
            for group in ("states", "measurements", "inputs")
            for c in ch.get(group, [])
        )
    except (TypeError, KeyError, AttributeError):
        ok = False
    if not ok:
        raise BundleError(f"{path}: malformed channels entry")
    for role in ("transition", "measurement"):
        _check_side(b[role], role, path, n)
    dt = b["sample_time"]
    if isinstance(dt, bool) or not isinstance(dt, int | float) or not math.isfinite(dt) or dt <= 0:
        raise _bad(path, "sample_time", f"must be finite and positive, got {dt!r}")
    prior = b["prior"]
    if not isinstance(prior, dict) or not all(
        isinstance(prior.get(k), Tensor) for k in ("mean", "cov")
    ):
        raise BundleError(f"{path}: malformed prior entry (needs tensors mean and cov)")
    m0, P0 = prior["mean"], prior["cov"]
    if tuple(m0.shape) != (n,) or tuple(P0.shape) != (n, n):
        raise _bad(
            path,
            "prior",
            f"mean {tuple(m0.shape)} and cov {tuple(P0.shape)} do not match {n} states",
        )
    if not bool(torch.isfinite(m0).all()) or not bool(torch.isfinite(P0).all()):
        raise _bad(path, "prior", "not finite")
    P = P0.double()
    tol = PRIOR_PSD_RTOL * float(P.abs().max()) if n else 0.0
    if n and (float((P - P.mT).abs().max()) > tol or float(torch.linalg.eigvalsh(P).min()) < -tol):
        raise _bad(path, "prior.cov", "not symmetric positive semi-definite")
    tc = b.get("time_column", "time")
    if not isinstance(tc, str) or not tc:
        raise _bad(path, "time_column", f"must be a non-empty string, got {tc!r}")


def apply_calibration(side: ConditionalModel, entry: dict[str, Any] | None) -> ConditionalModel:
    """Wrap a side in a :class:`~torchfilt.models.CalibratedModel` with its stored variance scales
    and floor ``{"scale": [...], "floor": [...], "min_scale": s}`` (``None``: the side as it is).

    Raises:
        BundleError: the entry is malformed or its values are not finite and positive.
    """
    if not entry:
        return side
    try:
        cal = CalibratedModel(
            side,
            scale=entry["scale"],
            floor=entry["floor"],
            min_scale=float(entry.get("min_scale", 0.0)),
        )
    except (InputError, KeyError, TypeError, ValueError) as e:
        raise BundleError(f"invalid calibration entry ({e})") from None
    cal.requires_grad_(False)
    return cal


def load_model_spec(path: str | Path) -> ModelSpec:
    """A bundle's model with its channels, time column, sample time and default prior.

    Raises:
        BundleError: see :func:`load_bundle`; also a model entry that does not rebuild (a tensor
            of the wrong shape, a missing key), named in one line.
    """
    b = load_bundle(path)
    sides = []
    for role in ("transition", "measurement"):
        try:
            sides.append(build_side(b[role], role))
        except BundleError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as e:
            msg = " ".join(str(e).split())
            msg = re.sub(r"^Error\(s\) in loading state_dict for \w+: ", "", msg)[:300]
            raise BundleError(f"{path}: malformed {role} model ({type(e).__name__}: {msg})") from e
    cal = b.get("calibration") or {}
    if not isinstance(cal, dict):
        raise BundleError(f"{path}: malformed calibration entry")
    for i, role in enumerate(("transition", "measurement")):
        try:
            sides[i] = apply_calibration(sides[i], cal.get(role))
        except BundleError as e:
            raise BundleError(f"{path}: {role}: {e}") from None
    ch = b["channels"]
    return ModelSpec(
        model=StateSpaceModel(*sides),
        states=[tuple(c) for c in ch["states"]],  # type: ignore[misc]
        measurements=[tuple(c) for c in ch["measurements"]],  # type: ignore[misc]
        inputs=[tuple(c) for c in ch.get("inputs", [])],  # type: ignore[misc]
        sample_time=float(b["sample_time"]),
        prior_mean=b["prior"]["mean"],
        prior_cov=b["prior"]["cov"],
        source=str(path),
        info={
            **{
                k: b[k]
                for k in (
                    "schema",
                    "name",
                    "dataset",
                    "calibration",
                    "validation",
                    "recipe",
                    "created",
                )
                if b.get(k) is not None
            },
            **(
                {"measurement_only": b["transition"]["fit"]}
                if b["transition"].get("kind") == "inducing" and "fit" in b["transition"]
                else {}
            ),
        },
        time_column=str(b.get("time_column", "time")),
    )


def load_model(path: str | Path) -> StateSpaceModel:
    """The state-space model in a bundle, ready for :class:`~torchfilt.CKF`."""
    return load_model_spec(path).model


def upgrade_bundle(path: str | Path, out: str | Path) -> Path:
    """Rewrite a bundle (of any readable schema) as a ``torchfilt.bundle/2`` bundle with a
    checksum and the frozen predictors' caches (computed once here).

    Args:
        path: the bundle to read.
        out: where to write the new bundle (a different file: ``path`` is left as it is).

    Returns:
        ``out``.

    Raises:
        BundleError: ``path`` is not a usable bundle, or ``out`` is ``path``.
        OutputError: ``out`` exists or cannot be written.
    """
    from torchfilt.io.atomic import check_new_outputs

    path, out = Path(path), Path(out)
    if out.resolve() == path.resolve():
        raise BundleError(f"{out}: write the upgraded bundle to another file than {path}")
    check_new_outputs([out], force=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnverifiedBundleWarning)
        b = load_bundle(path)
        spec = load_model_spec(path)
    for role in ("transition", "measurement"):
        if b[role]["kind"] == "gp":
            side: Any = getattr(spec.model, role)
            side = side.base if isinstance(side, CalibratedModel) else side
            b[role] = {**b[role], "state": side.to_state()}
    b.setdefault("time_column", spec.time_column)
    return save_bundle(out, b)
