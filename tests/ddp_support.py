"""A data-parallel likelihood fit in spawned processes (``torch.distributed`` with ``gloo``), for
``tests/training/test_likelihood_ddp.py``."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import torchfilt
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import (
    CheckpointOptions,
    FitHooks,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
)

DT = torch.float64
RECORDINGS = 6
#: fit options shared by the single-process and the data-parallel fit
OPTIONS = dict(
    windows=WindowOptions(window=20, burn_in=5, refresh_every=5),
    iterations=15,
    optimizer=OptimizerOptions(lr=0.1),
)
#: the same through fit_measurement_only (L-BFGS: several collectives per iteration)
# noise_scale "none": with "auto" one process holds out whole recordings of its 6, and each of
# two processes the tails of its 3 (each splits its own), so the fits would differ
MO_OPTIONS = dict(windows=WindowOptions(window=20, burn_in=5), iterations=4, noise_scale="none")


def spawn(worker: Callable[..., None], args: tuple, world: int, results: list[Path]) -> None:
    """``mp.spawn(worker, args, nprocs=world)``; a process killed by a signal once every process
    has saved its results is let pass.

    Each worker saves its results atomically before its last barrier, then tears ``gloo`` down.
    One CI run lost rank 1 to ``SIGABRT`` ("terminate called without an active exception",
    from a C++ thread destroyed in that teardown, not reproduced in 27 stressed runs since);
    its results, and its peer's, were complete. What the tests check is in those files, so a
    crash after they exist is not a failure of the code under test; one before is raised.
    """
    try:
        mp.spawn(worker, args=args, nprocs=world, join=True)
    except mp.ProcessExitedException as e:
        if e.signal_name is None or not all(p.exists() for p in results):
            raise


def save(result: dict[str, object], path: Path) -> None:
    """``torch.save`` through a temporary file and a rename: a reader sees all or nothing."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(result, tmp)
    os.replace(tmp, path)


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
            x0=torch.zeros(1, dtype=DT),
            P0=torch.eye(1, dtype=DT),
            hooks=FitHooks(all_reduce=dist.all_reduce),
        )
        if measurement_only:
            fit = torchfilt.fit_measurement_only(
                model, y[rank::world], known_channels=[0], method="likelihood", **MO_OPTIONS, **kw
            ).detail
        else:
            fit = torchfilt.fit_likelihood(model, y[rank::world], **OPTIONS, **kw)
        with torch.no_grad():
            values = torch.stack([Q().reshape(()), R().reshape(())])
        result: dict[str, object] = {}
        if not measurement_only:
            result["resumed"] = _resume_apart(rank, world, y, Path(out), kw)
        result |= {
            "values": values,
            "loss": torch.tensor([h["loss"] for h in fit.history]),
            "log_likelihood": fit.log_likelihood,
            "measurements": fit.measurements,
        }
        save(result, Path(out) / f"rank{rank}.pt")
        dist.barrier()  # no process tears gloo down while its peer is still in a collective
    finally:
        dist.destroy_process_group()


def _resume_apart(rank: int, world: int, y: torch.Tensor, out: Path, kw: dict) -> torch.Tensor:
    """The likelihood fit resumed from checkpoints one checkpoint apart (rank 0 at iteration 10,
    rank 1 at 5, as after rank 1 was lost between the two saves): its final Q and R."""
    import shutil

    a, b = out / "lik_a", out / "lik_b"
    a.mkdir(exist_ok=True)
    b.mkdir(exist_ok=True)
    opts = dict(OPTIONS)

    def fit(iterations: int, path: Path) -> torch.Tensor:
        model, _, (Q, R) = problem()
        opts["iterations"] = iterations
        torchfilt.fit_likelihood(
            model,
            y[rank::world],
            **opts,
            **kw,
            checkpoint=CheckpointOptions(path, every=5, resume=True),
        )
        with torch.no_grad():
            return torch.stack([Q().reshape(()), R().reshape(())])

    fit(5, a / f"rank{rank}.pt")
    if rank == 1:
        shutil.copy(a / "rank1.pt", b / "rank1.pt")
    fit(10, a / f"rank{rank}.pt")
    if rank == 0:
        shutil.copy(a / "rank0.pt", b / "rank0.pt")
    dist.barrier()
    return fit(int(OPTIONS["iterations"]), b / f"rank{rank}.pt")


# ----------------------------------------------------------------------------------- EM
A_EM = torch.tensor([[0.8, 0.4], [-0.4, 0.6]], dtype=DT)
H_EM = torch.tensor([[1.0, 0.0]], dtype=DT)
A_EM_INIT = torch.tensor([[0.5, 0.2], [-0.1, 0.4]], dtype=DT)
#: recordings of different lengths: a shard pads to its own longest, the whole set to 60
EM_LENGTHS = (60, 45, 60, 50)
GP_LENGTHS = (40, 30, 40, 35)
EM_KW = dict(
    x0=torch.zeros(2, dtype=DT),
    P0=torch.eye(2, dtype=DT),
    known_channels=[0],
    stopping=StoppingOptions(tol=0.0),
)
GP_KW = dict(EM_KW, m_step_iterations=3)


def em_data(lengths: tuple[int, ...], seed: int = 3) -> list[torch.Tensor]:
    """Measurements of a 2-state linear system with a known H = [1, 0], one per length."""
    g = torch.Generator().manual_seed(seed)
    LQ = torch.linalg.cholesky(torch.tensor([[0.2, 0.05], [0.05, 0.3]], dtype=DT))
    out = []
    for T in lengths:
        x, ys = torch.zeros(2, dtype=DT), []
        for _ in range(T):
            x = A_EM @ x + LQ @ torch.randn(2, generator=g, dtype=DT)
            ys.append(H_EM @ x + 0.2 * torch.randn(1, generator=g, dtype=DT))
        out.append(torch.stack(ys))
    return out


def em_linear() -> torchfilt.LinearGaussianModel:
    return torchfilt.LinearGaussianModel(
        A_EM_INIT, H_EM, 0.3 * torch.eye(2, dtype=DT), torch.eye(1, dtype=DT)
    )


def em_gp() -> torchfilt.StateSpaceModel:
    """A GP transition (4 inducing points) around the initial linear map, learnable Q and R."""
    from torchfilt.models import CholeskyCovariance, InducingTransition, LinearModel

    f = InducingTransition(2, 4, linear=A_EM_INIT, outputscale=0.01)
    f.init_inducing(torch.randn(40, 2, generator=torch.Generator().manual_seed(2), dtype=DT))
    h = LinearModel(H_EM, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return torchfilt.StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))


def linear_values(m: torchfilt.StateSpaceModel) -> torch.Tensor:
    """A, Q, R of a fitted linear model, flattened."""
    sys = torchfilt.models.linear_system(m)
    assert sys is not None
    return torch.cat(
        [
            sys.A.reshape(-1),
            m.transition.noise_cov().reshape(-1),
            m.measurement.noise_cov().reshape(-1),
        ]
    ).detach()


def em_worker(rank: int, world: int, init: str, out: str) -> None:
    """Data-parallel EM on the recordings ``rank::world``: the linear EM (6 iterations), a GP EM
    (3 iterations, plain and ``accelerate=True``), and the linear EM resumed from checkpoints
    one iteration apart (rank 0 at 3, rank 1 at 2, as after a process lost between the two
    saves)."""
    import shutil

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        red = dict(hooks=FitHooks(all_reduce=dist.all_reduce))
        y = em_data(EM_LENGTHS)[rank::world]
        lin = torchfilt.fit_em(em_linear(), y, iterations=6, **EM_KW, **red)
        gp_model = em_gp()
        gp = torchfilt.fit_em(
            gp_model, em_data(GP_LENGTHS, seed=4)[rank::world], iterations=3, **GP_KW, **red
        )
        # SQUAREM over the gradient M-step: every extrapolation decision on the summed values
        fast_model = em_gp()
        fast = torchfilt.fit_em(
            fast_model, em_data(GP_LENGTHS, seed=4)[rank::world], iterations=3,
            accelerate=True, **GP_KW, **red,
        )  # fmt: skip
        # checkpoints one iteration apart: rank 1's from a fit of 2 iterations, rank 0's from one
        # of 3 (whose last checkpoint keeps the one of iteration 2 it made itself)
        a, b, c = Path(out) / "a", Path(out) / "b", Path(out) / "c"
        for d in (a, b, c):
            d.mkdir(exist_ok=True)
        torchfilt.fit_em(
            em_linear(), y, iterations=2, checkpoint=a / f"rank{rank}.pt", **EM_KW, **red
        )
        torchfilt.fit_em(
            em_linear(), y, iterations=3, checkpoint=c / f"rank{rank}.pt", **EM_KW, **red
        )
        if rank == 1:
            shutil.copy(a / "rank1.pt", b / "rank1.pt")  # rank 1 "lost" after iteration 2
        else:
            shutil.copy(c / "rank0.pt", b / "rank0.pt")  # rank 0 saved iteration 3
        dist.barrier()
        resumed = torchfilt.fit_em(
            em_linear(),
            y,
            iterations=6,
            **EM_KW,
            **red,
            checkpoint=CheckpointOptions(b / f"rank{rank}.pt", resume=True),
        )
        result = {
            "linear": linear_values(lin.model),
            "linear_ll": torch.tensor([h["log_likelihood"] for h in lin.history]),
            "measurements": lin.measurements,
            "gp": torch.cat([p.detach().reshape(-1) for p in gp_model.parameters()]),
            "gp_ll": torch.tensor([h["log_likelihood"] for h in gp.history]),
            "fast": torch.cat([p.detach().reshape(-1) for p in fast_model.parameters()]),
            "fast_ll": torch.tensor([h["log_likelihood"] for h in fast.history]),
            "resumed": linear_values(resumed.model),
            "resumed_ll": torch.tensor([h["log_likelihood"] for h in resumed.history]),
        }
        save(result, Path(out) / f"em_rank{rank}.pt")
        dist.barrier()  # no process tears gloo down while its peer is still in a collective
    finally:
        dist.destroy_process_group()


def abort_worker(rank: int, out: str, save_first: bool) -> None:
    """Rank 1 dies of ``SIGABRT``, after saving its result (``save_first``) or before; rank 0
    saves its result and waits for the signal: :func:`spawn`'s two cases."""
    import time

    if rank == 0 or save_first:
        save({"rank": rank}, Path(out) / f"abort{rank}.pt")
    if rank == 1:
        if save_first:
            while not (Path(out) / "abort0.pt").exists():
                time.sleep(0.01)
        os.abort()
    time.sleep(60)  # terminated by mp.spawn once rank 1 is gone
