"""Re-entry tracking (Wei & Song 2013, sec. 3): Monte Carlo comparison of cubature Kalman filters.

CKF1 uses the true model; CKF2 a radar offset M = 3e5 instead of 1e5 (spec mf-ckf.md, sec. 5). Every
filter sees the same measurement noise in the same run. Prints a table of time-averaged RMSE and
mean NEES per state plus failed runs, writes ``results.json`` and error-over-time figures like the
paper's figures 3-5.

    python scripts/reproduce_reentry.py --runs 200 --seed 0 --out out/reentry
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.filters import FilterResult
from torchfilt.plots import plot_errors
from torchfilt.systems import reentry

STATE_NAMES = ["altitude", "velocity", "ballistic coeff."]
UNITS = ["ft", "ft/s", None]

FilterFn = Callable[[torch.Tensor], FilterResult]


def filters() -> dict[str, FilterFn]:
    """The filters compared, each a function of the measurements ``(runs, T, 1)``."""
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float64)
    P0 = reentry.prior_cov()
    ckf1 = torchfilt.CKF(reentry.model())
    ckf2 = torchfilt.CKF(reentry.model(reentry.RADAR_M_WRONG))
    return {
        "CKF1 (true model)": lambda y: ckf1.filter(y, x0=x0, P0=P0),
        "CKF2 (M = 3e5)": lambda y: ckf2.filter(y, x0=x0, P0=P0),
    }


def summarize(truth: torch.Tensor, res: FilterResult) -> dict:
    """Failure count, time-averaged RMSE, mean NEES per state and overall (successful runs)."""
    ok = torch.isfinite(res.mean).all(-1).all(-1) & torch.isfinite(res.cov).all(-1).all(-1).all(-1)
    n_ok = int(ok.sum())
    out: dict = {"runs": int(ok.numel()), "failed": int((~ok).sum())}
    finite_t = torch.isfinite(res.mean).all(-1)  # (runs, T)
    first_bad = torch.where(finite_t.all(-1), -1, (~finite_t).float().argmax(-1))
    fails = first_bad[first_bad >= 0].double() + 1
    out["failure_step_median"] = float(fails.median()) if fails.numel() else None
    if n_ok == 0:
        out.update(rmse=[float("nan")] * 3, nees_state=[float("nan")] * 3, nees=float("nan"))
        return out
    err = res.mean[ok] - truth[ok]
    var = res.cov[ok].diagonal(dim1=-2, dim2=-1)
    rmse_t = err.pow(2).mean(0).sqrt()  # (T, n): RMS over runs at each time
    out["rmse"] = rmse_t.mean(0).tolist()  # time-averaged
    out["rmse_pooled"] = err.pow(2).mean((0, 1)).sqrt().tolist()
    out["nees_state"] = (err.pow(2) / var).mean((0, 1)).tolist()
    out["nees"] = float(torchfilt.nees(truth[ok], res.mean[ok], res.cov[ok]).mean())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--runs", type=int, default=200, help="Monte Carlo runs (>= 100)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/reentry"))
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    sim = reentry.simulate_truth(args.runs, seed=args.seed)
    truth, y = sim.states, sim.measurements
    results, errors, timings = {}, {}, {}
    for name, fn in filters().items():
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", torchfilt.NumericsWarning)
            res = fn(y)
        timings[name] = time.perf_counter() - t0
        results[name] = summarize(truth, res)
        results[name]["numerics_warnings"] = len(caught)
        results[name]["seconds"] = timings[name]
        errors[name] = res.mean - truth
    headers = [
        "filter",
        "failed",
        *(f"RMSE {s}" for s in STATE_NAMES),
        *(f"NEES {s}" for s in STATE_NAMES),
        "NEES (n=3)",
    ]
    rows = [
        [name, f"{r['failed']}/{r['runs']}", *r["rmse"], *r["nees_state"], r["nees"]]
        for name, r in results.items()
    ]
    print(f"Re-entry tracking, {args.runs} Monte Carlo runs, seed {args.seed}, T = {reentry.STEPS}")
    print("RMSE: time average of the RMS over successful runs; NEES: mean over runs and time.")
    print(table(headers, rows))
    args.out.mkdir(parents=True, exist_ok=True)
    times = torch.arange(1, reentry.STEPS + 1, dtype=torch.float64) * reentry.DT
    fig = plot_errors(
        errors,
        times=times,
        state_names=STATE_NAMES,
        units=UNITS,
        title=f"Re-entry tracking: RMS error over {args.runs} runs (band: IQR)",
    )
    fig.savefig(args.out / "errors.png")
    payload = {
        "experiment": "reentry",
        "runs": args.runs,
        "seed": args.seed,
        "steps": reentry.STEPS,
        "integrator": f"RK4, {reentry.SUBSTEPS} sub-steps per {reentry.DT} s",
        "filters": results,
        "environment": environment(),
    }
    write_json(args.out / "results.json", payload)
    print(f"wrote {args.out / 'results.json'} and {args.out / 'errors.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
