"""A data-parallel likelihood fit in spawned processes (``torch.distributed`` with ``gloo``), for
``tests/test_likelihood_ddp.py``."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.distributed as dist

import torchfilt
from torchfilt.models.params import ScalarCovariance

DT = torch.float64
RECORDINGS = 6
#: fit options shared by the single-process and the data-parallel fit
OPTIONS = dict(window=20, burn_in=5, iterations=15, refresh_every=5, lr=0.1)
#: the same through fit_measurement_only (L-BFGS: several collectives per iteration)
MO_OPTIONS = dict(window=20, burn_in=5, iterations=4)


def problem() -> tuple[torchfilt.StateSpaceModel, torch.Tensor, tuple[ScalarCovariance, ...]]:
    """A scalar linear system with unknown Q and R, ``RECORDINGS`` recordings of 60 steps."""
    g = torch.Generator().manual_seed(0)
    A = torch.tensor([[0.9]], dtype=DT)
    x = torch.zeros(RECORDINGS, 1, dtype=DT)
    ys = []
    for _ in range(60):
        x = x @ A.mT + 0.5 * torch.randn(RECORDINGS, 1, generator=g, dtype=DT)
        ys.append(x + 0.3 * torch.randn(RECORDINGS, 1, generator=g, dtype=DT))
    Q, R = ScalarCovariance(1.0, 1, dtype=DT), ScalarCovariance(1.0, 1, dtype=DT)
    model = torchfilt.StateSpaceModel(lambda x, u: x @ A.mT, lambda x, u: x, Q=Q, R=R)
    return model, torch.stack(ys, 1), (Q, R)


def worker(rank: int, world: int, init: str, out: str, measurement_only: bool = False) -> None:
    """Fit on the recordings ``rank::world`` with summed gradients; each rank writes its result.
    ``measurement_only``: through ``fit_measurement_only(method="likelihood")`` (gauge: the
    measurement map is known)."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        model, y, (Q, R) = problem()
        kw = dict(
            x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), all_reduce=dist.all_reduce
        )
        if measurement_only:
            fit = torchfilt.fit_measurement_only(
                model, y[rank::world], known_channels=[0], method="likelihood", **MO_OPTIONS, **kw
            ).detail
        else:
            fit = torchfilt.fit_likelihood(model, y[rank::world], **OPTIONS, **kw)
        with torch.no_grad():
            values = torch.stack([Q().reshape(()), R().reshape(())])
        result = {
            "values": values,
            "loss": torch.tensor([h["loss"] for h in fit.history]),
            "log_likelihood": fit.log_likelihood,
            "measurements": fit.measurements,
        }
        torch.save(result, Path(out) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()
