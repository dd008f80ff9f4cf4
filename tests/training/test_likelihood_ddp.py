"""Data-parallel likelihood fitting: two processes, each with half of the recordings, whose
log-likelihoods and gradients are summed by ``torch.distributed`` (``gloo``), take the same steps
as one process with all of them."""

from __future__ import annotations

import ddp_support
import pytest
import torch
import torch.multiprocessing as mp

import torchfilt


def test_two_processes_fit_like_one(tmp_path):
    world = 2
    init = f"file://{tmp_path / 'rendezvous'}"
    files = [tmp_path / f"rank{r}.pt" for r in range(world)]
    ddp_support.spawn(ddp_support.worker, (world, init, str(tmp_path)), world, files)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(world)]

    model, y, (Q, R) = ddp_support.problem()
    fit = torchfilt.fit_likelihood(
        model,
        y,
        x0=torch.zeros(1, dtype=torch.float64),
        P0=torch.eye(1, dtype=torch.float64),
        **ddp_support.OPTIONS,
    )
    with torch.no_grad():
        want = torch.stack([Q().reshape(()), R().reshape(())])
    losses = torch.tensor([h["loss"] for h in fit.history])
    for r in ranks:
        # every process ends with the parameters of the single fit (sums in another order)
        assert torch.allclose(r["values"], want, rtol=1e-9, atol=0), (r["values"], want)
        assert torch.allclose(r["loss"], losses, rtol=1e-10, atol=0)
        assert abs(r["log_likelihood"] - fit.log_likelihood) <= 1e-9 * abs(fit.log_likelihood)
        assert r["measurements"] == fit.measurements
        # resumed from checkpoints one checkpoint apart: the same fit
        assert torch.allclose(r["resumed"], want, rtol=1e-9, atol=0), (r["resumed"], want)
    # the fit moved: the test would notice a reduction that did nothing
    assert not torch.allclose(want, torch.ones(2, dtype=torch.float64), rtol=1e-2)
    assert torch.equal(ranks[0]["values"], ranks[1]["values"])


def test_measurement_only_likelihood_fit_in_two_processes(tmp_path):
    """``fit_measurement_only(method="likelihood", all_reduce=...)``: L-BFGS, whose line search
    evaluates several times per iteration, stays in step across the processes."""
    world = 2
    init = f"file://{tmp_path / 'rendezvous'}"
    files = [tmp_path / f"rank{r}.pt" for r in range(world)]
    ddp_support.spawn(ddp_support.worker, (world, init, str(tmp_path), True), world, files)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(world)]
    model, y, (Q, R) = ddp_support.problem()
    kw = dict(x0=torch.zeros(1, dtype=torch.float64), P0=torch.eye(1, dtype=torch.float64))
    torchfilt.fit_measurement_only(
        model, y, known_channels=[0], method="likelihood", **ddp_support.MO_OPTIONS, **kw
    )
    with torch.no_grad():
        want = torch.stack([Q().reshape(()), R().reshape(())])
    for r in ranks:
        assert torch.allclose(r["values"], want, rtol=1e-8, atol=0), (r["values"], want)
    assert not torch.allclose(want, torch.ones(2, dtype=torch.float64), rtol=1e-2)


def test_spawn_lets_pass_only_a_crash_after_every_result_is_saved(tmp_path):
    """The tests' ``spawn`` forgives a process killed after every process saved its results
    (gloo's teardown), and raises for one killed before."""
    files = [tmp_path / f"abort{r}.pt" for r in range(2)]
    ddp_support.spawn(ddp_support.abort_worker, (str(tmp_path), True), 2, files)
    assert [torch.load(f, weights_only=True)["rank"] for f in files] == [0, 1]
    other = tmp_path / "before"
    other.mkdir()
    files = [other / f"abort{r}.pt" for r in range(2)]
    with pytest.raises(mp.ProcessExitedException, match="SIGABRT"):
        ddp_support.spawn(ddp_support.abort_worker, (str(other), False), 2, files)
