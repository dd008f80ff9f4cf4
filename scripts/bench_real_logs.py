"""Real input-output logs: free-run prediction of learned models against an N4SID baseline.

Issue #27's last acceptance row: on classic system-identification logs, standardised, a model
learned from the measurements alone should predict the held-out output in free run (after a
short burn-in) at least as well as an independent N4SID baseline, with 95% coverage of the
output in ``[0.85, 0.99]``.

Logs (not shipped; ``--data DIR`` holds the CSV files). The copies used here come from the
public GitHub repository ``Rafa7046/Non_Linear_Identification``, which gathered them from their
sources:

* ``ball-and-beam.csv`` (DaISy, ESAT-SISTA ball-and-beam practicum; columns ``u, y``; 1000
  samples): the first two thirds train, the rest is held out;
* ``robot-arm.csv`` (DaISy, flexible robot arm; ``u, y``; 1024 samples): the same split;
* ``tanque.csv`` (nonlinearbenchmark.org, cascaded tanks with overflow; ``uEst, uVal, yEst,
  yVal``; 1024 + 1024 samples): the benchmark's own estimation and validation records;
* ``exchanger.csv`` (DaISy 97-002, a liquid-saturated steam heat exchanger; input the liquid
  flow rate ``q``, output the outlet liquid temperature ``th``; 4000 samples at 1 s): the
  first two thirds train, the rest is held out.

Standardisation uses the training part's mean and standard deviation. Every model has
``--order`` states (default 4). Rows:

* ``N4SID (nfoursid)``: the independent baseline, ``nfoursid.NFourSID`` (``num_block_rows``
  ``--block-rows``, default 20; both N4SIDs gave unstable models of these stable systems
  with 10), simulated in its own convention ``s_{k+1} = A s_k + B u_k``,
  ``y_k = C s_k + D u_k`` from an initial state fitted by least squares to the burn-in outputs
  (no coverage: the baseline gives a point prediction);
* ``torchfilt subspace``: :func:`~torchfilt.models.subspace_identify` (the library's own N4SID);
* ``torchfilt subspace, stable=True``: the same with ``stable=True``, for the plants known to be
  stable (all but the ball and beam): an estimate with a pole on or outside the unit circle is
  made again inside it. The rows below start from the plain estimate;
* ``torchfilt subspace + EM``: that model refined by :func:`~torchfilt.training.fit_em` with its
  defaults (``H`` of the one output held: the gauge);
* ``torchfilt subspace + EM + L-BFGS``: the EM model made learnable
  (:meth:`~torchfilt.models.LinearGaussianModel.learnable`: ``A``, ``B``, ``Q``, ``R``) and
  finished by :func:`~torchfilt.training.fit_likelihood` with L-BFGS and its defaults. These
  logs are nearly noise-free, where EM creeps (its ``R`` tends to zero, its likelihood gains a
  little every iteration, and the 100-iteration budget ends it unconverged); L-BFGS on the
  exact likelihood converges from there;
* ``torchfilt GP (measurement only)``: :meth:`InducingTransition.model_from_linear` on the best
  linear fit (the L-BFGS one where it raised EM's likelihood, else EM's; ``start`` in the JSON),
  ``--inducing`` points on its smoothed training states, then
  :func:`~torchfilt.training.fit_measurement_only` with its defaults (``method="auto"``: EM
  and the likelihood method from the same start, 30 iterations each, the better log-likelihood
  on the last fifth of the training log kept; ``noise_scale="auto"``: that fifth then scales the
  process noise; until 2026-12-05 the default was EM alone);
* ``torchfilt GP (measurement only, accelerate=True)``: the same with SQUAREM cycles over EM's
  gradient M-step (``accelerate=True``; each of the 30 iterations three or four M-steps).

Every torchfilt row is evaluated by :func:`~torchfilt.filters.free_run`: the first ``--burn-in``
(20) held-out samples are filtered from the prior ``N(0, P0)`` (the subspace fit's ``P0``), then
the rest is predicted from the inputs alone. Reported per row: free-run RMSE of the standardised
output over the steps after the burn-in, the mean 95% coverage of the output's predictive
interval (``R`` included), and the training seconds.

    python scripts/bench_real_logs.py --data DIR --out OUT
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _common import environment, table, write_json
from torch import Tensor

import torchfilt
from torchfilt.exceptions import TorchfiltError
from torchfilt.filters import free_run, kalman_smoother
from torchfilt.models import InducingTransition, LinearGaussianModel, subspace_identify
from torchfilt.training import fit_em, fit_likelihood, fit_measurement_only

D = torch.float64
#: the logs: file, the columns of (train u, train y, test u, test y), or (u, y) split by time
LOGS: dict[str, dict[str, Any]] = {
    "ball-and-beam": {"file": "ball-and-beam.csv", "columns": ("u", "y"), "stable": False},
    "robot-arm": {"file": "robot-arm.csv", "columns": ("u", "y"), "stable": True},
    "cascaded-tanks": {
        "file": "tanque.csv",
        "columns": ("uEst", "yEst", "uVal", "yVal"),
        "stable": True,
    },
    "exchanger": {"file": "exchanger.csv", "columns": ("q", "th"), "stable": True},
}
#: share of a single log that trains (the rest is held out)
TRAIN_SHARE = 2 / 3


def read_log(path: Path, columns: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    """``(u_train, y_train, u_test, y_test)`` as float64 columns ``(T,)``."""
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    cols = {c: np.array([float(r[c]) for r in rows if r.get(c, "") != ""]) for c in columns}
    if len(columns) == 4:
        return tuple(cols[c] for c in columns)
    u, y = cols[columns[0]], cols[columns[1]]
    k = int(len(y) * TRAIN_SHARE)
    return u[:k], y[:k], u[k:], y[k:]


def standardised(
    u_tr: np.ndarray, y_tr: np.ndarray, u_te: np.ndarray, y_te: np.ndarray
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The four series scaled by the training part's mean and standard deviation, as
    ``(1, T, 1)`` tensors."""
    mu, su, my, sy = u_tr.mean(), u_tr.std(), y_tr.mean(), y_tr.std()

    def t(x: np.ndarray, m: float, s: float) -> Tensor:
        return torch.tensor((x - m) / s, dtype=D).reshape(1, -1, 1)

    return t(u_tr, mu, su), t(y_tr, my, sy), t(u_te, mu, su), t(y_te, my, sy)


def n4sid_row(
    u_tr: Tensor, y_tr: Tensor, u_te: Tensor, y_te: Tensor, order: int, rows: int, burn: int
) -> dict[str, Any]:
    """The nfoursid baseline: identified on the training part, simulated on the held-out one
    from a least-squares initial state over the burn-in."""
    import pandas as pd
    from nfoursid.nfoursid import NFourSID

    t0 = time.perf_counter()
    frame = pd.DataFrame({"y": y_tr.reshape(-1).numpy(), "u": u_tr.reshape(-1).numpy()})
    sid = NFourSID(frame, output_columns=["y"], input_columns=["u"], num_block_rows=rows)
    sid.subspace_identification()
    ss, _ = sid.system_identification(rank=order)
    seconds = time.perf_counter() - t0
    A, B, C, Dm = (np.asarray(m, dtype=float) for m in (ss.a, ss.b, ss.c, ss.d))
    u, y = u_te.reshape(-1).numpy(), y_te.reshape(-1).numpy()
    # the response to the inputs from s_0 = 0, and the observability rows C A^k of s_0
    T, n = len(y), A.shape[0]
    forced, obs, s, Ak = np.empty(T), np.empty((T, n)), np.zeros(n), np.eye(n)
    for k in range(T):
        forced[k] = (C @ s + Dm @ u[k : k + 1]).item()
        obs[k] = (C @ Ak).reshape(-1)
        s = A @ s + (B @ u[k : k + 1]).reshape(-1)
        Ak = A @ Ak
    s0 = np.linalg.lstsq(obs[:burn], y[:burn] - forced[:burn], rcond=None)[0]
    pred = forced + obs @ s0
    rmse = float(np.sqrt(np.mean((pred[burn:] - y[burn:]) ** 2)))
    return {"rmse": rmse, "coverage95": None, "train_s": seconds}


def torchfilt_row(model: Any, y_te: Tensor, u_te: Tensor, P0: Tensor, burn: int) -> dict[str, Any]:
    """Free-run RMSE and 95% output coverage after ``burn`` filtered held-out samples."""
    n = P0.shape[-1]
    with torch.no_grad():
        fc = free_run(model, y_te, u_te, x0=torch.zeros(n, dtype=D), P0=P0, burn_in=burn)
    mean, cov, y = fc.output_mean[:, burn:], fc.output_cov[:, burn:], y_te[:, burn:]
    if not bool(torch.isfinite(mean).all() and torch.isfinite(cov).all()):
        return {"rmse": math.nan, "coverage95": math.nan, "finite": False}
    # the library's metrics, on the output: (1, T, 1) means and (1, T, 1, 1) covariances
    rmse = float(torchfilt.rmse(y, mean, dim=(0, 1, 2)))
    cover = float(torchfilt.coverage(y, mean, cov).mean())
    # the squared error over the predicted variance, averaged: 1 for honest bands, below 1 for
    # bands wider than the errors (coverage above 0.95), above 1 for narrower ones
    ratio = float(((y - mean) ** 2 / cov.diagonal(dim1=-2, dim2=-1)).mean())
    return {"rmse": rmse, "coverage95": cover, "error_over_variance": ratio, "finite": True}


def lbfgs_row(
    em_model: Any, data: tuple[Tensor, Tensor, Tensor, Tensor], sub: Any, P0: Tensor, burn: int
) -> tuple[dict[str, Any], LinearGaussianModel | None]:
    """The EM model made learnable and finished by ``fit_likelihood`` (L-BFGS, defaults): the
    row, and the fitted model (``None`` if the fit raised)."""
    y_tr, u_tr, y_te, u_te = data
    t0 = time.perf_counter()
    try:
        lin = em_model.learnable()
        lf = fit_likelihood(lin, y_tr, u_tr, x0=sub.x0, P0=sub.P0, optimizer="lbfgs")
    except TorchfiltError as e:
        return _raised(e, time.perf_counter() - t0), None
    seconds = time.perf_counter() - t0
    row = {
        **torchfilt_row(lin, y_te, u_te, P0, burn),
        "train_s": seconds,
        "lbfgs_iterations": lf.iterations,
        "stopped": lf.stopped,
        "log_likelihood": lf.log_likelihood,
    }
    return row, lin


#: the GP row with SQUAREM cycles over EM's gradient M-step
ACCEL_ROW = "torchfilt GP (measurement only, accelerate=True)"


def gp_from_linear(
    start: LinearGaussianModel, sub: Any, y_tr: Tensor, u_tr: Tensor, inducing: int
) -> torchfilt.StateSpaceModel:
    """The GP model that starts exactly at ``start``: ``InducingTransition.model_from_linear``
    with ``inducing`` points on ``start``'s smoothed training states (from the subspace fit
    ``sub``'s prior), lengthscales the spread of those states and the inputs."""
    with torch.no_grad():
        states = kalman_smoother(start, y_tr, u_tr, x0=sub.x0, P0=sub.P0).mean[0]
    cloud = torch.cat([states, u_tr[0]], -1)
    return InducingTransition.model_from_linear(
        start, inducing=inducing, states=states, inputs=u_tr[0], lengthscale=cloud.std(0)
    )


def gp_row(
    start: LinearGaussianModel,
    sub: Any,
    data: tuple[Tensor, Tensor, Tensor, Tensor],
    P0: Tensor,
    burn: int,
    inducing: int,
    accelerate: bool | None,
) -> dict[str, Any]:
    """``InducingTransition.model_from_linear(start)`` fitted by ``fit_measurement_only`` at
    its defaults (``accelerate`` aside): the row (its ``train_s`` from the GP's start)."""
    y_tr, u_tr, y_te, u_te = data
    t0 = time.perf_counter()
    gp = gp_from_linear(start, sub, y_tr, u_tr, inducing)
    try:
        mo = fit_measurement_only(
            gp, y_tr, u_tr, x0=sub.x0, P0=sub.P0, known_channels=[0], accelerate=accelerate
        )
    except TorchfiltError as e:
        return _raised(e, time.perf_counter() - t0)
    return {
        **torchfilt_row(mo.model, y_te, u_te, P0, burn),
        "train_s": time.perf_counter() - t0,
        "iterations": mo.iterations,
        "stopped": mo.stopped,
        "initial_log_likelihood": mo.initial_log_likelihood,
        "log_likelihood": mo.log_likelihood,
        "e_steps": mo.history[-1].get("e_steps") if mo.history else None,
        "noise_scale": None if mo.noise_scale is None else mo.noise_scale._asdict(),
        "method": mo.method,
        "compared": mo.compared,
    }


def _raised(e: TorchfiltError, seconds: float) -> dict[str, Any]:
    """The row of a fit that raised: its message, no figures."""
    return {"rmse": math.nan, "coverage95": math.nan, "train_s": seconds, "raised": str(e)}


def run_log(name: str, data: Path, args: argparse.Namespace) -> dict[str, Any]:
    spec = LOGS[name]
    u_tr, y_tr, u_te, y_te = standardised(*read_log(data / spec["file"], spec["columns"]))
    n, burn = args.order, args.burn_in
    rows: dict[str, dict[str, Any]] = {}
    rows["N4SID (nfoursid)"] = n4sid_row(u_tr, y_tr, u_te, y_te, n, args.block_rows, burn)

    t0 = time.perf_counter()
    sub = subspace_identify(y_tr, u_tr, order=n, block_rows=args.block_rows)
    t_sub = time.perf_counter() - t0
    P0 = sub.P0.reshape(-1, n, n)[0]
    rows["torchfilt subspace"] = {
        **torchfilt_row(sub.model, y_te, u_te, P0, burn),
        "train_s": t_sub,
        "spectral_radius": float(torch.linalg.eigvals(sub.model.A).abs().max()),
    }
    if spec["stable"]:  # a plant known to be stable: the estimate kept inside the unit circle
        t0 = time.perf_counter()
        st = subspace_identify(y_tr, u_tr, order=n, block_rows=args.block_rows, stable=True)
        rows["torchfilt subspace, stable=True"] = {
            **torchfilt_row(st.model, y_te, u_te, st.P0.reshape(-1, n, n)[0], burn),
            "train_s": time.perf_counter() - t0,
            "spectral_radius": float(torch.linalg.eigvals(st.model.A).abs().max()),
        }
    t0 = time.perf_counter()
    try:
        em = fit_em(sub.model, y_tr, u_tr, x0=sub.x0, P0=sub.P0, known_channels=[0])
    except TorchfiltError as e:
        rows["torchfilt subspace + EM"] = _raised(e, t_sub + time.perf_counter() - t0)
        for row in ("torchfilt GP (measurement only)", ACCEL_ROW):
            rows[row] = {**_raised(e, 0.0), "raised": "(no EM model)"}
        return _summary(rows, y_tr, y_te, n, burn)
    t_em = t_sub + time.perf_counter() - t0
    rows["torchfilt subspace + EM"] = {
        **torchfilt_row(em.model, y_te, u_te, P0, burn),
        "train_s": t_em,
        "em_iterations": em.iterations,
        "stopped": em.stopped,
        "log_likelihood": em.log_likelihood,
    }
    lbfgs, lin = lbfgs_row(em.model, (y_tr, u_tr, y_te, u_te), sub, P0, burn)
    lbfgs["train_s"] += t_em
    rows["torchfilt subspace + EM + L-BFGS"] = lbfgs

    # the GP starts from the best linear fit: L-BFGS's where it raised the likelihood
    assert isinstance(em.model, LinearGaussianModel)  # fit_em keeps a linear model linear
    better = lin is not None and lbfgs["log_likelihood"] > em.log_likelihood
    start, t_start = (lin, lbfgs["train_s"]) if better else (em.model, t_em)
    assert start is not None
    data_ = (y_tr, u_tr, y_te, u_te)
    for accelerate, row in ((None, "torchfilt GP (measurement only)"), (True, ACCEL_ROW)):
        rows[row] = gp_row(start, sub, data_, P0, burn, args.inducing, accelerate)
        rows[row]["train_s"] += t_start
        rows[row]["start"] = "EM + L-BFGS" if better else "EM"
    return _summary(rows, y_tr, y_te, n, burn)


def _summary(
    rows: dict[str, dict[str, Any]], y_tr: Tensor, y_te: Tensor, n: int, burn: int
) -> dict[str, Any]:
    base = rows["N4SID (nfoursid)"]["rmse"]
    for r in rows.values():
        r["rmse_over_n4sid"] = r["rmse"] / base if base > 0 else math.nan
    return {
        "train_steps": int(y_tr.shape[1]),
        "test_steps": int(y_te.shape[1]),
        "order": n,
        "burn_in": burn,
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="folder with the logs' CSV files")
    ap.add_argument("--out", type=Path, default=Path("out/bench_real_logs"))
    ap.add_argument("--logs", default=",".join(LOGS), help="comma-separated, of " + ", ".join(LOGS))
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--block-rows", type=int, default=20)
    ap.add_argument("--burn-in", type=int, default=20)
    ap.add_argument("--inducing", type=int, default=16)
    args = ap.parse_args(argv)
    names = [s.strip() for s in args.logs.split(",") if s.strip()]
    if unknown := sorted(set(names) - set(LOGS)):
        ap.error(f"--logs: unknown {unknown}; choose from {', '.join(LOGS)}")
    missing = [LOGS[k]["file"] for k in names if not (args.data / LOGS[k]["file"]).is_file()]
    if missing:
        ap.error(f"--data {args.data}: missing {missing}")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    results = {k: run_log(k, args.data, args) for k in names}
    body = [
        [k, row, r["rmse"], r["rmse_over_n4sid"], r.get("coverage95"), r["train_s"]]
        for k, res in results.items()
        for row, r in res["rows"].items()
    ]
    print("free-run RMSE of the standardised output after the burn-in; coverage of the 95% band")
    print(table(["log", "model", "RMSE", "/ N4SID", "95% cov.", "train s"], body))
    write_json(
        args.out / "bench_real_logs.json",
        {"logs": results, "args": {k: str(v) for k, v in vars(args).items()},
         "environment": environment()},
    )  # fmt: skip
    print(f"wrote {args.out / 'bench_real_logs.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
