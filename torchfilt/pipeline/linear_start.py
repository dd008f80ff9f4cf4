"""The linear-EM candidate start of a ``states = "none"`` run (see
:func:`torchfilt.pipeline.run_stages._start`): a linear-Gaussian model fitted to the training
measurements by a short :func:`~torchfilt.training.fit_em` (:data:`LINEAR_EM_ITERATIONS` SQUAREM
cycles, ``fit_em``'s default for a linear model) from N4SID starts
(:func:`~torchfilt.models.subspace_start` with :data:`BLOCK_ROWS_FACTORS` times the default
block rows, each as estimated and, where its ``A`` has an eigenvalue on or outside the unit
circle, also stabilised; the highest log-likelihood after the EM kept; from a random walk where
the data has missing values or no subspace fit succeeds), turned into a GP transition that starts
exactly at it (:meth:`~torchfilt.models.InducingTransition.from_linear`) under the recipe's own
measurement model.

Why the stabilised starts: on the real logs of ``scripts/bench_real_logs_train.py`` an N4SID
estimate with a pole outside the unit circle (the robot arm's, at both block rows) led its EM
to a lower training likelihood than the same estimate stabilised (285.1 against 403.3 nats at
``R`` 1e-2; 583.7 against 1016.0 at 1e-4), and its GP to a free run that diverged (4.5x
N4SID's error); on an unstable plant (the ball and beam) the estimate as it came stays ahead
(614.6 against -761.8), so the likelihood, not a rule, decides. ``[measurement_only] stable =
true`` (a plant known to be stable) keeps the stabilised starts alone and a start whose EM
leaves the unit circle as it was before the EM.

A non-linear sensor ``h`` is linearised at the prior mean, ``h(x) ~ c + J x``: the EM fits
``y - c`` with ``H = J`` and the sensor's ``R`` held fixed, so only ``A``, ``B`` and ``Q`` are
learned; the candidate then uses ``h`` itself, and its held-out score (computed by the caller
with ``h``) is what decides whether it is kept. Everything here is deterministic, so a resumed
run recomputes the same candidate.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import TorchfiltError
from torchfilt.filters import kalman_smoother
from torchfilt.io.recording import Recording
from torchfilt.models import (
    CholeskyCovariance,
    InducingTransition,
    LinearGaussianModel,
    StateSpaceModel,
    subspace_start,
)
from torchfilt.models.subspace import default_block_rows
from torchfilt.training.measurement_only import fit_em

__all__ = ["BLOCK_ROWS_FACTORS", "LINEAR_EM_ITERATIONS", "LinearStart", "linear_em_start"]

#: Multiples of :func:`~torchfilt.models.subspace.default_block_rows` whose N4SID starts the
#: linear EM tries (the recordings allowing); the higher log-likelihood after the EM is kept. On
#: the robot-arm log of ``scripts/bench_real_logs_train.py`` (4 states, 546 training steps,
#: ``R`` 1e-2) the default 10 rows gave a pole at 1.46 and an EM fit at -99.3 nats whose free
#: run diverged (RMSE 2e43); 20 rows gave 285.1 nats and a free run at 0.66 of N4SID's error.
BLOCK_ROWS_FACTORS = (1, 2)
#: EM iterations of the linear candidate, each a SQUAREM cycle (three E-steps or more): its cost
#: stays a small part of the stage (under a second on 12 x 300 steps), and on nearly noise-free
#: logs the cycles climb where plain EM creeps.
LINEAR_EM_ITERATIONS = 20


class LinearStart(NamedTuple):
    """The linear-EM candidate.

    Attributes:
        model: the GP model that starts exactly at the fitted linear model's transition.
        record: what the run records: ``start`` (``"linear EM"``), ``from`` (``"N4SID"`` or
            ``"random walk"``), ``em_iterations`` and the training ``log_likelihood`` of the
            linear model (in the linearised sensor), ``stabilised`` (the N4SID estimate was
            stabilised), ``unstable_after_em`` where ``stable`` kept a start as it was; from
            N4SID also ``block_rows`` and ``block_rows_tried`` (each start's rows, whether
            stabilised, and its log-likelihood).
    """

    model: StateSpaceModel
    record: dict[str, Any]


def _linearised(h: Any, m0: Tensor, n: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """``(J, c, R)``: ``h(x) ~ c + J x`` at ``m0`` and the sensor's constant ``R``; ``None`` for
    a sensor that takes inputs or has no constant noise."""
    if getattr(h, "input_dim", 0) or getattr(h, "time_varying_noise", False):
        return None
    R = h.noise_cov()
    if R is None:
        return None
    x = m0.detach().reshape(1, 1, n)
    J = torch.autograd.functional.jacobian(lambda z: h.predict(z, None).mean, x)
    J = J.reshape(-1, n)
    with torch.no_grad():
        c = h.predict(x, None).mean.reshape(-1) - J @ m0
    return J.detach(), c, R.detach().reshape(J.shape[0], J.shape[0])


class _Start(NamedTuple):
    """A start of the linear EM: the model, where it came from (``"N4SID"`` or ``"random
    walk"``), the N4SID block rows (``None``: the random walk) and whether N4SID's estimate was
    stabilised."""

    model: LinearGaussianModel
    source: str
    rows: int | None
    stabilised: bool


def _starts(
    walk: LinearGaussianModel,
    J: Tensor,
    R: Tensor,
    ys: list[Tensor],
    us: list[Tensor] | None,
    known: list[int],
    n: int,
    dtype: torch.dtype,
    stable: bool,
) -> list[_Start]:
    """The starts of the linear EM (measurement matrix ``J``, noise ``R``): N4SID with each of
    :data:`BLOCK_ROWS_FACTORS` times the default block rows that the data allow (complete data
    only), as estimated and, where its ``A`` has an eigenvalue on or outside the unit circle,
    stabilised (:func:`~torchfilt.models.subspace_start`'s ``stable``; with ``stable``: that
    one alone); else the random walk ``walk``."""
    out: list[_Start] = []
    if not all(bool(torch.isfinite(y).all()) for y in ys):
        return [_Start(walk, "random walk", None, False)]
    base = default_block_rows(n, J.shape[-2])
    for rows in (f * base for f in BLOCK_ROWS_FACTORS):
        for stabilised in (False, True):
            try:
                sub = subspace_start(
                    walk, ys, us, known_channels=known, block_rows=rows, stable=stabilised
                ).model
            except (TorchfiltError, RuntimeError):  # too short, unstable, gauge not matched
                continue
            model = LinearGaussianModel(
                sub.A.to(dtype), J, sub.transition.noise_cov().to(dtype), R,  # type: ignore[union-attr]
                None if sub.B is None else sub.B.to(dtype),
            )  # fmt: skip
            if not stabilised and spectral_radius(model.A) < 1.0:
                out.append(_Start(model, "N4SID", rows, False))
                break  # stable as estimated: nothing to stabilise
            if stabilised or not stable:
                out.append(_Start(model, "N4SID", rows, stabilised))
    return out or [_Start(walk, "random walk", None, False)]


class _Fitted(NamedTuple):
    """A start after the linear EM: the model kept, its training log-likelihood, the EM
    iterations kept (0: the start itself) and, where ``stable`` kept the start because the EM
    left the unit circle, the EM's spectral radius."""

    start: _Start
    model: LinearGaussianModel
    log_likelihood: float
    iterations: int
    unstable_after_em: float | None

    def marks(self) -> dict[str, Any]:
        """What the record says of the start besides its likelihood."""
        out: dict[str, Any] = {"stabilised": self.start.stabilised}
        if self.unstable_after_em is not None:
            out["unstable_after_em"] = self.unstable_after_em
        return out


def spectral_radius(A: Tensor) -> float:
    """The largest eigenvalue modulus of ``A`` ``(n, n)``."""
    return float(torch.linalg.eigvals(A.detach()).abs().max())


def _fit_start(
    start: _Start,
    ys: list[Tensor],
    us: list[Tensor] | None,
    m0: Tensor,
    P0: Tensor,
    known: list[int],
    dtype: torch.dtype,
    stable: bool,
) -> _Fitted | None:
    """The linear EM from ``start`` (``H`` and ``R`` held); ``None`` where it fails. With
    ``stable`` and an EM that ends with an eigenvalue of ``A`` on or outside the unit circle,
    the (stable) start itself instead, at the likelihood the EM found there; a start that is not
    stable itself (the random walk, on the circle) keeps its EM's result."""
    try:
        fit = fit_em(
            start.model, ys, us, x0=m0, P0=P0, known_channels=known, fixed=("H", "R"),
            iterations=LINEAR_EM_ITERATIONS, dtype=dtype,
        )  # fmt: skip
    except TorchfiltError:
        return None
    if not isinstance(fit.model, LinearGaussianModel) or not math.isfinite(fit.log_likelihood):
        return None
    rho = spectral_radius(fit.model.A)
    if stable and rho >= 1.0 and spectral_radius(start.model.A) < 1.0:
        ll = fit.initial_log_likelihood
        return _Fitted(start, start.model, ll, 0, rho) if math.isfinite(ll) else None
    return _Fitted(start, fit.model, fit.log_likelihood, fit.iterations, None)


def linear_em_start(
    h: Any,
    train: list[Recording],
    *,
    n: int,
    nu: int,
    m0: Tensor,
    P0: Tensor,
    q0: Tensor,
    inducing: int,
    known: list[int],
    dtype: torch.dtype,
    stable: bool = False,
) -> LinearStart | None:
    """The linear-EM candidate start (see the module docstring), or ``None`` where the sensor
    cannot be linearised (inputs, no constant noise) or the fit fails.

    Args:
        h: the recipe's measurement model.
        train: the training recordings (measurements from the second step, as the stage fits).
        n: the state dimension.
        nu: the input dimension (0: none).
        m0: the prior mean ``(n,)``.
        P0: the prior covariance ``(n, n)``.
        q0: the random-walk start's process-noise variances ``(n,)``.
        inducing: the number of inducing points of the GP transition.
        known: the known measurement channels (the gauge).
        dtype: the floating dtype.
        stable: the plant is known to be stable (``[measurement_only] stable``): N4SID
            re-estimates an unstable ``A`` (:func:`~torchfilt.models.subspace_identify`'s
            ``stable``), and a start whose EM ends with an eigenvalue of ``A`` on or outside
            the unit circle is kept as it was before the EM (recorded as
            ``unstable_after_em``, the EM's spectral radius).

    Returns:
        A :class:`LinearStart`, or ``None``.
    """
    m0, P0 = m0.to(dtype), P0.to(dtype)
    lin = _linearised(h, m0, n)
    if lin is None:
        return None
    J, c, R = (t.to(dtype) for t in lin)
    ys = [rec.measurements[1:].to(dtype) - c for rec in train]
    us = [rec.inputs[:-1].to(dtype) for rec in train] if nu else None  # type: ignore[index]
    B0 = torch.zeros(n, nu, dtype=dtype) if nu else None
    walk = LinearGaussianModel(torch.eye(n, dtype=dtype), J, torch.diag(q0.to(dtype)), R, B0)
    tried: list[dict[str, Any]] = []
    best: _Fitted | None = None
    for start in _starts(walk, J, R, ys, us, known, n, dtype, stable):
        fitted = _fit_start(start, ys, us, m0, P0, known, dtype, stable)
        if fitted is None:
            continue
        if start.rows is not None:
            tried.append(
                {"block_rows": start.rows, "log_likelihood": fitted.log_likelihood} | fitted.marks()
            )
        if best is None or fitted.log_likelihood > best.log_likelihood:
            best = fitted
    if best is None:
        return None
    model = best.model
    with torch.no_grad():
        xs = [
            kalman_smoother(model, y, u, x0=m0, P0=P0).mean
            for y, u in zip(ys, us if us is not None else [None] * len(ys), strict=True)
        ]
    X = torch.cat(xs)
    U = torch.cat(us) if us is not None else None
    ok = torch.isfinite(X).all(-1)
    X, U = X[ok], None if U is None else U[ok]
    if X.shape[0] < max(inducing, 2):
        return None
    cloud = X if U is None else torch.cat([X, U], -1)
    spread = cloud.std(0)
    ls = torch.where(spread > 1e-6, spread, torch.ones_like(spread))
    f = InducingTransition.from_linear(
        model.A, model.B, inducing=inducing, states=X, inputs=U, lengthscale=ls
    )
    Q = model.transition.noise_cov()
    assert Q is not None
    record = {
        "start": "linear EM",
        "from": best.start.source,
        "em_iterations": best.iterations,
        "linear_log_likelihood": best.log_likelihood,
        **best.marks(),
    }
    if best.start.rows is not None:
        record |= {"block_rows": best.start.rows, "block_rows_tried": tried}
    return LinearStart(StateSpaceModel(f, h, Q=CholeskyCovariance(Q.detach().clone())), record)
