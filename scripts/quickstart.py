"""Quick-start demo: track a re-entering vehicle with the cubature Kalman filter and smoother.

Simulates the radar re-entry problem (Athans et al. 1968), filters and smooths one recording with
the CKF, and writes a figure of the estimates with 95% bands and a NIS consistency plot.

    python scripts/quickstart.py --out out/quickstart
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import torch

import torchfilt
from torchfilt.plots import plot_estimates, plot_nis
from torchfilt.systems import reentry


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/quickstart"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    sim = reentry.simulate_truth(1, seed=args.seed)
    y, truth = sim.measurements[0], sim.states[0]
    ckf = torchfilt.CKF(reentry.model())
    sm = ckf.smooth(y, x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov())
    times = torch.arange(1, reentry.STEPS + 1) * reentry.DT
    names, units = ["altitude", "velocity", "ballistic coeff."], ["ft", "ft/s", None]
    fig = plot_estimates(
        sm,
        times=times,
        truth=truth,
        state_names=names,
        units=units,
        title="Re-entry tracking: cubature RTS smoother (filter in orange)",
    )
    fig.savefig(args.out / "estimates.png")
    plot_nis(sm.filtered, times=times).savefig(args.out / "nis.png")
    rf = torchfilt.rmse(truth, sm.filtered.mean)
    rs = torchfilt.rmse(truth, sm.mean)
    for i, n in enumerate(names):
        print(f"{n:>18}: filter RMSE {float(rf[i]):.4g}, smoother RMSE {float(rs[i]):.4g}")
    print(f"wrote {args.out / 'estimates.png'} and {args.out / 'nis.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
