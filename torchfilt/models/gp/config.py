"""The structural options of a GP model, as a plain, serialisable record."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from torchfilt.exceptions import InputError
from torchfilt.models.gp.kernels import KERNELS

__all__ = ["GPConfig", "GroupSpec", "resolve_inputs"]

Role = Literal["transition", "measurement"]


@dataclass(frozen=True)
class GroupSpec:
    """Outputs that share one batch GP: same input columns, same training rows.

    Attributes:
        outputs: output indices (into ``0..d-1``).
        features: input-feature indices (into the concatenated ``[x, u]``, ``0..n+nu-1``).
    """

    outputs: tuple[int, ...]
    features: tuple[int, ...]


@dataclass(frozen=True)
class GPConfig:
    """Everything needed to rebuild a GP model's structure (the numbers live in its state dict).

    Attributes:
        role: ``"transition"`` (inputs ``(x_k, u_k)``, target ``x_{k+1}``) or ``"measurement"``
            (inputs ``(x_k, u_k)``, target ``y_k``).
        state_dim: ``n``.
        input_dim: ``nu`` (0 without inputs).
        out_dim: ``d`` (``n`` for a transition, ``m`` for a measurement).
        kernel: ``"rbf"`` (default), ``"matern32"``, ``"matern52"`` or ``"matern12"``, with one
            lengthscale per input (ARD).
        structure: ``"independent"`` (a batch of independent GPs, the default), ``"multitask"``
            (linear model of coregionalisation over the outputs, exact) or ``"sparse"`` (SVGP with
            inducing points, independent outputs).
        groups: how outputs share GPs (from input selection and missing-data patterns).
        increment: the GP learns ``x_{k+1} - x_k``.
        prior_mean: the GP learns the residual from a user-given nominal model (a callable, not
            stored; re-attach it with ``from_state(..., prior_mean=fn)``).
        num_latents: LMC latent kernels (``structure="multitask"``).
        task_rank: rank of each coregionalisation matrix (``structure="multitask"``).
        num_inducing: inducing points per output (``structure="sparse"``).
        noise_floor: lower bound of each output's likelihood noise variance, in target units.
        noise_fixed: the likelihood noise is held fixed (not learned).
        constant_outputs: outputs whose (residual) target had no spread in the data, e.g. the
            increment of a constant parameter. They get no GP: their prediction is the base plus
            that constant, with zero variance.

    Raises:
        InputError: an unknown ``role``, ``kernel`` or ``structure``, ``increment`` with
            ``prior_mean`` or for a measurement, or a non-positive size.
    """

    role: Role
    state_dim: int
    input_dim: int
    out_dim: int
    kernel: str = "rbf"
    structure: str = "independent"
    groups: tuple[GroupSpec, ...] = ()
    increment: bool = False
    prior_mean: bool = False
    num_latents: int = 1
    task_rank: int = 1
    num_inducing: int = 256
    noise_floor: tuple[float, ...] = field(default=())
    noise_fixed: bool = False
    constant_outputs: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.role not in ("transition", "measurement"):
            raise InputError(f"role must be 'transition' or 'measurement', got {self.role!r}")
        if self.kernel not in KERNELS:
            raise InputError(f"kernel must be one of {sorted(KERNELS)}, got {self.kernel!r}")
        if self.structure not in ("independent", "multitask", "sparse"):
            raise InputError(
                f"structure must be 'independent', 'multitask' or 'sparse', got {self.structure!r}"
            )
        if self.increment and self.prior_mean:
            raise InputError(
                "increment and prior_mean are exclusive: a prior mean already predicts the "
                "target; the GP learns target - prior_mean(x, u)"
            )
        if self.increment and self.role != "transition":
            raise InputError("increment=True is for transitions (it learns x_{k+1} - x_k)")
        if self.num_latents < 1 or self.task_rank < 1 or self.num_inducing < 1:
            raise InputError("num_latents, task_rank and num_inducing must be positive")

    @property
    def features(self) -> int:
        """Number of input features ``n + nu``."""
        return self.state_dim + self.input_dim

    def to_dict(self) -> dict[str, Any]:
        """Plain types only (safe for ``torch.load(weights_only=True)``)."""
        out = asdict(self)
        out["groups"] = [
            {"outputs": list(g.outputs), "features": list(g.features)} for g in self.groups
        ]
        out["noise_floor"] = list(self.noise_floor)
        out["constant_outputs"] = list(self.constant_outputs)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GPConfig:
        """Inverse of :meth:`to_dict`."""
        d = dict(d)
        d["groups"] = tuple(
            GroupSpec(tuple(int(i) for i in g["outputs"]), tuple(int(i) for i in g["features"]))
            for g in d.get("groups", ())
        )
        d["noise_floor"] = tuple(float(v) for v in d.get("noise_floor", ()))
        d["constant_outputs"] = tuple(int(v) for v in d.get("constant_outputs", ()))
        return cls(**d)


def resolve_inputs(
    inputs: Sequence[int] | Sequence[Sequence[int]] | None, out_dim: int, features: int, name: str
) -> list[tuple[int, ...]]:
    """Per-output input-feature selection from the user's ``inputs`` option.

    Args:
        inputs: ``None`` (every output sees every feature), one list of feature indices shared by
            all outputs, or one list per output.
        out_dim: number of outputs ``d``.
        features: number of features ``n + nu``.
        name: argument name for error messages.

    Returns:
        ``d`` sorted tuples of feature indices.
    """
    if inputs is None:
        return [tuple(range(features))] * out_dim
    items = list(inputs)
    if not items:
        raise InputError(f"{name}: must not be empty")
    per_output = all(isinstance(i, Sequence) and not isinstance(i, str) for i in items)
    shared = all(isinstance(i, int) and not isinstance(i, bool) for i in items)
    if not (per_output or shared):
        raise InputError(
            f"{name}: expected a list of feature indices or one list per output, got {inputs!r}"
        )
    lists: list[list[Any]] = (
        [list(i) for i in items] if per_output else [list(items)] * out_dim  # type: ignore[call-overload]
    )
    if len(lists) != out_dim:
        raise InputError(f"{name}: {len(lists)} selections given for {out_dim} outputs")
    out = []
    for j, sel in enumerate(lists):
        if not sel:
            raise InputError(f"{name}[{j}]: output {j} must see at least one input")
        for i in sel:
            if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < features:
                raise InputError(
                    f"{name}[{j}]: feature index {i!r} out of range; features are 0..{features - 1} "
                    "(state components first, then inputs u)"
                )
        if len(set(sel)) != len(sel):
            raise InputError(f"{name}[{j}]: repeated feature index in {sel}")
        out.append(tuple(sorted(int(i) for i in sel)))
    return out
