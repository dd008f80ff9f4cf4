"""Data-parallel fits on Ray: :func:`calibrate_ray` and :func:`fit_measurement_only_ray`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import torch

from torchfilt.exceptions import InputError
from torchfilt.pipeline.distributed.group import GROUP_TIMEOUT, _run_group

__all__ = ["calibrate_ray", "fit_measurement_only_ray"]


def calibrate_ray(
    model: Any,
    recordings: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    workers: int = 2,
    address: str | None = None,
    validation: Any = None,
    sides: Sequence[str] = ("transition", "measurement"),
    window: int | None = 100,
    burn_in: int = 20,
    iterations: int = 150,
    lr: float = 0.1,
    optimizer: str = "adam",
    patience: int = 15,
    inflate_only: bool = True,
    gp: str = "none",
    atol: float | None = None,
    per_iteration: int | None = 16,
    dtype: torch.dtype = torch.float64,
    callback: Callable[[Any], bool | None] | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    checkpoint_every: int = 10,
    timeout: float = GROUP_TIMEOUT,
    callback_on: Literal["actors", "driver"] = "actors",
) -> Any:
    """:func:`~torchfilt.training.calibrate` as a data-parallel job on Ray.

    The recordings are dealt to ``workers`` Ray actors (recording ``i`` to actor ``i % workers``),
    which form a ``torch.distributed`` ``gloo`` group: each filters its own windows and the
    log-likelihood, the measurement count and the gradient are summed over the group at every
    evaluation, so all take the steps of one calibration on all recordings (equal to it up to the
    order of the sums; tested). Each actor checkpoints into ``checkpoint/rank{r}.ckpt``.

    **A lost worker.** A collective cannot lose a member: when an actor dies (its process killed,
    out of memory) or does not reach a collective within ``timeout`` seconds, the others fail in
    their next collective, every actor is stopped, and a :class:`~torchfilt.exceptions.WorkerError`
    names the rank. Run the same call again with ``resume=True`` to continue from the checkpoints:
    the actors agree on the latest iteration all of them saved (each checkpoint also keeps the
    one before it), and the result equals an uninterrupted fit (tested).

    Args:
        model, recordings, x0, P0, validation, sides, window, burn_in, iterations, lr,
        optimizer, patience, inflate_only, gp, atol, per_iteration, dtype, checkpoint_every: as in
            :func:`~torchfilt.training.calibrate` (``recordings`` a list of recordings or a
            :class:`~torchfilt.training.likelihood.Sequences` whose ``x0``/``P0`` are shared).
        workers: Ray actors, one CPU each; the cluster must have that many free at once.
        address: Ray cluster (see :func:`ray_session`).
        callback: called in every actor's process after each iteration (its rank is
            ``torch.distributed.get_rank()``); one returning ``True`` stops all. Sent to the
            actors, so it must pickle. With ``callback_on="driver"``: see there.
        checkpoint: folder of the actors' checkpoints (``None``: no checkpoints, and a lost
            worker means starting again).
        resume: continue from the checkpoints in ``checkpoint``.
        timeout: seconds a collective waits for the other actors before it fails (the longest
            one actor may compute between two collectives, e.g. filter its shard, must stay
            below it).
        callback_on: ``"actors"`` (above), or ``"driver"``: ``callback`` is called in this
            process with rank 0's state after each iteration, in order, while rank 0 waits for
            it (before that iteration's checkpoint); its ``True`` stops all, and an exception it
            raises stops the actors (their checkpoints kept: ``resume=True`` continues) and is
            raised here. It need not pickle.

    Returns:
        The :class:`~torchfilt.training.calibrate.CalibrationResult` of actor 0.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` below 1 or more than the recordings or the cluster's CPUs, or a
            bad ``timeout``.
        WorkerError: an actor was lost (see above).
    """
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "validation": validation,
        "sides": tuple(sides),
        "window": window,
        "burn_in": burn_in,
        "iterations": iterations,
        "lr": lr,
        "optimizer": optimizer,
        "patience": patience,
        "inflate_only": inflate_only,
        "gp": gp,
        "atol": atol,
        "per_iteration": per_iteration,
        "dtype": dtype,
        "callback": callback,
        "resume": resume,
        "checkpoint_every": checkpoint_every,
    }
    return _run_group(
        "calibrate_ray", "calibrate", model, recordings, options, workers, address, checkpoint,
        timeout, callback_on,
    )  # fmt: skip


def fit_measurement_only_ray(
    model: Any,
    recordings: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    known_channels: Sequence[int] | None,
    method: str = "likelihood",
    workers: int = 2,
    address: str | None = None,
    iterations: int = 100,
    window: int | None = None,
    burn_in: int = 0,
    validation: Any = None,
    optimizer: str = "lbfgs",
    lr: float | None = None,
    tol: float | None = None,
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    dtype: torch.dtype = torch.float64,
    callback: Callable[[Any], bool | None] | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    checkpoint_every: int = 1,
    timeout: float = GROUP_TIMEOUT,
    callback_on: Literal["actors", "driver"] = "actors",
) -> Any:
    """:func:`~torchfilt.training.fit_measurement_only` as a data-parallel job on Ray: the same
    group of actors as :func:`calibrate_ray` (recordings dealt round-robin, one checkpoint per
    actor, ``resume``, a :class:`~torchfilt.exceptions.WorkerError` for a lost worker). With
    ``method="likelihood"`` the gradients are summed over ``gloo`` at every L-BFGS evaluation;
    with ``method="em"`` each actor runs the E-step on its recordings and the M-step sums the
    expected sufficient statistics (linear model) or the expected complete-data log-likelihood
    and its gradient (any other), see :func:`~torchfilt.training.fit_em`.

    Args:
        model, x0, P0, known_channels, method, iterations, window, burn_in, validation,
        optimizer, lr, tol, learn_measurement_noise, m_step_iterations, dtype,
        checkpoint_every: as in :func:`~torchfilt.training.fit_measurement_only`.
        recordings: a :class:`~torchfilt.training.likelihood.Sequences` (``y``, ``u``; shared
            ``x0``/``P0``).
        workers, address, callback, checkpoint, resume, timeout, callback_on: as in
            :func:`calibrate_ray`.

    Returns:
        Actor 0's :class:`~torchfilt.training.measurement_only.MeasurementOnlyFit`.

    Raises:
        InputError: ``method`` not ``"em"`` or ``"likelihood"``; see :func:`calibrate_ray`.
        WorkerError: an actor was lost.
    """
    if method not in ("em", "likelihood"):
        raise InputError(f"method must be 'em' or 'likelihood', got {method!r}")
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "known_channels": known_channels,
        "method": method,
        "iterations": iterations,
        "window": window,
        "burn_in": burn_in,
        "validation": validation,
        "optimizer": optimizer,
        "lr": lr,
        "tol": tol,
        "learn_measurement_noise": learn_measurement_noise,
        "m_step_iterations": m_step_iterations,
        "dtype": dtype,
        "callback": callback,
        "resume": resume,
        "checkpoint_every": checkpoint_every,
    }
    return _run_group(
        "fit_measurement_only_ray", "measurement_only", model, recordings, options, workers,
        address, checkpoint, timeout, callback_on,
    )  # fmt: skip
