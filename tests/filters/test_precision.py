"""The exact Kalman path in float32 (issue 24, item 1): the float64 run of the same data is the
reference. A float32 run either matches it within float32 tolerance with no warning, or it is
actually wrong and a PrecisionWarning (a DivergenceWarning) says so and how to fix it.

The model is a poorly observable constant-acceleration model (dt = 1, the position measured),
10^4 steps, a batch of 8.
"""

from __future__ import annotations

import warnings

import pytest
import torch

import torchfilt.filters.kalman_runners as runners
from torchfilt import CKF, LinearGaussianModel
from torchfilt.exceptions import DivergenceWarning, PrecisionWarning
from torchfilt.filters.kalman_checks import precision_problems, warn_precision
from torchfilt.filters.results import KalmanFilterResult

T, B = 10_000, 8
A = torch.tensor([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
H = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
G = torch.tensor([[1 / 6], [0.5], [1.0]], dtype=torch.float64)
R = torch.eye(1, dtype=torch.float64)
X0 = torch.zeros(B, 3, dtype=torch.float64)
P0 = 10.0 * torch.eye(3, dtype=torch.float64)


def _model(q: float, dtype: torch.dtype) -> LinearGaussianModel:
    Q = q * G @ G.T
    return LinearGaussianModel(A.to(dtype), H.to(dtype), Q.to(dtype), R.to(dtype))


def _simulate(q: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """True states ``(B, T, 3)`` and measurements ``(B, T, 1)`` in float64."""
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(T, B, 1, generator=g, dtype=torch.float64) * q**0.5
    v = torch.randn(B, T, 1, generator=g, dtype=torch.float64)
    x, xs = torch.zeros(B, 3, dtype=torch.float64), []
    for t in range(T):
        x = x @ A.T + w[t] @ G.T
        xs.append(x)
    X = torch.stack(xs, -2)
    return X, X @ H.T + v


def _run(q: float, y: torch.Tensor, dtype: torch.dtype, **kw):
    """Filter ``y`` in ``dtype``; the result and the torchfilt warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = CKF(_model(q, dtype), sqrt=kw.pop("sqrt", False)).filter(
            y.to(dtype), x0=X0.to(dtype), P0=P0.to(dtype), path="kalman", **kw
        )
    return res, [w for w in caught if issubclass(w.category, PrecisionWarning)]


def _nees_vs(ref, res) -> float:
    """Mean NEES of ``res``'s means against the float64 reference's moments."""
    e = (res.mean.double() - ref.mean).unsqueeze(-1)
    P = ref.cov.expand(*ref.mean.shape, 3)
    return float((e.mT @ torch.linalg.solve(P, e)).mean())


def _var_ratio(ref, res) -> tuple[float, float]:
    r = res.cov.double().diagonal(dim1=-2, dim2=-1) / ref.cov.diagonal(dim1=-2, dim2=-1)
    return float(r.min()), float(r.max())


@pytest.mark.parametrize("q", [1e-4, 1e-8])
@pytest.mark.parametrize("runner", ["kalman-riccati", "kalman-fast"])
def test_float32_plain_runners_follow_the_float64_covariance(q: float, runner: str) -> None:
    """Zero-mean data (the means stay small, only the covariance recursion is at stake): the
    float32 Riccati and fast runners used to drift off the Riccati solution (variances up to 870
    times too large, or indefinite covariances); they match float64 and do not warn."""
    y = torch.randn(B, T, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    mask = None
    if runner == "kalman-fast":  # a missing value: the covariances depend on the data
        mask = torch.ones(B, T, 1, dtype=torch.bool)
        mask[0, 0, 0] = False
    ref, warned64 = _run(q, y, torch.float64, mask=mask)
    res, warned = _run(q, y, torch.float32, mask=mask)
    assert res.numerics.execution == ref.numerics.execution == runner
    assert not warned64 and not warned
    lo, hi = _var_ratio(ref, res)
    assert 0.99 < lo and hi < 1.01, (lo, hi)
    assert _nees_vs(ref, res) < 1e-3


@pytest.mark.parametrize("sqrt", [False, True])
def test_float32_means_beyond_resolution_warn(sqrt: bool) -> None:
    """Simulated data: the position grows to 4e8 while its standard deviation stays below 1, so
    float32 rounds the means by far more than their uncertainty (the square-root form as much
    as the plain one). The float64 reference says the float32 run is wrong, and it warns."""
    q = 1e-2
    _, y = _simulate(q, seed=0)
    ref, warned64 = _run(q, y, torch.float64, sqrt=sqrt)
    assert not warned64
    res, warned = _run(q, y, torch.float32, sqrt=sqrt)
    assert _nees_vs(ref, res) > 10.0  # the float32 run is actually wrong
    assert len(warned) == 1 and issubclass(warned[0].category, DivergenceWarning)
    message = str(warned[0].message)
    assert "float32" in message and "rounded" in message and "float64" in message
    assert "square-root form does not help" in message


def test_riccati_tail_from_an_indefinite_covariance_warns(monkeypatch) -> None:
    """The Riccati runner as it was (no symmetrization in float32; the other runners keep
    theirs): its covariance loses definiteness. Where the loss first shows depends on the
    machine's float32 rounding, and either way the answer is never silently wrong: if it shows
    in an innovation variance, the runner's own factor check re-plans to the next runner (the
    result says so and matches float64); if only the converged tail repeats an indefinite
    covariance, the check of the returned covariances sees it and names the fixes."""
    run_riccati = runners._run_riccati

    def unsymmetrized(*args, **kwargs):
        drifts = runners._drifts
        runners._drifts = lambda dtype: False
        try:
            return run_riccati(*args, **kwargs)
        finally:
            runners._drifts = drifts

    monkeypatch.setattr(runners, "_run_riccati", unsymmetrized)
    q = 1e-4
    y = torch.randn(B, T, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref, _ = _run(q, y, torch.float64)
    res, warned = _run(q, y, torch.float32)
    lo, hi = _var_ratio(ref, res)
    if res.numerics.execution == "kalman-riccati":
        assert torch.linalg.eigvalsh(res.cov.double()).min() < 0  # the run is wrong
        assert lo < 0.5 or hi > 2.0, (lo, hi)
        assert len(warned) == 1
        message = str(warned[0].message)
        assert "lost positive definiteness" in message
        assert "float64" in message and "sqrt=True" in message and "jitter" in message
    else:  # caught by the runner itself: re-planned, and the answer is right
        assert res.numerics.fallback == "kalman-riccati: a covariance failed to factor"
        assert 0.99 < lo and hi < 1.01, (lo, hi)
        assert not warned


def _result(mean: torch.Tensor, cov: torch.Tensor) -> KalmanFilterResult:
    fields = {k: mean.new_empty(0) for k in KalmanFilterResult._fields}
    fields.update(mean=mean, cov=cov, numerics=None)
    return KalmanFilterResult(**fields)


def test_precision_check_counts_indefinite_steps_of_a_shared_tail() -> None:
    """One covariance sequence expanded over the batch (as the Riccati runner returns it), the
    last two of four steps indefinite: half the steps count; a noiseless (exactly singular,
    positive semi-definite) state does not count, nor does its zero variance."""
    good = torch.diag(torch.tensor([1.0, 0.0]))  # the second state is known exactly
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    cov = torch.stack([good, good, bad, bad]).expand(5, 4, 2, 2)
    mean = torch.zeros(5, 4, 2)
    indefinite, resolution = precision_problems(_result(mean, cov))
    assert indefinite == 0.5 and resolution == 0.0
    with pytest.warns(PrecisionWarning, match="definiteness at 50.0% of the steps"):
        warn_precision(_result(mean, cov), sqrt=False, stacklevel=1)
    indefinite, _ = precision_problems(_result(mean[:, :2], cov[:, :2]))
    assert indefinite == 0.0


def test_precision_check_resolution_in_units_of_the_standard_deviation() -> None:
    """``eps |m| / sd``: a mean of 2^20 with unit variance is rounded by 2^20 eps."""
    eps = torch.finfo(torch.float32).eps
    mean = torch.tensor([[[2.0**20, 1.0]]])
    cov = torch.eye(2).expand(1, 1, 2, 2)
    _, resolution = precision_problems(_result(mean, cov))
    assert resolution == pytest.approx(2.0**20 * eps)


def test_the_advice_fits_the_dtype() -> None:
    """A float64 result is not told to run in float64: the indefinite case names the
    square-root form and a jitter floor, the rounded-means case a divergent transition; a
    float32 result is told to run in float64 in both."""
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    for dtype in (torch.float64, torch.float32):
        indefinite = _result(torch.zeros(1, 2, 2, dtype=dtype), bad.to(dtype).expand(1, 2, 2, 2))
        rounded = _result(
            torch.tensor([[[1e30, 1.0]]], dtype=dtype), torch.eye(2, dtype=dtype).expand(1, 1, 2, 2)
        )
        for res, words in ((indefinite, "Use the square-root form"), (rounded, "Re-centre")):
            with pytest.warns(PrecisionWarning) as record:
                warn_precision(res, sqrt=False, stacklevel=1)
            message = str(record[0].message)
            if dtype == torch.float64:
                assert "Run in float64" not in message and words in message, message
            else:
                assert "Run in float64 (the model and the data .double())" in message, message
        if dtype == torch.float64:
            assert "a transition that diverges" in message
