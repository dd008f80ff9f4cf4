"""Throughput of data-parallel fits: one process against Ray actors in one ``gloo`` group.

The same recordings, fitted by one process (1 thread, in this script's process) and by
``calibrate_ray`` / ``fit_measurement_only_ray`` with 1 and 2 Ray actors (1 thread each; the
recordings dealt round-robin, sums over ``gloo``), side by side in one run:

* ``calibrate``: the likelihood fit of ``calibrate`` (pendulum, Q scale and floor of the
  transition, Adam: one evaluation of the windowed filter likelihood and its gradient per
  iteration, one collective);
* ``em linear``: ``fit_measurement_only(method="em")`` of a 2-state linear-Gaussian model
  (CKF + RTS E-step, closed-form M-step: two collectives per iteration, one of them the
  sufficient statistics);
* ``em gp``: the same EM with a GP transition (``InducingTransition``): the gradient M-step, one
  collective per L-BFGS evaluation.

Seconds per iteration come from the fit's own history (``elapsed`` of rank 0 between the first
and the last iteration), so the actors' start-up (process start, imports, the rendezvous, the
first E-step) is not in it; the whole call's wall time (``wall_s``) is reported too.
``rec_steps_per_s`` is recordings x steps / (seconds per iteration). The load average is printed
before each row: on a machine shared with other jobs the numbers move with it.

    python scripts/bench_dataparallel.py --out scripts/results/cpu-2026-12-02-dataparallel
    python scripts/bench_dataparallel.py --recordings 8 --steps 50 --iterations 3   # quicker
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.models import CholeskyCovariance, InducingTransition, LinearModel
from torchfilt.optim import OptimizerOptions, StoppingOptions, WindowOptions
from torchfilt.pipeline import calibrate_ray, fit_measurement_only_ray
from torchfilt.pipeline.distributed import ray_session
from torchfilt.systems import pendulum

DT = torch.float64
A = torch.tensor([[0.8, 0.4], [-0.4, 0.6]], dtype=DT)
H = torch.tensor([[1.0, 0.0]], dtype=DT)
A_INIT = torch.tensor([[0.5, 0.2], [-0.1, 0.4]], dtype=DT)


def linear_data(recordings: int, steps: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    LQ = torch.linalg.cholesky(torch.tensor([[0.2, 0.05], [0.05, 0.3]], dtype=DT))
    x, ys = torch.zeros(recordings, 2, dtype=DT), []
    for _ in range(steps):
        x = x @ A.mT + torch.randn(recordings, 2, generator=g, dtype=DT) @ LQ.mT
        ys.append(x @ H.mT + 0.2 * torch.randn(recordings, 1, generator=g, dtype=DT))
    return torch.stack(ys, 1)


def linear_model() -> torchfilt.LinearGaussianModel:
    return torchfilt.LinearGaussianModel(
        A_INIT, H, 0.3 * torch.eye(2, dtype=DT), torch.eye(1, dtype=DT)
    )


def gp_model() -> torchfilt.StateSpaceModel:
    f = InducingTransition(2, 8, linear=A_INIT, outputscale=0.01)
    f.init_inducing(torch.randn(64, 2, generator=torch.Generator().manual_seed(2), dtype=DT))
    h = LinearModel(H, CholeskyCovariance(torch.eye(1, dtype=DT)), name="measurement")
    return torchfilt.StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))


def per_iteration(history: list[dict[str, Any]]) -> float:
    """Seconds per iteration between the first and the last iteration of a fit's history."""
    if len(history) < 2:
        return float(history[-1]["elapsed"]) if history else float("nan")
    return (float(history[-1]["elapsed"]) - float(history[0]["elapsed"])) / (len(history) - 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recordings", type=int, default=64)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--iterations", type=int, default=12, help="iterations of each fit")
    ap.add_argument("--gp-iterations", type=int, default=3, help="EM iterations of the GP fit")
    ap.add_argument("--out", type=Path, default=Path("out/bench_dataparallel"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    R, T, its = args.recordings, args.steps, args.iterations
    x0p = torch.tensor([1.0, 0.0], dtype=DT)
    sim = torchfilt.simulate(
        pendulum.model(qc=30.0, R=0.001), T, x0p, batch_shape=(R,),
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    cal_y = sim.measurements
    cal_kw: dict[str, Any] = dict(
        x0=x0p, P0=0.1 * torch.eye(2, dtype=DT), sides=("transition",),
        windows=WindowOptions(window=100, burn_in=20), iterations=its,
        optimizer=OptimizerOptions(lr=0.2),
    )  # fmt: skip
    y = linear_data(R, T)
    y_gp = y[:, : max(T // 2, 2)]
    em_kw: dict[str, Any] = dict(
        x0=torch.zeros(2, dtype=DT), P0=torch.eye(2, dtype=DT), known_channels=[0], method="em",
        stopping=StoppingOptions(tol=0.0),
        # the fit itself is timed: no held-out split (one process and the actors would split
        # differently; see fit_measurement_only_ray)
        noise_scale="none",
    )  # fmt: skip

    def local(kind: str) -> tuple[Any, list[dict[str, Any]], float]:
        if kind == "calibrate":
            res: Any = torchfilt.calibrate(pendulum.model(R=0.001), cal_y, **cal_kw)
            return res, res.fit.history, res.fit.log_likelihood
        if kind == "em linear":
            res = torchfilt.fit_measurement_only(linear_model(), y, iterations=its, **em_kw)
        else:
            res = torchfilt.fit_measurement_only(
                gp_model(), y_gp, iterations=args.gp_iterations, m_step_iterations=5, **em_kw
            )
        return res, res.history, res.log_likelihood

    def on_ray(kind: str, workers: int) -> tuple[Any, list[dict[str, Any]], float]:
        if kind == "calibrate":
            res: Any = calibrate_ray(pendulum.model(R=0.001), cal_y, workers=workers, **cal_kw)
            return res, res.fit.history, res.fit.log_likelihood
        if kind == "em linear":
            res = fit_measurement_only_ray(
                linear_model(), y, workers=workers, iterations=its, **em_kw
            )
        else:
            res = fit_measurement_only_ray(
                gp_model(), y_gp, workers=workers, iterations=args.gp_iterations,
                m_step_iterations=5, **em_kw,
            )  # fmt: skip
        return res, res.history, res.log_likelihood

    rows: list[dict[str, Any]] = []
    with ray_session(workers=2):
        for kind in ("calibrate", "em linear", "em gp"):
            steps = R * (y_gp.shape[1] if kind == "em gp" else T)
            ref_ll = None
            for path, workers in (("local", 1), ("ray", 1), ("ray", 2)):
                load = os.getloadavg()[0]
                t0 = time.perf_counter()
                _, hist, ll = local(kind) if path == "local" else on_ray(kind, workers)
                wall = time.perf_counter() - t0
                s_it = per_iteration(hist)
                ref_ll = ll if ref_ll is None else ref_ll
                row = {
                    "fit": kind,
                    "path": "1 process" if path == "local" else f"Ray, {workers} actor(s)",
                    "workers": workers,
                    "iterations": len(hist),
                    "s_per_iteration": s_it,
                    "rec_steps_per_s": steps / s_it,
                    "wall_s": wall,
                    "load_average_1min": load,
                    "log_likelihood": ll,
                    "rel_diff_to_1_process": abs(ll - ref_ll) / abs(ref_ll),
                }
                rows.append(row)
                print(
                    f"{kind:9s} {row['path']:16s} {s_it:.3f} s/it, wall {wall:.1f} s, "
                    f"load {load:.2f}",
                    file=sys.stderr,
                )
    for r in rows:
        base = next(b for b in rows if b["fit"] == r["fit"] and b["path"] == "1 process")
        r["speedup"] = base["s_per_iteration"] / r["s_per_iteration"]
    payload = {
        "benchmark": "data-parallel fits: 1 process vs Ray actors (gloo)",
        "recordings": R,
        "steps": T,
        "gp_steps": int(y_gp.shape[1]),
        "iterations": its,
        "gp_iterations": args.gp_iterations,
        "dtype": "float64",
        "environment": environment(),
        "load_average_end": os.getloadavg(),
        "rows": rows,
        "note": "s_per_iteration from rank 0's history (start-up excluded); wall_s: the whole call",
    }
    write_json(args.out / "bench_dataparallel.json", payload)
    print(f"{R} recordings x {T} steps (GP EM: {y_gp.shape[1]} steps), float64, 1 thread/process")
    headers = ["fit", "path", "s/iter", "rec*steps/s", "speed-up", "wall s", "load 1 min"]
    print(
        table(
            headers,
            [
                [
                    r["fit"],
                    r["path"],
                    r["s_per_iteration"],
                    r["rec_steps_per_s"],
                    r["speedup"],
                    r["wall_s"],
                    r["load_average_1min"],
                ]
                for r in rows
            ],
        )
    )
    print(f"load average at the end: {payload['load_average_end']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
