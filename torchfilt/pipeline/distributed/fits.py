"""Data-parallel fits on Ray: :func:`calibrate_ray` and :func:`fit_measurement_only_ray`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import torch

from torchfilt.exceptions import InputError
from torchfilt.optim import (
    CheckpointOptions,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
    deprecated_fit_keywords,
    resolve_options,
)
from torchfilt.pipeline.distributed.group import GROUP_TIMEOUT, _run_group

__all__ = ["calibrate_ray", "fit_measurement_only_ray"]


@deprecated_fit_keywords("calibrate")
def calibrate_ray(
    model: Any,
    y: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    workers: int = 2,
    address: str | None = None,
    validation: Any = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    callback: Callable[[Any], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    sides: Sequence[str] = ("transition", "measurement"),
    inflate_only: bool = True,
    gp: str = "none",
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
        model: the model to calibrate, as in :func:`~torchfilt.training.calibrate`.
        y: the training data, any kind :func:`~torchfilt.training.calibrate`'s ``y``
            takes (:mod:`torchfilt.training.data`: a list of recordings, a
            :class:`~torchfilt.training.data.Sequences` whose ``x0``/``P0`` are shared, ...),
            dealt to the actors by recording.
        x0: prior mean ``(n,)`` (or one per recording), as in :func:`~torchfilt.training.calibrate`.
        P0: prior covariance ``(n, n)`` (or one per recording), as in :func:`~torchfilt.training.calibrate`.
        workers: Ray actors, one CPU each; the cluster must have that many free at once.
        address: Ray cluster (see :func:`ray_session`).
        callback: called in every actor's process after each iteration (its rank is
            ``torch.distributed.get_rank()``); one returning ``True`` stops all. Sent to the
            actors, so it must pickle. With ``callback_on="driver"``: see there.
        checkpoint: folder of the actors' checkpoints, or a
            :class:`~torchfilt.optim.CheckpointOptions` whose ``path`` is that folder (``None``:
            no checkpoints, and a lost worker means starting again); its ``resume=True``
            continues from the checkpoints in the folder.
        validation: as in :func:`~torchfilt.training.calibrate`.
        iterations: as in :func:`~torchfilt.training.calibrate`.
        optimizer: as in :func:`~torchfilt.training.calibrate`.
        windows: as in :func:`~torchfilt.training.calibrate`.
        stopping: as in :func:`~torchfilt.training.calibrate` (the flat keywords of before warn as there).
        dtype: as in :func:`~torchfilt.training.calibrate`.
        sides: as in :func:`~torchfilt.training.calibrate`.
        inflate_only: as in :func:`~torchfilt.training.calibrate`.
        gp: as in :func:`~torchfilt.training.calibrate`.
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
    ckpt = _checkpoint("calibrate", checkpoint)
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "validation": validation,
        "sides": tuple(sides),
        "iterations": iterations,
        "optimizer": optimizer,
        "windows": windows,
        "stopping": stopping,
        "inflate_only": inflate_only,
        "gp": gp,
        "dtype": dtype,
        "callback": callback,
        "checkpoint": ckpt,
    }
    return _run_group(
        "calibrate_ray", "calibrate", model, y, options, workers, address, ckpt.path,
        timeout, callback_on,
    )  # fmt: skip


def _checkpoint(fit: str, checkpoint: CheckpointOptions | str | Path | None) -> CheckpointOptions:
    """The checkpoints of a group's fit: ``path`` the actors' folder, ``every`` set."""
    return resolve_options(fit, checkpoint=checkpoint).checkpoint


@deprecated_fit_keywords("measurement_only")
def fit_measurement_only_ray(
    model: Any,
    y: Any,
    *,
    x0: torch.Tensor,
    P0: torch.Tensor,
    known_channels: Sequence[int] | None,
    workers: int = 2,
    address: str | None = None,
    validation: Any = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    checkpoint: CheckpointOptions | str | Path | None = None,
    callback: Callable[[Any], bool | None] | None = None,
    dtype: torch.dtype = torch.float64,
    method: str = "likelihood",
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    accelerate: bool | None = None,
    compile: bool | Literal["step", "loop"] = False,
    noise_scale: Literal["auto", "none", "held-out"] = "auto",
    holdout: float = 0.2,
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
        model: the model, as in :func:`~torchfilt.training.fit_measurement_only`.
        y: the training data, any kind
            :func:`~torchfilt.training.fit_measurement_only`'s ``y`` takes
            (:mod:`torchfilt.training.data`: a :class:`~torchfilt.training.data.Sequences` of
            ``y``, ``u`` and shared ``x0``/``P0``, a list of recordings, ...), dealt to the
            actors by recording.
        x0: prior mean ``(n,)`` or ``(..., n)``, as in :func:`~torchfilt.training.fit_measurement_only`.
        P0: prior covariance ``(n, n)`` or ``(..., n, n)``, as in :func:`~torchfilt.training.fit_measurement_only`.
        known_channels: as in :func:`~torchfilt.training.fit_measurement_only`.
        workers: as in :func:`calibrate_ray`.
        address: as in :func:`calibrate_ray`.
        validation: as in :func:`~torchfilt.training.fit_measurement_only`.
        iterations: as in :func:`~torchfilt.training.fit_measurement_only`.
        optimizer: as in :func:`~torchfilt.training.fit_measurement_only`.
        windows: as in :func:`~torchfilt.training.fit_measurement_only`.
        stopping: as in :func:`~torchfilt.training.fit_measurement_only` (the flat keywords of before warn as there).
        checkpoint: as in :func:`calibrate_ray`.
        callback: as in :func:`calibrate_ray`.
        dtype: as in :func:`~torchfilt.training.fit_measurement_only`.
        method: as in :func:`~torchfilt.training.fit_measurement_only`.
        learn_measurement_noise: as in :func:`~torchfilt.training.fit_measurement_only`.
        m_step_iterations: as in :func:`~torchfilt.training.fit_measurement_only`.
        accelerate: as in :func:`~torchfilt.training.fit_measurement_only` (SQUAREM cycles;
            every actor takes the same steps: they use the summed likelihood).
        compile: as in :func:`~torchfilt.training.fit_measurement_only` (each actor compiles
            its own filter).
        noise_scale: as in :func:`~torchfilt.training.fit_measurement_only` (default
            ``"auto"``): each actor holds out part of its own recordings (whole ones where it
            has at least 5, else the tails), and the scores are summed over the actors, so all
            choose the same scale. The split is not the one process's split of all the
            recordings, so the fit equals the one-process fit where the two splits agree
            (e.g. tails everywhere), or with ``"none"``.
        holdout: as in :func:`~torchfilt.training.fit_measurement_only`.
        timeout: as in :func:`calibrate_ray`.
        callback_on: as in :func:`calibrate_ray`.

    Returns:
        Actor 0's :class:`~torchfilt.training.measurement_only.MeasurementOnlyFit`.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``method`` not ``"auto"``, ``"both"``, ``"em"`` or ``"likelihood"``, or as
            in :func:`calibrate_ray`.
        WorkerError: an actor was lost.
    """
    if method not in ("auto", "both", "em", "likelihood"):
        raise InputError(f"method must be 'auto', 'both', 'em' or 'likelihood', got {method!r}")
    ckpt = _checkpoint("measurement_only", checkpoint)
    options: dict[str, Any] = {
        "x0": x0,
        "P0": P0,
        "known_channels": known_channels,
        "method": method,
        "iterations": iterations,
        "optimizer": optimizer,
        "windows": windows,
        "stopping": stopping,
        "validation": validation,
        "learn_measurement_noise": learn_measurement_noise,
        "m_step_iterations": m_step_iterations,
        "accelerate": accelerate,
        "compile": compile,
        "noise_scale": noise_scale,
        "holdout": holdout,
        "dtype": dtype,
        "callback": callback,
        "checkpoint": ckpt,
    }
    return _run_group(
        "fit_measurement_only_ray", "measurement_only", model, y, options, workers,
        address, ckpt.path, timeout, callback_on,
    )  # fmt: skip
