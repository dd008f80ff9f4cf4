"""Throughput of filtering recordings: locally batched against Ray with 1 and 2 workers.

Re-entry recordings (analytic model, T = 60, float64, CSV in and out, the filter only), filtered
end to end by ``filter_recordings`` (one process, 1 thread) and by ``filter_recordings_ray`` on a
local Ray instance with 1 and 2 CPUs (one task = one batch, each worker 1 thread). Ray's start-up
(``ray.init``, a few seconds) is outside the clock; everything else, from the first read to the
summary file, is inside.

Local and Ray runs alternate (best of ``--repeats`` each), so both see the same load on a shared
machine. Per-task overhead: with 1 worker the tasks run one after another, so ``(Ray 1-worker time -
local time) / tasks`` is what a task costs beyond the filtering the local path does for the same
batch (scheduling, argument transfer, the worker's marker files, the driver's completion checks).
Its share of a task is ``overhead / (overhead + batch * local cost per recording)``; the batch size
from which it is under 10% is where that share crosses 0.1 (interpolated on the measured sizes).

    python scripts/bench_ray.py --out scripts/results/cpu-2026-12-01-ray
    python scripts/bench_ray.py --recordings 256 --batch-sizes 8 64   # quicker
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import filter_recordings, filter_recordings_ray
from torchfilt.pipeline.distributed import ray_session

SYSTEM = "reentry"


def _time(fn: Any, out: Path, repeats: int) -> tuple[float, Any]:
    best, res = float("inf"), None
    for _ in range(repeats):
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        res = fn(out)
        best = min(best, time.perf_counter() - t0)
    return best, res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recordings", type=int, default=512)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--batch-sizes", type=int, nargs="*", default=[4, 16, 64, 256])
    ap.add_argument("--repeats", type=int, default=2, help="best of this many runs per row")
    ap.add_argument("--out", type=Path, default=Path("out/bench_ray"))
    ap.add_argument(
        "--components-only",
        action="store_true",
        help="only split the local per-recording cost into filtering and file I/O, and time "
        "empty Ray tasks (the scheduling floor of a task)",
    )
    ap.add_argument(
        "--device", default="cpu", help="device of the filtering in --components-only (cuda)"
    )
    ap.add_argument(
        "--no-empty-tasks",
        action="store_true",
        help="--components-only without the empty Ray tasks (where Ray is not installed)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    work = Path(tempfile.mkdtemp(prefix="bench_ray."))
    try:
        simulate_dataset(SYSTEM, work / "data", recordings=args.recordings, steps=args.steps)
        recs = sorted((work / "data").glob("*.csv"))
        model = f"system:{SYSTEM}"
        if args.components_only:
            _components(
                recs,
                work,
                max(args.batch_sizes),
                args.repeats,
                args.out,
                device=args.device,
                empty_tasks=not args.no_empty_tasks,
            )
            return 0
        rows: list[dict[str, Any]] = []
        local: dict[int, float] = {}  # best local time per batch size, over both sessions
        adjacent: dict[tuple[int, int], float] = {}  # (workers, batch): local, measured alongside
        for workers in (1, 2):
            with ray_session(workers=workers):
                # warm the workers (process start, imports, a large batch) outside the clock
                filter_recordings_ray(
                    model, recs[:64], work / "warm", batch_size=32, progress=False
                )
                shutil.rmtree(work / "warm")
                for b in args.batch_sizes:
                    # local and Ray runs alternate, so both see the same load on a shared machine
                    t_loc, t_ray, res = float("inf"), float("inf"), None
                    for _ in range(args.repeats):
                        t, _ = _time(
                            lambda o, b=b: filter_recordings(model, recs, o, batch_size=b),
                            work / "local",
                            1,
                        )
                        t_loc = min(t_loc, t)
                        t, r = _time(
                            lambda o, b=b: filter_recordings_ray(
                                model, recs, o, batch_size=b, progress=False
                            ),
                            work / "ray",
                            1,
                        )
                        if t < t_ray:
                            t_ray, res = t, r
                    adjacent[workers, b] = t_loc
                    local[b] = min(local.get(b, float("inf")), t_loc)
                    assert res is not None
                    d = res["distributed"]
                    compute = sum(x["compute_s"] for x in d["task_times"])
                    rows.append(
                        {
                            "path": "ray",
                            "workers": workers,
                            "batch": b,
                            "seconds": t_ray,
                            "local_alongside_s": t_loc,
                            "tasks": d["tasks"],
                            "task_compute_s": compute,
                            "prepare_s": d["prepare_s"],
                        }
                    )
                    print(
                        f"batch {b}: local {t_loc:.2f} s, ray {workers} workers {t_ray:.2f} s",
                        file=sys.stderr,
                    )
        rows = [
            {"path": "local", "workers": 1, "batch": b, "seconds": local[b]}
            for b in args.batch_sizes
        ] + rows
        n = len(recs)
        for r in rows:
            r["recordings_per_s"] = n / r["seconds"]
        over: dict[int, float] = {}
        for r in rows:
            if r["path"] == "ray" and r["workers"] == 1:
                b = r["batch"]
                per_task = (r["seconds"] - adjacent[1, b]) / r["tasks"]
                per_rec = adjacent[1, b] / n
                r["overhead_per_task_s"] = per_task
                r["overhead_share"] = per_task / (per_task + b * per_rec)
                over[b] = r["overhead_share"]
        crossing = _crossing(over, 0.10)
        # extra time of Ray (1 worker) over local = per_task * tasks + per_recording * n: a least
        # squares fit over the batch sizes separates the two
        one = [r for r in rows if r["path"] == "ray" and r["workers"] == 1]
        fit = None
        if len(one) >= 2:
            A = torch.tensor([[r["tasks"], n] for r in one], dtype=torch.float64)
            y = torch.tensor(
                [r["seconds"] - adjacent[1, r["batch"]] for r in one], dtype=torch.float64
            )
            coef = torch.linalg.lstsq(A, y[:, None]).solution[:, 0]
            fit = {"per_task_s": float(coef[0]), "per_recording_s": float(coef[1])}
        payload = {
            "benchmark": "filter recordings: local batched vs Ray",
            "system": SYSTEM,
            "recordings": n,
            "steps": args.steps,
            "dtype": "float64",
            "io": "CSV recordings in, filtered-estimate CSV out (no smoother, no plots)",
            "environment": environment(),
            "rows": rows,
            "overhead_below_10pct_from_batch": crossing,
            "overhead_fit": fit,
            "local_seconds_per_recording": {b: local[b] / n for b in local},
            "note": "best of --repeats runs per row; Ray start-up (ray.init) not timed",
        }
        write_json(args.out / "bench_ray.json", payload)
        print(f"{n} {SYSTEM} recordings, T = {args.steps}, float64, CSV in/out, 1 thread/worker")
        headers = ["path", "workers", "batch", "tasks", "s", "rec/s", "overhead/task s", "share"]
        print(
            table(
                headers,
                [
                    [
                        r["path"],
                        r["workers"],
                        r["batch"],
                        r.get("tasks"),
                        r["seconds"],
                        r["recordings_per_s"],
                        r.get("overhead_per_task_s"),
                        r.get("overhead_share"),
                    ]
                    for r in rows
                ],
            )
        )
        print(f"Ray overhead under 10% of a task from batch size: {crossing}")
        print(f"overhead fit (extra s = per_task * tasks + per_recording * n): {fit}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def _components(
    recs: list[Path],
    work: Path,
    batch: int,
    repeats: int,
    out: Path,
    *,
    device: str = "cpu",
    empty_tasks: bool = True,
) -> None:
    """Per recording: the whole local path at ``batch`` against the CKF alone on the same batch
    in memory, both on ``device``; the difference is reading the CSV, writing the estimates
    (atomic, fsync) and the summary."""
    from torchfilt.filters import CKF
    from torchfilt.io import read_recording
    from torchfilt.pipeline import resolve_model

    spec = resolve_model(f"system:{SYSTEM}")
    recs = recs[:batch]
    n = len(recs)
    whole, _ = _time(
        lambda o: filter_recordings(f"system:{SYSTEM}", recs, o, batch_size=batch, device=device),
        work / "comp",
        repeats,
    )
    rs = [read_recording(p, spec.channels, optional=("state",)) for p in recs]
    y = torch.stack([r.measurements[1:] for r in rs]).to(device)
    filt = CKF(spec.model.to(device))
    x0, P0 = spec.prior_mean.to(device), spec.prior_cov.to(device)
    t = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        filt.filter(y, x0=x0, P0=P0)
        if y.device.type == "cuda":
            torch.cuda.synchronize()
        t.append(time.perf_counter() - t0)
    ckf = min(t[1:])
    payload = {
        "system": SYSTEM,
        "device": device,
        "batch": n,
        "local_path_s_per_recording": whole / n,
        "ckf_only_s_per_recording": ckf / n,
        "io_and_bookkeeping_s_per_recording": (whole - ckf) / n,
        "environment": environment(),
    }
    payload["empty_task"] = _empty_tasks() if empty_tasks else "not run (--no-empty-tasks)"
    write_json(out / "bench_ray_components.json", payload)
    print(json.dumps(payload, indent=2, default=float))


def _noop(job: Any, spec: Any, shard: list[int]) -> int:
    return len(shard)


def _empty_tasks(count: int = 200) -> dict[str, float]:
    """Seconds per task of a task that does nothing but receive the job's two object references
    and a shard, on 1 worker: one at a time (submit, wait) and all submitted at once."""
    import ray

    from torchfilt.pipeline import resolve_model

    with ray_session(workers=1):
        remote = ray.remote(_noop).options(num_cpus=1, max_retries=3)
        job = ray.put({"names": [f"r{i}" for i in range(10_000)]})
        spec = ray.put(resolve_model(f"system:{SYSTEM}"))
        ray.get([remote.remote(job, spec, [0]) for _ in range(20)])  # warm
        t0 = time.perf_counter()
        for i in range(count):
            ray.get(remote.remote(job, spec, [i]))
        serial = (time.perf_counter() - t0) / count
        t0 = time.perf_counter()
        ray.get([remote.remote(job, spec, [i]) for i in range(count)])
        pipelined = (time.perf_counter() - t0) / count
    return {"serial_s_per_task": serial, "pipelined_s_per_task": pipelined, "tasks": count}


def _crossing(share: dict[int, float], level: float) -> float | None:
    """The batch size from which the overhead share stays below ``level``: the smallest measured
    size with every larger one below too, log-linearly interpolated from the last size above;
    ``None`` if the largest measured size is not below."""
    pts = sorted(share.items())
    if not pts or pts[-1][1] >= level:
        return None
    k = len(pts) - 1
    while k > 0 and pts[k - 1][1] < level:
        k -= 1
    if k == 0:
        return float(pts[0][0])
    (b0, s0), (b1, s1) = pts[k - 1], pts[k]
    f = (s0 - level) / (s0 - s1)
    return float(math.exp(math.log(b0) + f * (math.log(b1) - math.log(b0))))


if __name__ == "__main__":
    sys.exit(main())
