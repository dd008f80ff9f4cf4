"""Data-parallel EM: two processes, each with half of the recordings (of different lengths),
whose expected sufficient statistics (linear M-step), expected complete-data log-likelihood and
gradient (gradient M-step, every L-BFGS evaluation) and filter log-likelihood are summed by
``torch.distributed`` (``gloo``), give the EM of one process on all of them; a resume from
checkpoints one iteration apart (a process lost between the two saves) gives it too."""

from __future__ import annotations

import ddp_support
import torch

import torchfilt

RTOL = 1e-9


def close(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(torch.allclose(a, b, rtol=RTOL, atol=RTOL * float(b.abs().max())))


def test_two_processes_em_like_one(tmp_path):
    world = 2
    init = f"file://{tmp_path / 'rendezvous'}"
    files = [tmp_path / f"em_rank{r}.pt" for r in range(world)]
    ddp_support.spawn(ddp_support.em_worker, (world, init, str(tmp_path)), world, files)
    ranks = [torch.load(tmp_path / f"em_rank{r}.pt", weights_only=True) for r in range(world)]

    y = ddp_support.em_data(ddp_support.EM_LENGTHS)
    lin = torchfilt.fit_em(ddp_support.em_linear(), y, iterations=6, **ddp_support.EM_KW)
    want = ddp_support.linear_values(lin.model)
    want_ll = torch.tensor([h["log_likelihood"] for h in lin.history])
    gp_model = ddp_support.em_gp()
    gp = torchfilt.fit_em(
        gp_model, ddp_support.em_data(ddp_support.GP_LENGTHS, seed=4), iterations=3,
        **ddp_support.GP_KW,
    )  # fmt: skip
    want_gp = torch.cat([p.detach().reshape(-1) for p in gp_model.parameters()])
    want_gp_ll = torch.tensor([h["log_likelihood"] for h in gp.history])
    fast_model = ddp_support.em_gp()
    fast = torchfilt.fit_em(
        fast_model, ddp_support.em_data(ddp_support.GP_LENGTHS, seed=4), iterations=3,
        accelerate=True, **ddp_support.GP_KW,
    )  # fmt: skip
    want_fast = torch.cat([p.detach().reshape(-1) for p in fast_model.parameters()])
    want_fast_ll = torch.tensor([h["log_likelihood"] for h in fast.history])
    for r in ranks:
        assert close(r["linear"], want), (r["linear"], want)
        assert close(r["linear_ll"], want_ll)
        assert r["measurements"] == lin.measurements
        assert close(r["gp"], want_gp), (r["gp"] - want_gp).abs().max()
        assert close(r["gp_ll"], want_gp_ll)
        assert close(r["fast"], want_fast), (r["fast"] - want_fast).abs().max()
        assert close(r["fast_ll"], want_fast_ll)
        assert close(r["resumed"], want), (r["resumed"], want)
        assert close(r["resumed_ll"], want_ll)
    # the fits moved: a reduction that did nothing would not pass
    assert want_ll[-1] > lin.initial_log_likelihood + 10
    assert gp.log_likelihood > gp.initial_log_likelihood + 1
    assert fast.history[-1]["e_steps"] > 2 * 3  # an extrapolation was tried
    assert torch.equal(ranks[0]["linear"], ranks[1]["linear"])
    assert torch.equal(ranks[0]["gp"], ranks[1]["gp"])
