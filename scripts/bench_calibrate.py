"""Speed of likelihood training through the filter: re-entry with GP models, 64 windows x 100 steps.

One iteration is a forward pass of the batched CKF over all windows, the log-likelihood, and its
gradient with respect to the calibration parameters (variance scales and floors of both GP
sides), as :func:`torchfilt.calibrate` runs it. The GPs (``GPTransition`` in increment form and
``GPMeasurement`` on altitude) are fitted on ``--samples`` re-entry transitions (S = 2000 by
default; few Adam iterations, which does not change the cost of a prediction). Rows: the eager
filter and the compiled step (``compile=True``), each timed over ``--repeats`` iterations after
warm-up; the compiled row reports its first-call (compile) time separately. On a GPU machine
``--device cuda`` adds the same rows there.

    python scripts/bench_calibrate.py --out out/bench_calibrate

The end-to-end time of the Plaza2 calibration is measured by ``scripts/plaza_example.py``
(``timings_s["calibrate learned filter"]`` in its ``results.json``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.systems import reentry
from torchfilt.training.likelihood import step_log_likelihood

DT = torch.float64


def models(samples: int, seed: int) -> torchfilt.StateSpaceModel:
    log = reentry.record_training_data(samples, seed=seed)
    f = torchfilt.GPTransition.fit(
        log.states, increment=True, iterations=20, subset=None, progress=False, seed=seed
    )
    h = torchfilt.GPMeasurement.fit(
        log.states, log.measurements, inputs=[0], iterations=20, subset=None, progress=False
    )
    return torchfilt.StateSpaceModel(
        torchfilt.CalibratedModel(f, min_scale=1.0), torchfilt.CalibratedModel(h, min_scale=1.0)
    )


def one_iteration(
    filt: torchfilt.CKF, y: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor
) -> float:
    filt.zero_grad()
    res = filt.filter(y, x0=x0, P0=P0)
    ll = step_log_likelihood(res)[..., 10:].sum()
    ll.backward()
    return float(ll.detach())


def bench(
    model: torchfilt.StateSpaceModel,
    windows: int,
    steps: int,
    device: str,
    compile: bool,
    repeats: int,
) -> dict[str, Any]:
    model = model.to(device)
    sim = reentry.simulate_truth(windows, steps=steps, seed=1)
    y = sim.measurements.to(device)
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT, device=device).expand(windows, 3)
    P0 = reentry.prior_cov().to(device)
    filt = torchfilt.CKF(model, compile=compile)
    t0 = time.perf_counter()
    one_iteration(filt, y, x0, P0)
    first = time.perf_counter() - t0
    one_iteration(filt, y, x0, P0)
    times = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        one_iteration(filt, y, x0, P0)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    times.sort()
    med = times[len(times) // 2]
    return {
        "device": device,
        "compiled": compile,
        "first_call_s": first,
        "seconds_per_iteration": med,
        "iterations_per_second": 1.0 / med,
        "windows": windows,
        "steps": steps,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_calibrate"))
    ap.add_argument("--samples", type=int, default=2000, help="GP training transitions (S)")
    ap.add_argument("--windows", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-compile", action="store_true", help="skip the compiled row")
    ap.add_argument("--device", action="append", default=None, help="cpu (default) and/or cuda")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    model = models(args.samples, seed=0)
    fit_s = time.perf_counter() - t0
    rows = []
    for device in args.device or ["cpu"]:
        for compile in [False] if args.no_compile else [False, True]:
            try:
                rows.append(bench(model, args.windows, args.steps, device, compile, args.repeats))
            except Exception as e:  # a compile failure is a result to report, not a crash
                rows.append(
                    {"device": device, "compiled": compile, "error": f"{type(e).__name__}: {e}"}
                )
    headers = ["device", "path", "iterations/s", "s/iteration", "first call [s]"]
    body = [
        [
            r["device"],
            "compiled" if r["compiled"] else "eager",
            f"{r['iterations_per_second']:.3g}" if "error" not in r else r["error"][:60],
            f"{r['seconds_per_iteration']:.3g}" if "error" not in r else "-",
            f"{r['first_call_s']:.3g}" if "error" not in r else "-",
        ]
        for r in rows
    ]
    print(
        f"likelihood training, re-entry GP models (S = {args.samples}), {args.windows} windows x "
        f"{args.steps} steps, forward + gradient, {args.threads} thread(s)"
    )
    print(table(headers, body))
    write_json(
        args.out / "bench_calibrate.json",
        {
            "benchmark": "bench_calibrate",
            "command": " ".join(["python", "scripts/bench_calibrate.py", *sys.argv[1:]]),
            "samples": args.samples,
            "gp_fit_seconds": fit_s,
            "rows": rows,
            "environment": environment(),
        },
    )
    print(f"wrote {args.out / 'bench_calibrate.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
