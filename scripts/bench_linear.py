"""Linear-Gaussian filtering and smoothing: torchfilt's exact Kalman path against its peers.

All peers run in the same invocation, one thread each, pinned to the same core, float64, CPU:
torchfilt's exact path (sequential, and parallel-in-time), torchfilt's CKF on the same model
(``path="cubature"``, what linear models ran before), filterpy's ``KalmanFilter`` (a Python loop)
and dynamax's jitted ``lgssm_filter`` / ``lgssm_smoother`` (run by ``--jax-python``, a separate
venv with JAX: ``scripts/_dynamax_peer.py``). Every peer's means are compared with torchfilt's
(``max_diff``), so all compute the same thing. Figures are the median of ``--repeats`` runs after a
warm-up, in microseconds per time step (per sequence-step for batches); ``vs_*`` columns are
the peer's time over torchfilt's exact sequential time (> 1: torchfilt is faster). With all data
observed and one ``P0`` for the batch torchfilt computes one covariance sequence for the whole
batch; the "own covs" column gives each sequence its own ``P0``, so that it keeps one covariance
per sequence as dynamax's vmap does (like for like).

    python scripts/bench_linear.py --out out/bench_linear --jax-python /work/wt/jaxenv/bin/python

Rows: batch 1 with n = 2, 8, 32 (m = n / 2); batch 256 with n = 8, one covariance per sequence;
the RTS smoother at n = 32, batch 1. The torchfilt filter rows ask for what the dynamax peer
returns (means and log-likelihood; the "all fields" column returns every field of the result).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json

import torchfilt
from torchfilt.filters import kalman_filter, kalman_smoother

PEER = Path(__file__).resolve().parent / "_dynamax_peer.py"


def problem(n: int, m: int, T: int, batch: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A stable random model and simulated measurements (float64)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.95 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    Q = 0.1 * np.eye(n)
    R = 0.5 * np.eye(m)
    y = rng.standard_normal((batch, T, m)) if batch > 1 else rng.standard_normal((T, m))
    return dict(A=A, H=H, Q=Q, R=R, m0=np.zeros(n), P0=np.eye(n), y=y)


def torch_runner(
    p: dict[str, np.ndarray],
    *,
    smoother: bool,
    parallel: bool,
    path: str = "kalman",
    per_sequence: bool = False,
    all_fields: bool = False,
):
    """torchfilt's run; ``per_sequence`` gives ``P0`` per sequence, so that the filter keeps one
    covariance per sequence (as dynamax's vmap does) instead of sharing one for the batch. The
    filter returns what the dynamax peer returns, means and log-likelihood
    (``outputs=("mean", "log_likelihood")``), unless ``all_fields``."""
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    model = torchfilt.LinearGaussianModel(t(p["A"]), t(p["H"]), t(p["Q"]), t(p["R"]))
    y, x0, P0 = t(p["y"]), t(p["m0"]), t(p["P0"])
    if per_sequence and y.dim() == 3:
        P0 = P0.expand(y.shape[0], *P0.shape).clone()
    if path == "cubature":
        ckf = torchfilt.CKF(model)

        def run() -> torch.Tensor:
            if smoother:
                return ckf.smooth(y, x0=x0, P0=P0, path="cubature").mean
            return ckf.filter(y, x0=x0, P0=P0, path="cubature").mean

        return run

    def run_exact() -> torch.Tensor:
        if smoother:
            return kalman_smoother(model, y, x0=x0, P0=P0, parallel=parallel).mean
        outputs = None if all_fields else ("mean", "log_likelihood")
        return kalman_filter(model, y, x0=x0, P0=P0, parallel=parallel, outputs=outputs).mean

    return run_exact


def filterpy_runner(p: dict[str, np.ndarray], *, smoother: bool):
    from filterpy.kalman import KalmanFilter

    n, m = p["A"].shape[0], p["H"].shape[0]

    def run() -> np.ndarray:
        kf = KalmanFilter(dim_x=n, dim_z=m)
        kf.F, kf.H, kf.Q, kf.R = p["A"], p["H"], p["Q"], p["R"]
        kf.x, kf.P = p["m0"].copy(), p["P0"].copy()
        means, covs = [], []
        for z in p["y"]:
            kf.predict()
            kf.update(z)
            means.append(kf.x.copy())
            covs.append(kf.P.copy())
        if not smoother:
            return np.array(means)
        T = len(means)
        Fs, Qs = np.repeat(p["A"][None], T, 0), np.repeat(p["Q"][None], T, 0)
        return kf.rts_smoother(np.array(means), np.array(covs), Fs, Qs)[0]

    return run


def dynamax_peer(
    jax_python: str | None, p: dict[str, np.ndarray], task: str, repeats: int
) -> tuple[float | None, np.ndarray | None, str]:
    """Seconds and means of dynamax's ``task`` in the JAX venv, or ``None`` and why not."""
    if not jax_python:
        return None, None, "not run (no --jax-python)"
    m1 = p["A"] @ p["m0"]
    P1 = p["A"] @ p["P0"] @ p["A"].T + p["Q"]
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, A=p["A"], H=p["H"], Q=p["Q"], R=p["R"], m1=m1, P1=P1, y=p["y"])
        env = dict(os.environ, XLA_FLAGS="--xla_cpu_multi_thread_eigen=false", OMP_NUM_THREADS="1")
        env.pop("PYTHONPATH", None)
        out = subprocess.run(
            [jax_python, str(PEER), str(src), str(dst), task, str(repeats)],
            capture_output=True,
            text=True,
            env=env,
        )
        if out.returncode != 0:
            return None, None, f"failed: {out.stderr.strip().splitlines()[-1:]}"
        info = json.loads(out.stdout.strip().splitlines()[-1])
        return float(info["seconds"]), np.load(dst)["mean"], f"dynamax, jax {info['jax']}"


def _diff(a: Any, b: torch.Tensor) -> float | None:
    if a is None:
        return None
    return float(np.max(np.abs(np.asarray(a) - b.numpy())))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=500, help="T (default 500)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jax-python", default=None, help="python of a venv with dynamax")
    ap.add_argument("--cpu", type=int, default=0, help="core to pin every peer to")
    ap.add_argument("--out", type=Path, default=Path("out/bench_linear"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    T = args.steps
    cases = [
        ("filter", 1, 2),
        ("filter", 1, 8),
        ("filter", 1, 32),
        ("filter", 256, 8),
        ("smoother", 1, 32),
    ]
    rows = []
    peers = ""
    with torch.no_grad():
        for kind, batch, n in cases:
            m = max(n // 2, 1)
            p = problem(n, m, T, batch)
            smoother = kind == "smoother"
            ref_fn = torch_runner(p, smoother=smoother, parallel=False)
            ref = ref_fn()
            per = T * batch
            row: dict[str, Any] = {"case": kind, "batch": batch, "n": n, "m": m, "T": T}
            row["torchfilt_us"] = timeit(ref_fn, args.repeats) / per * 1e6
            if not smoother:
                full = torch_runner(p, smoother=False, parallel=False, all_fields=True)
                row["all_fields_us"] = timeit(full, args.repeats) / per * 1e6
            else:
                row["all_fields_us"] = None
            par_fn = torch_runner(p, smoother=smoother, parallel=True)
            row["parallel_us"] = timeit(par_fn, args.repeats) / per * 1e6
            row["parallel_max_diff"] = _diff(par_fn(), ref)
            ckf_fn = torch_runner(p, smoother=smoother, parallel=False, path="cubature")
            row["ckf_us"] = timeit(ckf_fn, 1) / per * 1e6
            row["ckf_max_diff"] = _diff(ckf_fn(), ref)
            if batch > 1:  # like for like with dynamax's vmap: one covariance per sequence
                own = torch_runner(p, smoother=smoother, parallel=False, per_sequence=True)
                row["per_sequence_us"] = timeit(own, args.repeats) / per * 1e6
                row["per_sequence_max_diff"] = _diff(own(), ref)
            else:
                row["per_sequence_us"] = row["per_sequence_max_diff"] = None
            if batch == 1:
                fp = filterpy_runner(p, smoother=smoother)
                row["filterpy_us"] = timeit(fp, args.repeats) / per * 1e6
                row["filterpy_max_diff"] = _diff(fp(), ref)
            else:
                row["filterpy_us"] = row["filterpy_max_diff"] = None
            secs, mean, peers = dynamax_peer(
                args.jax_python, p, "smoother" if smoother else "filter", args.repeats
            )
            row["dynamax_us"] = None if secs is None else secs / per * 1e6
            row["dynamax_max_diff"] = _diff(mean, ref)
            for peer in ("ckf", "filterpy", "dynamax", "parallel", "per_sequence"):
                v = row[f"{peer}_us"]
                row[f"vs_{peer}"] = None if v is None else v / row["torchfilt_us"]
            rows.append(row)
            print(f"done {kind} batch {batch} n {n}", file=sys.stderr)
    headers = ["case", "batch", "n", "torchfilt", "all fields", "own covs", "parallel", "CKF"]
    headers += ["filterpy"]
    headers += ["dynamax", "filterpy/tf", "dynamax/tf", "dynamax/own", "max diff"]
    body = [
        [
            r["case"],
            r["batch"],
            r["n"],
            r["torchfilt_us"],
            r["all_fields_us"],
            r["per_sequence_us"],
            r["parallel_us"],
            r["ckf_us"],
            r["filterpy_us"],
            r["dynamax_us"],
            r["vs_filterpy"],
            r["vs_dynamax"],
            None if r["per_sequence_us"] is None or r["dynamax_us"] is None
            else r["dynamax_us"] / r["per_sequence_us"],
            max(
                (r[k] for k in ("parallel_max_diff", "ckf_max_diff", "filterpy_max_diff",
                                "dynamax_max_diff", "per_sequence_max_diff") if r[k] is not None),
                default=None,
            ),
        ]
        for r in rows
    ]  # fmt: skip
    print(f"microseconds per sequence-step, T = {T}, float64, 1 thread; peers: {peers}")
    print(table(headers, body))
    write_json(
        args.out / "bench_linear.json",
        {"rows": rows, "peers": peers, "environment": environment(), "T": T},
    )
    print(f"wrote {args.out / 'bench_linear.json'}")


if __name__ == "__main__":
    main()
