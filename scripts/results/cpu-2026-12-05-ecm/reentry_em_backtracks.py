"""EM on the re-entry radar case of ``scripts/reproduce_measurement_only.py`` (8 training runs,
its start) with 4 and with 12 step halvings: where it stops and the parameters it ends at.

Run from a checkout: ``PYTHONPATH=. python
scripts/results/cpu-2026-12-05-ecm/reentry_em_backtracks.py --out OUT.json``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # scripts/
import reproduce_measurement_only as rmo

from torchfilt.systems import reentry
from torchfilt.training import fit_em


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    train = reentry.simulate_truth(8, seed=11)  # the script's training runs (seed 0 + 11)
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=rmo.DT), reentry.prior_cov()
    rows = {}
    for backtracks in (4, 12):
        fit = fit_em(
            rmo.radar_model(), train.measurements, x0=x0, P0=P0, known_channels=[0],
            iterations=30, backtracks=backtracks,
        )  # fmt: skip
        drag, sensor = rmo.radar_parts(fit.model)
        rows[backtracks] = {
            "initial_log_likelihood": fit.initial_log_likelihood,
            "log_likelihood": fit.log_likelihood,
            "iterations": fit.iterations,
            "stopped": fit.stopped,
            "gamma": float(drag.log_gamma.detach().exp()),
            "gain": float(sensor.scale.detach()),
            "offset_ft": float(sensor.bias.detach()),
        }
        print(backtracks, rows[backtracks])
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
