"""A new user's own system through ``torchfilt train``, timed, and scored against the true model.

Issue #27's first acceptance row: a 2-state oscillator of one's own with an input and a nonlinear
position sensor, 12 recordings x 300 steps with the states logged, a recipe written from the docs
with every fit at its default (no iterations, no validation split), trained by the CLI on this
machine. Reported: the wall time of ``torchfilt train`` and of each stage (from the run's
``metrics.jsonl``), and, on 4 test recordings, the learned filter's RMSE against the true-model
CKF's (same prior, same data) and its mean NEES (n = 2: consistent near 2).

The system (dt = 0.1 s; w ~ N(0, 0.05^2) on the velocity, e ~ N(0, 0.05^2) on the sensor)::

    v+ = v + dt (-4 p - 0.5 v - 0.2 p^3 + u)     (semi-implicit Euler: stable)
    p' = p + dt v+,   v' = v+ + w
    y  = 2 tanh(p / 2) + e

    python scripts/bench_train.py --out scripts/results/<run>/bench_train [--quick]

Prints a table and writes ``bench_train.json``. ``--quick``: 3 x 60 steps (a smoke run for the
test suite, not a figure).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _common import environment, table, write_json

DT, Q_STD, R_STD = 0.1, 0.05, 0.05
RECIPE = """name = "oscillator"
seed = 0

[dataset]
path = "oscillator"

[transition]
increment = true

[measurement]
inputs = ["position"]
"""


def f_true(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The true transition ``(..., 2), (..., 1) -> (..., 2)``."""
    p, v = x[..., 0], x[..., 1]
    v_next = v + DT * (-4.0 * p - 0.5 * v - 0.2 * p**3 + u[..., 0])
    return torch.stack([p + DT * v_next, v_next], -1)


def h_true(x: torch.Tensor) -> torch.Tensor:
    """The true sensor ``(..., 2) -> (..., 1)``."""
    return 2.0 * torch.tanh(x[..., :1] / 2.0)


def simulate(n: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` recordings of ``steps + 1`` rows: states ``(n, T+1, 2)``, inputs ``(n, T+1, 1)``
    (row k's input drives the step to row k+1) and readings ``(n, T+1, 1)`` (row 0 unread)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.empty(n, steps + 1, 2, dtype=torch.float64)
    t = torch.arange(steps + 1, dtype=torch.float64) * DT
    freq = 0.5 + torch.rand(n, 1, generator=g, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(n, 1, generator=g, dtype=torch.float64)
    u = (1.5 * torch.sin(freq * t + phase)).unsqueeze(-1)
    x[:, 0] = torch.randn(n, 2, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.5])
    for k in range(steps):
        w = torch.zeros(n, 2, dtype=torch.float64)
        w[:, 1] = Q_STD * torch.randn(n, generator=g, dtype=torch.float64)
        x[:, k + 1] = f_true(x[:, k], u[:, k]) + w
    y = h_true(x) + R_STD * torch.randn(n, steps + 1, 1, generator=g, dtype=torch.float64)
    y[:, 0] = float("nan")
    return x.numpy(), u.numpy(), y.numpy()


def write_dataset(root: Path, train: int, test: int, steps: int, seed: int) -> None:
    """The CSV logs and the manifest (train and test splits only, as the user had)."""
    root.mkdir(parents=True)
    x, u, y = simulate(train + test, steps, seed)
    entries = []
    for r in range(train + test):
        lines = ["t,position,velocity,force,position_meas"]
        for k in range(steps + 1):
            cell = "" if math.isnan(y[r, k, 0]) else f"{y[r, k, 0]:.17g}"
            lines.append(
                f"{k * DT:.17g},{x[r, k, 0]:.17g},{x[r, k, 1]:.17g},{u[r, k, 0]:.17g},{cell}"
            )
        name = f"log_{r:02d}.csv"
        (root / name).write_text("\n".join(lines) + "\n")
        entries.append({"file": name, "split": "train" if r < train else "test"})
    manifest = {
        "schema": "torchfilt.dataset/1",
        "name": "oscillator",
        "sample_time": DT,
        "time": {"name": "t", "unit": "s"},
        "channels": [
            {"name": "position", "role": "state", "unit": "m"},
            {"name": "velocity", "role": "state", "unit": "m/s"},
            {"name": "force", "role": "input", "unit": "N"},
            {"name": "position_meas", "role": "measurement", "unit": "m"},
        ],
        "recordings": entries,
    }
    (root / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


def stage_times(run: Path) -> dict[str, float]:
    """Seconds per stage: the last ``elapsed`` each stage logged in ``metrics.jsonl``."""
    out: dict[str, float] = {}
    for line in (run / "metrics.jsonl").read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "stage" in rec and "elapsed" in rec:
            out[rec["stage"]] = max(out.get(rec["stage"], 0.0), float(rec["elapsed"]))
    return out


def score(run: Path, data: Path) -> dict[str, float]:
    """The learned and the true-model CKF on the test logs: RMSE ratio and mean NEES."""
    import torchfilt as tf
    from torchfilt.models.functional import FunctionModel
    from torchfilt.pipeline.bundle import load_model_spec

    spec = load_model_spec(run / "model.pt")
    ds = tf.load_dataset(data)
    tests = ds.split("test")
    xs = torch.stack([r.states.to(torch.float64) for r in tests])
    us = torch.stack([r.inputs.to(torch.float64) for r in tests])
    ys = torch.stack([r.measurements.to(torch.float64) for r in tests])
    x0, P0 = spec.prior_mean.to(torch.float64), spec.prior_cov.to(torch.float64)
    y, u, x = ys[:, 1:], us[:, :-1], xs[:, 1:]
    learned = tf.CKF(spec.model.to(torch.float64)).filter(y, u, x0=x0, P0=P0)
    Q = torch.diag(torch.tensor([1e-12, Q_STD**2], dtype=torch.float64))
    R = torch.tensor([[R_STD**2]], dtype=torch.float64)
    true = tf.StateSpaceModel(
        FunctionModel(f_true, Q), FunctionModel(lambda x, u=None: h_true(x), R)
    )
    ref = tf.CKF(true).filter(y, u, x0=x0, P0=P0)
    rmse_l = tf.rmse(x, learned.mean, dim=(-3, -2))
    rmse_t = tf.rmse(x, ref.mean, dim=(-3, -2))
    return {
        "rmse_learned": rmse_l.tolist(),
        "rmse_true_model": rmse_t.tolist(),
        "rmse_ratio": float(rmse_l.norm() / rmse_t.norm()),
        "nees_learned": float(tf.nees(x, learned.mean, learned.cov).mean()),
        "nees_true_model": float(tf.nees(x, ref.mean, ref.cov).mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="scripts/results/bench_train")
    ap.add_argument("--quick", action="store_true", help="3 x 60 steps: a smoke run")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = Path(args.out)
    work = out / "work"
    if work.exists():
        raise SystemExit(f"{work} exists: remove it or choose another --out")
    train, test, steps = (3, 2, 60) if args.quick else (12, 4, 300)
    write_dataset(work / "oscillator", train, test, steps, args.seed)
    (work / "oscillator.toml").write_text(RECIPE)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "torchfilt", "train", "oscillator.toml", "--out", "run", "--quiet"],
        cwd=work,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"torchfilt train failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    stages = stage_times(work / "run")
    scores = score(work / "run", work / "oscillator")
    rows = [["train (wall, CLI)", wall]] + [[f"  stage {k}", v] for k, v in stages.items()]
    rows += [[k, v] for k, v in scores.items() if isinstance(v, float)]
    print(table(["measure", "value"], rows))
    payload = {
        "environment": environment(),
        "system": {"recordings": train, "test": test, "steps": steps, "dt": DT},
        "recipe": RECIPE,
        "train_wall_s": wall,
        "stage_s": stages,
        **scores,
        "log_tail": (work / "run" / "train.log").read_text()[-4000:],
    }
    write_json(out / "bench_train.json", payload)


if __name__ == "__main__":
    main()
