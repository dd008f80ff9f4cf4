"""Filter throughput: torchfilt's CKF against filterpy and dynamax, all rows in one run.

Re-entry, analytic model, RK4 with 10 sub-steps per 1 s step, T = 60, float64 on the CPU (one
thread by default). filterpy gets its fastest form: dynamics written with plain Python floats.
dynamax (if installed) runs its UKF with alpha = 1, beta = 0, kappa = 0, which is the CKF, under
``jax.jit`` (``+ vmap`` for batches), in float64, returning the log-likelihood and the filtered
means and covariances; torchfilt returns the same (``outputs=("mean", "cov", "log_likelihood")``).
torchfilt runs eager, ``compile="step"`` (one compiled call per step, what ``compile=True`` takes)
and ``compile="loop"`` (the whole time loop compiled as one ``torch.while_loop`` over the step).
The re-entry model is timed twice: as ``torchfilt.systems.reentry`` writes it (hand-tuned) and as a
user would (``torch.stack`` of the derivative components inside a generic RK4). A linear model
with n = 8 at batch 256 completes the acceptance table of issue 13. Each figure is the median of
``--repeats`` timed runs after a warm-up; first-call (compile) times are reported beside them.
Prints a table and writes ``results.json``.

    python scripts/bench_filter.py --out out/bench_filter
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

# JAX (dynamax rows on the GPU) must not pre-allocate most of the GPU memory that torch uses.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json

import torchfilt
from torchfilt.systems import reentry

T = reentry.STEPS
#: what the dynamax rows return (log-likelihood, filtered means and covariances)
LIKE_DYNAMAX = ("mean", "cov", "log_likelihood")


# --------------------------------------------------------------------------- filterpy
def filterpy_runner(y: np.ndarray) -> Callable[[], None]:
    """filterpy's CubatureKalmanFilter with the dynamics in plain Python floats."""
    from filterpy.kalman import CubatureKalmanFilter

    gamma, M, H = reentry.GAMMA, reentry.RADAR_M, reentry.RADAR_H
    sub = reentry.SUBSTEPS

    def fx(x: np.ndarray, dt: float) -> np.ndarray:
        x1, x2, x3 = float(x[0]), float(x[1]), float(x[2])
        h = dt / sub
        for _ in range(sub):
            k1a, k1v = -x2, -math.exp(-gamma * x1) * x2 * x2 * x3
            a, v = x1 + 0.5 * h * k1a, x2 + 0.5 * h * k1v
            k2a, k2v = -v, -math.exp(-gamma * a) * v * v * x3
            a, v = x1 + 0.5 * h * k2a, x2 + 0.5 * h * k2v
            k3a, k3v = -v, -math.exp(-gamma * a) * v * v * x3
            a, v = x1 + h * k3a, x2 + h * k3v
            k4a, k4v = -v, -math.exp(-gamma * a) * v * v * x3
            x1 += h / 6.0 * (k1a + 2 * k2a + 2 * k3a + k4a)
            x2 += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        return np.array([x1, x2, x3])

    def hx(x: np.ndarray) -> np.ndarray:
        d = float(x[0]) - H
        return np.array([math.sqrt(M * M + d * d)])

    def run() -> None:
        ckf = CubatureKalmanFilter(3, 1, reentry.DT, hx, fx)
        ckf.x = np.array(reentry.PRIOR_MEAN)
        ckf.P = np.diag(reentry.PRIOR_COV_DIAG)
        ckf.Q = np.zeros((3, 3))
        ckf.R = np.array([[reentry.R_VAR]])
        for t in range(y.shape[0]):
            ckf.predict()
            ckf.update(y[t])

    return run


# --------------------------------------------------------------------------- torchfilt
def user_reentry_model(dtype: torch.dtype = torch.float64) -> torchfilt.StateSpaceModel:
    """Re-entry as a user would write it: a ``torch.stack`` drift inside a generic RK4 loop."""
    gamma, M, H = reentry.GAMMA, reentry.RADAR_M, reentry.RADAR_H
    h = reentry.DT / reentry.SUBSTEPS

    def drift(x: torch.Tensor) -> torch.Tensor:
        return torch.stack(
            [
                -x[..., 1],
                -torch.exp(-gamma * x[..., 0]) * x[..., 1] ** 2 * x[..., 2],
                0 * x[..., 2],
            ],
            dim=-1,
        )

    def f(x: torch.Tensor) -> torch.Tensor:
        for _ in range(reentry.SUBSTEPS):
            k1 = drift(x)
            k2 = drift(x + 0.5 * h * k1)
            k3 = drift(x + 0.5 * h * k2)
            k4 = drift(x + h * k3)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    def hx(x: torch.Tensor) -> torch.Tensor:
        return torch.sqrt(M**2 + (x[..., :1] - H) ** 2)

    return torchfilt.StateSpaceModel(
        f,
        hx,
        Q=torch.zeros(3, 3, dtype=dtype),
        R=torch.tensor([[reentry.R_VAR]], dtype=dtype),
    )


def linear_problem(n: int, m: int, batch: int, seed: int = 0) -> dict[str, Any]:
    """A stable random linear-Gaussian model (n states, m outputs) and ``batch`` recordings."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(n, n, generator=gen, dtype=torch.float64)
    A = 0.95 * A / torch.linalg.eigvals(A).abs().max()
    H = torch.randn(m, n, generator=gen, dtype=torch.float64)
    Q, R = 0.01 * torch.eye(n, dtype=torch.float64), 0.1 * torch.eye(m, dtype=torch.float64)
    model = torchfilt.LinearGaussianModel(A, H, Q, R)
    sim = torchfilt.simulate(
        model, T, torch.zeros(n, dtype=torch.float64), batch_shape=(batch,), generator=gen
    )
    return {"A": A, "H": H, "Q": Q, "R": R, "model": model, "y": sim.measurements}


def torchfilt_runner(
    y: torch.Tensor,
    *,
    compile: bool | str,
    sqrt: bool = False,
    model: torchfilt.StateSpaceModel | None = None,
    x0: torch.Tensor | None = None,
    P0: torch.Tensor | None = None,
    path: str = "auto",
) -> tuple[Callable[[], None], float]:
    """A closure filtering ``y`` with torchfilt, and the time its first call took; ``path``
    as in ``GaussianFilter.filter`` (``"cubature"`` keeps a linear model on the CKF)."""
    dtype, device = y.dtype, y.device
    if x0 is None or P0 is None:
        x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=dtype, device=device)
        P0 = reentry.prior_cov(dtype).to(device)
    if model is None:
        model = reentry.model(dtype=dtype).to(device)
    filt = torchfilt.CKF(model, sqrt=sqrt, compile=compile)  # type: ignore[arg-type]

    def run() -> None:
        with torch.inference_mode(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
            filt.filter(y, x0=x0, P0=P0, outputs=LIKE_DYNAMAX, path=path)
            if device.type == "cuda":
                torch.cuda.synchronize()

    t0 = time.perf_counter()
    run()
    first = time.perf_counter() - t0
    with torch.inference_mode(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
        res = filt.filter(y, x0=x0, P0=P0, outputs=LIKE_DYNAMAX, path=path)
        EXECUTIONS[id(run)] = res.numerics.execution if res.numerics is not None else res.path
    return run, first


#: the execution (numerics path) each torchfilt runner took, by id(run), for the JSON rows
EXECUTIONS: dict[int, str] = {}


# --------------------------------------------------------------------------- GPU
def graphed_runner(y: torch.Tensor, *, compile: bool) -> tuple[Callable[[], None], float]:
    """A closure replaying a CUDA graph of the whole run, and the time capture took."""
    dtype, device = y.dtype, y.device
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=dtype, device=device)
    P0 = reentry.prior_cov(dtype).to(device)
    filt = torchfilt.CKF(reentry.model(dtype=dtype).to(device), compile=compile)
    t0 = time.perf_counter()
    with torch.inference_mode(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
        graphed = filt.graphed(y, x0=x0, P0=P0)
    torch.cuda.synchronize()
    capture = time.perf_counter() - t0

    def run() -> None:
        with torch.inference_mode(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
            graphed.filter(y, clone=False)
        torch.cuda.synchronize()

    return run, capture


def dynamax_runner(
    y: np.ndarray,
    m0: np.ndarray | None = None,
    P0: np.ndarray | None = None,
    *,
    x64: bool = False,
    linear: dict[str, Any] | None = None,
) -> tuple[Callable[[], Any], float]:
    """dynamax's UKF with alpha = 1, beta = 0, kappa = 0 (that is the CKF), jit (+ vmap).

    dynamax's first step is an update of ``N(m0, P0)``; by default the paper's prior. ``x64``
    runs in float64 (the CPU rows), ``linear`` the linear problem of :func:`linear_problem`.
    """
    import jax

    jax.config.update("jax_enable_x64", x64)
    import jax.numpy as jnp
    from dynamax.nonlinear_gaussian_ssm import (  # type: ignore[import-not-found]
        ParamsNLGSSM,
        UKFHyperParams,
        unscented_kalman_filter,
    )

    gamma, M, H = reentry.GAMMA, reentry.RADAR_M, reentry.RADAR_H
    sub, h = reentry.SUBSTEPS, reentry.DT / reentry.SUBSTEPS

    def drift(x: Any) -> Any:
        return jnp.stack([-x[1], -jnp.exp(-gamma * x[0]) * x[1] ** 2 * x[2], jnp.zeros_like(x[2])])

    def rk4(_: Any, x: Any) -> Any:
        k1 = drift(x)
        k2 = drift(x + 0.5 * h * k1)
        k3 = drift(x + 0.5 * h * k2)
        k4 = drift(x + h * k3)
        return x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

    def f(x: Any) -> Any:
        # the sub-steps in lax.fori_loop: dynamax's fastest form (unrolled, the traced program
        # grows with the sub-steps and runs several times slower at large batches)
        return jax.lax.fori_loop(0, sub, rk4, x)

    def hx(x: Any) -> Any:
        return jnp.sqrt(M**2 + (x[:1] - H) ** 2)

    dt = jnp.float64 if x64 else jnp.float32
    if linear is None:
        params = ParamsNLGSSM(
            initial_mean=jnp.asarray(reentry.PRIOR_MEAN if m0 is None else m0, dtype=dt),
            initial_covariance=jnp.asarray(
                np.diag(reentry.PRIOR_COV_DIAG) if P0 is None else P0, dtype=dt
            ),
            dynamics_function=f,
            dynamics_covariance=jnp.zeros((3, 3), dtype=dt),
            emission_function=hx,
            emission_covariance=jnp.full((1, 1), reentry.R_VAR, dtype=dt),
        )
    else:
        A, Hm = (jnp.asarray(linear[k].numpy(), dtype=dt) for k in ("A", "H"))
        n = A.shape[0]
        params = ParamsNLGSSM(
            initial_mean=jnp.zeros(n, dtype=dt),
            initial_covariance=jnp.eye(n, dtype=dt),
            dynamics_function=lambda x: A @ x,
            dynamics_covariance=jnp.asarray(linear["Q"].numpy(), dtype=dt),
            emission_function=lambda x: Hm @ x,
            emission_covariance=jnp.asarray(linear["R"].numpy(), dtype=dt),
        )
    hyper = UKFHyperParams(alpha=1.0, beta=0.0, kappa=0.0)

    def one(ys: Any) -> Any:
        post = unscented_kalman_filter(params, ys, hyper)
        return post.marginal_loglik, post.filtered_means, post.filtered_covariances

    fn = jax.jit(one if y.ndim == 2 else jax.vmap(one))
    yj = jax.device_put(jnp.asarray(y, dtype=dt))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(yj))
    first = time.perf_counter() - t0

    def run() -> Any:
        return jax.block_until_ready(fn(yj))

    return run, first


def gpu_benchmark(
    args: argparse.Namespace,
    rows: list[dict[str, Any]],
    record: Callable[..., None],
    variants: list[tuple[bool, str]],
) -> dict[str, Any]:
    """GPU rows (float32): eager, per-step compiled, CUDA graph (eager and compiled); dynamax."""
    out: dict[str, Any] = {"device": torch.cuda.get_device_name(), "errors": []}
    print(f"GPU: {out['device']}, float32, batches {args.gpu_batches}", flush=True)
    big = max(args.gpu_batches)
    sim = reentry.simulate_truth(big, seed=0, dtype=torch.float32)
    y_all = sim.measurements
    for batch in args.gpu_batches:
        yg = y_all[:batch].cuda()
        reps = max(3, args.repeats)
        for compile_, tag in variants:
            try:
                run, first = torchfilt_runner(yg, compile=compile_)
                record(f"torchfilt CKF float32, {tag}", "cuda", batch, timeit(run, reps), first)
            except Exception as e:  # report and go on: one failing row must not lose the rest
                out["errors"].append(f"{tag} batch {batch}: {type(e).__name__}: {e}"[:400])
                print("  ERROR", out["errors"][-1], flush=True)
            try:
                run, first = graphed_runner(yg, compile=compile_)
                record(
                    f"torchfilt CKF float32, {tag} + CUDA graph",
                    "cuda",
                    batch,
                    timeit(run, reps),
                    first,
                )
            except Exception as e:
                out["errors"].append(f"graph {tag} batch {batch}: {type(e).__name__}: {e}"[:400])
                print("  ERROR", out["errors"][-1], flush=True)
        del yg
        torch.cuda.empty_cache()
    if args.no_dynamax or not importlib.util.find_spec("dynamax"):
        out["dynamax"] = "not run (not installed)" if not args.no_dynamax else "skipped"
        return out
    try:
        import jax

        out["dynamax"] = f"dynamax with jax {jax.__version__} on {jax.devices()[0]}"
        # Same computation? Start dynamax from torchfilt's first predicted state (float64 CPU
        # reference) and compare the filtered means of one sequence.
        y0 = y_all[:1].double()
        ref = torchfilt.CKF(reentry.model()).filter(
            y0, x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov()
        )
        run, _ = dynamax_runner(
            y0[0].float().numpy(),
            ref.predicted_mean[0, 0].numpy(),
            ref.predicted_cov[0, 0].numpy(),
        )
        dm = torch.as_tensor(np.array(run()[1]), dtype=torch.float64)
        sd = ref.cov[0].diagonal(dim1=-2, dim2=-1).sqrt()
        diff = ((dm - ref.mean[0]).abs() / sd).amax(0)
        out["dynamax_vs_torchfilt_max_diff_in_sd"] = diff.tolist()
        print(f"  dynamax vs torchfilt (float64), max |diff| / sd per state: {diff.tolist()}")
        for batch in args.gpu_batches:
            yb = y_all[:batch].numpy()
            run, first = dynamax_runner(yb[0] if batch == 1 else yb)
            record(
                "dynamax UKF-as-CKF float32, jit" + (" + vmap" if batch > 1 else ""),
                "cuda",
                batch,
                timeit(run, max(3, args.repeats)),
                first,
            )
    except Exception as e:
        out["errors"].append(f"dynamax: {type(e).__name__}: {e}"[:400])
        print("  ERROR", out["errors"][-1], flush=True)
    for r in rows:
        if r["device"] != "cuda" or r["name"].startswith("dynamax"):
            continue
        ref = next(
            (d for d in rows if d["name"].startswith("dynamax") and d["batch"] == r["batch"]), None
        )
        if ref is not None:
            r["ratio_to_dynamax"] = r["sequence_steps_per_s"] / ref["sequence_steps_per_s"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_filter"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--linear-batch", type=int, default=256, help="batch of the linear n = 8 rows")
    ap.add_argument(
        "--gpu-batches",
        type=int,
        nargs="+",
        default=[1, 1000, 10_000, 100_000],
        help="batch sizes of the GPU rows (float32)",
    )
    ap.add_argument(
        "--gpu-only", action="store_true", help="skip the CPU rows (run on the GPU machine)"
    )
    ap.add_argument(
        "--no-dynamax", action="store_true", help="skip dynamax even if it is importable"
    )
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile rows")
    ap.add_argument("--cckf", action="store_true", help="also run the constrained-CKF benchmark")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    rows: list[dict[str, Any]] = []
    if not args.gpu_only:
        sim = reentry.simulate_truth(max(args.batch, 1), seed=0)
        y1 = sim.measurements[:1]
        yB = sim.measurements[: args.batch]

    def record(
        name: str, device: str, batch: int, seconds: float, first: float | None = None
    ) -> None:
        rows.append(
            {
                "name": name,
                "device": device,
                "batch": batch,
                "seconds_per_run": seconds,
                "us_per_step": seconds / T * 1e6,
                "sequence_steps_per_s": batch * T / seconds,
                "first_call_s": first,
            }
        )
        print(f"  {name:<42} {batch * T / seconds:12.4g} seq-steps/s", flush=True)

    variants = [(False, "eager")] + ([] if args.no_compile else [(True, "torch.compile")])
    cpu_variants: list[tuple[bool | str, str]] = [(False, "eager")]
    if not args.no_compile:
        # compile=True is "auto", which takes "step"
        cpu_variants += [("step", 'compile="step"'), ("loop", 'compile="loop"')]
    have_dynamax = not args.no_dynamax and importlib.util.find_spec("dynamax") is not None
    if not args.gpu_only:
        print(f"Re-entry CKF, T = {T}, float64, {args.threads} CPU thread(s)")
        fp = filterpy_runner(y1[0].numpy())
        record("filterpy CKF (Python-float dynamics)", "cpu", 1, timeit(fp, args.repeats))
        for batch, yb in ((1, y1), (args.batch, yB)):
            reps = args.repeats if batch == 1 else max(3, args.repeats // 2)
            for compile_, tag in cpu_variants:
                run, first = torchfilt_runner(yb, compile=compile_)
                record(f"torchfilt CKF, {tag}", "cpu", batch, timeit(run, reps), first)
                rows[-1]["execution"] = EXECUTIONS.get(id(run))
            if have_dynamax:
                ynp = yb.numpy()
                run, first = dynamax_runner(ynp[0] if batch == 1 else ynp, x64=True)
                name = "dynamax UKF-as-CKF, jit" + (" + vmap" if batch > 1 else "")
                record(name, "cpu", 1 if batch == 1 else batch, timeit(run, reps), first)
        # the model as a user writes it
        user = user_reentry_model()
        for compile_, tag in cpu_variants:
            run, first = torchfilt_runner(y1, compile=compile_, model=user)
            record(
                f"torchfilt CKF, user-written model, {tag}",
                "cpu",
                1,
                timeit(run, args.repeats),
                first,
            )
            rows[-1]["execution"] = EXECUTIONS.get(id(run))
        # linear, n = 8, batch 256
        lin = linear_problem(8, 4, args.linear_batch)
        x0l, P0l = torch.zeros(8, dtype=torch.float64), torch.eye(8, dtype=torch.float64)
        for compile_, tag in cpu_variants:
            run, first = torchfilt_runner(
                lin["y"], compile=compile_, model=lin["model"], x0=x0l, P0=P0l, path="cubature"
            )
            record(
                f"torchfilt CKF, linear n=8, {tag}",
                "cpu",
                args.linear_batch,
                timeit(run, max(3, args.repeats // 2)),
                first,
            )
            rows[-1]["execution"] = EXECUTIONS.get(id(run))
        run, first = torchfilt_runner(lin["y"], compile=False, model=lin["model"], x0=x0l, P0=P0l)
        record(
            "torchfilt exact Kalman path, linear n=8",
            "cpu",
            args.linear_batch,
            timeit(run, max(3, args.repeats // 2)),
            first,
        )
        rows[-1]["execution"] = EXECUTIONS.get(id(run))
        if have_dynamax:
            run, first = dynamax_runner(lin["y"].numpy(), x64=True, linear=lin)
            record(
                "dynamax UKF-as-CKF, linear n=8, jit + vmap",
                "cpu",
                args.linear_batch,
                timeit(run, max(3, args.repeats // 2)),
                first,
            )
        # ratios to the dynamax row of the same problem and batch
        for r in rows:
            if r["device"] != "cpu" or r["name"].startswith("dynamax") or "filterpy" in r["name"]:
                continue
            lin_row = "linear" in r["name"]
            ref = next(
                (
                    d
                    for d in rows
                    if d["name"].startswith("dynamax")
                    and d["device"] == "cpu"
                    and d["batch"] == r["batch"]
                    and ("linear" in d["name"]) == lin_row
                ),
                None,
            )
            if ref is not None:
                r["ratio_to_dynamax"] = r["sequence_steps_per_s"] / ref["sequence_steps_per_s"]

    gpu: dict[str, Any] = {}
    if torch.cuda.is_available():
        gpu = gpu_benchmark(args, rows, record, variants)
    else:
        gpu["note"] = "not measured: no CUDA device on this machine"
        print("  GPU rows: not measured (no CUDA device)")

    dynamax = "installed" if importlib.util.find_spec("dynamax") else "not installed"
    if "dynamax" in gpu:
        dynamax = gpu["dynamax"]

    cckf: dict[str, Any] | None = None
    if args.cckf:
        from bench_cckf import run_cckf_benchmark  # type: ignore[import-not-found]

        cckf = run_cckf_benchmark(repeats=max(3, args.repeats))

    fp_rate = next((r["sequence_steps_per_s"] for r in rows if "filterpy" in r["name"]), None)
    for r in rows:
        r["ratio_to_filterpy"] = None if fp_rate is None else r["sequence_steps_per_s"] / fp_rate
    print()
    print(
        table(
            [
                "implementation",
                "device",
                "batch",
                "us/step",
                "seq-steps/s",
                "x filterpy",
                "x dynamax",
                "first call s",
            ],
            [
                [
                    r["name"],
                    r["device"],
                    r["batch"],
                    r["us_per_step"],
                    r["sequence_steps_per_s"],
                    "" if r["ratio_to_filterpy"] is None else r["ratio_to_filterpy"],
                    r.get("ratio_to_dynamax", ""),
                    "" if r["first_call_s"] is None else r["first_call_s"],
                ]
                for r in rows
            ],
        )
    )
    payload = {
        "benchmark": "reentry CKF throughput",
        "steps": T,
        "substeps": reentry.SUBSTEPS,
        "dtype": "float64 (CPU), float32 (GPU)",
        "gpu_timing": "median of --repeats runs after a warm-up; torch.cuda.synchronize / "
        "jax.block_until_ready before the clock is read",
        "rows": rows,
        "gpu": gpu,
        "dynamax": dynamax,
        "cckf": cckf,
        "environment": environment(),
    }
    write_json(args.out / "results.json", payload)
    print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
