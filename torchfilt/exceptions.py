"""Named warnings and errors raised by torchfilt.

Every layer may import this module; it imports nothing from torchfilt.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "BundleError",
    "CholeskyJitterWarning",
    "ConvergenceWarning",
    "DataError",
    "DivergenceWarning",
    "ExecutionError",
    "FitError",
    "GaugeError",
    "InfeasibleError",
    "InputError",
    "InputTypeError",
    "MissingDependencyError",
    "MissingFileError",
    "MissingKeyError",
    "ModelError",
    "NotDetectableError",
    "NumericsWarning",
    "OutputError",
    "PrecisionWarning",
    "RecipeError",
    "RunError",
    "ShapeError",
    "TorchfiltError",
    "TorchfiltWarning",
    "WorkerError",
]


class TorchfiltWarning(UserWarning):
    """Base class of every warning torchfilt emits."""


class NumericsWarning(TorchfiltWarning, RuntimeWarning):
    """A numerical safeguard changed the computation (jitter, projection, clipping)."""


class CholeskyJitterWarning(NumericsWarning):
    """A matrix was not numerically positive definite and jitter was added to factor it."""


class ConvergenceWarning(NumericsWarning):
    """An iterative solver stopped before meeting its tolerance for some problems of a batch."""


class DivergenceWarning(NumericsWarning):
    """A filter produced non-finite estimates for some sequences of a batch."""


class PrecisionWarning(DivergenceWarning):
    """The exact Kalman filter's results are not reliable in the working precision (typically
    float32): a covariance lost positive definiteness, or the means are so large that their
    rounding is comparable to their standard deviations. The estimates are finite but
    over-confident; the message says how to fix it (float64, the square-root form, a jitter floor
    on ``Q``, or re-centring the state)."""


# ---------------------------------------------------------------------------------------- errors
# Every error caused by what a user passed in (arguments, files, recipes, run directories) is a
# ``TorchfiltError``. The CLI catches exactly these (one line, exit 2); anything else is a bug and
# keeps its traceback. Each subclass also derives from the builtin exception it refines, so
# ``except ValueError`` keeps working.


class TorchfiltError(Exception):
    """Base class of every error torchfilt raises for bad input. The message names the argument,
    file or key and says what is wrong."""


class InputError(TorchfiltError, ValueError):
    """An argument of a public function is invalid (value, dtype, option)."""


class InputTypeError(InputError, TypeError):
    """An argument has the wrong type or dtype (also a ``TypeError``)."""


class GaugeError(InputError):
    """A state-space model to be learned from measurements alone has no fixed gauge: nothing pins
    its state coordinates (a known measurement map for some channels, or an anchored output). The
    message names what must be fixed."""


class ShapeError(InputError):
    """An argument has the wrong shape. The message names the argument and the expected shape."""


class ModelError(TorchfiltError, ValueError):
    """A model is inconsistent: its outputs do not match its declared dimensions, or its
    parameters are invalid."""


class NotDetectableError(ModelError):
    """A state-space pair is not detectable (or not stabilisable): no steady-state gain exists."""


class InfeasibleError(TorchfiltError, RuntimeError):
    """A constrained problem has no feasible point (or the solver did not converge)."""


class RecipeError(InputError):
    """A recipe is invalid; the message names the file and the key."""


class RunError(TorchfiltError, RuntimeError):
    """A run directory cannot be used as asked (resume without a run, a changed recipe, ...)."""


class ExecutionError(TorchfiltError, RuntimeError):
    """A filter run could not be carried out as planned (a CUDA-graph capture whose step
    synchronised with the host, a record sink that did not receive every step); the message
    names the cause."""


class FitError(TorchfiltError, RuntimeError):
    """A fit could not go on: its objective is not finite at its start, or a step of it failed
    numerically (a factorisation that failed even with jitter, a non-finite log-likelihood after
    a step). The message names the fit (``fit_em``, ``fit_measurement_only(method="likelihood")``,
    ...) and the step (the start, or the iteration and its E-step, M-step or likelihood
    evaluation) and says what to change.

    Attributes:
        fit: the fit's name.
        step: the step that failed, in words.
    """

    def __init__(self, message: str, *, fit: str = "", step: str = "") -> None:
        super().__init__(message)
        self.fit, self.step = fit, step


class WorkerError(RunError):
    """A data-parallel job lost a worker (its process died or was killed, or it did not reach a
    collective within the timeout). The message names the rank and says how to continue (the
    same call with ``resume=True`` continues from the workers' checkpoints)."""


class OutputError(TorchfiltError, OSError):
    """An output cannot be written: it exists (and ``--force`` was not given), its folder is a
    file or is read-only, or the disk is full. The message names the path."""


class MissingDependencyError(TorchfiltError, ImportError):
    """An optional dependency a feature needs is not installed; the message says how to install
    it (e.g. ``pip install 'torchfilt[distributed]'`` for Ray)."""


class MissingKeyError(TorchfiltError, KeyError):
    """A name that was asked for does not exist (a recording's channel, ...). The message names it
    and lists the names there are. Also a ``KeyError``; ``str()`` gives the plain message."""

    def __str__(self) -> str:
        return Exception.__str__(self)


class MissingFileError(TorchfiltError, FileNotFoundError):
    """An input file a feature reads does not exist where it must be (for example a data file an
    optional package should ship). The message names the path and how to get it."""


class BundleError(TorchfiltError, ValueError):
    """A file is not a usable torchfilt model bundle (foreign, corrupted, tampered or unsafe)."""


class DataError(TorchfiltError, ValueError):
    """A data file is invalid. The message names the file and, where it applies, the column and row.

    Attributes:
        path: the offending file.
        column: the offending column, if any.
        line: the 1-based line in the file (CSV, header = line 1) or 0-based row (NPZ), if any.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | Path | None = None,
        column: str | None = None,
        line: int | None = None,
        row: int | None = None,
    ) -> None:
        where = []
        if path is not None:
            where.append(str(path))
        if column is not None:
            where.append(f"column {column!r}")
        if line is not None:
            where.append(f"line {line}")
        if row is not None:
            where.append(f"row {row}")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.path = None if path is None else Path(path)
        self.column = column
        self.line = line
        self.row = row
