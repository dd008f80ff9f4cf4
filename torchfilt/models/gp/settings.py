"""The GPyTorch numerical settings torchfilt uses, as explicit context managers.

GPyTorch's defaults are not exact: above ``max_cholesky_size`` (800 points) it replaces Cholesky
factorisations by conjugate gradients and stochastic Lanczos quadrature, and ``fast_pred_var``
(LOVE) replaces the predictive variance with a low-rank approximation shared across the outputs of a
batch. Measured on this project's problems those defaults moved predictive means by 0.05-0.14 and
variances by more than their own size (standardised units, 5000 points). torchfilt therefore trains
and predicts with :func:`exact_settings`: dense Cholesky at every size, exact log-determinants and
solves, exact predictive variances. The fast path inside a filter is the frozen predictor
(:mod:`torchfilt.models.gp.predictor`), not GPyTorch's approximations.

:func:`gpytorch_default_settings` restores GPyTorch's stock behaviour plus ``fast_pred_var`` and
exists only to benchmark against it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import gpytorch

__all__ = ["MAX_CHOLESKY_SIZE", "exact_settings", "gpytorch_default_settings"]

#: Matrices up to this size are factored by Cholesky (i.e. always).
MAX_CHOLESKY_SIZE = 10**9
#: GPyTorch's own default.
GPYTORCH_MAX_CHOLESKY_SIZE = 800


@contextmanager
def exact_settings() -> Iterator[None]:
    """Dense Cholesky everywhere; exact solves, log-determinants and predictive variances."""
    with ExitStack() as stack:
        stack.enter_context(gpytorch.settings.max_cholesky_size(MAX_CHOLESKY_SIZE))
        stack.enter_context(
            gpytorch.settings.fast_computations(
                covar_root_decomposition=False, log_prob=False, solves=False
            )
        )
        stack.enter_context(gpytorch.settings.fast_pred_var(False))
        stack.enter_context(gpytorch.settings.skip_posterior_variances(False))
        yield


@contextmanager
def gpytorch_default_settings() -> Iterator[None]:
    """GPyTorch's default numerics with LOVE (``fast_pred_var``) on: its fastest predictive path."""
    with ExitStack() as stack:
        stack.enter_context(gpytorch.settings.max_cholesky_size(GPYTORCH_MAX_CHOLESKY_SIZE))
        stack.enter_context(gpytorch.settings.fast_computations(True, True, True))
        stack.enter_context(gpytorch.settings.fast_pred_var(True))
        yield
