"""Built-in systems by name: model, channel names and units, sample time, and initial states.

Used by ``torchfilt simulate`` and the data-generation script to write synthetic recordings.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.models import StateSpaceModel
from torchfilt.systems import pendulum, reaction, reentry

__all__ = ["SYSTEMS", "SystemSpec", "get_system"]


@dataclass(frozen=True)
class SystemSpec:
    """A built-in system.

    Attributes:
        name: registry key.
        description: one line.
        model: factory of the true model (float64).
        states: state channel names and units.
        measurements: measurement channel names and units.
        sample_time: time between steps.
        steps: default number of steps per recording.
        initial: ``(runs, generator) -> (runs, n)`` initial states of simulated recordings.
        prior_mean: filter prior mean ``(n,)``.
        prior_cov: filter prior covariance ``(n, n)``.
        inputs: input channel names and units (none for autonomous systems).
        time_unit: unit of time.
        nominal: ``(**params) -> f(x, u)``, the transition with changed physical parameters
            (a nominal, possibly wrong, physics model to serve as a GP prior mean).
    """

    name: str
    description: str
    model: Callable[[], StateSpaceModel]
    states: list[tuple[str, str]]
    measurements: list[tuple[str, str]]
    sample_time: float
    steps: int
    initial: Callable[[int, torch.Generator], Tensor]
    prior_mean: Callable[[], Tensor]
    prior_cov: Callable[[], Tensor]
    inputs: list[tuple[str, str]] = field(default_factory=list)
    time_unit: str = "s"
    nominal: Callable[..., Callable[..., Tensor]] | None = None

    def nominal_transition(self, **params: float) -> Callable[..., Tensor]:
        """The transition with its physical parameters replaced by ``params``.

        Args:
            **params: the physical parameters to change, by name (``gamma=...``).

        Returns:
            The transition ``f(x, u)``, mapping ``(..., n)`` to ``(..., n)``.

        Raises:
            InputError: the system has no nominal model, or a parameter it does not take.
        """
        if self.nominal is None:
            raise InputError(f"system {self.name!r} has no nominal model with parameters")
        try:
            return self.nominal(**params)
        except TypeError as e:
            raise InputError(
                f"system {self.name!r}: bad nominal-model parameters {params}: {e}"
            ) from None


def _reentry_initial(runs: int, gen: torch.Generator) -> Tensor:
    """Truth initial states around the paper's x0: altitude and velocity spread as the filter
    prior (sd 1000 ft, 2000 ft/s); ballistic coefficient log-uniform in [3e-4, 3e-3]."""
    x0 = torch.tensor(reentry.X0_TRUE, dtype=torch.float64).expand(runs, 3).clone()
    z = torch.randn(runs, 2, generator=gen, dtype=torch.float64)
    x0[:, 0] += 1e3 * z[:, 0]
    x0[:, 1] += 2e3 * z[:, 1]
    logb = torch.empty(runs, dtype=torch.float64).uniform_(
        float(torch.log(torch.tensor(3e-4))), float(torch.log(torch.tensor(3e-3))), generator=gen
    )
    x0[:, 2] = logb.exp()
    return x0


def _pendulum_initial(runs: int, gen: torch.Generator) -> Tensor:
    return torch.stack(
        [
            torch.empty(runs, dtype=torch.float64).uniform_(-1.5, 1.5, generator=gen),
            torch.zeros(runs, dtype=torch.float64),
        ],
        -1,
    )


def _reaction_initial(runs: int, gen: torch.Generator) -> Tensor:
    """Partial pressures drawn uniformly in [0.5, 10] x [0.5, 5] (covers both papers' starts)."""
    lo = torch.tensor([0.5, 0.5], dtype=torch.float64)
    hi = torch.tensor([10.0, 5.0], dtype=torch.float64)
    return lo + (hi - lo) * torch.rand(runs, 2, generator=gen, dtype=torch.float64)


SYSTEMS: dict[str, SystemSpec] = {
    "reentry": SystemSpec(
        name="reentry",
        description="radar tracking of a re-entering vehicle (Athans et al. 1968; Wei & Song 2013)",
        model=reentry.model,
        states=[("altitude", "ft"), ("velocity", "ft/s"), ("ballistic", "")],
        measurements=[("range", "ft")],
        sample_time=reentry.DT,
        steps=reentry.STEPS,
        initial=_reentry_initial,
        prior_mean=lambda: torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float64),
        prior_cov=reentry.prior_cov,
        nominal=lambda gamma=reentry.GAMMA: functools.partial(reentry.transition, gamma=gamma),
    ),
    "reaction": SystemSpec(
        name="reaction",
        description="gas-phase reaction 2A -> B, total pressure measured (Liu, Zhang & Chu 2018)",
        model=reaction.model,
        states=[("PA", "atm"), ("PB", "atm")],
        measurements=[("pressure", "atm")],
        sample_time=reaction.DT,
        steps=reaction.STEPS,
        initial=_reaction_initial,
        prior_mean=lambda: reaction.prior_mean("paper"),
        prior_cov=reaction.prior_cov,
        nominal=lambda k1=reaction.K1: functools.partial(reaction.transition, k1=k1),
    ),
    "pendulum": SystemSpec(
        name="pendulum",
        description="noisy pendulum of Särkkä & Svensson (2023), angle observed through sin",
        model=pendulum.model,
        states=[("angle", "rad"), ("angular_velocity", "rad/s")],
        measurements=[("sin_angle", "")],
        sample_time=0.01,
        steps=500,
        initial=_pendulum_initial,
        prior_mean=lambda: torch.zeros(2, dtype=torch.float64),
        prior_cov=lambda: torch.eye(2, dtype=torch.float64),
    ),
}


def get_system(name: str) -> SystemSpec:
    """Look a built-in system up by name.

    Args:
        name: ``"reentry"``, ``"reaction"`` or ``"pendulum"``.

    Returns:
        The system's :class:`SystemSpec`.

    Raises:
        InputError: an unknown name (the message lists the known ones).
    """
    try:
        return SYSTEMS[name]
    except KeyError:
        raise InputError(
            f"unknown system {name!r}; built-in systems are {sorted(SYSTEMS)}"
        ) from None
