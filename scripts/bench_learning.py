"""Learning: likelihood gradients and EM, torchfilt against dynamax and pykalman (issue 27 s.2).

Every peer runs in the same invocation, one thread each, pinned to the same core, float64, CPU:
torch with ``torch.set_num_threads(1)``; dynamax (jitted, in a separate JAX Python given by
``--jax-python``: ``scripts/_dynamax_learning_peer.py``) with
``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``; pykalman in the
same JAX Python. Models are written as a user would: a ``LinearGaussianModel`` with an
``nn.Parameter`` ``A`` and ``CholeskyCovariance`` noises; the re-entry and 2A -> B transitions
as ``nn.Module`` s with a learnable constant.

    python scripts/bench_learning.py --out out/bench_learning --jax-python /work/wt/jaxenv/bin/python

Rows (seconds; ``ratio`` = torchfilt / peer, < 1: torchfilt is faster):

* ``linear grad``: one log-likelihood + gradient w.r.t. ``(A, Q, R)`` of a 4-state, 2-output
  linear-Gaussian model, 20 recordings x 500 steps (torchfilt's exact path, ``kalman_filter``
  then ``backward``; dynamax's ``jit(value_and_grad)`` of ``vmap(lgssm_filter)``);
* ``linear EM iteration``: one EM iteration on the same data (torchfilt ``fit_em`` with
  ``accelerate=False``: median of its per-iteration times; dynamax: one jitted ``e_step`` +
  ``m_step``; pykalman: ``em(n_iter=1)`` on the first recording, pykalman fits one sequence);
* ``linear time to optimum``: seconds until the log-likelihood is within 0.1 nats per sequence
  of the optimum (columns ``torchfilt s`` / ``dynamax s``; ``None``: never in the run). The
  optimum is the likelihood maximised by 60 L-BFGS iterations on the exact likelihood, untimed
  (``optimum_per_sequence`` in the JSON), or the best any method on the 20 recordings reaches
  if that is higher. Beside it: the time to within 0.1 of the method's *own* best (``to own best
  s``: rewards a method that stops early on a flat ridge) and to the level dynamax's EM ends at
  (``to dynamax's s``: who gets there first). torchfilt ``fit_em`` runs plain
  (``accelerate=False``) and with its default SQUAREM (one row per iteration: a cycle of three
  E-steps or more), ``fit_likelihood`` with L-BFGS; both learn ``A, Q, R`` with ``H`` known;
  dynamax's EM learns ``H`` too (its M-step is all or nothing; ``H`` adds only a change of state
  coordinates) and holds the first step's prior at the start's ``A`` (see the peer), so its
  optimum can differ slightly from the reference's; pykalman
  learns ``A, Q, R`` on one recording (own best only). Every EM runs its whole budget (no
  stopping rule): 1500 iterations (``--em-iterations``; pykalman's 300,
  ``--pykalman-iterations``), as dynamax's EM needs about 1400 to come within 0.1 nats per
  sequence of the optimum;
* ``reentry grad``: one log-likelihood + gradient w.r.t. the air-density decay and the diagonal
  ``Q`` of the re-entry model (RK4, 10 sub-steps), 64 windows x 100 steps (torchfilt's CKF;
  dynamax's UKF with ``alpha=1, beta=0, kappa=0``, which is the cubature rule, RK4 sub-steps in
  ``jax.lax.fori_loop``, the peer's fastest form);
* ``reentry grad`` with ``CKF(compile=True)`` (row ``reentry-compiled``): the same with the
  filter's step compiled (under autograd the plan compiles one step, forward and backward, and
  runs it at every step); ``torchfilt_compile_s`` in the JSON is its first call less a timed one;
* ``2A->B EM iteration``: one EM iteration on the 2A -> B reaction (learnable rate constant,
  ``Q`` and ``R``), 8 recordings x 400 steps (torchfilt only: no peer has EM for a nonlinear
  model), eager and with ``fit_em(compile="loop")`` (the filter's time loop compiled; its
  first compile is in the first iteration, so the median per-iteration time leaves it out and
  ``total_s`` keeps it).

Run it with ``TORCHINDUCTOR_CACHE_DIR`` set to an empty folder: the compiled re-entry row's
first call is then the cold compile (a warm cache from an earlier run makes it a few seconds).

``--quick`` runs tiny sizes (a smoke test). ``compile_s`` is the peer's first (compiling) call; ``rel diff`` the relative difference of
the peer's log-likelihood from torchfilt's (``grad_rel_diff`` in the JSON: of the gradient).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json
from bench_reaction_em import problem as reaction_problem

import torchfilt
from torchfilt.filters import CKF, kalman_filter
from torchfilt.models import CholeskyCovariance, DiagonalCovariance
from torchfilt.optim import StoppingOptions
from torchfilt.systems import reentry
from torchfilt.training import fit_em, fit_likelihood

PEER = Path(__file__).resolve().parent / "_dynamax_learning_peer.py"
D = torch.float64
#: "at the optimum": within this many nats per sequence of the method's best log-likelihood
NATS_PER_SEQUENCE = 0.1


# ----------------------------------------------------------------------------------- problems
def linear_problem(B: int, T: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A 4-state, 2-output model, data simulated from it, and a start ``(A, Q, R)`` off it."""
    rng = np.random.default_rng(seed)
    n, m = 4, 2
    A = rng.standard_normal((n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    Q, R = 0.1 * np.eye(n), 0.2 * np.eye(m)
    x = rng.multivariate_normal(np.zeros(n), np.eye(n), size=B)
    y = np.empty((B, T, m))
    for t in range(T):
        x = x @ A.T + rng.multivariate_normal(np.zeros(n), Q, size=B)
        y[:, t] = x @ H.T + rng.multivariate_normal(np.zeros(m), R, size=B)
    A_start = 0.5 * A + 0.2 * np.eye(n)
    return dict(
        A=A_start, H=H, Q=0.3 * np.eye(n), R=0.5 * np.eye(m), m0=np.zeros(n), P0=np.eye(n), y=y
    )


def learnable(model: torchfilt.LinearGaussianModel) -> list[Tensor]:
    """``A`` and the noises' parameters, each once (``A`` is among ``model.parameters()`` when
    the model registers the ``nn.Parameter`` it was given, and not when it keeps a buffer)."""
    out: list[Tensor] = []
    for t in [model.A, *model.parameters()]:
        if all(t is not o for o in out):
            out.append(t)
    return out


def linear_model(p: dict[str, np.ndarray]) -> torchfilt.LinearGaussianModel:
    """The learnable model a user writes: ``A`` a parameter, ``Q`` and ``R`` Cholesky factors."""
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    return torchfilt.LinearGaussianModel(
        nn.Parameter(t(p["A"])), t(p["H"]), CholeskyCovariance(t(p["Q"])),
        CholeskyCovariance(t(p["R"])),
    )  # fmt: skip


class ReentryTransition(nn.Module):
    """The re-entry dynamics with a learnable air-density decay (RK4, 10 sub-steps)."""

    def __init__(self, gamma: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.tensor(gamma, dtype=D))

    def forward(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        return reentry.transition(x, gamma=self.gamma)


def reentry_problem(B: int, T: int) -> tuple[torchfilt.StateSpaceModel, dict[str, Any]]:
    sim = reentry.simulate_truth(B, steps=T, seed=0)
    q = torch.tensor([1e2, 1e2, 1e-8], dtype=D)
    model = torchfilt.StateSpaceModel(
        ReentryTransition(1.1 * reentry.GAMMA),
        reentry.measurement,
        Q=DiagonalCovariance(q),
        R=torch.tensor([[reentry.R_VAR]], dtype=D),
    )
    # the windows start from a prior with a ballistic-coefficient variance of 1e-5 (the paper's
    # 1e-4 lets one run of 64 diverge, on both sides, and the summed likelihood is NaN)
    P0 = torch.diag(torch.tensor([1e6, 4e6, 1e-5], dtype=D))
    data = dict(y=sim.measurements, m0=torch.tensor(reentry.PRIOR_MEAN, dtype=D), P0=P0)
    return model, data


# ----------------------------------------------------------------------------------- peers
def run_peer(
    jax_python: str | None, arrays: dict[str, Any], task: str, repeats: int, cpu: int
) -> tuple[dict[str, Any] | None, dict[str, np.ndarray] | None, str]:
    """``(info, arrays)`` of the peer's ``task`` in the JAX Python, or ``None`` and why not."""
    if not jax_python:
        return None, None, "not run (no --jax-python)"
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **{k: np.asarray(v) for k, v in arrays.items()})
        env = dict(
            os.environ,
            XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
            OMP_NUM_THREADS="1",
        )
        env.pop("PYTHONPATH", None)
        cmd = [jax_python, str(PEER), str(src), str(dst), task, str(repeats)]
        if shutil.which("taskset"):
            cmd = ["taskset", "-c", str(cpu), *cmd]
        out = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if out.returncode != 0:
            return None, None, f"failed: {out.stderr.strip().splitlines()[-1:]}"
        info = json.loads(out.stdout.strip().splitlines()[-1])
        return info, dict(np.load(dst)), "ok"


def time_to_optimum(lls: np.ndarray, elapsed: np.ndarray, sequences: int) -> float | None:
    """Seconds until ``lls`` is within the tolerance of its best (``elapsed[i]``: when
    ``lls[i]`` was reached)."""
    lls = np.asarray(lls, dtype=float)
    ok = np.isfinite(lls)
    if not ok.any():
        return None
    return _time_to(lls, elapsed, lls[ok].max() - NATS_PER_SEQUENCE * sequences)


def _time_to(lls: np.ndarray, elapsed: np.ndarray, level: float) -> float | None:
    """Seconds until ``lls`` first reaches ``level`` (``None``: never in the run)."""
    ok = np.asarray(lls, dtype=float) >= level
    return float(elapsed[int(np.argmax(ok))]) if ok.any() else None


# ----------------------------------------------------------------------------------- rows
def linear_grad_row(p: dict[str, np.ndarray], args: argparse.Namespace) -> dict[str, Any]:
    model = linear_model(p)
    y = torch.tensor(p["y"], dtype=D)
    x0, P0 = torch.tensor(p["m0"], dtype=D), torch.tensor(p["P0"], dtype=D)
    params = learnable(model)

    def run() -> Tensor:
        for q in params:
            q.grad = None
        ll = kalman_filter(model, y, x0=x0, P0=P0, outputs=("log_likelihood",)).log_likelihood
        total = ll.sum()
        total.backward()
        return total.detach()

    secs = timeit(run, args.repeats)
    value = float(run())
    row: dict[str, Any] = {"row": "linear grad", "torchfilt_s": secs, "torchfilt_value": value}
    Lq = np.linalg.cholesky(p["Q"])
    Lr = np.linalg.cholesky(p["R"])
    info, out, why = run_peer(
        args.jax_python, {**p, "Lq": Lq, "Lr": Lr}, "lgssm_grad", args.repeats, args.cpu
    )
    row["peer"] = "dynamax jit(value_and_grad(vmap(lgssm_filter)))" if info else why
    if info and out:
        row.update(peer_s=info["seconds"], compile_s=info["compile_seconds"])
        gA = model.A.grad.numpy()  # type: ignore[union-attr]
        row["max_diff"] = abs(float(out["value"]) - value) / abs(value)
        row["grad_rel_diff"] = float(np.abs(out["grad_A"] - gA).max() / np.abs(gA).max())
        row["versions"] = info["versions"]
    return row


def _em_history(fit: Any) -> tuple[np.ndarray, np.ndarray]:
    ll = np.array([fit.initial_log_likelihood] + [r["log_likelihood"] for r in fit.history])
    el = np.array([0.0] + [r["elapsed"] for r in fit.history])
    return ll, el


def linear_em_rows(p: dict[str, np.ndarray], args: argparse.Namespace) -> list[dict[str, Any]]:
    y = torch.tensor(p["y"], dtype=D)
    B = int(y.shape[0])
    x0, P0 = torch.tensor(p["m0"], dtype=D), torch.tensor(p["P0"], dtype=D)
    known = list(range(y.shape[-1]))
    curves: list[tuple[str, str, np.ndarray, np.ndarray, int]] = []  # (who, method, ll, t, seqs)
    for accelerate, method in ((False, "torchfilt fit_em (plain EM)"),
                               (None, "torchfilt fit_em (default: SQUAREM)")):  # fmt: skip
        em = fit_em(
            linear_model(p), y, x0=x0, P0=P0, known_channels=known, iterations=args.em_iterations,
            stopping=StoppingOptions(tol=0.0, rtol=0.0, atol=0.0), accelerate=accelerate,
        )  # fmt: skip
        curves.append(("torchfilt_s", method, *_em_history(em), B))
    plain_el = curves[0][3]  # the plain fit's times: its per-iteration cost
    counted = int(torch.isfinite(y).sum())
    lmodel = linear_model(p)
    lik = fit_likelihood(
        lmodel, y, parameters=learnable(lmodel), x0=x0, P0=P0, optimizer="lbfgs",
        iterations=args.lik_iterations, stopping=StoppingOptions(rtol=0.0),
    )  # fmt: skip
    lik_ll = np.array([lik.initial_log_likelihood] + [-r["loss"] * counted for r in lik.history])
    lik_el = np.array([0.0] + [r["elapsed"] for r in lik.history])
    curves.append(("torchfilt_s", "torchfilt fit_likelihood (L-BFGS)", lik_ll, lik_el, B))
    iter_row: dict[str, Any] = {
        "row": "linear EM iteration",
        "method": "plain EM (accelerate=False)",
        "torchfilt_s": float(np.median(np.diff(plain_el))),
    }
    m1 = p["A"] @ p["m0"]
    P1 = p["A"] @ p["P0"] @ p["A"].T + p["Q"]
    arrays = {**p, "m1": m1, "P1": P1}
    info, out, why = run_peer(args.jax_python, arrays, "lgssm_em", args.em_iterations, args.cpu)
    iter_row["peer"] = "dynamax jit(vmap(e_step) + m_step)" if info else why
    if info and out:
        iter_row.update(peer_s=info["seconds"], compile_s=info["compile_seconds"])
        el = np.concatenate([[0.0], out["elapsed"][:-1]])  # ll[i] is before iteration i
        curves.append(("peer_s", "dynamax EM (learns H too)", out["log_likelihood"], el, B))
    info, out, why = run_peer(
        args.jax_python, arrays, "pykalman_em", args.pykalman_iterations, args.cpu
    )
    iter_row["pykalman_s"] = info["seconds"] if info and out else None
    if info and out:
        curves.append(
            ("peer_s", "pykalman EM (1 recording)", out["log_likelihood"], out["elapsed"], 1)
        )
    # the optimum per sequence on the 20 recordings (pykalman fits one): a long L-BFGS run,
    # untimed, or the best any method reached if that is higher
    optimum = max(
        reference_optimum(p, y, x0, P0, args.reference_iterations) / B,
        *(float(np.nanmax(c[2])) / c[4] for c in curves if c[4] == B),
    )
    # the level dynamax's EM ends at (its best less the tolerance): who gets there first
    peer_best = [float(np.nanmax(c[2])) / c[4] for c in curves if c[1].startswith("dynamax")]
    opt_rows: list[dict[str, Any]] = []
    for who, method, ll, el, seqs in curves:
        row: dict[str, Any] = {
            "row": "linear time to optimum",
            "method": method,
            "to_own_best_s": time_to_optimum(ll, el, seqs),
            "best_per_sequence": float(np.nanmax(ll)) / seqs,
        }
        if seqs == B:
            row[who] = _time_to(ll, el, (optimum - NATS_PER_SEQUENCE) * seqs)
            row["optimum_per_sequence"] = optimum
            if peer_best:
                level = (peer_best[0] - NATS_PER_SEQUENCE) * seqs
                row["to_dynamax_level_s"] = _time_to(ll, el, level)
        opt_rows.append(row)
    return [iter_row, *opt_rows]


def reference_optimum(
    p: dict[str, np.ndarray], y: Tensor, x0: Tensor, P0: Tensor, iterations: int
) -> float:
    """The maximised log-likelihood (summed over the recordings ``y``) of the linear problem
    ``p``, from ``iterations`` of L-BFGS on the exact likelihood (untimed: the reference of the
    time-to-optimum row)."""
    model = linear_model(p)
    fit_likelihood(
        model, y, parameters=learnable(model), x0=x0, P0=P0, optimizer="lbfgs",
        iterations=iterations, stopping=StoppingOptions(tol=0.0, rtol=0.0, atol=0.0),
    )  # fmt: skip
    with torch.no_grad():
        return float(kalman_filter(model, y, x0=x0, P0=P0).log_likelihood.sum())


def reentry_row(B: int, T: int, args: argparse.Namespace, compile: bool = False) -> dict[str, Any]:
    model, d = reentry_problem(B, T)
    ckf = CKF(model, compile=compile)
    params = list(model.parameters())

    def run() -> Tensor:
        for q in params:
            q.grad = None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = ckf.filter(d["y"], x0=d["m0"], P0=d["P0"], path="cubature")
        total = res.log_likelihood.sum()
        total.backward()
        return total.detach()

    t0 = time.perf_counter()
    run()  # a compiled filter compiles here (under autograd: one compiled step, forward and back)
    first = time.perf_counter() - t0
    secs = timeit(run, args.repeats)
    value = float(run())
    row: dict[str, Any] = {
        "row": "reentry grad",
        "method": f"CKF(compile={compile})",
        "torchfilt_s": secs,
        "torchfilt_value": value,
        "torchfilt_first_s": first,
    }
    if compile:
        row["torchfilt_compile_s"] = first - secs
    gamma = float(1.1 * reentry.GAMMA)
    arrays = {
        "y": d["y"].numpy(), "m0": d["m0"].numpy(), "P0": d["P0"].numpy(),
        "R": np.array([[reentry.R_VAR]]), "dt": reentry.DT, "substeps": reentry.SUBSTEPS,
        "radar_m": reentry.RADAR_M, "radar_h": reentry.RADAR_H, "gamma": gamma,
        "logq": np.log([1e2, 1e2, 1e-8]),
    }  # fmt: skip
    info, out, why = run_peer(args.jax_python, arrays, "ukf_grad", args.repeats, args.cpu)
    row["peer"] = "dynamax jit(value_and_grad(vmap(unscented_kalman_filter))), fori_loop RK4" if (
        info
    ) else why  # fmt: skip
    if info and out:
        row.update(peer_s=info["seconds"], compile_s=info["compile_seconds"])
        row["max_diff"] = abs(float(out["value"]) - value) / abs(value)
        row["peer_value"] = float(out["value"])
    return row


def reaction_row(
    B: int, T: int, args: argparse.Namespace, compile: bool | str = False
) -> dict[str, Any]:
    model, d = reaction_problem(B, T)
    with warnings.catch_warnings():  # a warm-up: the first L-BFGS imports torch's compiler stack
        warnings.simplefilter("ignore")
        warm, dw = reaction_problem(1, 10)
        fit_em(warm, dw["y"], x0=dw["m0"], P0=dw["P0"], known_channels=[0], iterations=1)
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_em(
            model, d["y"], x0=d["m0"], P0=d["P0"], known_channels=[0],
            iterations=args.nonlinear_iterations, stopping=StoppingOptions(tol=0.0, rtol=0.0),
            **({"compile": compile} if compile else {}),  # an older checkout has no compile
        )  # fmt: skip
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    ll, el = _em_history(fit)
    return {
        "row": "2A->B EM iteration",
        "method": f"fit_em(compile={compile!r})",
        "torchfilt_s": float(np.median(np.diff(el))) if len(el) > 1 else None,
        "per_iteration_s": np.diff(el).tolist(),
        "total_s": total,
        # CPU seconds of the whole fit (its start's E-step, and a compile, included) per
        # iteration: less sensitive than wall time to other processes on a loaded machine
        "cpu_s_per_iteration": cpu / max(fit.iterations, 1),
        "iterations": fit.iterations,
        "final_log_likelihood": float(ll[-1]),
        "peer": "no peer (no EM for nonlinear models)",
    }


def budgets(args: argparse.Namespace) -> dict[str, tuple[int, int]]:
    """The problem sizes, and the iteration budgets set on ``args``: those of ``--quick`` or of
    the full run, where ``--em-iterations`` and ``--pykalman-iterations`` were not given."""
    if args.quick:
        sizes = dict(lin=(3, 30), reentry=(4, 10), reaction=(2, 20))
        budget = dict(em_iterations=3, lik_iterations=3, pykalman_iterations=3)
        budget["reference_iterations"] = 3
        args.nonlinear_iterations, args.repeats = 2, 1
    else:
        sizes = dict(lin=(20, 500), reentry=(64, 100), reaction=(8, 400))
        budget = dict(em_iterations=1500, lik_iterations=6, pykalman_iterations=300)
        budget["reference_iterations"] = 60
        args.nonlinear_iterations = 4
    for name, default in budget.items():
        if getattr(args, name, None) is None:
            setattr(args, name, default)
    return sizes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--jax-python", default=None, help="python of a venv with dynamax, pykalman")
    ap.add_argument("--cpu", type=int, default=0, help="core to pin every peer to")
    ap.add_argument(
        "--rows", default="linear,em,reentry,reentry-compiled,reaction", help="comma-separated"
    )
    ap.add_argument(
        "--em-iterations",
        type=int,
        default=None,
        help="iterations of the linear EM curves of torchfilt and dynamax (default 1500: long "
        "enough for both to reach the optimum, which dynamax's EM needs about 1400 for)",
    )
    ap.add_argument(
        "--pykalman-iterations",
        type=int,
        default=None,
        help="iterations of pykalman's EM curve (default 300; about 85 ms each)",
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_learning"))
    ap.add_argument(
        "--reaction-compile",
        default="eager,loop",
        help="fit_em compile modes of the 2A->B rows, comma-separated: eager, loop, step",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    sizes = budgets(args)
    wanted = set(args.rows.split(","))
    rows: list[dict[str, Any]] = []
    p = linear_problem(*sizes["lin"])
    if "linear" in wanted:
        rows.append(linear_grad_row(p, args))
        print("done linear grad", file=sys.stderr)
    if "em" in wanted:
        rows.extend(linear_em_rows(p, args))
        print("done linear EM", file=sys.stderr)
    if "reentry" in wanted:
        rows.append(reentry_row(*sizes["reentry"], args))
        print("done reentry", file=sys.stderr)
    if "reentry-compiled" in wanted:
        rows.append(reentry_row(*sizes["reentry"], args, compile=True))
        print("done reentry (compiled)", file=sys.stderr)
    if "reaction" in wanted:
        for mode in args.reaction_compile.split(","):
            compile = {"eager": False, "loop": "loop", "step": "step"}[mode]
            rows.append(reaction_row(*sizes["reaction"], args, compile=compile))
            print(f"done 2A->B ({mode})", file=sys.stderr)
    for r in rows:
        tf, peer = r.get("torchfilt_s"), r.get("peer_s")
        r["ratio"] = tf / peer if tf is not None and peer else None
    headers = ["row", "method", "torchfilt s", "dynamax s", "pykalman s", "ratio", "compile s"]
    headers += ["rel diff", "to own best s", "to dynamax's s"]
    body = [
        [
            r["row"], r.get("method"), r.get("torchfilt_s"), r.get("peer_s"), r.get("pykalman_s"),
            r.get("ratio"), r.get("compile_s"), r.get("max_diff"), r.get("to_own_best_s"),
            r.get("to_dynamax_level_s"),
        ]
        for r in rows
    ]  # fmt: skip
    print(f"seconds, float64, 1 thread, sizes {sizes}; ratio = torchfilt / dynamax")
    print(table(headers, body))
    versions = next((r["versions"] for r in rows if "versions" in r), None)
    write_json(
        args.out / "bench_learning.json",
        {
            "rows": rows,
            "sizes": sizes,
            "peer_versions": versions,
            "nats_per_sequence": NATS_PER_SEQUENCE,
            "environment": environment(),
            "quick": args.quick,
        },
    )
    print(f"wrote {args.out / 'bench_learning.json'}")
    return (
        0
        if all(r.get("torchfilt_s") is None or math.isfinite(r["torchfilt_s"]) for r in rows)
        else 1
    )


if __name__ == "__main__":
    raise SystemExit(main())
