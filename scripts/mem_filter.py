"""Peak memory of a batched filter against the size of what it returns (CPU, eager, float64).

Each configuration runs in a fresh child process. The child builds the inputs, warms up on a small
batch, then resets the kernel's peak-RSS counter (``echo 5 > /proc/self/clear_refs``) and filters
``B`` sequences; the peak is ``VmHWM`` (from ``/proc/self/status``) minus the RSS just before the
call. torch's CPU tensors come from ``malloc``/``mmap``, so ``tracemalloc`` cannot see them but
RSS does. ``results`` is the bytes of the returned tensors' storages (each counted once);
``retained`` is the RSS still held after the results are deleted.

    python scripts/mem_filter.py --out out/mem_filter        # B = 10^4, T = 60, n = 3, m = 2
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt

CONFIGS = {
    "ckf": "CKF, sigma-point path (path='cubature')",
    "ckf_mean_ll": "CKF, sigma-point path, outputs=('mean', 'log_likelihood')",
    "kalman": "exact Kalman path (default); one covariance shared by the batch",
    "kalman_per_seq": "exact path, P0 given per sequence (one covariance per sequence)",
    "kalman_sqrt": "exact Kalman path, square-root",
    "kalman_mean_ll": "exact path, outputs=('mean', 'log_likelihood')",
    "parallel": "parallel-in-time path (parallel=True)",
    "kalman_grad": "exact path with autograd recording (Q requires grad)",
}


def _status(key: str) -> int:
    """A ``/proc/self/status`` entry in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


def _storage_bytes(res: Any) -> int:
    seen: dict[int, int] = {}
    leaves = [*res.filtered, res.mean, res.cov, res.gain] if hasattr(res, "filtered") else res
    for t in leaves:
        if isinstance(t, torch.Tensor):
            s = t.untyped_storage()
            seen[s.data_ptr()] = s.nbytes()
    return sum(seen.values())


def _problem(B: int, T: int, n: int, m: int, grad: bool = False) -> tuple[Any, ...]:
    gen = torch.Generator().manual_seed(0)
    d = torch.float64
    A = 0.9 * torch.eye(n, dtype=d) + 0.05 * torch.randn(n, n, generator=gen, dtype=d)
    H = torch.randn(m, n, generator=gen, dtype=d)
    Q = (0.1 * torch.eye(n, dtype=d)).requires_grad_(grad)
    model = torchfilt.LinearGaussianModel(A, H, Q, torch.eye(m, dtype=d))
    y = torch.randn(B, T, m, generator=gen, dtype=d)
    return model, y, torch.zeros(n, dtype=d), torch.eye(n, dtype=d)


def _run(name: str, model: Any, y: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor) -> Any:
    kw: dict[str, Any] = dict(x0=x0, P0=P0)
    sqrt = name == "kalman_sqrt"
    filt = torchfilt.CKF(model, sqrt=sqrt)
    if name == "ckf":
        return filt.filter(y, **kw, path="cubature")
    if name == "ckf_mean_ll":
        return filt.filter(y, **kw, path="cubature", outputs=("mean", "log_likelihood"))
    if name in ("kalman_per_seq", "kalman_sqrt", "kalman_grad"):
        kw["P0"] = P0.expand(y.shape[0], *P0.shape).clone()  # one covariance per sequence
    if name == "kalman_mean_ll":
        return filt.filter(y, **kw, outputs=("mean", "log_likelihood"))
    if name == "parallel":
        return filt.filter(y, **kw, parallel=True)
    return filt.filter(y, **kw)


def child(name: str, B: int, T: int, n: int, m: int) -> dict[str, Any]:
    torch.set_num_threads(1)
    grad = name == "kalman_grad"
    model, y, x0, P0 = _problem(B, T, n, m, grad)
    ctx = torch.enable_grad() if grad else torch.no_grad()
    with ctx:
        # warm-up: libraries, allocator, and every lazily imported module of the code paths the
        # full batch takes (batches of 64 and more use the unrolled small-matrix kernels)
        _run(name, model, y[:8], x0, P0)
        _run(name, model, y[: min(y.shape[0], 128)], x0, P0)
        gc.collect()
        before = _status("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")
        res = _run(name, model, y, x0, P0)
        peak = _status("VmHWM") - before
        results = _storage_bytes(res)
        full = B * T * 8 * (3 * n * n + 2 * n + 2 * m + m * m) + B * T * m + B * 8
        del res
        gc.collect()
        retained = _status("VmRSS") - before
    return {
        "config": name,
        "peak_bytes": peak,
        "results_bytes": results,
        "full_results_bytes": full,
        "peak_over_results": peak / results,
        "peak_over_full_results": peak / full,
        "retained_bytes": retained,
        "peak_bytes_per_BTn2": peak / (B * T * n * n),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--n", type=int, default=3)
    ap.add_argument("--m", type=int, default=2)
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS))
    ap.add_argument("--out", type=Path, default=Path("out/mem_filter"))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    dims = (args.batch, args.steps, args.n, args.m)
    if args.child:
        print(json.dumps(child(args.child, *dims)))
        return
    rows = []
    for name in args.configs:
        cmd = [sys.executable, __file__, "--child", name, "--batch", str(args.batch)]
        cmd += ["--steps", str(args.steps), "--n", str(args.n), "--m", str(args.m)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    mib = 2.0**20
    print(f"B = {args.batch}, T = {args.steps}, n = {args.n}, m = {args.m}, float64, eager, CPU")
    print(
        table(
            ["config", "peak MiB", "results MiB", "peak/results", "retained MiB", "B/(BTn^2)"],
            [
                [
                    r["config"],
                    r["peak_bytes"] / mib,
                    r["results_bytes"] / mib,
                    r["peak_over_results"],
                    r["retained_bytes"] / mib,
                    r["peak_bytes_per_BTn2"],
                ]
                for r in rows
            ],
        )
    )
    payload = {
        "dims": dict(zip(("B", "T", "n", "m"), dims, strict=True)),
        "method": "peak RSS (VmHWM after clear_refs=5) minus RSS before the call",
        "rows": rows,
        "configs": CONFIGS,
        "environment": environment(),
    }
    write_json(args.out / "mem_filter.json", payload)
    print(f"wrote {args.out / 'mem_filter.json'}")


if __name__ == "__main__":
    main()
