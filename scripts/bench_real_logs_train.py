"""Real input-output logs through ``torchfilt train``: the ``states = "none"`` stage's defaults.

:mod:`bench_real_logs` fits the measurement-only GP in Python with
:func:`~torchfilt.training.fit_measurement_only`'s defaults, which learn the sensor's noise
``R`` with the transition. On these nearly noise-free logs that ``R`` falls towards zero (the
robot arm's to 1e-11 of the output's variance, shrinking about 3% an iteration), the
likelihood rises a little every iteration, and the fit ends at its 30-iteration budget
unconverged. The pipeline's stage holds the sensor's ``R`` as the recipe gives it (its
``learn_measurement_noise`` is off by default), as a user who knows the sensor would.

This script runs each log through :func:`~torchfilt.pipeline.train_recipe` as a user would
write it: a dataset folder (the training part as one recording, the held-out part as a test
recording), a sensor of one's own (``y = x[0]``, ``[measurement] model =
"realsensor:first_state"``) with ``R`` a fraction (``--noise``) of the standardised output's
variance, the prior ``N(0, I)``, and every other key at its default (the stage's 30-iteration
budget, its validation tail, its candidate starts, the calibration stage). Reported per log
and ``R``: the stage's stop (``"converged"`` within the budget, or ``"iterations"``), the
calibration's, the wall time of ``train``, and the bundle's model evaluated as
:mod:`bench_real_logs` does (free-run RMSE of the standardised held-out output after
``--burn-in`` filtered samples, against the same N4SID baseline; 95% coverage of the output).

    python scripts/bench_real_logs_train.py --data DIR --out OUT
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch
from _common import environment, table, write_json
from bench_real_logs import LOGS, n4sid_row, read_log, standardised, torchfilt_row
from torch import Tensor

from torchfilt.pipeline import load_bundle, load_model_spec, train_recipe

SENSOR = '''"""The sensor of the real-log bench: the output is the first state."""


def first_state(x):
    """(..., n) -> (..., 1)."""
    return x[..., :1]
'''

RECIPE = """name = "{name}"
seed = 0
states = "none"

[dataset]
path = "{data}"

[measurement]
model = "realsensor:first_state"
R = [{R!r}]

[filter]
mean = {mean}
cov_diag = {cov}
"""


def write_dataset(root: Path, n: int, parts: tuple[Tensor, Tensor, Tensor, Tensor]) -> None:
    """``root/manifest.json`` and two recordings: the training part (split ``train``; the
    stage holds its tail out for validation) and the held-out part (``test``). Row 0 is the
    prior's time (no measurement); the input of row ``k`` drives the step to row ``k + 1``."""
    u_tr, y_tr, u_te, y_te = parts
    root.mkdir(parents=True, exist_ok=True)
    states = [f"s{i + 1}" for i in range(n)]
    manifest = {
        "schema": "torchfilt.dataset/1",
        "name": root.name,
        "sample_time": 1.0,
        "time": {"name": "time", "unit": "sample"},
        "channels": [{"name": s, "role": "state"} for s in states]
        + [{"name": "u", "role": "input"}, {"name": "y", "role": "measurement"}],
        "recordings": [
            {"file": "train.csv", "split": "train"},
            {"file": "test.csv", "split": "test"},
        ],
    }
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    for file, u, y in (("train.csv", u_tr, y_tr), ("test.csv", u_te, y_te)):
        # no state columns (a states = "none" run never reads them); the last row's input
        # drives no step: 0
        us, ys = u[0, :, 0].tolist(), y[0, :, 0].tolist()
        lines = ["time,u,y", f"0,{us[0]!r},"]
        lines += [
            f"{k + 1},{0.0 if k + 1 == len(ys) else us[k + 1]!r},{ys[k]!r}" for k in range(len(ys))
        ]
        (root / file).write_text("\n".join(lines) + "\n")


def train_row(
    name: str, parts: tuple[Tensor, ...], R: float, args: argparse.Namespace, work: Path
) -> dict[str, Any]:
    """Train the log with ``[measurement] R = [R]`` and every stage at its defaults; the row."""
    n, tag = args.order, f"{name}_R{R:g}"
    data = work / name / "data"
    if not (data / "manifest.json").exists():
        write_dataset(data, n, parts)  # type: ignore[arg-type]
    recipe = work / f"{tag}.toml"
    text = RECIPE.format(name=tag, data=data.as_posix(), R=R, mean=[0.0] * n, cov=[1.0] * n)
    recipe.write_text(text + ("\n[measurement_only]\nstable = true\n" if args.stable else ""))
    run = work / f"run_{tag}"
    t0 = time.perf_counter()
    with (work / f"{tag}.stderr").open("w") as stream:
        bundle = train_recipe(recipe, run, force=True, progress=False, stream=stream)
    seconds = time.perf_counter() - t0
    spec = load_model_spec(bundle)
    _, _, u_te, y_te = parts
    row = torchfilt_row(spec.model, y_te, u_te, spec.prior_cov.to(torch.float64), args.burn_in)
    b = load_bundle(bundle)
    fit = b["transition"]["fit"]
    row |= {
        "R": R,
        "train_s": seconds,
        "stopped": fit["stopped"],
        "iterations": fit["iterations"],
        "budget": fit["options"]["iterations"],
        "method": fit["method"],
        "start": list(fit.get("candidates", [])),
        "calibration": (b.get("calibration") or {}).get("fit"),
        "log": (run / "train.log").read_text().splitlines(),
    }
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="folder with the logs' CSV files")
    ap.add_argument("--out", type=Path, default=Path("out/bench_real_logs_train"))
    ap.add_argument("--logs", default="robot-arm,cascaded-tanks,exchanger,ball-and-beam")
    ap.add_argument("--noise", default="1e-2,1e-4", help="R / var(y), comma-separated")
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--block-rows", type=int, default=20)
    ap.add_argument("--burn-in", type=int, default=20)
    ap.add_argument(
        "--stable",
        action="store_true",
        help="[measurement_only] stable = true (the plants said to be stable)",
    )
    args = ap.parse_args(argv)
    names = [s.strip() for s in args.logs.split(",") if s.strip()]
    if unknown := sorted(set(names) - set(LOGS)):
        ap.error(f"--logs: unknown {unknown}; choose from {', '.join(LOGS)}")
    noises = [float(s) for s in args.noise.split(",") if s.strip()]
    work = args.out / "work"
    work.mkdir(parents=True, exist_ok=True)
    (work / "realsensor.py").write_text(SENSOR)
    sys.path.insert(0, str(work.resolve()))
    torch.set_num_threads(1)
    results: dict[str, Any] = {}
    for name in names:
        spec = LOGS[name]
        parts = standardised(*read_log(args.data / spec["file"], spec["columns"]))
        base = n4sid_row(*parts, args.order, args.block_rows, args.burn_in)
        rows = {"N4SID (nfoursid)": base}
        for R in noises:  # standardised output: var(y_train) = 1
            rows[f"train, R = {R:g}"] = train_row(name, parts, R, args, work)
        for r in rows.values():
            r["rmse_over_n4sid"] = r["rmse"] / base["rmse"]
        results[name] = rows
        print(f"{name}: done", flush=True)
    body = [
        [k, row, r["rmse"], r["rmse_over_n4sid"], r.get("coverage95"), r.get("stopped", "-"),
         r.get("iterations", "-"), r["train_s"]]
        for k, rows in results.items()
        for row, r in rows.items()
    ]  # fmt: skip
    print("free-run RMSE of the standardised output after the burn-in; coverage of the 95% band")
    print(table(["log", "model", "RMSE", "/ N4SID", "95% cov.", "stopped", "its", "s"], body))
    write_json(
        args.out / "bench_real_logs_train.json",
        {"logs": results, "args": {k: str(v) for k, v in vars(args).items()},
         "environment": environment()},
    )  # fmt: skip
    print(f"wrote {args.out / 'bench_real_logs_train.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
