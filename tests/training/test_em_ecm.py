"""ECM in the gradient M-step of :func:`~torchfilt.training.fit_em`: a maps block that found
nothing is left out of the next M-steps (1, then 2, 4, 8, ... at most ``MAPS_PAUSE_MAX``) and
tried again; a maps block that carries the gain is never left out; a resumed fit takes the same
pauses as an uninterrupted one (float64, seeded)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

import torchfilt.training.em_steps as em_steps
from torchfilt.models import (
    CholeskyCovariance,
    FunctionModel,
    InducingTransition,
    LinearModel,
    StateSpaceModel,
)
from torchfilt.optim import CheckpointOptions, StoppingOptions
from torchfilt.training import fit_em

DT = torch.float64
A = torch.tensor([[0.8, 0.4], [-0.4, 0.6]], dtype=DT)
H = torch.tensor([[1.0, 0.0]], dtype=DT)
X0, P0 = torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)
KW = dict(x0=X0, P0=P0, known_channels=[0], stopping=StoppingOptions(tol=0.0, rtol=0.0))


def _data(T: int = 120, seed: int = 4) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x, ys = torch.zeros(2, dtype=DT), []
    for _ in range(T):
        x = A @ x + 0.4 * torch.randn(2, generator=g, dtype=DT)
        ys.append(H @ x + 0.2 * torch.randn(1, generator=g, dtype=DT))
    return torch.stack(ys)


class _Idle(nn.Module):
    """The true linear map, with a parameter that changes nothing: its block finds nothing."""

    def __init__(self) -> None:
        super().__init__()
        self.theta = nn.Parameter(torch.zeros(3, dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x @ A.T + 0.0 * self.theta.sum()


def _idle_model() -> StateSpaceModel:
    f = FunctionModel(_Idle(), CholeskyCovariance(0.02 * torch.eye(2, dtype=DT)), name="transition")
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return StateSpaceModel(f, h)


def _gp_model() -> StateSpaceModel:
    f = InducingTransition(2, 6, linear=0.6 * A, outputscale=0.01, lengthscale=1.0)
    f.init_inducing(torch.randn(50, 2, generator=torch.Generator().manual_seed(1), dtype=DT))
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))


@pytest.fixture
def skips(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """Whether each joint step left the maps out, in order."""
    seen: list[bool] = []
    real = em_steps._gradient_m_step

    def spy(*args, **kwargs):
        if kwargs["blocks"] is em_steps._M_STEP_BLOCKS[0]:
            seen.append(bool(kwargs["skip_maps"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(em_steps, "_gradient_m_step", spy)
    return seen


def _schedule(steps: int) -> list[bool]:
    """The pauses of a maps block that never finds anything, from the rule's statement."""
    out: list[bool] = []
    pause = 1
    while len(out) < steps:
        out.append(False)  # tried, found nothing: left out of the next `pause` joint steps
        out.extend([True] * pause)
        pause = min(2 * pause, em_steps.MAPS_PAUSE_MAX)
    return out[:steps]


def test_an_idle_maps_block_is_paused_and_tried_again(skips, monkeypatch):
    y = _data()
    paused = fit_em(_idle_model(), y, iterations=14, **KW)
    assert paused.stopped == "iterations"
    assert skips == _schedule(14)
    assert skips.count(False) == 4  # M-steps 1, 3, 6 and 11 ran the maps block
    # leaving out a block that finds nothing changes nothing else: the same climb as never pausing
    skips.clear()
    monkeypatch.setattr(em_steps, "MAPS_IDLE_SHARE", -math.inf)
    every = fit_em(_idle_model(), y, iterations=14, **KW)
    assert not any(skips)
    ours = [h["log_likelihood"] for h in paused.history]
    theirs = [h["log_likelihood"] for h in every.history]
    assert ours == pytest.approx(theirs, rel=1e-10, abs=1e-9)
    assert ours[-1] > paused.initial_log_likelihood + 1.0  # the noise steps did climb


def test_a_maps_block_that_carries_the_gain_is_never_paused(skips):
    fit = fit_em(_gp_model(), _data(), iterations=8, **KW)
    assert len(skips) == 8 and not any(skips)
    assert fit.log_likelihood > fit.initial_log_likelihood


def test_resumed_fit_takes_the_same_pauses(skips, tmp_path):
    y = _data()
    full = fit_em(_idle_model(), y, iterations=7, **KW)
    want = list(skips)
    assert want == _schedule(7)
    ck = tmp_path / "ecm.pt"
    skips.clear()
    fit_em(_idle_model(), y, iterations=4, checkpoint=ck, **KW)
    saved = torch.load(ck, weights_only=False)
    # M-steps 1 and 3 found nothing (pauses of 1, then 2); M-step 4 was the pause's first
    assert saved["ecm"] == [1, 4]
    skips.clear()
    resumed = fit_em(
        _idle_model(), y, iterations=7, checkpoint=CheckpointOptions(ck, resume=True), **KW
    )
    assert skips == want[4:]  # M-step 5 is still inside the pause begun at M-step 3
    assert [h["log_likelihood"] for h in resumed.history] == [
        h["log_likelihood"] for h in full.history
    ]
