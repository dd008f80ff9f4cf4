"""The data of the fits: one idea, one name.

Every fit (:func:`~torchfilt.training.fit_likelihood`, :func:`~torchfilt.training.fit_em`,
:func:`~torchfilt.training.fit_measurement_only`, :func:`~torchfilt.training.calibrate`) takes its
training data as ``(y, u=None)``, in the filter convention (:mod:`torchfilt.filters`: step ``t``
updates with ``y[..., t, :]`` after predicting with ``u[..., t, :]``). ``y`` is any of

- measurements ``(..., T, m)``: a batch of recordings of one length (NaN is missing), with
  inputs ``u`` ``(..., T, nu)`` or ``None``;
- a list of ``(T_i, m)`` tensors of different lengths, with ``u`` a list of ``(T_i, nu)``;
- a :class:`Sequences` (the measurements and inputs together, and optionally their own prior);
  ``u`` must then be ``None``;
- a list of :class:`~torchfilt.io.Recording` in the log layout (row 0 is the prior's time, as in
  :func:`~torchfilt.pipeline.filter_recordings`: ``y = measurements[1:]``,
  ``u = inputs[:-1]``; :meth:`Sequences.from_recordings`); ``u`` must then be ``None``.

The held-out data of ``validation=`` may be any of the same kinds. :func:`as_sequences` turns
each of them into one :class:`Sequences`: the one conversion all the fits use.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, TypeAlias

from torch import Tensor

from torchfilt.exceptions import InputError
from torchfilt.io import Recording

__all__ = ["FitData", "Sequences", "as_sequences"]


class Sequences(NamedTuple):
    """Recordings given as tensors: the training data of a fit, or its held-out data for early
    stopping (filtered whole, every step counted).

    Attributes:
        y: measurements ``(..., T, m)`` or a list of ``(T_i, m)``; NaN is missing.
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None``.
        x0: prior means ``(..., n)`` or ``(n,)``; ``None``: the fit's ``x0=`` (for held-out
            data: the training prior, when it is one shared ``(n,)``).
        P0: prior covariances ``(..., n, n)`` or ``(n, n)``; ``None``: the fit's ``P0=``
            likewise.
    """

    y: Tensor | Sequence[Tensor]
    u: Tensor | Sequence[Tensor] | None = None
    x0: Tensor | None = None
    P0: Tensor | None = None

    @classmethod
    def from_recordings(cls, recordings: Sequence[Recording], *, name: str = "y") -> Sequences:
        """The measurements and inputs of recordings in the log layout, in the filter convention.

        Row 0 of a recording is its prior's time (as in
        :func:`~torchfilt.pipeline.filter_recordings`): its measurements of ``(T_i + 1, m)``
        rows give ``y = measurements[1:]`` ``(T_i, m)`` and its inputs ``u = inputs[:-1]``
        ``(T_i, nu)`` (the input row ``t`` drives the step to the measurement row ``t + 1``).

        Args:
            recordings: the recordings, each with at least 2 rows.
            name: the argument the recordings came as, for the error messages.

        Returns:
            A :class:`Sequences` of lists (``u`` ``None`` when the recordings have no inputs;
            ``x0``, ``P0`` ``None``).

        Raises:
            InputError: no recordings, an item that is not a
                :class:`~torchfilt.io.Recording`, a recording of fewer than 2 rows, or
                recordings of which only some have inputs.
        """
        recs = list(recordings)
        if not recs:
            raise InputError(f"{name}: no recordings given")
        for i, r in enumerate(recs):
            if not isinstance(r, Recording):
                raise InputError(
                    f"{name}[{i}]: expected a Recording (every item of a list of recordings), "
                    f"got {type(r).__name__}"
                )
            if len(r) < 2:
                raise InputError(
                    f"{name}[{i}]: {r.name} needs at least 2 rows (row 0 is the prior's time)"
                )
        with_inputs = [r.inputs is not None for r in recs]
        if any(with_inputs) and not all(with_inputs):
            i = with_inputs.index(not with_inputs[0])
            raise InputError(
                f"{name}[{i}]: {recs[i].name} {'has' if with_inputs[i] else 'has no'} inputs, "
                f"{name}[0] {'has' if with_inputs[0] else 'has none'}; give recordings of one "
                "dataset"
            )
        ys = [r.measurements[1:] for r in recs]
        us = [r.inputs[:-1] for r in recs] if with_inputs[0] else None  # type: ignore[index]
        return cls(ys, us)


#: The kinds of value a fit's ``y`` (and ``validation``) accepts (see the module docstring).
FitData: TypeAlias = Tensor | Sequence[Tensor] | Sequences | Sequence[Recording]


def as_sequences(
    y: FitData,
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    x0: Tensor | None = None,
    P0: Tensor | None = None,
    name: str = "y",
) -> Sequences:
    """A fit's data ``(y, u)`` of any accepted kind as one :class:`Sequences`.

    Args:
        y: measurements ``(..., T, m)``, a list of ``(T_i, m)``, a :class:`Sequences`, or a list
            of :class:`~torchfilt.io.Recording` in the log layout
            (:meth:`Sequences.from_recordings`).
        u: inputs ``(..., T, nu)`` or a list of ``(T_i, nu)`` for a tensor or a list of
            tensors; ``None`` for a :class:`Sequences` or recordings, which carry their own.
        x0: the prior mean ``(n,)`` or ``(..., n)`` to use where the data carry none (a
            :class:`Sequences`' own ``x0``, when not ``None``, is kept).
        P0: the prior covariance ``(n, n)`` or ``(..., n, n)``, likewise.
        name: the argument ``y`` came as (``"y"``, ``"validation"``), for the error messages.

    Returns:
        A :class:`Sequences` with the measurements, the inputs and the prior. The tensors are
        not checked or copied here: the fit checks them.

    Raises:
        InputError: inputs ``u`` given with a :class:`Sequences` or with recordings, or
            recordings that :meth:`Sequences.from_recordings` refuses.
    """
    if isinstance(y, Sequences):
        _check_no_inputs(u, name, "a Sequences, which carries its own inputs (Sequences(y, u))")
        data = y
    elif not isinstance(y, Tensor) and _is_recordings(y):
        _check_no_inputs(u, name, "recordings, which carry their own inputs (inputs[:-1])")
        data = Sequences.from_recordings(y, name=name)  # type: ignore[arg-type]
    else:
        data = Sequences(y, u)  # type: ignore[arg-type]
    return Sequences(
        data.y,
        data.u,
        x0 if data.x0 is None else data.x0,
        P0 if data.P0 is None else data.P0,
    )


def _is_recordings(y: object) -> bool:
    """Whether ``y`` is a list (any sequence) whose first item is a Recording."""
    if not isinstance(y, Sequence) or isinstance(y, str) or len(y) == 0:
        return False
    return isinstance(y[0], Recording)


def _check_no_inputs(u: object, name: str, what: str) -> None:
    """Refuse inputs ``u`` given beside data that carry their own."""
    if u is not None:
        raise InputError(f"u: must be None when {name} is {what}; give the inputs inside {name}")
