"""Discretisation of continuous-time dynamics."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

__all__ = ["rk4"]


def rk4(
    drift: Callable[[Tensor, Tensor | None], Tensor],
    x: Tensor,
    u: Tensor | None,
    dt: float,
    substeps: int = 1,
) -> Tensor:
    """Integrate ``dx/dt = drift(x, u)`` over ``dt`` with ``substeps`` classical Runge-Kutta steps.

    ``u`` is held constant over the interval (zero-order hold).

    Args:
        drift: continuous dynamics, ``(..., n), (..., nu) -> (..., n)``.
        x: initial states, shape ``(..., n)``.
        u: inputs, shape ``(..., nu)``, or ``None``.
        dt: interval length.
        substeps: number of RK4 steps of length ``dt / substeps``.

    Returns:
        States after ``dt``, shape ``(..., n)``.
    """
    h = dt / substeps
    for _ in range(substeps):
        k1 = drift(x, u)
        k2 = drift(x + 0.5 * h * k1, u)
        k3 = drift(x + 0.5 * h * k2, u)
        k4 = drift(x + h * k3, u)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x
