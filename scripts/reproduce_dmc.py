"""Reproduce Xie, Ding & Chen (2016), sections 3.1 and 3.2: DMC open-loop prediction by a steady-state
Kalman filter, on the Shell heavy-oil fractionator.

Section 3.2 (integrating CVs, observer and filter):
  rows 2-3 of the fractionator made integrating, T = 1 min, N = 100, all three CVs in the integrating
  layout, Q_Y = 0.01 I, Q_y = I, u = [0.5, 0.3, -0.5] from k = 0 (u(-1) = 0), v1 = 0 / -5 / 5 and
  v2 = 0 / 5 / -5 switching at k = 48 and k = 498. The truth is the realisation itself started at 0; the
  estimate starts with every element 5. Noise-free: the observer error must converge to zero (reported
  at k = 50, 200, 1000). With white measurement noise of covariance I: tracking error statistics.
  The Lee-Morari-Garcia realisation (section-2 corrections) is run on the same data for comparison.

Section 3.1 (stable CVs, closed loop):
  T = 4 min, N = 100, P = 15, M = 8, Lambda = diag(3, 5, 3), Q_Y = 0.5 I, Q_y = I, plant output x 0.9,
  disturbance [0.2; 0.1] for k in [64, 78] and [1; -1] from k = 122, |u| <= 0.5, |du| <= 0.1. The same
  controller and target layer run once with the Kalman-filter prediction and once with the classical
  DMC prediction (constant output correction, h = 1); the largest differences are reported. This default
  run uses the single weighted QP of torchfilt.dmc.WeightedTarget over the Table-1 rows (priorities ->
  weights), which isolates the prediction module.

Section 3.1 as the paper runs it (--double-layer): the double-layered DMC of Li & Ding (2015). The
  steady-state target calculation torchfilt.dmc.MultiPriorityTarget (hard limits, then the Table-1
  priorities stage by stage by LP, then the economic QP with h = [-2, 1, 2], u2 minimum-move,
  J_min = -0.4 and the priority-6 rows) feeds the dynamic layer DMCController (P = 15, M = 8,
  Lambda = diag(3, 5, 3), soft CV bounds +/-0.4 with the q weights, hard CV limits +/-0.7, input and
  move limits). Run with the KF prediction and with the classical correction; reports the largest
  differences, the hard limits over the run and the active SSTC constraints at each steady state.

Usage:
  PYTHONPATH=. python scripts/reproduce_dmc.py [--out out/dmc] [--steps-31 250] [--steps-32 1000]
  PYTHONPATH=. python scripts/reproduce_dmc.py --double-layer [--out out/dmc] [--steps-31 250]

Writes results.json and fig_32_observer.png, fig_32_filter.png, fig_32_error.png, fig_31_cv.png,
fig_31_mv.png into --out, and prints a table; with --double-layer, results_double_layer.json,
fig_31dl_cv.png and fig_31dl_mv.png.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from torchfilt.dmc import (
    DMCController,
    LMGPredictor,
    MultiPriorityTarget,
    OpenLoopPredictor,
    SampledPlant,
    SSTCResult,
    StepResponseModel,
    Target,
    TargetRow,
    WeightedTarget,
    integrating_fractionator,
    run_closed_loop,
    shell_fractionator,
)
from torchfilt.plots import style

D = torch.float64
DPI = 150
COLORS = {"truth": "black", "est": "tab:blue", "meas": "0.65", "kf": "tab:blue", "cl": "tab:orange"}
CHECK_KS = (50, 200, 1000)
#: Transient excluded from the steady tracking statistics of section 3.2.
TRANSIENT = 200


# ---------------------------------------------------------------------------------------------- 3.2
def section_32(steps: int, seed: int) -> dict:
    Gu, Gv = integrating_fractionator()
    model = StepResponseModel.from_transfer_functions(
        Gu, Gv, dt=1.0, horizon=100, integrating=[True, True, True]
    )
    t0 = time.perf_counter()
    pred = OpenLoopPredictor(model, Q_Y=0.01, Q_y=1.0)
    t_gain = time.perf_counter() - t0
    lmg = LMGPredictor(model, Q_Y=0.01, Q_y=1.0)
    r = pred.realization
    K = steps + 1
    du = torch.zeros(K, 3, dtype=D)
    du[0] = torch.tensor([0.5, 0.3, -0.5], dtype=D)
    v = torch.zeros(K, 2, dtype=D)
    v[48:498] = torch.tensor([-5.0, 5.0], dtype=D)
    v[498:] = torch.tensor([5.0, -5.0], dtype=D)
    dv = torch.diff(v, dim=0, prepend=torch.zeros(1, 2, dtype=D))
    X = [torch.zeros(r.state_dim, dtype=D)]
    for k in range(1, K):
        X.append(r.A @ X[-1] + r.B @ du[k - 1] + r.Bv @ dv[k])
    Xt = torch.stack(X)
    y_true = Xt @ r.H.mT
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(K, 3, generator=g, dtype=D)
    x0 = torch.full((r.state_dim,), 5.0, dtype=D)
    z0 = lmg.realization.embedding @ x0  # the same initial estimate in LMG coordinates

    out: dict = {"settings": {"T": 1.0, "N": 100, "Q_Y": 0.01, "Q_y": 1.0, "steps": steps}}
    runs = {}
    for label, y in (("observer", y_true), ("filter", y_true + noise)):
        t0 = time.perf_counter()
        run = pred.run(y[1:], du[:-1], dv[1:], x0=x0)
        t_run = time.perf_counter() - t0
        run_lmg = lmg.run(y[1:], du[:-1], dv[1:], x0=z0)
        Xh = torch.cat([x0[None], run.states])
        yh = Xh @ r.H.mT
        err = (Xt - Xh).norm(dim=-1)
        rel = err / Xt.norm(dim=-1).clamp_min(1.0)
        e_y = yh - y_true
        runs[label] = dict(y=y, yhat=yh, err=err)
        res: dict = {
            "state_error_norm_at": {str(k): float(err[k]) for k in (0, *CHECK_KS) if k < K},
            "relative_state_error_at": {str(k): float(rel[k]) for k in (0, *CHECK_KS) if k < K},
            "output_error_max_after_200": float(e_y[TRANSIENT:].abs().max()),
            "lmg_vs_ours_max_abs_prediction_diff": float(
                (run_lmg.predictions - run.predictions).abs().max()
            ),
            "prediction_scale": float(run.predictions.abs().max()),
            "run_seconds": t_run,
        }
        if label == "filter":
            steady = slice(TRANSIENT, K)
            res["tracking"] = {
                f"y{j + 1}": {
                    "rmse_filtered": float(e_y[steady, j].pow(2).mean().sqrt()),
                    "mean_error": float(e_y[steady, j].mean()),
                    "max_abs_error": float(e_y[steady, j].abs().max()),
                    "rmse_measurement": float(noise[steady, j].pow(2).mean().sqrt()),
                }
                for j in range(3)
            }
            # whole prediction vector y(k+i|k), i = 1..N, against the true free response
            P_err = run.predictions[TRANSIENT - 1 :] - pred.predictions(Xt[TRANSIENT:])
            res["tracking"]["prediction_rmse_all_horizons"] = float(P_err.pow(2).mean().sqrt())
        out[label] = res
    out["gain_seconds"] = t_gain
    out["closed_loop_spectral_radius"] = float(
        torch.linalg.eigvals(pred.error_dynamics).abs().max()
    )
    out["_runs"] = runs
    out["_y_true"] = y_true
    return out


def plot_32(res: dict, outdir: Path) -> list[str]:
    files = []
    y_true = res["_y_true"].numpy()
    k = np.arange(y_true.shape[0])
    for label, title, fname in (
        (
            "observer",
            "Section 3.2, noise-free observer (estimate starts at 5, truth at 0)",
            "fig_32_observer.png",
        ),
        (
            "filter",
            "Section 3.2, steady-state Kalman filter, measurement noise cov I",
            "fig_32_filter.png",
        ),
    ):
        run = res["_runs"][label]
        yh, y = run["yhat"].numpy(), run["y"].numpy()
        fig, axes = plt.subplots(3, 2, figsize=(11, 7.5), sharex="col")
        for j in range(3):
            for c, (lo, hi) in enumerate(((0, len(k)), (0, 51))):
                ax = axes[j, c]
                sl = slice(lo, hi)
                if label == "filter":
                    ax.plot(k[sl], y[sl, j], ".", ms=2, color=COLORS["meas"], label="measurement")
                ax.plot(k[sl], y_true[sl, j], color=COLORS["truth"], lw=1.4, label="true y")
                ax.plot(
                    k[sl], yh[sl, j], "--", color=COLORS["est"], lw=1.2, label="estimate y(k|k)"
                )
                kind = "stable" if j == 0 else "integrating"
                ax.set_ylabel(f"y{j + 1} ({kind})\n[dimensionless]")
                ax.grid(alpha=0.3)
            axes[j, 0].legend(loc="best", fontsize=8)
        axes[0, 0].set_title("whole run")
        axes[0, 1].set_title("first 50 samples")
        for c in range(2):
            axes[2, c].set_xlabel("time k (min; T = 1 min)")
        fig.suptitle(title)
        fig.savefig(outdir / fname, dpi=DPI)
        plt.close(fig)
        files.append(fname)
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, color in (("observer", "tab:blue"), ("filter", "tab:orange")):
        err = res["_runs"][label]["err"].numpy()
        name = "noise-free observer" if label == "observer" else "with measurement noise"
        ax.semilogy(k, np.maximum(err, 1e-16), color=color, label=name)
    ax.axhline(1e-8, color="red", ls=":", label="1e-8")
    ax.set_xlabel("time k (min; T = 1 min)")
    ax.set_ylabel(r"state error $\|\tilde Y(k) - \hat{Y}(k|k)\|_2$ [dimensionless]")
    ax.set_title("Section 3.2: observation error")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.savefig(outdir / "fig_32_error.png", dpi=DPI)
    plt.close(fig)
    files.append("fig_32_error.png")
    return files


# ---------------------------------------------------------------------------------------------- 3.1
#: External targets and their range (paper: y1,ss, y2,ss, u3,ss have external targets, ET_range 0.5).
#: Assumed: the ET values are the Table-1 ideal values and the ET bounds are ET +/- ET_range / 2.
ET = {("y", 0): 0.6, ("y", 1): -0.3, ("u", 2): 0.3}
ET_HALF_RANGE = 0.25
CV_SOFT, CV_HARD = 0.5, 0.7


def table1_rows() -> list[TargetRow]:
    """The paper's Table 1 (multi-priority SSTC parameters) as weighted target rows.

    Priority 0 (made 1 here, the highest): the hard CV limits +/-0.7. Priorities 1..6 of the table
    shift by one. The economic stage (h = [-2, 1, 2], J_min = -0.4; u2 minimum-move) is the lowest.
    """
    R = TargetRow
    et_lo = {v: x - ET_HALF_RANGE for v, x in ET.items()}
    et_hi = {v: x + ET_HALF_RANGE for v, x in ET.items()}
    rows = [
        R(("y", j), kind, s * CV_HARD, 0.2, 1)
        for j in range(3)
        for kind, s in (("lower", -1), ("upper", 1))
    ]
    table = [  # (priority, kind, variable, value, equal-concern error), Table 1
        (1, "lower", ("y", 1), -CV_SOFT, 0.20),
        (1, "upper", ("y", 2), CV_SOFT, 0.20),
        (1, "upper", ("u", 2), et_hi[("u", 2)], 0.25),
        (2, "ideal", ("y", 1), -0.3, 0.25),
        (3, "lower", ("u", 2), et_lo[("u", 2)], 0.25),
        (3, "lower", ("y", 0), et_lo[("y", 0)], 0.25),
        (3, "upper", ("y", 1), et_hi[("y", 1)], 0.25),
        (4, "upper", ("y", 0), et_hi[("y", 0)], 0.25),
        (4, "upper", ("y", 1), CV_SOFT, 0.20),
        (4, "lower", ("y", 2), -CV_SOFT, 0.20),
        (5, "ideal", ("u", 2), 0.3, 0.25),
        (5, "ideal", ("y", 0), 0.6, 0.25),
        (6, "lower", ("y", 0), -CV_SOFT, 0.20),
        (6, "upper", ("y", 0), CV_SOFT, 0.20),
        (6, "lower", ("y", 1), et_lo[("y", 1)], 0.25),
    ]
    rows += [R(var, kind, val, ecr, p + 1) for p, kind, var, val, ecr in table]
    rows += [
        R(("lin", [0.0, 0.0, 0.0, -2.0, 1.0, 2.0]), "ideal", -0.4, 1.0, 8),  # economics, J_min
        R(("u", 1), "hold", 0.0, 1.0, 8),  # u2: minimum-move variable
    ]
    return rows


#: Table 1 as (priority, kind, variable, value, equal-concern error).
def table1() -> list[tuple[int, str, tuple[str, int], float, float]]:
    et_lo = {v: x - ET_HALF_RANGE for v, x in ET.items()}
    et_hi = {v: x + ET_HALF_RANGE for v, x in ET.items()}
    return [
        (1, "lower", ("y", 1), -CV_SOFT, 0.20),
        (1, "upper", ("y", 2), CV_SOFT, 0.20),
        (1, "upper", ("u", 2), et_hi[("u", 2)], 0.25),
        (2, "ideal", ("y", 1), -0.3, 0.25),
        (3, "lower", ("u", 2), et_lo[("u", 2)], 0.25),
        (3, "lower", ("y", 0), et_lo[("y", 0)], 0.25),
        (3, "upper", ("y", 1), et_hi[("y", 1)], 0.25),
        (4, "upper", ("y", 0), et_hi[("y", 0)], 0.25),
        (4, "upper", ("y", 1), CV_SOFT, 0.20),
        (4, "lower", ("y", 2), -CV_SOFT, 0.20),
        (5, "ideal", ("u", 2), 0.3, 0.25),
        (5, "ideal", ("y", 0), 0.6, 0.25),
        (6, "lower", ("y", 0), -CV_SOFT, 0.20),
        (6, "upper", ("y", 0), CV_SOFT, 0.20),
        (6, "lower", ("y", 1), et_lo[("y", 1)], 0.25),
    ]


#: Dynamic layer (spec 3.1; the reading of the garbled source): per CV (q^1, q^0, q^2) = weight of a
#: soft lower-bound violation, tracking weight, weight of a soft upper-bound violation.
Q_WEIGHTS = ((2.0, 0.5, 2.0), (1.0, 0.8, 1.0), (2.5, 1.0, 4.0))
Z_SOFT = 0.4
#: Steady states reported: the last sample before each disturbance change, and the end of the run.
STEADY_KS = (63, 121)


def double_layer(model: StepResponseModel) -> tuple[MultiPriorityTarget, DMCController]:
    """The SSTC and dynamic layer of section 3.1 (spec 3.1, Table 1)."""
    rows = [TargetRow(var, kind, val, ecr, p) for p, kind, var, val, ecr in table1()]
    sstc = MultiPriorityTarget(
        model,
        rows,
        u_min=-0.5,
        u_max=0.5,
        du_ss_max=0.1,
        y_min=-CV_HARD,
        y_max=CV_HARD,
        cost=[-2.0, 1.0, 2.0],
        minimum_move=[1],
        J_min=-0.4,
    )
    q = torch.tensor(Q_WEIGHTS, dtype=D)
    ctrl = DMCController(
        model,
        P=15,
        M=8,
        Q=q[:, 1],
        Lambda=torch.tensor([3.0, 5.0, 3.0]),
        W=1.0,  # the Omega weights (I) on the MV ideal values
        u_min=-0.5,
        u_max=0.5,
        du_max=0.1,
        y_min=-CV_HARD,
        y_max=CV_HARD,
        z_min=-Z_SOFT,
        z_max=Z_SOFT,
        q_lower=q[:, 0],
        q_upper=q[:, 2],
    )
    return sstc, ctrl


class RecordingTarget:
    """Wraps the SSTC and keeps every :class:`SSTCResult` (for the active-constraint report)."""

    def __init__(self, sstc: MultiPriorityTarget) -> None:
        self.sstc = sstc
        self.log: list[SSTCResult] = []

    def __call__(self, y_ss: torch.Tensor, u_prev: torch.Tensor) -> Target:
        res = self.sstc.solve(y_ss, u_prev)
        self.log.append(res)
        return Target(res.y, res.u)


def section_31_double_layer(steps: int) -> dict:
    Gu, Gv = shell_fractionator()
    model = StepResponseModel.from_transfer_functions(Gu, Gv, dt=4.0, horizon=100)
    plant = SampledPlant(Gu, Gv, dt=4.0, steps=steps, output_scale=0.9)
    v = torch.zeros(steps, 2, dtype=D)
    v[64:79] = torch.tensor([0.2, 0.1], dtype=D)
    v[122:] = torch.tensor([1.0, -1.0], dtype=D)
    sstc, ctrl = double_layer(model)
    predictors = {
        "kf": OpenLoopPredictor(model, Q_Y=0.5, Q_y=1.0),
        "classical": OpenLoopPredictor.classical(model, h=1.0),
    }
    runs, logs, secs = {}, {}, {}
    for name, p in predictors.items():
        rec = RecordingTarget(sstc)
        t0 = time.perf_counter()
        runs[name] = run_closed_loop(plant, p, ctrl, rec, v)
        secs[name] = time.perf_counter() - t0
        logs[name] = rec.log
    a, b = runs["kf"], runs["classical"]
    dy, du_ = (a.y - b.y).abs(), (a.u - b.u).abs()
    steady = [k for k in (*STEADY_KS, steps - 1) if k < steps]
    res = {
        "settings": {
            "T": 4.0,
            "N": 100,
            "P": 15,
            "M": 8,
            "Lambda": [3, 5, 3],
            "Q_Y": 0.5,
            "Q_y": 1.0,
            "mismatch": 0.9,
            "steps": steps,
            "classical_h": 1.0,
            "table1": [list(r) for r in table1()],
            "ET": {f"{k[0]}{k[1] + 1}": x for k, x in ET.items()},
            "ET_range": 2 * ET_HALF_RANGE,
            "economics": {"h": [-2.0, 1.0, 2.0], "minimum_move": ["u2"], "J_min": -0.4},
            "dynamic": {
                "z": [-Z_SOFT, Z_SOFT],
                "q_lower_tracking_upper": Q_WEIGHTS,
                "Omega": 1.0,
                "hard_cv": [-CV_HARD, CV_HARD],
            },
        },
        "max_abs_cv_difference": float(dy.max()),
        "max_abs_cv_difference_at_k": int(dy.amax(1).argmax()),
        "max_abs_mv_difference": float(du_.max()),
        "max_abs_mv_difference_at_k": int(du_.amax(1).argmax()),
        "rms_cv_difference": float((a.y - b.y).pow(2).mean().sqrt()),
        "cv_range": float(a.y.abs().max()),
        "max_abs_y": {n: float(r.y.abs().max()) for n, r in runs.items()},
        "max_abs_u": {n: float(r.u.abs().max()) for n, r in runs.items()},
        "max_abs_du": {n: float(r.du.abs().max()) for n, r in runs.items()},
        "steady_states": {
            n: [
                {
                    "k": k,
                    "y": runs[n].y[k].tolist(),
                    "u": runs[n].u[k].tolist(),
                    "y_target": runs[n].y_target[k].tolist(),
                    "u_target": runs[n].u_target[k].tolist(),
                    "sstc_active": logs[n][k].active,
                    "dynamic_soft_bounds_violated": [
                        f"y{j + 1} {'above' if y > 0 else 'below'} {'+' if y > 0 else '-'}"
                        f"{Z_SOFT} by {abs(y) - Z_SOFT:.3g}"
                        for j, y in enumerate(runs[n].y[k].tolist())
                        if abs(y) > Z_SOFT
                    ],
                    "sstc_stage_costs": logs[n][k].stage_costs.tolist(),
                }
                for k in steady
            ]
            for n in runs
        },
        "closed_loop_seconds": secs,
        "_runs": runs,
    }
    return res


def section_31(steps: int) -> dict:
    Gu, Gv = shell_fractionator()
    model = StepResponseModel.from_transfer_functions(Gu, Gv, dt=4.0, horizon=100)
    plant = SampledPlant(Gu, Gv, dt=4.0, steps=steps, output_scale=0.9)
    v = torch.zeros(steps, 2, dtype=D)
    v[64:79] = torch.tensor([0.2, 0.1], dtype=D)
    v[122:] = torch.tensor([1.0, -1.0], dtype=D)
    target = WeightedTarget(model, table1_rows(), u_min=-0.5, u_max=0.5, du_ss_max=0.1)
    ctrl = DMCController(
        model,
        P=15,
        M=8,
        Q=1.0,
        Lambda=torch.tensor([3.0, 5.0, 3.0]),
        u_min=-0.5,
        u_max=0.5,
        du_max=0.1,
    )
    t0 = time.perf_counter()
    kf = OpenLoopPredictor(model, Q_Y=0.5, Q_y=1.0)
    t_gain = time.perf_counter() - t0
    classical = OpenLoopPredictor.classical(model, h=1.0)
    runs, secs = {}, {}
    for name, p in (("kf", kf), ("classical", classical)):
        t0 = time.perf_counter()
        runs[name] = run_closed_loop(plant, p, ctrl, target, v)
        secs[name] = time.perf_counter() - t0
    a, b = runs["kf"], runs["classical"]
    dy, du_ = (a.y - b.y).abs(), (a.u - b.u).abs()
    ky, ku = int(dy.amax(1).argmax()), int(du_.amax(1).argmax())
    blk = a.y.abs().max()
    res = {
        "settings": {
            "T": 4.0,
            "N": 100,
            "P": 15,
            "M": 8,
            "Lambda": [3, 5, 3],
            "Q_Y": 0.5,
            "Q_y": 1.0,
            "mismatch": 0.9,
            "steps": steps,
            "classical_h": 1.0,
        },
        "max_abs_cv_difference": float(dy.max()),
        "max_abs_cv_difference_at_k": ky,
        "max_abs_mv_difference": float(du_.max()),
        "max_abs_mv_difference_at_k": ku,
        "rms_cv_difference": float((a.y - b.y).pow(2).mean().sqrt()),
        "cv_range": float(blk),
        "final": {
            name: {
                "y": r.y[-1].tolist(),
                "u": r.u[-1].tolist(),
                "y_target": r.y_target[-1].tolist(),
            }
            for name, r in runs.items()
        },
        "max_abs_u": {name: float(r.u.abs().max()) for name, r in runs.items()},
        "max_abs_du": {name: float(r.du.abs().max()) for name, r in runs.items()},
        "kf_gain_first_elements_cv1": kf.gain[:4, 0].tolist(),
        "gain_seconds": t_gain,
        "closed_loop_seconds": secs,
        "_runs": runs,
        "_v": v,
    }
    return res


def plot_31(
    res: dict, outdir: Path, prefix: str = "fig_31", title: str = "", zone: float | None = None
) -> list[str]:
    a, b = res["_runs"]["kf"], res["_runs"]["classical"]
    K = a.y.shape[0]
    t = 4.0 * np.arange(K)
    files = []
    for what, fname in (("cv", f"{prefix}_cv.png"), ("mv", f"{prefix}_mv.png")):
        fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True)
        for j in range(3):
            ax = axes[j]
            if what == "cv":
                ax.plot(t, a.y[:, j], color=COLORS["kf"], lw=1.4, label="KF prediction (ours)")
                ax.plot(
                    t,
                    b.y[:, j],
                    "--",
                    color=COLORS["cl"],
                    lw=1.2,
                    label="classical DMC prediction (h = 1)",
                )
                ax.plot(t, a.y_target[:, j], ":", color="0.3", lw=1.0, label="target y_t (KF run)")
                for bound, style in ((CV_SOFT, (0, (4, 3))), (CV_HARD, (0, (1, 2)))):
                    ax.axhline(bound, color="red", ls=style, lw=0.8)
                    ax.axhline(-bound, color="red", ls=style, lw=0.8)
                if zone is not None:  # the dynamic layer's soft CV bounds
                    ax.axhline(zone, color="tab:green", ls=(0, (2, 2)), lw=0.8)
                    ax.axhline(-zone, color="tab:green", ls=(0, (2, 2)), lw=0.8)
                ax.set_ylabel(f"CV y{j + 1}\n[dimensionless]")
            else:
                ax.step(
                    t,
                    a.u[:, j],
                    where="post",
                    color=COLORS["kf"],
                    lw=1.4,
                    label="KF prediction (ours)",
                )
                ax.step(
                    t,
                    b.u[:, j],
                    "--",
                    where="post",
                    color=COLORS["cl"],
                    lw=1.2,
                    label="classical DMC prediction (h = 1)",
                )
                ax.axhline(0.5, color="red", ls=(0, (4, 3)), lw=0.8)
                ax.axhline(-0.5, color="red", ls=(0, (4, 3)), lw=0.8)
                ax.set_ylabel(f"MV u{j + 1}\n[dimensionless]")
            for k0, k1 in ((64, 79), (122, K)):
                ax.axvspan(4.0 * k0, 4.0 * min(k1, K), color="0.92", zorder=0)
            ax.grid(alpha=0.3)
        axes[0].legend(loc="lower right", fontsize=8)
        axes[-1].set_xlabel("time (min; T = 4 min); shaded: measured disturbance active")
        name = "controlled variables" if what == "cv" else "manipulated variables"
        fig.suptitle(
            f"Section 3.1{title}, fractionator closed loop (plant gain x 0.9): {name}\n"
            f"largest KF-vs-classical difference: CV {res['max_abs_cv_difference']:.3g}, "
            f"MV {res['max_abs_mv_difference']:.3g}"
        )
        fig.savefig(outdir / fname, dpi=DPI)
        plt.close(fig)
        files.append(fname)
    return files


# ---------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default="out/dmc", help="output directory (default out/dmc)")
    ap.add_argument("--steps-31", type=int, default=250, help="closed-loop samples (T = 4 min)")
    ap.add_argument("--steps-32", type=int, default=1000, help="observer samples (T = 1 min)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the measurement noise (3.2)")
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (1 is fastest for these small matrices)",
    )
    ap.add_argument("--no-plots", action="store_true", help="skip the figures")
    ap.add_argument(
        "--double-layer",
        action="store_true",
        help="run section 3.1 as the paper does: multi-priority SSTC + dynamic layer (only)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    if args.double_layer:
        return main_double_layer(args, outdir)
    t_all = time.perf_counter()
    r32 = section_32(args.steps_32, args.seed)
    r31 = section_31(args.steps_31)
    files: list[str] = []
    if not args.no_plots:
        with style():  # the torchfilt house style (palette, grid, spines)
            files = plot_32(r32, outdir) + plot_31(r31, outdir)
    total = time.perf_counter() - t_all

    clean = {
        "section_3_2": {k: v for k, v in r32.items() if not k.startswith("_")},
        "section_3_1": {k: v for k, v in r31.items() if not k.startswith("_")},
        "figures": files,
        "total_seconds": total,
        "environment": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "threads": args.threads,
            "machine": platform.machine(),
        },
        "command": "PYTHONPATH=. python scripts/reproduce_dmc.py "
        f"--out {args.out} --steps-31 {args.steps_31} --steps-32 {args.steps_32} --seed {args.seed}",
    }
    (outdir / "results.json").write_text(json.dumps(clean, indent=2))

    o, f = r32["observer"], r32["filter"]
    print("Section 3.2 (integrating CVs; T = 1, N = 100, Q_Y = 0.01 I, Q_y = I)")
    print(f"  {'k':>6} {'||Y - Yhat|| noise-free':>26} {'relative':>12}")
    for k, val in o["state_error_norm_at"].items():
        print(f"  {k:>6} {val:26.3e} {o['relative_state_error_at'][k]:12.3e}")
    print(
        f"  closed-loop spectral radius of the observer: {r32['closed_loop_spectral_radius']:.4f}"
    )
    print(
        f"  LMG vs ours, max |prediction difference|: noise-free "
        f"{o['lmg_vs_ours_max_abs_prediction_diff']:.2e}, noisy "
        f"{f['lmg_vs_ours_max_abs_prediction_diff']:.2e} (predictions up to "
        f"{f['prediction_scale']:.0f})"
    )
    print(f"  with noise (cov I), k >= {TRANSIENT}:")
    print(f"  {'CV':>4} {'RMSE y(k|k)':>12} {'mean err':>10} {'max |err|':>10} {'RMSE meas.':>11}")
    for j in range(3):
        tr = f["tracking"][f"y{j + 1}"]
        print(
            f"  {'y' + str(j + 1):>4} {tr['rmse_filtered']:12.4f} {tr['mean_error']:10.4f} "
            f"{tr['max_abs_error']:10.4f} {tr['rmse_measurement']:11.4f}"
        )
    print(
        f"  RMSE of all predictions y(k+i|k), i = 1..100: "
        f"{f['tracking']['prediction_rmse_all_horizons']:.4f}"
    )
    print()
    print("Section 3.1 (stable CVs, closed loop; T = 4, N = 100, P = 15, M = 8, mismatch 0.9)")
    print(
        f"  max |y_KF - y_classical| = {r31['max_abs_cv_difference']:.4f} at k = "
        f"{r31['max_abs_cv_difference_at_k']} (CV range {r31['cv_range']:.3f}); "
        f"RMS {r31['rms_cv_difference']:.4f}"
    )
    print(
        f"  max |u_KF - u_classical| = {r31['max_abs_mv_difference']:.4f} at k = "
        f"{r31['max_abs_mv_difference_at_k']}"
    )
    for name, fin in r31["final"].items():
        print(
            f"  final {name:>9}: y = {np.round(fin['y'], 4).tolist()}, "
            f"u = {np.round(fin['u'], 4).tolist()}"
        )
    print()
    print(
        f"Runtimes ({args.threads} thread(s)): 3.2 gain {r32['gain_seconds']:.2f} s, 3.2 run "
        f"{o['run_seconds']:.2f} s per {args.steps_32} samples; 3.1 gain {r31['gain_seconds']:.2f} s,"
        f" closed loops {r31['closed_loop_seconds']['kf']:.1f} s / "
        f"{r31['closed_loop_seconds']['classical']:.1f} s; total {total:.1f} s"
    )
    print(f"Wrote {outdir / 'results.json'} and {len(files)} figures.")
    return clean


def main_double_layer(args: argparse.Namespace, outdir: Path) -> dict:
    t_all = time.perf_counter()
    r = section_31_double_layer(args.steps_31)
    files: list[str] = []
    if not args.no_plots:
        with style():
            files = plot_31(r, outdir, "fig_31dl", " (double-layered DMC)", zone=Z_SOFT)
    total = time.perf_counter() - t_all
    clean = {
        "section_3_1_double_layer": {k: v for k, v in r.items() if not k.startswith("_")},
        "figures": files,
        "total_seconds": total,
        "environment": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "threads": args.threads,
            "machine": platform.machine(),
        },
        "command": "PYTHONPATH=. python scripts/reproduce_dmc.py --double-layer "
        f"--out {args.out} --steps-31 {args.steps_31}",
    }
    tmp = outdir / "results_double_layer.json.tmp"
    tmp.write_text(json.dumps(clean, indent=2))
    tmp.replace(outdir / "results_double_layer.json")

    print("Section 3.1, double-layered DMC (multi-priority SSTC + dynamic layer; T = 4, N = 100,")
    print("P = 15, M = 8, Lambda = diag(3, 5, 3), plant output x 0.9)")
    print(f"  {'':<34} {'KF prediction':>14} {'classical':>10}")
    for key, label in (
        ("max_abs_y", "max |y(k)| (hard limit 0.7)"),
        ("max_abs_u", "max |u(k)| (limit 0.5)"),
        ("max_abs_du", "max |du(k)| (limit 0.1)"),
    ):
        print(f"  {label:<34} {r[key]['kf']:14.4f} {r[key]['classical']:10.4f}")
    print(
        f"  max |y_KF - y_classical| = {r['max_abs_cv_difference']:.4f} at k = "
        f"{r['max_abs_cv_difference_at_k']} (CV range {r['cv_range']:.3f}; RMS "
        f"{r['rms_cv_difference']:.4f}); max |u_KF - u_classical| = "
        f"{r['max_abs_mv_difference']:.4f} at k = {r['max_abs_mv_difference_at_k']}"
    )
    for name in ("kf", "classical"):
        for st in r["steady_states"][name]:
            print(
                f"  {name:>9} k = {st['k']:>3}: y = {np.round(st['y'], 3).tolist()}, "
                f"u = {np.round(st['u'], 3).tolist()}, y_t = {np.round(st['y_target'], 3).tolist()}"
                f", u_t = {np.round(st['u_target'], 3).tolist()}"
            )
            print(f"  {'':>9} SSTC active: {'; '.join(st['sstc_active']) or 'none'}")
            soft = "; ".join(st["dynamic_soft_bounds_violated"]) or "none"
            print(f"  {'':>9} dynamic layer, soft CV bounds violated: {soft}")
    print(
        f"Runtimes ({args.threads} thread(s)): closed loops "
        f"{r['closed_loop_seconds']['kf']:.1f} s (KF) / {r['closed_loop_seconds']['classical']:.1f} s"
        f" (classical); total {total:.1f} s"
    )
    print(f"Wrote {outdir / 'results_double_layer.json'} and {len(files)} figures.")
    return clean


if __name__ == "__main__":
    main()
