"""The sigma-point filter's step as an object the engines run (:class:`CubatureStep`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from torch import Tensor, nn

from torchfilt.cubature import CubatureRule
from torchfilt.filters import steps
from torchfilt.filters.inputs import FilterInputs, model_noise
from torchfilt.filters.results import StepRecord
from torchfilt.filters.steps import Belief, Noise, PredictCache, UnitPoints, UpdateStats
from torchfilt.models import StateSpaceModel
from torchfilt.numerics import safe_cholesky

__all__ = ["CubatureStep"]


@dataclass(eq=False)
class CubatureStep:
    """:func:`~torchfilt.filters.steps.predict` then :func:`~torchfilt.filters.steps.update`
    with fixed options: the :class:`~torchfilt.filters.engine.Step` of
    :class:`~torchfilt.filters.GaussianFilter`.

    Attributes:
        model: the state-space model. rule: the cubature rule.
        sqrt: square-root form. redraw: re-draw the update's points.
        point_variance: how per-point model variances enter (``"total"`` or ``"mean"``).
    """

    model: StateSpaceModel
    rule: CubatureRule
    sqrt: bool = False
    redraw: bool = True
    point_variance: Literal["total", "mean"] = "total"

    def step(
        self,
        points: UnitPoints,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        Q: Noise,
        R: Noise,
    ) -> tuple[Belief, StepRecord, tuple[Tensor, ...]]:
        """One filter step.

        Args:
            points: the rule's unit points in the run's dtype and device.
            belief: the filtered belief about ``x_{t-1}``, ``mean (..., n)``, ``cov (..., n, n)``.
            y: measurement ``(..., m)``, missing entries set to 0. obs: bool ``(..., m)``.
            u: the input row of the step, ``(..., nu)`` (to ``f`` and ``h`` alike: the input
                convention of :mod:`torchfilt.filters`), or ``None``.
            Q: process noise of the step. R: measurement noise of the step.

        Returns:
            The filtered belief about ``x_t``, the step's :class:`~torchfilt.filters.results.StepRecord`
            and extra per-step outputs (none here).
        """
        pred, cache = self.predict(belief, u, points, Q)
        post, stats = self.update(pred, y, obs, u, points, R, cache)
        record = StepRecord(
            mean=post.mean,
            cov=post.cov,
            predicted_mean=pred.mean,
            predicted_cov=pred.cov,
            measurement_mean=stats.measurement_mean,
            innovation=stats.innovation,
            innovation_cov=stats.innovation_cov,
            log_likelihood=stats.log_likelihood,
            cross_cov=cache.cross_cov,
        )
        return post, record, ()

    def predict(
        self, belief: Belief, u: Tensor | None, points: UnitPoints, Q: Noise
    ) -> tuple[Belief, PredictCache]:
        """:func:`~torchfilt.filters.steps.predict` with this step's options."""
        return steps.predict(
            belief,
            self.model,
            u,
            points,
            sqrt=self.sqrt,
            point_variance=self.point_variance,
            noise=Q,
        )

    def update(
        self,
        belief: Belief,
        y: Tensor,
        obs: Tensor,
        u: Tensor | None,
        points: UnitPoints,
        R: Noise,
        cache: PredictCache | None,
    ) -> tuple[Belief, UpdateStats]:
        """:func:`~torchfilt.filters.steps.update` with this step's options."""
        return steps.update(
            belief,
            y,
            obs,
            self.model,
            points,
            u=u,
            sqrt=self.sqrt,
            redraw=self.redraw,
            point_variance=self.point_variance,
            noise=R,
            cache=cache,
        )

    def prior(self, inputs: FilterInputs) -> Belief:
        """The belief a run starts from: fresh copies of ``x0`` and ``P0`` (under
        inference_mode they are inference tensors like every later belief, so a compiled first
        step or chunk does not compile a variant of its own), factored in the square-root form
        only (the plain form factors the covariance in the step)."""
        mean, cov = inputs.x0.clone(), inputs.P0.clone()
        return Belief(mean, cov, safe_cholesky(cov, name="P0") if self.sqrt else None)

    def noise(self, side: nn.Module, t: int, like: Tensor) -> Noise:
        """The noise of ``side`` at step ``t`` (with its square root in the square-root form)."""
        cov = model_noise(side, t, like)
        return Noise(cov, None if cov is None or not self.sqrt else steps.noise_sqrt(cov))

    def points(self, like: Tensor) -> UnitPoints:
        """The rule's unit points in ``like``'s dtype and device."""
        return steps.unit_points(self.rule, self.model.state_dim, like)
