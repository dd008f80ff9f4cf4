"""A work-efficient associative scan (all-prefix combination) in plain ``torch``.

torch 2.13 has no public associative scan (``torch._higher_order_ops.associative_scan`` is
private), so this module provides one. It is the classic odd/even recursion (Blelloch 1990;
Ladner & Fischer 1980): combine neighbouring pairs, scan the half-length sequence of pair results
recursively, then fill in the even positions with one more combination. Each level is one batched
call of ``fn`` over all the pairs at once, so the work is ``O(T)`` combinations and the depth
``O(log T)`` batched calls; on an accelerator each call runs the ``T / 2^k`` combinations in
parallel.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import torch
from torch import Tensor

from torchfilt.exceptions import ShapeError

__all__ = ["associative_scan"]

E = TypeVar("E", bound=Sequence[Tensor])


def _interleave(even: Sequence[Tensor], odd: Sequence[Tensor], cls: type) -> Sequence[Tensor]:
    """Merge ``even[0], odd[0], even[1], odd[1], ...`` along dim 0 (``len(even) - len(odd)`` is 0
    or 1)."""
    out = []
    for e, o in zip(even, odd, strict=True):
        k = o.shape[0]
        pairs = torch.stack([e[:k], o], dim=1).flatten(0, 1)
        out.append(torch.cat([pairs, e[k:]], dim=0) if e.shape[0] > k else pairs)
    return _rebuild(cls, out)


def _rebuild(cls: type, leaves: list[Tensor]) -> Sequence[Tensor]:
    if cls is tuple or cls is list:
        return cls(leaves)  # type: ignore[no-any-return]
    return cls(*leaves)  # type: ignore[no-any-return]


def _slice(elems: Sequence[Tensor], sl: slice) -> Sequence[Tensor]:
    return _rebuild(type(elems), [x[sl] for x in elems])


def _scan(fn: Callable[[E, E], E], elems: E) -> E:
    T = elems[0].shape[0]
    if T < 2:
        return elems
    # combine neighbours (0,1), (2,3), ...: the inclusive prefixes at the odd positions, once the
    # half-length sequence of pairs is scanned
    pairs = fn(_slice(elems, slice(0, T - 1, 2)), _slice(elems, slice(1, T, 2)))  # type: ignore[arg-type]
    odd = _scan(fn, pairs)
    # the even positions 2, 4, ... follow from the odd prefix just before them
    k = (T - 1) // 2
    if k > 0:
        rest = fn(_slice(odd, slice(0, k)), _slice(elems, slice(2, T, 2)))  # type: ignore[arg-type]
        even = _rebuild(
            type(elems), [torch.cat([x[:1], r], 0) for x, r in zip(elems, rest, strict=True)]
        )
    else:
        even = _slice(elems, slice(0, 1))
    return _interleave(even, odd, type(elems))  # type: ignore[return-value]


def associative_scan(fn: Callable[[E, E], E], elems: E, *, reverse: bool = False) -> E:
    """Inclusive scan of an associative operator along dim 0 of every leaf.

    ``out[t] = elems[0] . elems[1] . ... . elems[t]`` where ``a . b = fn(a, b)`` and ``a`` comes
    first in time; with ``reverse=True``, ``out[t] = elems[t] . elems[t+1] . ... . elems[T-1]``
    (``fn(a, b)`` still receives the earlier element as ``a``).

    Args:
        fn: associative operator on batches of elements: it takes two tuples (or NamedTuples) of
            tensors whose leading dimension indexes independent pairs and returns one of the same
            structure.
        elems: tuple or NamedTuple of tensors, each ``(T, ...)`` with the same ``T``.
        reverse: scan from the end.

    Returns:
        The scanned elements, same structure and shapes as ``elems``.
    """
    if len(elems) == 0:
        raise ShapeError("elems: expected at least one tensor")
    T = elems[0].shape[0] if elems[0].dim() > 0 else -1
    for x in elems:
        if x.dim() == 0 or x.shape[0] != T:
            raise ShapeError(
                "elems: every tensor needs the same leading (scanned) dimension; got shapes "
                f"{[tuple(e.shape) for e in elems]}"
            )
    if not reverse:
        return _scan(fn, elems)

    def flipped(a: E, b: E) -> E:
        return fn(b, a)

    rev = _rebuild(type(elems), [x.flip(0) for x in elems])
    out = _scan(flipped, rev)  # type: ignore[arg-type]
    return _rebuild(type(elems), [x.flip(0) for x in out])  # type: ignore[return-value]
