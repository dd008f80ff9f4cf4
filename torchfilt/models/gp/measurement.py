"""``GPMeasurement``: a GP measurement model ``y_k = h(x_k, u_k) + v``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchfilt.models.gp.data import measurement_pairs
from torchfilt.models.gp.model import _ROLES, GPModel

__all__ = ["GPMeasurement"]


class GPMeasurement(GPModel):
    """A measurement model learned by GP regression: input ``x_k`` (and ``u_k``), target ``y_k``.

    ``predict(x, u)`` returns the predictive mean of ``y_k`` and its variance (latent variance +
    likelihood noise) per point; a :class:`~torchfilt.CKF` adds the cubature average of the latter
    to ``P_yy`` (the learned ``R``).

    Example:
        >>> import torch
        >>> from torchfilt.models.gp import GPMeasurement
        >>> x = torch.linspace(0, 3, 60, dtype=torch.float64).reshape(-1, 1).repeat(1, 2)
        >>> y = torch.sin(x[:, :1]) + 0.01 * torch.randn(60, 1, dtype=torch.float64)
        >>> h = GPMeasurement.fit(x, y, inputs=[0], iterations=30, progress=False)
        >>> h.predict(x[:3]).var.shape
        torch.Size([3, 1])

    Raises:
        InputError: not one group per ``config`` group, or a ``prior_mean`` that does not match
            ``config.prior_mean`` (build one with ``fit`` or ``from_state``).
    """

    role = "measurement"

    @classmethod
    def fit(
        cls,
        x: Tensor | Sequence[Tensor],
        y: Tensor | Sequence[Tensor],
        u: Tensor | Sequence[Tensor] | None = None,
        **options: Any,
    ) -> GPMeasurement:
        """Fit a GP measurement model and return it trained and frozen.

        Args:
            x: states ``(..., N, n)`` or a list of ``(T_i, n)`` recordings.
            y: measurements ``(..., N, m)`` or a list of ``(T_i, m)``; NaN entries are missing
                and are dropped per output.
            u: inputs ``(..., N, nu)``, a list, or ``None`` (the usual case: ``h`` of ``x`` only).
            **options: as for :meth:`GPTransition.fit <torchfilt.models.gp.GPTransition.fit>`
                except ``increment``; ``prior_mean`` is a nominal ``h0(x, u) -> y``. Input
                selection matters most here: a sensor that depends on some states only should
                see only those (``inputs=[0]``), or the GP extrapolates along the others.

        Returns:
            The trained, frozen model.
        """
        dtype = options.pop("dtype", torch.float64)
        pairs = measurement_pairs(x, y, u, dtype=dtype)
        return cls._fit(pairs, options)  # type: ignore[return-value]


_ROLES["measurement"] = GPMeasurement
