"""The fitting loop every fit runs, and the typed options the fits share.

Why a package of its own, at the numerics layer: the loop is needed by fits in two layers, the GP
hyperparameter training in :mod:`torchfilt.models.gp` (layer 3) and the likelihood, calibration
and EM fits in :mod:`torchfilt.training` (layer 7). A layer may import only from layers to its
left, so the loop sits below both and knows nothing of models, filters, files or terminals: it
needs only ``torch``. What depends on higher layers is passed in: the atomic file write of the
checkpoints (:func:`torchfilt.io.atomic_write`), the progress reporter
(:class:`torchfilt.io.progress.ProgressBar`, or the GP's light progress line) and the
``all_reduce`` of a data-parallel fit. Moving the GP training up into ``training`` instead would
have made ``GPModel.fit`` depend on the layer that uses the models.

* :mod:`torchfilt.optim.options`: ``OptimizerOptions``, ``WindowOptions``, ``StoppingOptions``,
  ``CheckpointOptions``, ``FitHooks`` and every fit's defaults (``DEFAULTS``, with a table of
  where they differ; ``resolve_options`` fills a fit's ``None`` options from it), and the
  decorator that keeps the fits' old flat keywords working for a release.
* :mod:`torchfilt.optim.loop`: ``FitLoop`` (iterations, progress, callback, data-parallel stop,
  stopping rules, checkpoints), ``GuardedStep`` (Adam / L-BFGS that never leaves the finite
  region), ``EarlyStopping``.
* :mod:`torchfilt.optim.checkpoint`: ``CheckpointFile`` (atomic, fingerprinted, bit-identical
  resume, data-parallel agreement on where to resume).

Stopping rules live in ``StoppingOptions`` and ``FitLoop._rule`` (the relative change over a
window of iterations, ``rtol`` / ``rtol_window``, is on by default); the estimate of the stage's
time and of what is left is drawn by ``FitLoop.run`` through the fit's reporter; parameters held
fixed (``fixed=``) are left out of the list a fit hands to ``GuardedStep`` by
``free_parameters``. Stochastic subsets of windows live in the likelihood fit's step
(:mod:`torchfilt.training.likelihood`); its full objective, evaluated every few iterations, is
the record entry the loop's rules watch (``FitLoop(monitor=...)``), and ``atol`` stops a fit in
nats of that objective.
"""

from torchfilt.optim.checkpoint import AtomicWrite, CheckpointFile, fingerprint
from torchfilt.optim.loop import (
    EarlyStopping,
    FitLoop,
    GuardedStep,
    Outcome,
    Reporter,
    StepResult,
    failed_step,
    free_parameters,
    make_optimizer,
    restore,
    snapshot,
)
from torchfilt.optim.options import (
    DEFAULTS,
    CheckpointOptions,
    FitDefaults,
    FitHooks,
    FitOptions,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
    deprecated_fit_keywords,
    field_docs,
    resolve_options,
)

__all__ = [
    "DEFAULTS",
    "AtomicWrite",
    "CheckpointFile",
    "CheckpointOptions",
    "EarlyStopping",
    "FitDefaults",
    "FitHooks",
    "FitLoop",
    "FitOptions",
    "GuardedStep",
    "OptimizerOptions",
    "Outcome",
    "Reporter",
    "StepResult",
    "StoppingOptions",
    "WindowOptions",
    "deprecated_fit_keywords",
    "failed_step",
    "field_docs",
    "fingerprint",
    "free_parameters",
    "make_optimizer",
    "resolve_options",
    "restore",
    "snapshot",
]
