"""Why measurement-only EM creeps on a nearly noise-free log: a diagnosis of one real log.

Issue #27 asks that measurement-only fits converge within their stage's default budget on real
logs; on the robot arm of :mod:`bench_real_logs` the GP's EM ends at its 30-iteration budget
still gaining. This script builds that GP start exactly as the bench does (the library's N4SID,
``fit_em``, the L-BFGS finish where it raised EM's likelihood, then
:meth:`~torchfilt.models.InducingTransition.model_from_linear` on the smoothed training states)
and runs three fits of it with :func:`~torchfilt.training.fit_measurement_only` (EM, defaults
otherwise):

* ``plain``: ``--iterations`` EM iterations (default 100): the log-likelihood after each, and
  how far each parameter group moved (largest absolute change);
* ``R at the boundary``: the same start with the measurement noise's standard deviation set to
  ``--boundary-sd`` (default 1e-9; the maximum-likelihood ``R`` heads for zero), then
  ``--short`` iterations (default 30). Its filters factor nearly singular covariances, so the
  library's :class:`~torchfilt.exceptions.CholeskyJitterWarning` is counted, not shown;
* ``noise floored``: the same start with every noise standard deviation (the Cholesky
  diagonals of ``Q`` and ``R``) raised to at least ``--floor-sd`` (default 1e-3), then
  ``--short`` iterations: the opposite cure, noise the fit can shed.

Each row reports the start's and the end's log-likelihood (the training part that EM fits,
``noise_scale="auto"`` holding out its last fifth), why the fit stopped, the seconds, the gain of
the last iteration, the noise standard deviations at the end, and the free-run RMSE and 95%
coverage of the standardised held-out output (as in the bench).

    python scripts/em_low_noise.py --data DIR --out OUT           # the robot arm
    python scripts/em_low_noise.py --data DIR --log exchanger --out OUT
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from _common import environment, table, write_json
from bench_real_logs import (
    LOGS,
    gp_from_linear,
    lbfgs_row,
    read_log,
    standardised,
    torchfilt_row,
)

from torchfilt.exceptions import CholeskyJitterWarning
from torchfilt.models import LinearGaussianModel, subspace_identify
from torchfilt.training import fit_em, fit_measurement_only

#: held-out samples filtered before the free run (as in the bench)
BURN = 20


def gp_start(log: str, data: Path, order: int, block_rows: int, inducing: int) -> dict[str, Any]:
    """The bench's GP start on ``log``: the model and what its fits and free runs need."""
    spec = LOGS[log]
    u_tr, y_tr, u_te, y_te = standardised(*read_log(data / spec["file"], spec["columns"]))
    sub = subspace_identify(y_tr, u_tr, order=order, block_rows=block_rows)
    P0 = sub.P0.reshape(-1, order, order)[0]
    em = fit_em(sub.model, y_tr, u_tr, x0=sub.x0, P0=sub.P0, known_channels=[0])
    assert isinstance(em.model, LinearGaussianModel)
    lbfgs, lin = lbfgs_row(em.model, (y_tr, u_tr, y_te, u_te), sub, P0, BURN)
    start = lin if lin is not None and lbfgs["log_likelihood"] > em.log_likelihood else em.model
    assert start is not None
    return {
        "gp": gp_from_linear(start, sub, y_tr, u_tr, inducing),
        "fit": (y_tr, u_tr, sub.x0, sub.P0),
        "test": (y_te, u_te, P0),
        "linear": {
            "em_log_likelihood": em.log_likelihood,
            "lbfgs_log_likelihood": lbfgs["log_likelihood"],
            "start": "EM" if start is em.model else "EM + L-BFGS",
        },
    }


def noise_sds(model: Any) -> dict[str, list[float]]:
    """The Cholesky diagonals (standard deviations) of ``Q`` and ``R``."""
    out = {}
    for side in ("transition", "measurement"):
        raw = getattr(model, side).noise_param.raw_diag
        out[side] = raw.detach().exp().reshape(-1).tolist()
    return out


def run_fit(start: dict[str, Any], iterations: int, prepare: Any = None) -> dict[str, Any]:
    """A deep copy of the start, changed by ``prepare``, fitted for ``iterations``: the row."""
    model = copy.deepcopy(start["gp"])
    if prepare is not None:
        with torch.no_grad():
            prepare(model)
    y, u, x0, P0 = start["fit"]
    before = {k: p.detach().clone() for k, p in model.named_parameters()}
    trace: list[float] = []
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CholeskyJitterWarning)
        fit = fit_measurement_only(
            model, y, u, x0=x0, P0=P0, known_channels=[0], iterations=iterations,
            callback=lambda s: trace.append(s.log_likelihood),
        )  # fmt: skip
        seconds = time.perf_counter() - t0
        y_te, u_te, P0_te = start["test"]
        row = torchfilt_row(fit.model, y_te, u_te, P0_te, BURN)
    jitter = [w for w in caught if issubclass(w.category, CholeskyJitterWarning)]
    for w in caught:  # any other warning is shown as usual
        if w not in jitter:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    moved = {
        k: float((p.detach() - before[k]).abs().max())
        for k, p in model.named_parameters()
        if p.numel()
    }
    lls = [fit.initial_log_likelihood, *trace]
    return {
        **row,
        "initial_log_likelihood": fit.initial_log_likelihood,
        "log_likelihood": fit.log_likelihood,
        "iterations": fit.iterations,
        "stopped": fit.stopped,
        "seconds": seconds,
        "log_likelihood_trace": trace,
        "last_gain": lls[-1] - lls[-2] if len(lls) > 1 else math.nan,
        "moved": moved,
        "noise_sd": noise_sds(model),  # the fitted parameters (fit.model adds the noise scale)
        "jitter_warnings": len(jitter),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="folder with the logs' CSV files")
    ap.add_argument("--out", type=Path, default=Path("out/em_low_noise"))
    ap.add_argument("--log", default="robot-arm", choices=sorted(LOGS))
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--block-rows", type=int, default=20)
    ap.add_argument("--inducing", type=int, default=16)
    ap.add_argument("--iterations", type=int, default=100, help="plain EM iterations")
    ap.add_argument("--short", type=int, default=30, help="iterations of the other two fits")
    ap.add_argument("--boundary-sd", type=float, default=1e-9)
    ap.add_argument("--floor-sd", type=float, default=1e-3)
    args = ap.parse_args(argv)
    if not (args.data / LOGS[args.log]["file"]).is_file():
        ap.error(f"--data {args.data}: missing {LOGS[args.log]['file']}")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    start = gp_start(args.log, args.data, args.order, args.block_rows, args.inducing)
    log_b, log_f = math.log(args.boundary_sd), math.log(args.floor_sd)

    def boundary(m: Any) -> None:
        m.measurement.noise_param.raw_diag.fill_(log_b)

    def floored(m: Any) -> None:
        for side in (m.transition, m.measurement):
            side.noise_param.raw_diag.clamp_(min=log_f)

    rows = {
        "plain": run_fit(start, args.iterations),
        f"R at the boundary (sd {args.boundary_sd:g})": run_fit(start, args.short, boundary),
        f"noise floored (sd >= {args.floor_sd:g})": run_fit(start, args.short, floored),
    }
    print(f"{args.log}: GP start from {start['linear']['start']} (linear EM log-likelihood "
          f"{start['linear']['em_log_likelihood']:.1f}, L-BFGS "
          f"{start['linear']['lbfgs_log_likelihood']:.1f})")  # fmt: skip
    head = ["fit", "its", "stopped", "s", "loglik start", "loglik end", "last gain", "R sd",
            "min Q sd", "rmse", "cov95", "jitter warnings"]  # fmt: skip
    body = [
        [k, r["iterations"], r["stopped"], r["seconds"], r["initial_log_likelihood"],
         r["log_likelihood"], r["last_gain"], r["noise_sd"]["measurement"][0],
         min(r["noise_sd"]["transition"]), r["rmse"], r["coverage95"], r["jitter_warnings"]]
        for k, r in rows.items()
    ]  # fmt: skip
    print(table(head, body, fmt="{:.6g}"))
    print("largest parameter change of the plain fit, by group:")
    for k, v in rows["plain"]["moved"].items():
        print(f"  {k:45s} {v:.3g}")
    cmd = "python scripts/em_low_noise.py " + " ".join(argv if argv is not None else sys.argv[1:])
    payload = {
        "experiment": "em_low_noise",
        "command": cmd,
        "log": args.log,
        "linear": start["linear"],
        "rows": rows,
        "environment": environment(),
    }
    write_json(args.out / "results.json", payload)
    print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
