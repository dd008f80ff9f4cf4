"""The dtype rule: torchfilt computes in float32 or float64, and says so at the boundary.

The rule (one place; every public entry point applies it through the two helpers below):

- **Floating data** (measurements, states, covariances, bounds, training data, model outputs) must
  be ``float32`` or ``float64``. ``float16`` and ``bfloat16`` are **refused** with an
  :class:`~torchfilt.exceptions.InputTypeError` (an ``InputError``) that names the argument, never upcast behind the
  caller's back: torch has no half-precision Cholesky, eigen or triangular solves, and a result in
  a dtype other than the one passed in would be a silent change. Convert with ``.float()`` (or
  ``.double()``).
- **Complex, bool and other non-real dtypes** are refused: the imaginary part would be dropped.
- **Integers** are accepted only where an argument is converted to the dtype of the other data
  (``x0``, ``P0``, ``u``), never as the computing dtype: ``dtype=torch.int64`` for a fit is
  refused, since it would truncate the data.
- A model's output of another floating dtype is cast to the dtype of its points (see
  :class:`~torchfilt.models.FunctionModel`); a non-floating output is a
  :class:`~torchfilt.exceptions.ModelError`.

The checks read only tensor metadata: no host synchronisation, and static under ``torch.compile``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError

__all__ = ["COMPUTE_DTYPES", "check_compute_dtype", "check_real_tensor"]

#: The floating dtypes torchfilt computes in.
COMPUTE_DTYPES: tuple[torch.dtype, ...] = (torch.float32, torch.float64)

_INTEGER_DTYPES = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def check_compute_dtype(dtype: Any, name: str = "dtype") -> torch.dtype:
    """Refuse a computing dtype other than float32 / float64.

    Args:
        dtype: the requested dtype (``torch.float64``, ...).
        name: the argument's name, for the message.

    Returns:
        ``dtype``, unchanged.

    Raises:
        InputError: ``dtype`` is not a ``torch.dtype`` or not float32 / float64.
    """
    if not isinstance(dtype, torch.dtype):
        raise InputError(f"{name}: expected torch.float32 or torch.float64, got {dtype!r}")
    if dtype not in COMPUTE_DTYPES:
        raise InputError(
            f"{name}: torchfilt computes in torch.float32 or torch.float64, got {dtype} "
            "(half precision has no linear algebra in torch; integers would truncate the data)"
        )
    return dtype


def check_real_tensor(value: Tensor, name: str, *, integers: bool = False) -> Tensor:
    """Apply the dtype rule to a tensor argument (metadata only, no host synchronisation).

    Args:
        value: the argument, any shape.
        name: the argument's name, for the message.
        integers: accept integer tensors too (arguments that are cast to the other data's dtype).

    Returns:
        ``value``, unchanged (any shape).

    Raises:
        InputTypeError: ``value`` is float16 / bfloat16, complex, bool, or an integer tensor
            where ``integers`` is False (an :class:`~torchfilt.exceptions.InputError` too).
    """
    dtype = value.dtype
    if dtype in COMPUTE_DTYPES:
        return value
    if integers and dtype in _INTEGER_DTYPES:
        return value
    if dtype in (torch.float16, torch.bfloat16):
        raise InputTypeError(
            f"{name}: {dtype} is not supported; torchfilt computes in float32 or float64 "
            f"(convert with {name}.float())"
        )
    what = "float32, float64 or an integer type" if integers else "float32 or float64"
    raise InputTypeError(f"{name}: expected real numbers ({what}), got dtype {dtype}")
