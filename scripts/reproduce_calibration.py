"""Honest uncertainty from the filter likelihood: a two-tank process with slow sensor drift.

Two tanks in series, the first fed by a pump, each draining through an orifice
(``dt = 1 s``):

    h1' = h1 + dt (u + w - k sqrt(h1)),     h2' = h2 + dt (k sqrt(h1) - k sqrt(h2)),

with an inflow disturbance ``w`` that is autocorrelated (AR(1), ``RHO_W``), and level sensors

    y1 = h1 + v1,     y2 = h2 + d + v2,

whose second one drifts slowly (``d``: AR(1), ``RHO_D`` = 0.995, a time constant of 200 s) on top
of white noise ``v``. Neither the drift nor the colour of ``w`` is in any model.

GPs learn the transition and the sensors from logged states of ``TRAIN_RECORDINGS`` recordings
(one-step pairs: they see the one-step scatter of the residuals, as in the Plaza2 example). The
"learned" filter takes Q and R from their variances; the "calibrated" one adds
:func:`torchfilt.calibrate` on the same recordings' measurements and inputs only (no states).
Both filter ``TEST_RECORDINGS`` held-out recordings from the prior; the table gives RMSE, mean
NEES (n = 2; consistent: 2), 95% coverage per state and the mean NIS per measurement (1).

Prints the table, writes ``results.json`` and ``calibration.png`` (NEES over time, and the drift
next to the filters' 2-sd bands of tank 2) to ``--out``.

    python scripts/reproduce_calibration.py --out out/calibration
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import torch
from matplotlib.figure import Figure
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.models.drift import DriftModel, with_sensor_drift
from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.optim import OptimizerOptions, WindowOptions
from torchfilt.plots import PALETTE, style
from torchfilt.plots.style import TRUTH_COLOR

DT = torch.float64
#: orifice coefficient, sample time (s)
K, DT_S = 0.2, 1.0
#: inflow disturbance: AR(1) coefficient and innovation sd
RHO_W, SD_W = 0.9, 0.004
#: sensor drift of tank 2: AR(1) coefficient and stationary sd; white sensor noise sd
RHO_D, SD_D, SD_V = 0.995, 0.05, 0.02
#: recordings and their length
TRAIN_RECORDINGS, TEST_RECORDINGS, STEPS = 8, 16, 300
#: transition pairs the GP trains on
PAIRS = 600
#: prior around the true initial levels
P0_SD = 0.1
#: calibration windows, burn-in, iterations, Adam step
CAL_WINDOW, CAL_BURN_IN, CAL_ITERATIONS, CAL_LR = 60, 15, 50, 0.2
N = 2
#: initial drift time constant (s) and sd of the drift-state model (fitted by the likelihood)
DRIFT_TAU0, DRIFT_SD0 = 50.0, 0.02


def nominal(x: Tensor, u: Tensor | None) -> Tensor:
    """The tank physics (noise-free), ``(..., 2)`` levels and ``(..., 1)`` pump flow."""
    assert u is not None
    h1, h2 = x[..., 0], x[..., 1]
    q1 = K * h1.clamp_min(0.0).sqrt()
    q2 = K * h2.clamp_min(0.0).sqrt()
    return torch.stack([h1 + DT_S * (u[..., 0] - q1), h2 + DT_S * (q1 - q2)], -1)


def simulate(recs: int, seed: int) -> dict[str, Tensor]:
    """Recordings: states ``(R, T+1, 2)``, inputs ``(R, T, 1)`` (``u[k]`` drives step ``k``),
    measurements ``(R, T, 2)`` of the states after each step, and the drift ``(R, T)``."""
    g = torch.Generator().manual_seed(seed)
    # pump flow: piecewise constant, a new level every 50 s
    levels = 0.2 + 0.2 * torch.rand(recs, STEPS // 50 + 1, generator=g, dtype=DT)
    u = levels.repeat_interleave(50, dim=1)[:, :STEPS, None]
    x = ((u[:, 0, 0] / K) ** 2)[:, None].expand(recs, N).clone()
    x = x * (1 + 0.2 * torch.randn(recs, N, generator=g, dtype=DT))
    w = torch.zeros(recs, dtype=DT)
    d = SD_D * torch.randn(recs, generator=g, dtype=DT)
    xs, ys, ds = [x], [], []
    sd_e = SD_D * (1 - RHO_D**2) ** 0.5
    for t in range(STEPS):
        w = RHO_W * w + SD_W * torch.randn(recs, generator=g, dtype=DT)
        x = nominal(x, u[:, t]) + torch.stack([DT_S * w, torch.zeros_like(w)], -1)
        d = RHO_D * d + sd_e * torch.randn(recs, generator=g, dtype=DT)
        v = SD_V * torch.randn(recs, N, generator=g, dtype=DT)
        ys.append(torch.stack([x[:, 0], x[:, 1] + d], -1) + v)
        xs.append(x)
        ds.append(d)
    return {"x": torch.stack(xs, 1), "u": u, "y": torch.stack(ys, 1), "d": torch.stack(ds, 1)}


def fit_models(train: dict[str, Tensor], seed: int, iterations: int) -> torchfilt.StateSpaceModel:
    """GP transition (physics as prior mean, residual from levels and flow) and GP sensors."""
    x, u, y = train["x"], train["u"], train["y"]
    xk, uk, xn = x[:, :-1].reshape(-1, N), u.reshape(-1, 1), x[:, 1:].reshape(-1, N)
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(xk.shape[0], generator=g)[:PAIRS]
    f = GPTransition.fit(
        xk[idx],
        uk[idx],
        xn[idx],
        prior_mean=nominal,
        iterations=iterations,
        seed=seed,
        progress=False,
    )
    h = GPMeasurement.fit(
        x[:, 1:].reshape(-1, N)[idx],
        y.reshape(-1, N)[idx],
        prior_mean=lambda z: z,
        inputs=[[0], [1]],
        iterations=iterations,
        seed=seed,
        progress=False,
    )
    return torchfilt.StateSpaceModel(f, h)


def score(model: torchfilt.StateSpaceModel, test: dict[str, Tensor]) -> tuple[dict[str, Any], Any]:
    """RMSE, NEES and coverage of the physical states (the first ``N``), NIS per measurement."""
    x0 = test["x"][:, 0]
    P0 = (P0_SD**2) * torch.eye(N, dtype=DT)
    if isinstance(model, DriftModel):
        x0, P0 = model.prior(x0, P0)
    with torch.no_grad():
        full = torchfilt.CKF(model).filter(test["y"], test["u"], x0=x0, P0=P0)
    res = full._replace(mean=full.mean[..., :N], cov=full.cov[..., :N, :N])
    value, dof = torchfilt.nis(full)
    truth = test["x"][:, 1:]
    ne = torchfilt.nees(truth, res.mean, res.cov)
    return {
        "rmse": torchfilt.rmse(truth.reshape(-1, N), res.mean.reshape(-1, N)).tolist(),
        "nees_mean": float(ne.mean()),
        "coverage95": torchfilt.coverage(
            truth.reshape(-1, N), res.mean.reshape(-1, N), res.cov.reshape(-1, N, N)
        ).tolist(),
        "nis_per_measurement": float(value.sum() / dof.sum()),
    }, (res, ne)


def plot(test: dict[str, Tensor], runs: dict[str, Any]) -> Figure:
    with style():
        fig = Figure(figsize=(9.0, 6.5))
        ax1, ax2 = fig.subplots(2, 1, sharex=True)
        t = torch.arange(1, STEPS + 1).numpy()
        for i, (name, (res, ne)) in enumerate(runs.items()):
            ax1.semilogy(t, ne.mean(0).numpy(), color=PALETTE[i], label=name)
            sd = res.cov[0, :, 1, 1].sqrt().numpy()
            err = (res.mean[0, :, 1] - test["x"][0, 1:, 1]).numpy()
            ax2.plot(t, err, color=PALETTE[i], lw=1.0, label=f"{name}: error")
            ax2.fill_between(t, -2 * sd, 2 * sd, color=PALETTE[i], alpha=0.2, lw=0)
        ax1.axhline(N, color=TRUTH_COLOR, ls="--", lw=1.0, label=f"consistent: n = {N}")
        ax1.set_ylabel("NEES (mean over recordings)")
        ax1.legend(loc="upper right")
        ax2.plot(
            t, -test["d"][0].numpy(), color=TRUTH_COLOR, ls=":", lw=1.2, label="- sensor drift"
        )
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("tank 2 level error [m]")
        ax2.legend(loc="upper right", ncols=2)
        fig.suptitle(
            "Two tanks with a drifting level sensor: learned filter, before and after calibration"
        )
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/calibration"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=60, help="GP training iterations")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    train = simulate(TRAIN_RECORDINGS, seed=args.seed)
    test = simulate(TEST_RECORDINGS, seed=args.seed + 1000)
    t0 = time.perf_counter()
    learned = fit_models(train, args.seed, args.iterations)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    cal = torchfilt.calibrate(
        learned,
        train["y"],
        train["u"],
        x0=train["x"][:, 0],
        P0=(P0_SD**2) * torch.eye(N, dtype=DT),
        iterations=CAL_ITERATIONS,
        windows=WindowOptions(window=CAL_WINDOW, burn_in=CAL_BURN_IN),
        optimizer=OptimizerOptions(lr=CAL_LR),
    )
    cal_s = time.perf_counter() - t0
    # the same, with a drift state on the tank-2 sensor (time constant and sd fitted too)
    t0 = time.perf_counter()
    drifting = with_sensor_drift(learned, [1], time_constant=DRIFT_TAU0, sd=DRIFT_SD0)
    dx0, dP0 = drifting.prior(train["x"][:, 0], (P0_SD**2) * torch.eye(N, dtype=DT))
    cal_d = torchfilt.calibrate(
        drifting,
        train["y"],
        train["u"],
        x0=dx0,
        P0=dP0,
        iterations=CAL_ITERATIONS,
        windows=WindowOptions(window=CAL_WINDOW, burn_in=CAL_BURN_IN),
        optimizer=OptimizerOptions(lr=CAL_LR),
    )
    cal_d_s = time.perf_counter() - t0
    true_model = torchfilt.StateSpaceModel(
        nominal,
        lambda z, u: z,
        Q=torch.diag(torch.tensor([(DT_S * SD_W) ** 2 / (1 - RHO_W**2), 1e-12], dtype=DT)),
        R=torch.diag(torch.tensor([SD_V**2, SD_V**2 + SD_D**2], dtype=DT)),
    )
    rows: dict[str, Any] = {}
    runs: dict[str, Any] = {}
    for name, model in {
        "true physics, white-noise Q and R (stationary variances)": true_model,
        "learned (GP variances as Q and R)": learned,
        "learned, calibrated by the filter likelihood": cal.model,
        "learned + drift state on sensor 2, calibrated": cal_d.model,
    }.items():
        rows[name], runs[name] = score(model, test)
    headers = [
        "filter",
        "RMSE h1 [m]",
        "RMSE h2 [m]",
        "NEES mean",
        "cov95 h1",
        "cov95 h2",
        "NIS/meas",
    ]
    body = [
        [
            k,
            f"{r['rmse'][0]:.4f}",
            f"{r['rmse'][1]:.4f}",
            f"{r['nees_mean']:.3g}",
            f"{r['coverage95'][0]:.2f}",
            f"{r['coverage95'][1]:.2f}",
            f"{r['nis_per_measurement']:.3g}",
        ]
        for k, r in rows.items()
    ]
    print(
        f"two tanks, drifting sensor: {TRAIN_RECORDINGS} training / {TEST_RECORDINGS} test "
        f"recordings of {STEPS} s; NEES consistent at n = {N}"
    )
    print(table(headers, body))
    print(
        f"GP fit {fit_s:.0f} s, calibration {cal_s:.0f} s ({cal.fit.iterations} iterations, "
        f"{cal.fit.stopped}), with the drift state {cal_d_s:.0f} s; fitted drift: time constant "
        f"{cal_d.parameters['drift']['time_constant'][0]:.0f} s (true "
        f"{-DT_S / math.log(RHO_D):.0f}), sd {cal_d.parameters['drift']['sd'][0]:.3g} (true {SD_D})"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    plot(
        {k: v[:1] for k, v in test.items()}, {k: v for k, v in runs.items() if "learned" in k}
    ).savefig(args.out / "calibration.png")
    write_json(
        args.out / "results.json",
        {
            "experiment": "two-tank with sensor drift",
            "command": " ".join(["python", "scripts/reproduce_calibration.py", *sys.argv[1:]]),
            "settings": {
                "rho_w": RHO_W,
                "sd_w": SD_W,
                "rho_d": RHO_D,
                "sd_d": SD_D,
                "sd_v": SD_V,
                "train_recordings": TRAIN_RECORDINGS,
                "test_recordings": TEST_RECORDINGS,
                "steps": STEPS,
                "pairs": PAIRS,
                "window": CAL_WINDOW,
                "burn_in": CAL_BURN_IN,
                "iterations": CAL_ITERATIONS,
                "lr": CAL_LR,
            },
            "calibration_with_drift_state": {
                **cal_d.parameters,
                "stopped": cal_d.fit.stopped,
                "iterations": cal_d.fit.iterations,
            },
            "calibration": {
                **cal.parameters,
                "stopped": cal.fit.stopped,
                "iterations": cal.fit.iterations,
                "log_likelihood": [cal.fit.initial_log_likelihood, cal.fit.log_likelihood],
            },
            "results": rows,
            "timings_s": {
                "fit GPs": fit_s,
                "calibrate": cal_s,
                "calibrate with drift state": cal_d_s,
                "total": time.perf_counter() - t_start,
            },
            "environment": environment(),
        },
    )
    print(f"wrote results.json and calibration.png to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
