"""Hypothesis suite over ``subspace_identify`` (with and without ``stable``): small random
input-output data, valid or with one argument corrupted (a NaN, complex data, an order or a
block-row count out of range, inputs of the wrong length).

A corrupted case must be refused with a TorchfiltError that names the corrupted argument; a
valid one returns a finite model whose noise covariances are positive semi-definite and, with
``stable=True``, whose ``A`` has no eigenvalue outside the unit circle. See
tests/fuzz_support.py for the contract and the counts.
"""

from __future__ import annotations

import numpy as np
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.exceptions import ModelError
from torchfilt.models import subspace_identify

D = torch.float64

#: the corruption of a case, and the argument its refusal must name
CORRUPTIONS = {
    "none": None,
    "y NaN": "y",
    "y complex": "y",
    "order too large": "order",
    "order zero": "order",
    "block_rows zero": "block_rows",
    "u wrong length": "u",
}


def _check(data: st.DataObject) -> None:
    seed = data.draw(st.integers(0, 2**16), "seed")
    rng = np.random.default_rng(seed)
    m, p = data.draw(st.integers(1, 2), "m"), data.draw(st.integers(0, 1), "p")
    T = data.draw(st.integers(60, 160), "T")
    order = data.draw(st.integers(1, 3), "order")
    rows = data.draw(st.integers(order // m + 2, 8), "block_rows")
    stable = data.draw(st.booleans(), "stable")
    # half the cases valid, the rest spread over the corruptions
    corrupt = data.draw(st.booleans(), "corrupt")
    bad = sorted(c for c in CORRUPTIONS if c != "none")
    corruption = data.draw(st.sampled_from(bad), "corruption") if corrupt else "none"
    # a random system, stable or (sometimes) not, so that both branches of ``stable`` run
    A = rng.standard_normal((order, order)) * data.draw(st.floats(0.2, 0.9), "scale")
    B, C = rng.standard_normal((order, max(p, 1))), rng.standard_normal((m, order))
    u = rng.standard_normal((1, T, p)) if p else None
    x, y = np.zeros(order), np.zeros((1, T, m))
    for t in range(T):
        x = A @ x + (B @ u[0, t] if p else 0.0) + 0.1 * rng.standard_normal(order)
        x = np.clip(x, -1e3, 1e3)
        y[0, t] = C @ x + 0.1 * rng.standard_normal(m)
    yt = torch.tensor(y, dtype=D)
    ut = None if u is None else torch.tensor(u, dtype=D)
    kw = {"order": order, "block_rows": rows, "stable": stable}
    if corruption == "y NaN":
        yt[0, T // 2, 0] = float("nan")
    elif corruption == "y complex":
        yt = yt.to(torch.complex128)
    elif corruption == "order too large":
        kw["order"] = rows * m
    elif corruption == "order zero":
        kw["order"] = 0
    elif corruption == "block_rows zero":
        kw["block_rows"] = 0
    elif corruption == "u wrong length":
        ut = torch.zeros(1, T - 1, max(p, 1), dtype=D)
    out, _ = attempt("subspace_identify", subspace_identify, yt, ut, **kw)
    what = CORRUPTIONS[corruption]
    if what is not None:
        assert isinstance(out, Refused), (corruption, out)
        assert what in str(out.error), (corruption, out)
        return
    if isinstance(out, Refused):  # a valid case is refused only for a singular A
        assert isinstance(out.error, ModelError) and "singular" in str(out.error), out
        return
    model = out.model
    for M in (model.A, model.H, model.transition.noise_cov(), model.measurement.noise_cov()):
        assert bool(torch.isfinite(M).all())
    for S in (model.transition.noise_cov(), model.measurement.noise_cov(), out.P0):
        assert float(torch.linalg.eigvalsh(0.5 * (S + S.mT)).min()) >= -1e-9 * float(S.abs().max())
    if stable:
        assert float(torch.linalg.eigvals(model.A).abs().max()) <= 1.0 + 1e-9


test_subspace_fuzz, test_subspace_fuzz_long = property_tests(_check, short=30, long=400)


def teardown_module() -> None:
    print_stats()
