"""The pipeline's linear-EM candidate start (``torchfilt.pipeline.linear_start``) with plain EM
(before) and with SQUAREM cycles (``fit_em``'s default for a linear model, after), side by side.

For each simulated dataset: the candidate's training log-likelihood (in the linearised sensor),
its CKF log-likelihood on the held-out recordings (what the pipeline ranks the candidates by)
and its seconds. With ``--data DIR`` (the folder of ``robot-arm.csv``, see
``scripts/bench_real_logs.py``), also the whole ``states = "none"`` run through
:func:`torchfilt.train_recipe` on the flexible robot arm (standardised, the first two thirds
training, a sensor ``y = x1`` with ``R = 1e-4``; a third run with SQUAREM learns ``R`` from
there, ``[measurement_only] learn_measurement_noise = true``), and the free-run RMSE and 95%
coverage of the held-out third after a 20-step burn-in, as the bench scores it.

Run from a checkout: ``PYTHONPATH=. python
scripts/results/cpu-2026-12-05-linear-candidate/compare_candidates.py --out OUT.json [--data
DIR]``."""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import torch

import torchfilt
from torchfilt.filters import free_run
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import linear_start
from torchfilt.systems import get_system

D = torch.float64
#: (system, recordings, steps, seed)
CASES = [
    ("pendulum", 6, 200, 0),
    ("reentry", 6, 100, 0),
    ("reaction", 6, 50, 2),
    ("reaction", 10, 100, 0),
    ("reaction", 12, 300, 1),
]
ROBOT_RECIPE = """name = "robot-arm"
seed = 0
states = "none"

[dataset]
path = "data"

[measurement]
model = "robot_sensor:first"
R = [1e-4]

[filter]
mean = [0.0, 0.0, 0.0, 0.0]
cov_diag = [1.0, 1.0, 1.0, 1.0]
"""
ROBOT_SENSOR = '''import torch


def first(x: torch.Tensor) -> torch.Tensor:
    """y = x1: states (..., 4) -> (..., 1)."""
    return x[..., :1]
'''


def _accelerate(value: bool | None) -> Any:
    """Patch the candidate's ``fit_em`` to run with ``accelerate=value``."""
    real = linear_start.fit_em

    def fit_em(*args: Any, **kw: Any) -> Any:
        return real(*args, **{**kw, "accelerate": value})

    return mock.patch.object(linear_start, "fit_em", fit_em)


def candidate_row(case: tuple[str, int, int, int], accelerate: bool | None) -> dict[str, Any]:
    name, recordings, steps, seed = case
    folder = Path(tempfile.mkdtemp()) / "data"
    simulate_dataset(name, folder, recordings=recordings, steps=steps, seed=seed)
    ds = torchfilt.load_dataset(folder)
    train, held = ds.split("train"), ds.split("validation") or ds.split("test")
    spec = get_system(name)
    h = spec.model().measurement
    m0, P0 = spec.prior_mean().to(D), spec.prior_cov().to(D)
    nu = 0 if train[0].inputs is None else int(train[0].inputs.shape[-1])
    t0 = time.perf_counter()
    with _accelerate(accelerate):
        lin = linear_start.linear_em_start(
            h, train, n=int(m0.shape[0]), nu=nu, m0=m0, P0=P0, q0=1e-2 * P0.diagonal(),
            inducing=16, known=list(range(h.out_dim)), dtype=D,
        )  # fmt: skip
    seconds = time.perf_counter() - t0
    assert lin is not None
    score = 0.0
    with torch.no_grad():
        for r in held:
            u = None if not nu else r.inputs[:-1].to(D)  # type: ignore[index]
            res = torchfilt.CKF(lin.model).filter(r.measurements[1:].to(D), u, x0=m0, P0=P0)
            score += float(res.log_likelihood.sum())
    return {
        "case": f"{name} {recordings} x {steps} (seed {seed})",
        "accelerate": accelerate,
        "train_log_likelihood": lin.record["linear_log_likelihood"],
        "held_out_log_likelihood": score,
        "seconds": seconds,
    }


def _robot_dataset(csv_path: Path, folder: Path, learn: bool) -> None:
    """The robot-arm log as a torchfilt dataset: standardised by the training part's moments,
    the first two thirds one training recording, the rest one test recording."""
    with csv_path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    u = np.array([float(r["u"]) for r in rows])
    y = np.array([float(r["y"]) for r in rows])
    k = int(len(y) * 2 / 3)
    u = (u - u[:k].mean()) / u[:k].std()
    y = (y - y[:k].mean()) / y[:k].std()
    (folder / "data").mkdir(parents=True)
    for name, sl in (("train.csv", slice(0, k)), ("test.csv", slice(k, None))):
        lines = ["time,u,y"] + [
            f"{i},{float(a)!r},{'' if i == 0 else repr(float(b))}"
            for i, (a, b) in enumerate(zip(u[sl], y[sl], strict=True))
        ]
        (folder / "data" / name).write_text("\n".join(lines) + "\n")
    channels = [{"name": f"x{i}", "role": "state", "unit": ""} for i in range(1, 5)]
    channels += [{"name": "u", "role": "input", "unit": ""}, {"name": "y", "role": "measurement"}]
    manifest = {
        "schema": "torchfilt.dataset/1", "name": "robot-arm", "sample_time": 1.0,
        "channels": channels,
        "recordings": [{"file": "train.csv", "split": "train"}, {"file": "test.csv", "split": "test"}],
    }  # fmt: skip
    (folder / "data" / "manifest.json").write_text(json.dumps(manifest, indent=1))
    (folder / "robot_sensor.py").write_text(ROBOT_SENSOR)
    extra = "\n[measurement_only]\nlearn_measurement_noise = true\n" if learn else ""
    (folder / "robot.toml").write_text(ROBOT_RECIPE + extra)


def robot_row(csv_path: Path, accelerate: bool | None, learn: bool = False) -> dict[str, Any]:
    folder = Path(tempfile.mkdtemp())
    _robot_dataset(csv_path, folder, learn)
    sys.path.insert(0, str(folder))
    t0 = time.perf_counter()
    with _accelerate(accelerate):
        bundle = torchfilt.train_recipe(folder / "robot.toml", folder / "run", progress=False)
    seconds = time.perf_counter() - t0
    sys.path.remove(str(folder))
    log = (folder / "run" / "train.log").read_text().splitlines()
    ds = torchfilt.load_dataset(folder / "data", optional=("state",), require_finite=("input",))
    rec = ds.split("test")[0]
    sys.path.insert(0, str(folder))
    model = torchfilt.load_model(bundle)
    sys.path.remove(str(folder))
    y = rec.measurements[1:].to(D).unsqueeze(0)
    u = rec.inputs[:-1].to(D).unsqueeze(0)  # type: ignore[index]
    burn = 20
    with torch.no_grad():
        fc = free_run(
            model, y, u, x0=torch.zeros(4, dtype=D), P0=torch.eye(4, dtype=D), burn_in=burn
        )
    mean, cov, yy = fc.output_mean[:, burn:], fc.output_cov[:, burn:], y[:, burn:]
    return {
        "case": "robot arm through train_recipe (states = none)",
        "accelerate": accelerate,
        "learn_measurement_noise": learn,
        "seconds": seconds,
        "free_run_rmse": float(torchfilt.rmse(yy, mean, dim=(0, 1, 2))),
        "coverage95": float(torchfilt.coverage(yy, mean, cov).mean()),
        "log": [line.split(" ", 1)[1] for line in log if "transition:" in line],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for case in CASES:
        for acc in (False, None):
            rows.append(candidate_row(case, acc))
            r = rows[-1]
            print(
                f"{r['case']:<30} {'plain' if acc is False else 'SQUAREM':<8} train "
                f"{r['train_log_likelihood']:12.2f} held-out {r['held_out_log_likelihood']:12.2f} "
                f"{r['seconds']:6.2f} s",
                flush=True,
            )
    if args.data is not None:
        for acc, learn in ((False, False), (None, False), (None, True)):
            r = robot_row(args.data / "robot-arm.csv", acc, learn)
            rows.append(r)
            print(
                f"robot arm, train_recipe   {'plain' if acc is False else 'SQUAREM':<8} "
                f"{'R learned' if learn else 'R given':<10} "
                f"free-run RMSE {r['free_run_rmse']:.4f} coverage {r['coverage95']:.3f} "
                f"{r['seconds']:.1f} s",
                flush=True,
            )
            for line in r["log"]:
                print("   ", line)
    args.out.write_text(
        json.dumps(
            {
                "rows": rows,
                "finite": all(math.isfinite(r.get("held_out_log_likelihood", 0.0)) for r in rows),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
