"""The windows of a likelihood fit: long recordings cut into overlapping windows filtered as
one batch (:func:`window_data`), and the random subsets of them that an iteration of a fit on
subsets steps on (:func:`window_subset`). See :mod:`torchfilt.training.likelihood`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError

__all__ = ["window_data", "window_subset"]


class _Windows(NamedTuple):
    y: Tensor  # (W, L, m)
    u: Tensor | None  # (W, L, nu)
    counted: Tensor  # (W, L) bool: steps counted in the likelihood
    rec: Tensor  # (W,) recording index
    start: Tensor  # (W,) first step of the window in its recording


def window_data(
    y: Tensor, u: Tensor | None, lengths: Sequence[int], window: int | None, burn_in: int
) -> _Windows:
    """Cut padded recordings ``y (R, T, m)`` into overlapping windows (see the module docstring).

    Args:
        y: measurements ``(R, T, m)``, NaN-padded past each recording's length.
        u: inputs ``(R, T, nu)`` or ``None``.
        lengths: steps of each recording.
        window: window length ``L`` (``None``: whole recordings).
        burn_in: uncounted steps at the start of each window, ``0 <= burn_in < L``.

    Returns:
        Windows ``y (W, L, m)``, ``u (W, L, nu)``, the counted steps ``(W, L)``, and for each
        window its recording and first step ``(W,)``.
    """
    R, T = int(y.shape[0]), int(y.shape[1])
    L = T if window is None else int(window)
    if L < 1:
        raise InputError(f"window must be at least 1 step, got {window}")
    if not 0 <= burn_in < L:
        raise InputError(f"burn_in must be in [0, window) = [0, {L}), got {burn_in}")
    stride = L - burn_in
    ys, us, counts, recs, starts = [], [], [], [], []
    for r in range(R):
        s = 0
        while s + burn_in < lengths[r]:
            stop = min(s + L, lengths[r])
            yw = y.new_full((L, y.shape[-1]), math.nan)
            yw[: stop - s] = y[r, s:stop]
            ys.append(yw)
            if u is not None:
                uw = u.new_zeros(L, u.shape[-1])
                uw[: stop - s] = u[r, s:stop]
                us.append(uw)
            c = torch.zeros(L, dtype=torch.bool)
            c[burn_in : stop - s] = True
            counts.append(c)
            recs.append(r)
            starts.append(s)
            if stop >= lengths[r]:
                break
            s += stride
    if not ys:
        raise InputError(
            f"y: every recording is at most burn_in = {burn_in} steps long (lengths "
            f"{list(lengths)[:5]}): no step would be counted; use a smaller burn_in"
        )
    return _Windows(
        torch.stack(ys),
        None if u is None else torch.stack(us),
        torch.stack(counts),
        torch.tensor(recs),
        torch.tensor(starts),
    )


def window_subset(windows: int, size: int, seed: int, iteration: int) -> Tensor:
    """The windows of one iteration of a fit on subsets: ``size`` of ``windows`` drawn without
    replacement, uniformly, from ``(seed, iteration)`` alone (a resumed fit draws the same).

    Args:
        windows: the number of windows ``W``.
        size: the subset's size, ``1 <= size <= W``.
        seed: the fit's seed (any integer).
        iteration: the iteration (1-based).

    Returns:
        The window indices ``(size,)`` (int64), increasing.
    """
    if not 1 <= size <= windows:
        raise InputError(f"size must be in [1, windows] = [1, {windows}], got {size}")
    g = torch.Generator().manual_seed((int(seed) * 1_000_003 + int(iteration)) % (2**63))
    return torch.randperm(windows, generator=g)[:size].sort().values
