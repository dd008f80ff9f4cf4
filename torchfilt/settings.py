"""The switches that choose a numerics path, in one place.

Each switch is a context manager over a :mod:`contextvars` variable: it applies to the code run
inside its ``with`` block (and to no other thread or task), and it is restored on exit. Nothing
here is set globally at import time. Every :class:`~torchfilt.filters.FilterResult` records the
path its run took in its ``numerics`` field (a :class:`NumericsPath`), so a number can always be
traced to the switches that produced it.

* :func:`sync_free`: no host synchronisation in the numerics. A covariance that fails its Cholesky
  factorisation turns its sequence to NaN instead of being retried with jitter. Used around
  CUDA-graph warm-up and capture; ``torch.compile`` tracing implies it.
* :func:`small_matrix_kernels`: ``"auto"`` (default), ``"unrolled"`` or ``"library"``. For
  matrices up to 6x6 the entry-by-entry Cholesky and triangular solves of
  :mod:`torchfilt.numerics.small` replace LAPACK. ``"auto"`` takes them from a batch of 64
  matrices on; a filter resolves ``"auto"`` once per run from its batch size, so every step of a
  run takes the same kernels. The two agree to round-off. Compiled code always takes the unrolled
  kernels (they fuse into the surrounding code), whatever this switch says.
* :func:`skip_guard_checks`: let a ``compile=True`` filter skip Dynamo's guard checks after the
  first steps of a run (``torch.compiler.set_stance(skip_guard_eval_unsafe=True)``). Off by
  default: it is only safe when the model is not modified while a run is in progress.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from typing import Literal, NamedTuple

__all__ = [
    "RAY_BATCH_SIZE",
    "NumericsPath",
    "SmallKernels",
    "current_skip_guard_checks",
    "current_small_matrix_kernels",
    "is_sync_free",
    "skip_guard_checks",
    "small_matrix_kernels",
    "sync_free",
]

SmallKernels = Literal["auto", "unrolled", "library"]

#: Default recordings per Ray task of ``torchfilt filter --ray`` (``--batch-size``). Measured on
#: 2 CPUs (scripts/bench_ray.py, README "Distributed"): a task's fixed overhead (~15 ms) is under
#: 10% of the task from about 10 re-entry recordings and under 2% at 256, while 256 still makes
#: 40 tasks of 10^4 recordings to spread over the workers.
RAY_BATCH_SIZE = 256

_SYNC_FREE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "torchfilt_sync_free", default=False
)
_SMALL: contextvars.ContextVar[SmallKernels] = contextvars.ContextVar(
    "torchfilt_small_matrix_kernels", default="auto"
)
_SKIP_GUARDS: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "torchfilt_skip_guard_checks", default=False
)


class NumericsPath(NamedTuple):
    """Which numerics path a filter run took.

    Attributes:
        execution: ``"eager"``, ``"compiled-step"`` (one compiled call per step),
            ``"compiled-loop"`` (the whole time loop compiled as one ``torch.while_loop``),
            ``"compiled-chunks"`` (the loop compiled in chunks of unrolled steps, under autograd
            or for models the while-loop cannot capture) or ``"graphed"`` (CUDA graph replay).
        small_kernels: ``"unrolled"`` or ``"library"``: the small-matrix kernels used.
        on_failure: ``"jitter"`` (a failing Cholesky factor is retried with jitter, then NaN) or
            ``"nan"`` (sync-free: NaN at once).
        fallback: why the run did not take its first choice (a compiled while-loop that could
            not be traced, autograd under ``compile="loop"``, a factorisation that failed in a
            fast exact runner), or None. The exact Kalman path's ``execution`` is
            ``"kalman-parallel"``, ``"kalman-riccati"``, ``"kalman-fast"`` or
            ``"kalman-sequential"``.
    """

    execution: str
    small_kernels: str
    on_failure: str
    fallback: str | None = None


@contextlib.contextmanager
def sync_free(enabled: bool = True) -> Iterator[None]:
    """Run the numerics' host-synchronisation-free paths inside this block.

    Args:
        enabled: ``False`` restores the default (host checks allowed) inside the block.
    """
    token = _SYNC_FREE.set(bool(enabled))
    try:
        yield
    finally:
        _SYNC_FREE.reset(token)


def is_sync_free() -> bool:
    """Whether the current block is inside :func:`sync_free`."""
    return _SYNC_FREE.get()


@contextlib.contextmanager
def small_matrix_kernels(mode: SmallKernels) -> Iterator[None]:
    """Choose the small-matrix kernels inside this block.

    Args:
        mode: ``"auto"``, ``"unrolled"`` or ``"library"`` (see the module docstring).

    Raises:
        InputError: ``mode`` is not one of these.
    """
    if mode not in ("auto", "unrolled", "library"):
        from torchfilt.exceptions import InputError

        raise InputError(
            f"small_matrix_kernels: mode must be 'auto', 'unrolled' or 'library', got {mode!r}"
        )
    token = _SMALL.set(mode)
    try:
        yield
    finally:
        _SMALL.reset(token)


def current_small_matrix_kernels() -> SmallKernels:
    """The small-matrix kernel mode of the current block."""
    return _SMALL.get()


@contextlib.contextmanager
def skip_guard_checks(enabled: bool = True) -> Iterator[None]:
    """Let ``compile=True`` filters skip Dynamo's guard checks after a run's first steps.

    Only safe if nothing the compiled step reads (the model's parameters, its code) changes while a
    run is in progress.
    """
    token = _SKIP_GUARDS.set(bool(enabled))
    try:
        yield
    finally:
        _SKIP_GUARDS.reset(token)


def current_skip_guard_checks() -> bool:
    """Whether :func:`skip_guard_checks` is on in the current block."""
    return _SKIP_GUARDS.get()
