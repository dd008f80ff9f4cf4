"""The CKF's in-place result buffers (``RecordSink``): the same numbers, bit for bit, as stacking
the per-step records, with and without autograd, and ``outputs=`` on the sigma-point path."""

from __future__ import annotations

import math

import torch

import torchfilt
from torchfilt.filters.results import FilterResult, RecordSink, stack_records

DT = torch.float64


def _problem(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    model = torchfilt.StateSpaceModel(
        lambda x, u: torch.stack([x[..., 0] + 0.1 * torch.sin(x[..., 1]), 0.9 * x[..., 1]], -1),
        lambda x, u: x[..., :1] ** 2 + x[..., 1:],
        Q=0.01 * torch.eye(2, dtype=DT),
        R=0.1 * torch.eye(1, dtype=DT),
    )
    y = torch.randn(5, 12, 1, generator=g, dtype=DT)
    y[1, 3] = math.nan  # a missing measurement
    return model, y, torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit-equal, NaN where the other is NaN (innovations of missing components)."""
    if a.dtype == torch.bool:
        return torch.equal(a, b)
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())


def test_buffered_result_equals_stacked_records_bit_for_bit():
    model, y, x0, P0 = _problem()
    filt = torchfilt.CKF(model)
    with torch.no_grad():
        inputs = filt._prepare(y, x0=x0, P0=P0)
        _, records, _ = filt._scan(inputs)
        want = stack_records(records, inputs.obs.expand(*inputs.batch, *inputs.obs.shape[-2:]))
        got = filt.filter(y, x0=x0, P0=P0)
    for name in FilterResult._fields[:-1]:
        assert _same(getattr(got, name), getattr(want, name)), name
        assert not getattr(got, name).requires_grad


def test_autograd_runs_keep_the_graph_and_the_numbers():
    model, y, x0, P0 = _problem()
    x0 = x0.clone().requires_grad_(True)
    res = torchfilt.CKF(model).filter(y, x0=x0, P0=P0)
    with torch.no_grad():
        ref = torchfilt.CKF(model).filter(y, x0=x0, P0=P0)
    for name in FilterResult._fields[:-1]:
        assert _same(getattr(res, name).detach(), getattr(ref, name)), name
    (g,) = torch.autograd.grad(res.log_likelihood.sum(), x0)
    assert bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0


def test_outputs_on_the_sigma_point_path():
    model, y, x0, P0 = _problem()
    filt = torchfilt.CKF(model)
    with torch.no_grad():
        full = filt.filter(y, x0=x0, P0=P0)
        part = filt.filter(y, x0=x0, P0=P0, outputs=("mean", "log_likelihood"))
    assert torch.equal(part.mean, full.mean)
    assert torch.equal(part.log_likelihood, full.log_likelihood)
    assert part.cov.numel() == 0 and part.cross_cov.numel() == 0 and part.observed.numel() == 0


def test_sink_refuses_an_incomplete_run():
    sink = RecordSink(3)
    try:
        sink.result(torch.zeros(1, 3, 1, dtype=torch.bool))
    except RuntimeError as e:
        assert "0 of 3" in str(e)
    else:  # pragma: no cover
        raise AssertionError("an incomplete sink returned a result")
