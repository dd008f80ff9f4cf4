"""A user's own sensor as a recipe's known measurement model: ``[measurement] model =
"package.module:function"`` (an *entry point*), beside the built-in ``"system:NAME"``.

The entry point names an attribute of an importable module (on ``sys.path`` when the recipe is
trained and again when its bundle is loaded):

- a function ``h(x)`` or ``h(x, u)`` mapping states ``(..., n)`` (and inputs ``(..., nu)``) to
  measurements ``(..., m)``, broadcasting over leading dimensions (``x[..., 0]``, not ``x[0]``);
  the recipe then gives the measurement noise, ``R = [r_1, ..., r_m]`` (variances, a diagonal) or
  ``R = [[...], ...]`` (the full ``(m, m)`` matrix);
- or a :class:`~torchfilt.models.ConditionalModel` instance with its own noise (``R``, if given,
  is added to it).

It is a *known* model: its parameters are frozen, so it fixes the gauge of a ``states = "none"``
fit as a built-in system does, and it is checked the same way before any training (it must map
the dataset's ``n`` states to its ``m`` measurement channels). A bundle records the entry point,
``R`` and the SHA-256 of the module's source file; loading the bundle imports the module again
and refuses it if the file changed since training (the model would not be the one that was
trained and validated), as does ``torchfilt train --resume``.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import re
from pathlib import Path
from typing import Any

import torch

from torchfilt.exceptions import BundleError, RecipeError, TorchfiltError
from torchfilt.models import (
    CholeskyCovariance,
    ConditionalModel,
    CovarianceParameter,
    DiagonalCovariance,
    as_conditional,
)

__all__ = [
    "ENTRY_POINT",
    "build_entry_point",
    "entry_point_digest",
    "entry_point_entry",
    "is_entry_point",
    "learned_noise",
    "load_entry_point",
]

#: The syntax of an entry point: a dotted module path, a colon, an attribute name.
ENTRY_POINT = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*$")


def is_entry_point(spec: Any) -> bool:
    """Whether a recipe's ``model`` value names an entry point (``"package.module:function"``)
    rather than a built-in ``"system:NAME"``."""
    return (
        isinstance(spec, str) and not spec.startswith("system:") and bool(ENTRY_POINT.match(spec))
    )


def _where(role: str) -> str:
    return f"[{role}] model"


def _import(spec: str, role: str) -> tuple[Any, str | None]:
    """The object an entry point names and the SHA-256 of its module's source file (``None``
    for a module without one)."""
    mod_name, attr = spec.split(":", 1)
    try:
        mod = importlib.import_module(mod_name)
    except Exception as e:
        raise RecipeError(
            f'{_where(role)} = "{spec}": cannot import module {mod_name!r} '
            f"({type(e).__name__}: {e}); put the folder that holds it on sys.path (PYTHONPATH)"
        ) from None
    if not hasattr(mod, attr):
        raise RecipeError(
            f'{_where(role)} = "{spec}": module {mod_name!r} has no attribute {attr!r}'
        )
    try:
        src = inspect.getsourcefile(mod)
    except TypeError:
        src = None
    digest = None if src is None else hashlib.sha256(Path(src).read_bytes()).hexdigest()
    return getattr(mod, attr), digest


def entry_point_digest(spec: str, role: str) -> str | None:
    """The SHA-256 of the source file of the module an entry point names (``None``: no file).

    Raises:
        RecipeError: the module does not import or lacks the attribute.
    """
    return _import(spec, role)[1]


def _noise(R: Any, m: int | None, spec: str, role: str) -> torch.Tensor:
    where = f'[{role}] R (of model = "{spec}")'
    try:
        t = torch.as_tensor(R, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise RecipeError(f"{where}: expected a list of numbers or of lists, got {R!r}") from None
    if t.dim() == 1:
        t = torch.diag(t)
    if t.dim() != 2 or t.shape[0] != t.shape[1] or (m is not None and t.shape[0] != m):
        raise RecipeError(
            f"{where}: expected {m if m is not None else 'm'} variances or an (m, m) matrix for "
            f"the measurement channels, got shape {tuple(t.shape)}"
        )
    if not bool(torch.isfinite(t).all()) or not torch.allclose(t, t.T):
        raise RecipeError(f"{where}: must be finite and symmetric")
    if float(torch.linalg.eigvalsh(t).min()) <= 0:
        raise RecipeError(f"{where}: must be positive definite")
    return t


def _conditional(
    obj: Any, noise: torch.Tensor | None, spec: str, role: str, n: int
) -> ConditionalModel:
    try:
        return as_conditional(obj, noise, name=role, noise_name="R", in_dim=n)
    except TorchfiltError as e:
        raise RecipeError(f'{_where(role)} = "{spec}": {e}') from None


def load_entry_point(
    spec: str,
    R: Any,
    *,
    role: str,
    state_dim: int,
    obs_dim: int | None,
    input_dim: int = 0,
    learn_R: bool = False,
) -> tuple[ConditionalModel, str | None]:
    """Import an entry point and build the known side it names, checked against the dataset's
    dimensions.

    Args:
        spec: ``"package.module:function"``.
        R: the recipe's ``R`` (variances or a matrix), or ``None``.
        role: ``"measurement"`` (the table named in errors).
        state_dim: ``n``.
        obs_dim: ``m`` (the dataset's measurement channels), or ``None`` to take it from ``R``.
        input_dim: ``nu`` (probe inputs are zeros).
        learn_R: ``R`` (required) is the start of a learnable noise
            (``[measurement_only] learn_measurement_noise``): a
            :class:`~torchfilt.models.DiagonalCovariance` where the recipe gave variances, a
            :class:`~torchfilt.models.CholeskyCovariance` where it gave a matrix; its parameters
            alone are left free.

    Returns:
        The side, frozen but for a learnable ``R``, and the SHA-256 of the module's source file.

    Raises:
        RecipeError: the module does not import, the attribute is missing or neither callable
            nor a ConditionalModel, ``R`` is missing or malformed, or the side does not map
            ``(1, n)`` states to ``(1, m)`` measurements.
    """
    obj, digest = _import(spec, role)
    noise: Any = None if R is None else _noise(R, obs_dim, spec, role)
    if learn_R:
        if noise is None:
            raise RecipeError(
                f'[{role}] R: a learned noise of model = "{spec}" needs R (its start)'
            )
        flat = torch.as_tensor(R, dtype=torch.float64).dim() == 1
        noise = DiagonalCovariance(noise) if flat else CholeskyCovariance(noise)
    if isinstance(obj, ConditionalModel):
        side = _conditional(obj, noise, spec, role, state_dim)
    elif callable(obj):
        if noise is None:
            raise RecipeError(
                f'[{role}] R: model = "{spec}" is a function; give its measurement noise, '
                "R = [variances, one per measurement channel] or the full (m, m) matrix"
            )
        side = _conditional(obj, noise, spec, role, state_dim)
    else:
        raise RecipeError(
            f'{_where(role)} = "{spec}": expected a function h(x) or h(x, u) or a '
            f"ConditionalModel, got {type(obj).__name__}"
        )
    side.requires_grad_(False)
    if isinstance(noise, CovarianceParameter):
        noise.requires_grad_(True)
    x = torch.zeros(1, state_dim, dtype=torch.float64)
    u = torch.zeros(1, input_dim, dtype=torch.float64) if input_dim else None
    try:
        with torch.no_grad():
            out = side.predict(x, u).mean
    except Exception as e:
        raise RecipeError(
            f'{_where(role)} = "{spec}": evaluating it on (1, {state_dim}) states failed '
            f"({type(e).__name__}: {e})"
        ) from None
    m = obs_dim if obs_dim is not None else side.out_dim
    if tuple(out.shape) != (1, m):
        raise RecipeError(
            f'{_where(role)} = "{spec}": maps (1, {state_dim}) states to shape '
            f"{tuple(out.shape)}, expected (1, {m}) (the dataset's measurement channels)"
        )
    return side, digest


def learned_noise(side: ConditionalModel) -> torch.Tensor | None:
    """The learnable noise ``(m, m)`` of a side built with ``learn_R=True`` (detached), or
    ``None`` where it has none."""
    for mod in side.modules():
        if isinstance(mod, CovarianceParameter) and any(p.requires_grad for p in mod.parameters()):
            return mod().detach().clone()
    return None


def entry_point_entry(
    spec: str, R: Any, *, role: str, state_dim: int, obs_dim: int, input_dim: int = 0
) -> dict[str, Any]:
    """The bundle entry of an entry-point side: ``kind = "entry_point"``, the entry point, ``R``
    as a tensor (or ``None``), the dimensions and the module file's SHA-256 (checked on load)."""
    _, digest = load_entry_point(
        spec, R, role=role, state_dim=state_dim, obs_dim=obs_dim, input_dim=input_dim
    )
    return {
        "kind": "entry_point",
        "entry_point": spec,
        "R": None if R is None else _noise(R, obs_dim, spec, role),
        "state_dim": state_dim,
        "obs_dim": obs_dim,
        "input_dim": input_dim,
        "sha256": digest,
    }


def build_entry_point(entry: dict[str, Any], role: str) -> ConditionalModel:
    """Rebuild an entry-point side from its bundle entry, after checking that its module's source
    file is the one it was trained with.

    Raises:
        BundleError: the module does not import, or its file changed (another SHA-256).
    """
    spec = str(entry["entry_point"])
    R = entry.get("R")
    try:
        side, digest = load_entry_point(
            spec, None if R is None else R.tolist(), role=role,
            state_dim=int(entry["state_dim"]), obs_dim=int(entry["obs_dim"]),
            input_dim=int(entry.get("input_dim", 0)),
        )  # fmt: skip
    except RecipeError as e:
        raise BundleError(f"{role} entry point: {e}") from None
    if digest != entry.get("sha256"):
        raise BundleError(
            f'{role} entry point "{spec}": its module file changed since the bundle was trained '
            f"(sha256 {str(digest)[:12]}, trained with {str(entry.get('sha256'))[:12]}); retrain, "
            "or restore the module it was trained with"
        )
    return side
