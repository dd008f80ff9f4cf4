"""GP-model CKF on the re-entry problem: frozen predictor vs GPyTorch, variance forms, training time.

For each training-set size S (default 500, 2000, 5000) the script records S transition pairs with
:func:`torchfilt.systems.reentry.record_training_data` (trajectories from the filter's prior), fits
an exact GP transition (increment form, all three states) and an exact GP measurement (altitude
only), and filters one measurement sequence (T = 60) with the CKF (float64, law of total variance).
All of it in one run:

* **GPyTorch eval** — the same models called through GPyTorch in eval mode at every step, with
  the exact settings the product trains with (``exact``) and with GPyTorch's defaults plus LOVE
  (``fast_pred_var``, its fastest path; its means and variances are checked against exact ones).
* **frozen** — the plain-torch frozen predictor with each variance form: ``exact`` (cached
  Cholesky), ``lowrank`` (rank 32/128/512), ``auto`` (per model the smallest rank within 5 % of
  the exact variance on validation points, else exact), and ``sparse`` (an SVGP's own
  inducing-point variance, 256 inducing points, as an approximation of the exact GP).
* The variance error of each form is measured at the cubature points the filter actually visits
  (relative to the exact predictive variance, latent + noise); the fastest form whose maximum
  error stays below 5 % is the "chosen" one, and the headline speed-up is against GPyTorch with it.
* Training: the product recipe (hyperparameters on a random 1000-row subset, 150 Adam iterations,
  then conditioning on all S rows) and the per-iteration time of the exact marginal likelihood on
  all S rows.

GPU rows are reported as not measured when no CUDA device is present.

    PYTHONPATH=. python scripts/bench_gp_filter.py --out out/bench_gp
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit

from torchfilt import CKF, StateSpaceModel
from torchfilt.models import ConditionalModel, Prediction
from torchfilt.models.gp import GPMeasurement, GPModel, GPTransition
from torchfilt.pipeline.recipe import fit_options
from torchfilt.systems import reentry

DT = torch.float64
T = reentry.STEPS
#: Variance error below which a form counts as accurate (relative to the predictive variance).
VAR_TOL = 0.05
#: The product's training recipe.
RECIPE = {"iterations": 150, "lr": 0.05, "subset": 1000}
#: the recipe as the GP fits' keywords (``lr`` is the field of ``optimizer=``)
FIT: dict[str, Any] = {"subset": RECIPE["subset"], **fit_options(RECIPE, "gp")}
LOWRANKS = (32, 128, 512)
#: the variance forms of the GPU filter rows, in order (``--gpu-forms``)
GPU_FORMS = ["auto", "auto-float32", "lowrank-128", "lowrank-512", "sparse"]


# --------------------------------------------------------------------------- helpers
class GPyTorchEval(ConditionalModel):
    """A GP model called through GPyTorch in eval mode at every step (the baseline)."""

    def __init__(self, model: GPModel, fast_pred_var: bool) -> None:
        super().__init__()
        self.model = model
        self.fast = fast_pred_var
        self.out_dim, self.in_dim = model.out_dim, model.in_dim

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        return self.model.predict_gpytorch(x, u, fast_pred_var=self.fast)


class Recorder(ConditionalModel):
    """Passes through and keeps the points the filter evaluates."""

    def __init__(self, model: ConditionalModel) -> None:
        super().__init__()
        self.model = model
        self.out_dim, self.in_dim = model.out_dim, model.in_dim
        self.points: list[Tensor] = []

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        self.points.append(x.detach().reshape(-1, x.shape[-1]).clone())
        return self.model.predict(x, u)


def rel_err(a: Tensor, ref: Tensor) -> tuple[float, float]:
    """Max and 99th-percentile relative error over entries with a positive reference."""
    mask = ref > 0
    r = ((a - ref).abs() / ref)[mask]
    return float(r.max()), float(torch.quantile(r, 0.99))


# --------------------------------------------------------------------------- one size
def bench_size(S: int, args: argparse.Namespace, seq: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"S": S}
    rec = reentry.record_training_data(S, seed=args.seed)
    out["recording"] = {"recordings": len(rec.states), "rejected": rec.rejected}
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT)
    P0 = reentry.prior_cov()
    y = seq.measurements[0]

    # ---- training (product recipe), and per-iteration time of the full exact MLL
    t0 = time.perf_counter()
    f = GPTransition.fit(rec.states, increment=True, progress=False, variance="exact", **FIT)
    t_f = time.perf_counter() - t0
    t0 = time.perf_counter()
    h = GPMeasurement.fit(
        rec.states, rec.measurements, inputs=[0], progress=False, variance="exact", **FIT
    )
    t_h = time.perf_counter() - t0
    full_iters = args.full_iters
    t0 = time.perf_counter()
    f_full = GPTransition.fit(
        rec.states,
        increment=True,
        iterations=full_iters,
        subset=None,
        progress=False,
        variance="exact",
    )
    per_iter = (time.perf_counter() - t0) / max(full_iters, 1)
    del f_full
    out["training"] = {
        "recipe": RECIPE,
        "recipe_seconds_f": t_f,
        "recipe_seconds_h": t_h,
        "full_exact_mll_seconds_per_iteration_f": per_iter,
        "full_iterations_timed": full_iters,
        "noise_sd_h_ft": float(h.noise_variance.sqrt()),
        "noise_sd_f": f.noise_variance.sqrt().tolist(),
    }

    # ---- the cubature points the filter visits (frozen exact), and its accuracy
    rf, rh = Recorder(f), Recorder(h)
    res = CKF(StateSpaceModel(rf, rh)).filter(y, x0=x0, P0=P0)
    err = (res.mean - seq.states[0]).pow(2).mean(0).sqrt()
    out["filter_rmse_exact"] = err.tolist()
    Xf, Xh = torch.cat(rf.points), torch.cat(rh.points)
    with torch.no_grad():
        exact_f, exact_h = f.predict(Xf), h.predict(Xh)

    # ---- variance forms: accuracy at the visited points, per-call and per-step time
    six = Xf[:6].clone()
    forms: list[dict[str, Any]] = []

    def add_form(name: str, fm: ConditionalModel, hm: ConditionalModel, build_s: float) -> None:
        with torch.no_grad():
            pf, ph = fm.predict(Xf), hm.predict(Xh)
            call_f = timeit(lambda: fm.predict(six), args.repeats * 20)
            call_h = timeit(lambda: hm.predict(six), args.repeats * 20)
            ckf = CKF(StateSpaceModel(fm, hm))
            step = timeit(lambda: ckf.filter(y, x0=x0, P0=P0), args.repeats) / T
        vf = rel_err(pf.var, exact_f.var)
        vh = rel_err(ph.var, exact_h.var)
        mean_err_f = float(
            ((pf.mean - exact_f.mean).abs() / exact_f.var.sqrt().clamp_min(1e-300))[
                exact_f.var > 0
            ].max()
        )
        forms.append(
            {
                "form": name,
                "forms_f": getattr(fm, "variance_forms", None),
                "forms_h": getattr(hm, "variance_forms", None),
                "var_err_max_f": vf[0],
                "var_err_p99_f": vf[1],
                "var_err_max_h": vh[0],
                "var_err_p99_h": vh[1],
                "mean_err_f_in_sd": mean_err_f,
                "call_ms_f": call_f * 1e3,
                "call_ms_h": call_h * 1e3,
                "step_ms": step * 1e3,
                "steps_per_s": 1.0 / step,
                "build_s": build_s,
            }
        )
        print(
            f"  S={S} {name}: {step * 1e3:.3f} ms/step, var err f {vf[0]:.3g} h {vh[0]:.3g}",
            flush=True,
        )

    add_form("frozen exact", f, h, 0.0)
    for r in LOWRANKS:
        if r >= S:
            continue
        t0 = time.perf_counter()
        f.freeze("lowrank", rank=r)
        h.freeze("lowrank", rank=r)
        add_form(f"frozen lowrank {r}", f, h, time.perf_counter() - t0)
    t0 = time.perf_counter()
    f.freeze("auto")
    h.freeze("auto")
    add_form("frozen auto", f, h, time.perf_counter() - t0)
    if args.sparse:
        t0 = time.perf_counter()
        fs = GPTransition.fit(
            rec.states,
            increment=True,
            structure="sparse",
            num_inducing=256,
            iterations=args.sparse_iters,
            progress=False,
        )
        hs = GPMeasurement.fit(
            rec.states,
            rec.measurements,
            inputs=[0],
            structure="sparse",
            num_inducing=256,
            iterations=args.sparse_iters,
            progress=False,
        )
        add_form("frozen sparse (SVGP 256)", fs, hs, time.perf_counter() - t0)

    # ---- GPyTorch every step (exact settings; and defaults + LOVE)
    f.freeze("exact")
    h.freeze("exact")
    gpy: list[dict[str, Any]] = []
    for fast in (True, False):
        name = "gpytorch fast_pred_var" if fast else "gpytorch exact"
        ef, eh = GPyTorchEval(f, fast), GPyTorchEval(h, fast)
        steps = T if (fast or S <= args.gpytorch_exact_max_full) else args.gpytorch_exact_steps
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # GPyTorch's CG warnings under its defaults
            ckf = CKF(StateSpaceModel(ef, eh))
            step = (
                timeit(
                    lambda ckf=ckf, steps=steps: ckf.filter(y[:steps], x0=x0, P0=P0),
                    1 if not fast else args.repeats,
                    warmup=1 if fast else 0,
                )
                / steps
            )
            call_f = timeit(lambda ef=ef: ef.predict(six), 3 if not fast else args.repeats * 10)
            pf = ef.predict(Xf[: args.accuracy_points])
            ph = eh.predict(Xh[: args.accuracy_points])
        n = pf.mean.shape[0]
        vf = rel_err(pf.var, exact_f.var[:n])
        vh = rel_err(ph.var, exact_h.var[:n])
        mean_err = float(
            ((pf.mean - exact_f.mean[:n]).abs() / exact_f.var[:n].sqrt().clamp_min(1e-300))[
                exact_f.var[:n] > 0
            ].max()
        )
        gpy.append(
            {
                "form": name,
                "steps_timed": steps,
                "step_ms": step * 1e3,
                "call_ms_f": call_f * 1e3,
                "var_err_max_f": vf[0],
                "var_err_max_h": vh[0],
                "mean_err_f_in_sd": mean_err,
            }
        )
        print(f"  S={S} {name}: {step * 1e3:.3f} ms/step", flush=True)

    # ---- the chosen form and the speed-up
    ok = [r for r in forms if r["var_err_max_f"] < VAR_TOL and r["var_err_max_h"] < VAR_TOL]
    chosen = min(ok, key=lambda r: r["step_ms"]) if ok else None
    out["forms"] = forms
    out["gpytorch"] = gpy
    if chosen is not None:
        out["chosen"] = chosen["form"]
        for g in gpy:
            g["speedup_of_chosen"] = g["step_ms"] / chosen["step_ms"]
    fastest = min(forms, key=lambda r: r["step_ms"])
    out["fastest_any"] = fastest["form"]
    for g in gpy:
        g["speedup_of_fastest_any"] = g["step_ms"] / fastest["step_ms"]

    # ---- one sequence with torch.compile of the step (chosen form)
    if args.compile and chosen is not None:
        try:
            name = chosen["form"]
            if "lowrank" in name:
                r = int(name.split()[-1])
                f.freeze("lowrank", rank=r)
                h.freeze("lowrank", rank=r)
            elif "auto" in name:
                f.freeze("auto")
                h.freeze("auto")
            ckf = CKF(StateSpaceModel(f, h), compile=True)
            t0 = time.perf_counter()
            with torch.no_grad():
                ckf.filter(y, x0=x0, P0=P0)
            compile_s = time.perf_counter() - t0
            with torch.no_grad():
                step = timeit(lambda: ckf.filter(y, x0=x0, P0=P0), args.repeats, warmup=0) / T
            out["compiled"] = {
                "form": name,
                "step_ms": step * 1e3,
                "steps_per_s": 1 / step,
                "compile_s": compile_s,
            }
        except Exception as exc:  # report, don't abort the benchmark
            out["compiled"] = {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}

    # ---- one sequence, compiled, with the inducing-point (SVGP) predictor
    if args.compile and args.sparse:
        try:
            ckf = CKF(StateSpaceModel(fs, hs), compile=True)
            t0 = time.perf_counter()
            with torch.no_grad():
                res = ckf.filter(y, x0=x0, P0=P0)
            compile_s = time.perf_counter() - t0
            with torch.no_grad():
                step = timeit(lambda: ckf.filter(y, x0=x0, P0=P0), args.repeats, warmup=0) / T
            out["compiled_sparse"] = {
                "form": "frozen sparse (SVGP 256)",
                "step_ms": step * 1e3,
                "steps_per_s": 1 / step,
                "compile_s": compile_s,
                "filter_rmse": (res.mean - seq.states[0]).pow(2).mean(0).sqrt().tolist(),
            }
        except Exception as exc:
            out["compiled_sparse"] = {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}
    return out


# --------------------------------------------------------------------------- GPU
def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _sync_time(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> float:
    def run() -> None:
        fn()
        _sync()

    return timeit(run, repeats, warmup)


def gpu_filter(args: argparse.Namespace) -> dict[str, Any]:
    """Batch of ``--gpu-batch`` sequences, S = ``--gpu-S``, float32, on the GPU."""
    S, B, dev = args.gpu_S, args.gpu_batch, args.device
    out: dict[str, Any] = {"S": S, "batch": B, "dtype": "float32", "rows": [], "errors": []}
    out["device"] = torch.cuda.get_device_name() if dev == "cuda" else dev
    rec = reentry.record_training_data(S, seed=args.seed)
    t0 = time.perf_counter()
    f = GPTransition.fit(rec.states, increment=True, progress=False, device=dev, **FIT)
    h = GPMeasurement.fit(
        rec.states, rec.measurements, inputs=[0], progress=False, device=dev, **FIT
    )
    _sync()
    out["train_seconds_f_and_h_gpu_float64"] = time.perf_counter() - t0
    sim = reentry.simulate_truth(B, seed=1, dtype=torch.float32)
    y = sim.measurements.to(dev)
    x0 = torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float32, device=dev)
    P0 = reentry.prior_cov(torch.float32).to(dev)
    # float64 reference on a few sequences (CPU copy of the float64 exact model)
    ref_n = min(B, 32)
    fc, hc = copy.deepcopy(f).to("cpu"), copy.deepcopy(h).to("cpu")
    for m in (fc, hc):
        m.freeze("exact")
    with torch.no_grad():
        ref = CKF(StateSpaceModel(fc, hc)).filter(
            sim.measurements[:ref_n].double(), x0=x0.double().cpu(), P0=P0.double().cpu()
        )
    # (variance form, rank, model dtype, [(compile, CUDA graph), ...]). The filter is float32
    # throughout; a float64 model keeps the GP's kernel sums in float64 (a float32 GP predictor
    # loses accuracy: alpha = (K + s^2 I)^-1 y is large when the noise is small).
    every = [(False, False), (True, False), (False, True), (True, True)]
    best = [(True, True)]
    plans = {
        "auto": ("auto", None, torch.float64, best if args.gpu_quick else every),
        "auto-float32": ("auto", None, torch.float32, best),
        "lowrank-128": ("lowrank", 128, torch.float64, best),
        "lowrank-512": ("lowrank", 512, torch.float64, best),
        "sparse": ("sparse", 256, torch.float64, best),
        # not in the default set: the exact cached-Cholesky form alone (scripts/gpu_check.py)
        "exact": ("exact", None, torch.float64, best if args.gpu_quick else every),
    }
    plan = [plans[name] for name in args.gpu_forms]
    sparse_models: tuple[GPModel, GPModel] | None = None
    for variance, rank, mdtype, variants in plan:
        name = f"{variance}" + (f" {rank}" if rank else "") + f", model {str(mdtype)[6:]}"
        try:
            if variance == "sparse":
                # An SVGP of the same S rows, its own inducing-point variance (O(M^2) per point).
                if sparse_models is None:
                    t0 = time.perf_counter()
                    opts = dict(
                        structure="sparse",
                        num_inducing=rank,
                        iterations=args.sparse_iters,
                        progress=False,
                        device=dev,
                        chunk_size=args.gpu_chunk,
                    )
                    fs = GPTransition.fit(rec.states, increment=True, **opts)
                    hs = GPMeasurement.fit(rec.states, rec.measurements, inputs=[0], **opts)
                    sparse_models = (fs, hs)
                    out["sparse_train_s"] = time.perf_counter() - t0
                fm, hm = sparse_models
            else:
                for m in (f, h):
                    m.to(torch.float64).freeze(variance, rank=rank, chunk_size=args.gpu_chunk)
                    m.to(mdtype)
                fm, hm = f, h
            out_forms = {"f": fm.variance_forms, "h": hm.variance_forms}
            model = StateSpaceModel(fm, hm)
            for compile_, graph in variants if dev == "cuda" else variants[:1]:
                tag = (
                    f"{name}, "
                    + ("compiled" if compile_ else "eager")
                    + (" + CUDA graph" if graph else "")
                )
                try:
                    ckf = CKF(model, compile=compile_)
                    t0 = time.perf_counter()
                    with torch.no_grad(), warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        if graph:
                            g = ckf.graphed(y, x0=x0, P0=P0)
                            run = lambda g=g: g.filter(y, clone=False)  # noqa: E731
                        else:
                            run = lambda ckf=ckf: ckf.filter(y, x0=x0, P0=P0)  # noqa: E731
                        res = run()
                        _sync()
                        first = time.perf_counter() - t0
                        sec = _sync_time(run, args.repeats)
                    got = res.mean[:ref_n].double().cpu()
                    ok = torch.isfinite(ref.mean).all(-1).all(-1)
                    sd = ref.cov.diagonal(dim1=-2, dim2=-1).sqrt()[ok].clamp_min(1e-30)
                    rel = ((got - ref.mean)[ok].abs() / sd).amax()
                    fin = torch.isfinite(res.mean).all(-1).all(-1)
                    finite = float(fin.float().mean())
                    err = res.mean[fin].double().cpu() - sim.states[fin.cpu()].double()
                    rmse = err.pow(2).mean(0).sqrt().mean(0).tolist()  # time-averaged RMS
                    row = {
                        "predictor": tag,
                        "model_dtype": str(mdtype),
                        "forms": out_forms,
                        "seconds_per_run": sec,
                        "sequence_steps_per_s": B * T / sec,
                        "first_call_s": first,
                        "finite_fraction": finite,
                        "rmse_vs_truth": rmse,
                        "max_diff_vs_float64_exact_in_sd": float(rel),
                    }
                    out["rows"].append(row)
                    print(
                        f"  GPU S={S} batch={B} {tag}: {B * T / sec:.4g} seq-steps/s, "
                        f"diff vs float64 exact {float(rel):.2g} sd",
                        flush=True,
                    )
                except Exception as e:
                    out["errors"].append(f"{tag}: {type(e).__name__}: {e}"[:400])
                    print("  ERROR", out["errors"][-1], flush=True)
                if dev == "cuda":
                    torch.cuda.empty_cache()
        except Exception as e:
            out["errors"].append(f"{name}: {type(e).__name__}: {e}"[:400])
            print("  ERROR", out["errors"][-1], flush=True)
    return out


def gpu_svgp(args: argparse.Namespace) -> dict[str, Any]:
    """SVGP transition model on ``--svgp-n`` re-entry transitions, trained on the GPU."""
    N, held, dev = args.svgp_n, args.svgp_n // 10, args.device
    t0 = time.perf_counter()
    rec = reentry.record_training_data(N + held, seed=args.seed + 1, batch=1 << 17, device=dev)
    gen_s = time.perf_counter() - t0
    x = torch.cat([s[:-1] for s in rec.states])
    xn = torch.cat([s[1:] for s in rec.states])
    perm = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))
    tr, te = perm[:N], perm[N:]
    out: dict[str, Any] = {"transitions": N, "held_out": int(te.numel()), "generate_s": gen_s}
    t0 = time.perf_counter()
    model = GPTransition.fit(
        x[tr],
        None,
        xn[tr],
        increment=True,
        structure="sparse",
        num_inducing=args.svgp_inducing,
        batch_size=args.svgp_batch,
        iterations=args.svgp_iters,
        device=dev,
        progress=False,
    )
    _sync()
    out["train_s"] = time.perf_counter() - t0
    out.update(inducing=args.svgp_inducing, batch_size=args.svgp_batch, iterations=args.svgp_iters)
    with torch.no_grad():
        pred = model.predict(x[te].to(dev)).mean.cpu()
    err = pred - xn[te]
    out["one_step_rmse"] = err.pow(2).mean(0).sqrt().tolist()
    out["one_step_rmse_no_change_baseline"] = (x[te] - xn[te]).pow(2).mean(0).sqrt().tolist()
    out["target_sd"] = (xn[te] - x[te]).std(0).tolist()
    print(
        f"  SVGP on {N} transitions: {out['train_s']:.1f} s, one-step RMSE {out['one_step_rmse']}",
        flush=True,
    )
    return out


# --------------------------------------------------------------------------- main
def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[500, 2000, 5000])
    p.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (default 2)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--full-iters",
        type=int,
        default=3,
        help="iterations timed for the full-data exact marginal likelihood",
    )
    p.add_argument(
        "--gpytorch-exact-max-full",
        type=int,
        default=2000,
        help="largest S at which GPyTorch-exact runs all T steps (else a few)",
    )
    p.add_argument("--gpytorch-exact-steps", type=int, default=3)
    p.add_argument(
        "--accuracy-points",
        type=int,
        default=120,
        help="visited points at which GPyTorch's own variances are checked",
    )
    p.add_argument("--no-sparse", dest="sparse", action="store_false")
    p.add_argument("--sparse-iters", type=int, default=300)
    p.add_argument("--no-compile", dest="compile", action="store_false")
    p.add_argument("--out", type=Path, default=Path("out/bench_gp"))
    p.add_argument("--gpu-only", action="store_true", help="skip the CPU sizes")
    p.add_argument("--gpu-S", type=int, default=2000)
    p.add_argument("--gpu-batch", type=int, default=10_000)
    p.add_argument("--gpu-chunk", type=int, default=1 << 16, help="points per kernel chunk")
    p.add_argument("--gpu-quick", action="store_true", help="compiled + CUDA graph rows only")
    p.add_argument(
        "--gpu-forms",
        nargs="+",
        choices=[*GPU_FORMS, "exact"],
        default=GPU_FORMS,
        help="variance forms of the GPU filter rows (default: all but exact)",
    )
    p.add_argument("--no-svgp", dest="svgp", action="store_false", help="skip the 1e6 SVGP")
    p.add_argument("--svgp-n", type=int, default=1_000_000)
    p.add_argument("--svgp-inducing", type=int, default=512)
    p.add_argument("--svgp-batch", type=int, default=4096)
    p.add_argument("--svgp-iters", type=int, default=3000)
    p.add_argument("--device", default="cuda", help="device of the GPU section (cpu: smoke test)")
    p.add_argument("--force-gpu-section", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    seq = reentry.simulate_truth(1, seed=1)
    results: dict[str, Any] = {"environment": environment(), "sizes": []}
    if not args.gpu_only:
        for S in args.sizes:
            print(f"S = {S} ...", flush=True)
            results["sizes"].append(bench_size(S, args, seq))
    if torch.cuda.is_available() or args.force_gpu_section:
        results["gpu"] = {}
        sections = [("filter", gpu_filter)] + ([("svgp", gpu_svgp)] if args.svgp else [])
        for key, fn in sections:
            try:
                results["gpu"][key] = fn(args)
            except Exception as e:  # keep the other section's figures
                results["gpu"][key] = {"error": f"{type(e).__name__}: {e}"[:600]}
                print("  ERROR", results["gpu"][key]["error"], flush=True)
    else:
        results["gpu"] = "not measured (no GPU lent)"
    print_report(results)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    print(f"\nwrote {args.out / 'results.json'}")
    return results


def print_report(results: dict[str, Any]) -> None:
    print_gpu_report(results["gpu"])
    if not results["sizes"]:
        return
    env = results["environment"]
    print(
        f"\nre-entry, T = {T}, float64, CPU, {env['threads']} torch threads, "
        f"load average {env['load_average'][0]:.1f}"
    )
    rows = []
    for r in results["sizes"]:
        for fm in r["forms"]:
            rows.append(
                [
                    r["S"],
                    fm["form"],
                    fm["step_ms"],
                    fm["steps_per_s"],
                    fm["call_ms_f"],
                    fm["call_ms_h"],
                    fm["var_err_max_f"],
                    fm["var_err_p99_f"],
                    fm["var_err_max_h"],
                    str(fm["forms_f"]),
                ]
            )
        for g in r["gpytorch"]:
            rows.append(
                [
                    r["S"],
                    g["form"] + f" ({g['steps_timed']} steps)",
                    g["step_ms"],
                    1e3 / g["step_ms"],
                    g["call_ms_f"],
                    None,
                    g["var_err_max_f"],
                    None,
                    g["var_err_max_h"],
                    f"mean err {g['mean_err_f_in_sd']:.2g} sd",
                ]
            )
    print(
        table(
            [
                "S",
                "predictor",
                "ms/step",
                "steps/s",
                "f ms/call",
                "h ms/call",
                "var err f max",
                "f p99",
                "var err h max",
                "forms / note",
            ],
            rows,
        )
    )
    print()
    rows = []
    for r in results["sizes"]:
        g = {x["form"]: x for x in r["gpytorch"]}
        rows.append(
            [
                r["S"],
                r.get("chosen"),
                g["gpytorch fast_pred_var"].get("speedup_of_chosen"),
                g["gpytorch exact"].get("speedup_of_chosen"),
                r["fastest_any"],
                g["gpytorch fast_pred_var"]["speedup_of_fastest_any"],
                r.get("compiled", {}).get("steps_per_s"),
                r.get("compiled_sparse", {}).get("steps_per_s"),
                r["training"]["recipe_seconds_f"],
                r["training"]["full_exact_mll_seconds_per_iteration_f"],
                str([round(v, 2) for v in r["filter_rmse_exact"]]),
            ]
        )
    print(
        table(
            [
                "S",
                "chosen (var err < 5%)",
                "x vs LOVE",
                "x vs GPyTorch exact",
                "fastest any",
                "x vs LOVE",
                "compiled steps/s",
                "compiled SVGP steps/s",
                "train f recipe s",
                "exact MLL s/iter (f)",
                "RMSE (exact)",
            ],
            rows,
        )
    )


def print_gpu_report(gpu: Any) -> None:
    if not isinstance(gpu, dict):
        print(f"GPU (batch of 1e4 sequences, S = 2000, float32; SVGP on 1e6 transitions): {gpu}")
        return
    flt = gpu.get("filter", {})
    if flt.get("rows"):
        print(
            f"\nGPU {flt.get('device')}: GP-model CKF, S = {flt['S']}, "
            f"batch {flt['batch']}, float32, T = {T}"
        )
        print(
            table(
                [
                    "predictor",
                    "seq-steps/s",
                    "s/run",
                    "first call s",
                    "finite",
                    "diff vs f64 (sd)",
                    "RMSE x1, x2, x3",
                ],
                [
                    [
                        r["predictor"],
                        r["sequence_steps_per_s"],
                        r["seconds_per_run"],
                        r["first_call_s"],
                        r["finite_fraction"],
                        r["max_diff_vs_float64_exact_in_sd"],
                        ", ".join(f"{v:.3g}" for v in r["rmse_vs_truth"]),
                    ]
                    for r in flt["rows"]
                ],
            )
        )
    for e in flt.get("errors", []) + ([flt["error"]] if "error" in flt else []):
        print("  error:", e)
    sv = gpu.get("svgp", {})
    if "train_s" in sv:
        print(
            f"\nSVGP on {sv['transitions']} transitions ({sv['inducing']} inducing, batch "
            f"{sv['batch_size']}, {sv['iterations']} iterations): {sv['train_s']:.1f} s; one-step "
            f"RMSE {[round(v, 4) for v in sv['one_step_rmse']]} (no-change baseline "
            f"{[round(v, 4) for v in sv['one_step_rmse_no_change_baseline']]})"
        )
    elif sv:
        print("  SVGP error:", sv.get("error"))


if __name__ == "__main__":
    main()
