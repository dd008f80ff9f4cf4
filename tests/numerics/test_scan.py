"""The associative scan equals a sequential fold, forwards and backwards."""

from typing import NamedTuple

import pytest
import torch

from torchfilt.exceptions import ShapeError
from torchfilt.numerics.scan import associative_scan

#: a scan reassociates matrix products: rounding differs from the fold's
SCAN_TOL = 1e-12


class Affine(NamedTuple):
    """``x -> M x + v``; composition is associative but not commutative."""

    M: torch.Tensor
    v: torch.Tensor


def compose(a: Affine, b: Affine) -> Affine:
    """``a`` first, then ``b``."""
    return Affine(b.M @ a.M, (b.M @ a.v.unsqueeze(-1)).squeeze(-1) + b.v)


def fold(elems: Affine, reverse: bool) -> Affine:
    T = elems.M.shape[0]
    order = range(T - 1, -1, -1) if reverse else range(T)
    acc, out = None, {}
    for t in order:
        e = Affine(elems.M[t], elems.v[t])
        acc = e if acc is None else (compose(e, acc) if reverse else compose(acc, e))
        out[t] = acc
    return Affine(
        torch.stack([out[t].M for t in range(T)]), torch.stack([out[t].v for t in range(T)])
    )


@pytest.mark.parametrize("reverse", [False, True], ids=["forward", "reverse"])
@pytest.mark.parametrize("T", [1, 2, 3, 4, 5, 7, 8, 13, 32, 33])
def test_scan_equals_fold(T, reverse):
    gen = torch.Generator().manual_seed(T)
    elems = Affine(
        0.5 * torch.randn(T, 2, 3, 3, generator=gen, dtype=torch.float64),
        torch.randn(T, 2, 3, generator=gen, dtype=torch.float64),
    )
    got = associative_scan(compose, elems, reverse=reverse)
    want = fold(elems, reverse)
    assert isinstance(got, Affine)
    assert torch.allclose(got.M, want.M, rtol=SCAN_TOL, atol=SCAN_TOL)
    assert torch.allclose(got.v, want.v, rtol=SCAN_TOL, atol=SCAN_TOL)


def test_scan_plain_tuple_and_errors():
    x = torch.arange(1.0, 10.0, dtype=torch.float64)
    (got,) = associative_scan(lambda a, b: (a[0] + b[0],), (x,))
    assert torch.equal(got, torch.cumsum(x, 0))
    with pytest.raises(ShapeError, match="same leading"):
        associative_scan(lambda a, b: a, (x, x[:3]))
