"""One recipe with its likelihood stages data-parallel on Ray
(``torchfilt train RECIPE --ray --data-parallel N``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, Literal, TextIO

import torch

from torchfilt.exceptions import InputError, WorkerError
from torchfilt.optim import CheckpointOptions, OptimizerOptions, StoppingOptions, WindowOptions
from torchfilt.pipeline.distributed.fits import calibrate_ray, fit_measurement_only_ray
from torchfilt.pipeline.distributed.group import GROUP_TIMEOUT, _check_timeout
from torchfilt.pipeline.distributed.session import import_ray, ray_session
from torchfilt.pipeline.recipe import Recipe, load_recipe
from torchfilt.pipeline.run import StageFitters, train_recipe

__all__ = ["data_parallel_fitters", "train_recipe_data_parallel"]


def _measurement_only_stage_ray(
    model: Any,
    y: Any,
    u: Any = None,
    *,
    workers: int,
    timeout: float,
    x0: torch.Tensor,
    P0: torch.Tensor,
    known_channels: Sequence[int] | None,
    method: Literal["auto", "both", "em", "likelihood"] = "em",
    validation: Any = None,
    iterations: int | None = None,
    optimizer: OptimizerOptions | Literal["adam", "lbfgs"] | None = None,
    windows: WindowOptions | None = None,
    stopping: StoppingOptions | None = None,
    learn_measurement_noise: bool = True,
    m_step_iterations: int = 20,
    accelerate: bool | None = None,
    compile: bool = False,
    noise_scale: Literal["auto", "none", "held-out"] = "auto",
    callback: Callable[[Any], bool | None] | None = None,
    progress: bool = False,
    dtype: torch.dtype = torch.float64,
    checkpoint: CheckpointOptions | str | Path | None = None,
) -> Any:
    """:func:`fit_measurement_only_ray` called as :func:`~torchfilt.training.fit_measurement_only`
    (``y`` and ``u`` lists of ``(T_i, m)`` / ``(T_i, nu)``), the callback on the driver:
    the ``measurement_only`` fitter of :func:`train_recipe_data_parallel`. ``progress`` is
    ignored (the stage draws its own from the callback). ``validation`` (``method = "auto"``
    or ``"both"``: the recordings the methods are compared on) goes whole to every actor."""
    from torchfilt.training.data import as_sequences

    return fit_measurement_only_ray(
        model,
        as_sequences(y, u),
        x0=x0,
        P0=P0,
        known_channels=known_channels,
        method=method,
        validation=validation,
        workers=workers,
        iterations=iterations,
        optimizer=optimizer,
        windows=windows,
        stopping=stopping,
        learn_measurement_noise=learn_measurement_noise,
        m_step_iterations=m_step_iterations,
        accelerate=accelerate,
        compile=compile,
        noise_scale=noise_scale,
        dtype=dtype,
        callback=callback,
        checkpoint=checkpoint,
        timeout=timeout,
        callback_on="driver",
    )


def data_parallel_fitters(workers: int, *, timeout: float = GROUP_TIMEOUT) -> StageFitters:
    """The :class:`~torchfilt.pipeline.run.StageFitters` of :func:`train_recipe_data_parallel`:
    :func:`calibrate_ray` and :func:`fit_measurement_only_ray` on ``workers`` actors of the Ray
    session open when a stage runs, the stage's callback on the driver, the stage's checkpoint
    path the folder of the actors' checkpoints.

    Raises:
        InputError: ``workers`` is not a positive integer, or a bad ``timeout``.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"--data-parallel must be a positive integer, got {workers!r}")
    timeout = _check_timeout(timeout)
    return StageFitters(
        calibrate=partial(calibrate_ray, workers=workers, timeout=timeout, callback_on="driver"),
        measurement_only=partial(_measurement_only_stage_ray, workers=workers, timeout=timeout),
        name=f"data-parallel on {workers} Ray actors (--data-parallel {workers})",
        shards=workers,
    )


def train_recipe_data_parallel(
    recipe: str | Path | Recipe,
    out: str | Path,
    *,
    workers: int,
    address: str | None = None,
    cpus: int | None = None,
    resume: bool = False,
    force: bool = False,
    timeout: float = GROUP_TIMEOUT,
    progress: bool = True,
    stream: TextIO | None = None,
) -> Path:
    """:func:`~torchfilt.pipeline.train_recipe` with its likelihood stages data-parallel on Ray.

    The calibration stage runs :func:`calibrate_ray` and a ``states = "none"`` recipe's
    transition stage :func:`fit_measurement_only_ray`, each on ``workers`` actors (one CPU each)
    with the training recordings dealt round-robin (recording ``i`` to actor ``i % workers``);
    the GP stages, the validation and the bundle run in this process, as in a local run. The run
    directory, dataset log and bundle are those of a local run: the calibrated scales and floors
    and the learned transition equal the local ones up to the order of the sums (float64: to
    ~1e-9, tested), and ``metrics.jsonl``, ``train.log`` and the progress bar are written here
    from rank 0's per-iteration states. Each stage checkpoints into a folder in the run
    directory (``calibrate.ckpt/rank{r}.ckpt``, ``transition.ckpt/rank{r}.ckpt``), removed when
    the stage is done.

    ``config.json`` records the fitters (``"stage_fitters"``), and the run resumes only as it
    started: ``resume=True`` with the same ``workers`` continues it from its checkpoints to the
    bundle of an uninterrupted run (a lost actor is a
    :class:`~torchfilt.exceptions.WorkerError`, and resuming continues from the checkpoints all
    actors saved); :func:`~torchfilt.pipeline.train_recipe` (local) or other ``workers`` refuse
    it with a :class:`~torchfilt.exceptions.RunError`.

    Args:
        recipe: a recipe file or a :class:`~torchfilt.pipeline.Recipe`.
        out: run directory (visible under the same path to every actor: one machine or a shared
            filesystem).
        workers: Ray actors per data-parallel stage (``--data-parallel N``); at most the training
            recordings and the cluster's CPUs.
        address: Ray cluster (see :func:`ray_session`; ``None``: a new local instance, unless one
            is open in this process).
        cpus: CPUs of a new local instance (default: all; ``--workers``).
        resume: continue the run in ``out``.
        force: discard a run already in ``out``.
        timeout: seconds a collective waits for the other actors (see :func:`calibrate_ray`).
        progress: show progress bars (on a terminal; plain lines otherwise).
        stream: where progress goes (default ``sys.stderr``).

    Returns:
        Path of the model bundle ``out/model.pt``.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` not a positive integer or more than the training recordings or
            the cluster's CPUs, ``resume`` with ``force``, an unreachable cluster.
        RecipeError, DataError: as :func:`~torchfilt.pipeline.train_recipe` (before Ray starts).
        RunError: as :func:`~torchfilt.pipeline.train_recipe`, and a run started with other
            fitters.
        WorkerError: an actor was lost; ``resume=True`` continues.
    """
    import_ray()
    fitters = data_parallel_fitters(workers, timeout=timeout)
    if resume and force:
        raise InputError("--resume continues the run in --out and --force discards it: pick one")
    r = recipe if isinstance(recipe, Recipe) else load_recipe(recipe)  # errors before Ray starts
    with ray_session(address, workers=cpus) as ray:
        total = int(ray.cluster_resources().get("CPU", 0))
        if total < workers:
            raise InputError(
                f"--data-parallel {workers}: {workers} actors must run at once, but the Ray "
                f"cluster has {total} CPUs"
            )
        try:
            return train_recipe(
                r, out, resume=resume, force=force, progress=progress, stream=stream,
                fitters=fitters,
            )  # fmt: skip
        except WorkerError as e:
            raise WorkerError(
                f"{e}. For this run: resume it with --resume (resume=True) and the same "
                f"--ray --data-parallel {workers}"
            ) from None
