"""SQUAREM acceleration of the linear-Gaussian EM of :func:`~torchfilt.training.fit_em`.

EM converges linearly, and slowly where the likelihood is flat: on a 4-state, 2-output model
fitted to 20 x 500 steps, plain EM needs about 60 iterations to come within 0.1 nats per
sequence of its optimum, most of them in the slow tail. SQUAREM (Varadhan & Roland 2008, the
steplength "S3") reads the direction of that tail from two EM steps and extrapolates along it:

* ``theta_1 = M(theta_0)``, ``theta_2 = M(theta_1)`` (EM steps), ``r = theta_1 - theta_0``,
  ``v = theta_2 - 2 theta_1 + theta_0``;
* ``alpha = -|r| / |v|``, kept in ``[-max_step, -1]``;
* ``theta' = theta_0 - 2 alpha r + alpha^2 v`` (``alpha = -1`` gives ``theta_2`` exactly);
* one more EM step from ``theta'`` stabilises it.

The extrapolated point is kept only when its ``Q`` and ``R`` are positive semi-definite and its
filter log-likelihood is at least that of ``theta_0``, the cycle's start; otherwise ``alpha``
moves halfway to ``-1`` and, at ``-1``, the cycle is three plain EM steps. Since EM never lowers
the likelihood of a linear-Gaussian model, a cycle never does either. ``max_step`` starts at 1
and grows 4-fold each time the step reaches it (the scheme's default, so the first cycle is
plain EM).

The parameters are the matrices ``A, H, Q, R`` (and ``B, D``) of the closed-form M-step; a block
held fixed, or a known row of ``H``, has ``r = v = 0`` and stays where it is. In a data-parallel
fit every process holds the same parameters and the summed log-likelihood, so all take the same
decisions.

A non-linear model's gradient M-step (L-BFGS on the expected complete-data log-likelihood, with
its safeguards) is a deterministic map of the parameters too, and its tail is as slow: on the
robot-arm log of ``scripts/bench_real_logs.py`` a GP transition's EM gained 0.05 nats per
iteration after 80 iterations. :meth:`Squarem.cycle_gradient` applies the same scheme to the
model's free parameters (unconstrained: log-scales, inducing values, Cholesky factors), keeping
an extrapolation only where its filter log-likelihood is finite and at least that of the two
plain M-steps it extrapolates, so a cycle is never worse than two plain iterations. Its cost is
three or four M-steps, each with its filter and smoother.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator

import torch
from torch import Tensor

from torchfilt.numerics import symmetrize
from torchfilt.training.em_steps import SmoothedPairs, _EMProblem

__all__ = ["Squarem"]

#: halvings of the extrapolation towards ``alpha = -1`` before the plain EM step is taken
_BACKTRACKS = 3


class Squarem:
    """One accelerated EM cycle at a time over an :class:`_EMProblem` (:meth:`cycle` for the
    closed-form M-step of a linear-Gaussian model, :meth:`cycle_gradient` for the gradient
    M-step), keeping the largest extrapolation allowed between cycles.

    Attributes:
        max_step: the bound on ``|alpha|`` (starts at 1; grows 4-fold when reached).
        e_steps: E-steps run so far (each is one Kalman filter and smoother pass; with the
            gradient M-step, the M-steps and extrapolations, each with its filter).
    """

    def __init__(self) -> None:
        self.max_step = 1.0
        self.e_steps = 0

    def state(self) -> list[float]:
        """What a checkpoint keeps: ``[max_step, e_steps]``."""
        return [self.max_step, float(self.e_steps)]

    def load(self, values: list[float]) -> None:
        """Continue from :meth:`state` (a resumed fit then takes the same cycles)."""
        self.max_step, self.e_steps = float(values[0]), int(values[1])

    def iterate(
        self, em: _EMProblem, ll: float, sp: SmoothedPairs
    ) -> tuple[float, SmoothedPairs, bool]:
        """One iteration of an accelerated fit: :meth:`cycle` for the closed-form M-step of a
        linear-Gaussian model, :meth:`cycle_gradient` otherwise. The log-likelihood, the
        smoothed pairs, and whether the fit stalled (the gradient M-step only)."""
        if em.lin is None:
            return self.cycle_gradient(em, ll, sp)
        return (*self.cycle(em, ll, sp), False)

    def cycle(self, em: _EMProblem, ll: float, sp: SmoothedPairs) -> tuple[float, SmoothedPairs]:
        """One cycle from the parameters of ``em`` and their E-step ``(ll, sp)``: the parameters
        end at the stabilised extrapolation, and its log-likelihood and smoothed pairs are
        returned."""
        theta0 = em.state()
        em.closed_form(sp)
        _, sp1 = self._e_step(em)
        theta1 = em.state()
        em.closed_form(sp1)
        r, v = _directions(theta0, theta1, em.state())
        alpha = self._steplength(_norm(r), _norm(v))
        _, sp_x = self._extrapolated(em, theta0, r, v, alpha, ll)
        em.closed_form(sp_x)  # the stabilising EM step
        return self._e_step(em)

    def cycle_gradient(
        self, em: _EMProblem, ll: float, sp: SmoothedPairs
    ) -> tuple[float, SmoothedPairs, bool]:
        """One cycle over the gradient M-step of a non-linear model (each M-step is followed by
        its E-step, :meth:`_EMProblem.m_step`): two M-steps, the extrapolation (kept where its
        filter log-likelihood is finite and at least that of the second M-step, halved towards
        ``-1`` up to three times) and a stabilising M-step from it. The log-likelihood, the
        smoothed pairs, and whether the first M-step stalled (no block raised the likelihood:
        the parameters are where the cycle began)."""
        theta0 = em.state()
        ll1, sp1, stalled = em.m_step(ll, sp)
        self.e_steps += 1
        if stalled:
            return ll, sp, True
        theta1 = em.state()
        ll2, sp2, stalled = em.m_step(ll1, sp1)
        self.e_steps += 1
        if stalled:  # the second found nothing: the parameters are back at theta_1
            return ll1, sp1, False
        theta2 = em.state()
        r, v = _directions(theta0, theta1, theta2)
        for alpha in self._tried(self._steplength(_norm(r), _norm(v))):
            em.load(_point(theta0, r, v, alpha))
            self.e_steps += 1
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                ll_x, res_x = em.trial()
            if res_x is not None and math.isfinite(ll_x) and ll_x >= ll2:
                _replay(caught)  # the kept point's own warnings
                ll_s, sp_s, stalled = em.m_step(ll_x, em.smoothed(res_x))
                self.e_steps += 1
                return ll_s, sp_s, False
        em.load(theta2)
        return ll2, sp2, False

    def _steplength(self, nr: float, nv: float) -> float:
        """The S3 steplength ``alpha`` in ``[-max_step, -1]`` from ``|r|`` and ``|v|``; the
        bound grows 4-fold when reached."""
        alpha = -1.0
        if nv > 0 and math.isfinite(nr / nv):
            alpha = -min(max(nr / nv, 1.0), self.max_step)
        if alpha <= -self.max_step:
            self.max_step *= 4.0
        return alpha

    def _tried(self, alpha: float) -> Iterator[float]:
        """The steplengths an extrapolation tries, from ``alpha`` halved towards ``-1`` (at most
        :data:`_BACKTRACKS`; none at ``-1``): each one the caller rejects lowers ``max_step``."""
        for _ in range(_BACKTRACKS):
            if alpha > -1.0 - 1e-3:
                return
            yield alpha
            alpha = (alpha - 1.0) / 2.0
            self.max_step = max(1.0, -alpha)

    def _extrapolated(
        self,
        em: _EMProblem,
        theta0: list[Tensor],
        r: list[Tensor],
        v: list[Tensor],
        alpha: float,
        ll0: float,
    ) -> tuple[float, SmoothedPairs]:
        """Set ``em`` to the extrapolation at ``alpha`` (halved towards ``-1`` until it is
        admissible and no worse than ``ll0``, the cycle's start) and return its E-step. ``em``
        holds ``theta_2`` on entry: the point at ``alpha = -1``."""
        theta2 = em.state()
        for a in self._tried(alpha):
            em.load(_point(theta0, r, v, a))
            if _admissible(em):
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        ll_x, sp_x = self._e_step(em)
                    except torch.linalg.LinAlgError:
                        ll_x, sp_x = -math.inf, None
                if sp_x is not None and math.isfinite(ll_x) and ll_x >= ll0:
                    _replay(caught)  # the kept point's own warnings
                    return ll_x, sp_x
        em.load(theta2)
        return self._e_step(em)

    def _e_step(self, em: _EMProblem) -> tuple[float, SmoothedPairs]:
        self.e_steps += 1
        return em.e_step()


def _directions(
    theta0: list[Tensor], theta1: list[Tensor], theta2: list[Tensor]
) -> tuple[list[Tensor], list[Tensor]]:
    """``r = theta_1 - theta_0`` and ``v = theta_2 - 2 theta_1 + theta_0`` of a cycle."""
    r = [a - b for a, b in zip(theta1, theta0, strict=True)]
    v = [c - 2 * a + b for c, a, b in zip(theta2, theta1, theta0, strict=True)]
    return r, v


def _point(theta0: list[Tensor], r: list[Tensor], v: list[Tensor], alpha: float) -> list[Tensor]:
    """The extrapolation ``theta_0 - 2 alpha r + alpha^2 v``."""
    return [
        t + (-2.0 * alpha) * a + alpha * alpha * b for t, a, b in zip(theta0, r, v, strict=True)
    ]


def _replay(caught: list[warnings.WarningMessage]) -> None:
    """Emit the warnings recorded while a kept point was evaluated."""
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _norm(xs: list[Tensor]) -> float:
    """The Euclidean norm of the parameters ``xs`` stacked into one vector (float64)."""
    return math.sqrt(sum(float(x.detach().to(torch.float64).square().sum()) for x in xs))


def _admissible(em: _EMProblem) -> bool:
    """Whether the linear model's ``Q`` and ``R`` are positive semi-definite (an extrapolation
    may leave that cone; the closed-form step never does)."""
    lin = em.lin
    assert lin is not None  # acceleration serves the closed-form M-step only
    for S in (lin.Q, lin.R):
        S64 = S.detach().to(torch.float64)
        if not bool(torch.isfinite(S64).all()):
            return False
        eig = torch.linalg.eigvalsh(symmetrize(S64))
        if float(eig.min()) < 0.0:
            return False
    return True
