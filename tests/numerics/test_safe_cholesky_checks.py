"""safe_cholesky's one-read check for the common case (every entry finite, every factor found)
leaves every other case to the per-element check: entries whose sum overflows, a non-finite entry
in the triangle LAPACK does not read, a failed factor beside good ones, an empty batch."""

import numpy as np
import pytest
import torch

from torchfilt.exceptions import CholeskyJitterWarning
from torchfilt.numerics import safe_cholesky

D = torch.float64


def test_entries_whose_sum_overflows_still_factor_exactly():
    # finite entries near the largest float: their sum is inf, so the fast check cannot pass,
    # and the per-element check must still return the plain factor
    A = torch.tensor([[1e308, 0.0], [0.0, 1e308]], dtype=D).expand(3, 2, 2).clone()
    L = safe_cholesky(A)
    np.testing.assert_array_equal(L.numpy(), np.linalg.cholesky(A.numpy()))


def test_non_finite_entry_in_the_unread_triangle_is_nan():
    # LAPACK reads the lower triangle only, so its factor of this matrix is finite; the input is
    # not finite, so the element's factor is NaN, the others' exact
    A = torch.eye(2, dtype=D).repeat(3, 1, 1)
    A[1, 0, 1] = float("nan")
    L = safe_cholesky(A)
    assert bool(torch.isnan(L[1]).all())
    np.testing.assert_array_equal(L[[0, 2]].numpy(), np.eye(2)[None].repeat(2, 0))


def test_failed_factor_beside_good_ones_is_jittered_alone():
    good = torch.tensor([[4.0, 2.0], [2.0, 3.0]], dtype=D)
    singular = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=D)
    A = torch.stack([good, singular, good])
    with pytest.warns(CholeskyJitterWarning):
        L = safe_cholesky(A)
    np.testing.assert_array_equal(L[0].numpy(), np.linalg.cholesky(good.numpy()))
    assert bool(torch.isfinite(L[1]).all())
    np.testing.assert_allclose((L[1] @ L[1].mT).numpy(), singular.numpy(), atol=1e-9)


def test_empty_batch():
    A = torch.zeros(0, 3, 3, dtype=D)
    assert safe_cholesky(A).shape == (0, 3, 3)
