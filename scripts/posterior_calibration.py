"""Is the Laplace posterior of a fit calibrated? Re-entry radar, many independent training sets.

For each of ``--sets`` training sets (``--runs`` recordings each, from the paper's truth: the same
trajectory, new radar noise) the script finds the maximum-likelihood ``(log gamma, log gain,
offset)`` of the CKF's likelihood (Newton steps from the truth, ``Q = 0`` and ``R`` known) and
both covariances of :func:`torchfilt.parameter_posterior`. If a covariance is calibrated, the
errors' z-scores ``(theta_hat - theta_true) / sd`` have RMS 1 and 95% of the intervals
``theta_hat +- 1.96 sd`` hold the truth.

    python scripts/posterior_calibration.py --out scripts/results/cpu-2026-12-02-posterior
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import torch
from torch import nn

import torchfilt
from torchfilt.models import AffineSensor, FunctionModel, StateSpaceModel
from torchfilt.systems import reentry

DT = torch.float64
NAMES = ("transition._fn.log_gamma", "measurement.log_scale", "measurement.bias")


class Drag(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.log_gamma = nn.Parameter(torch.tensor(math.log(reentry.GAMMA), dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return reentry.transition(x, gamma=self.log_gamma.exp())


def radar() -> StateSpaceModel:
    """The true re-entry model with ``log gamma``, the radar gain and offset as parameters."""
    f = FunctionModel(Drag(), torch.zeros(3, 3, dtype=DT), name="transition")
    g = FunctionModel(reentry.measurement, torch.tensor([[reentry.R_VAR]], dtype=DT), out_dim=1)
    return StateSpaceModel(f, AffineSensor(g))


def mle(model: StateSpaceModel, y: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor) -> None:
    """Newton steps on the CKF's log-likelihood, in place."""
    params = dict(model.named_parameters())
    for _ in range(6):
        post = torchfilt.parameter_posterior(model, y, x0=x0, P0=P0, parameters=NAMES)
        ll = torchfilt.CKF(model).filter(y, x0=x0, P0=P0).log_likelihood.sum()
        grads = torch.autograd.grad(ll, [params[k] for k in NAMES])
        g = torch.cat([t.reshape(-1) for t in grads])
        step = post.cov @ g
        with torch.no_grad():
            i = 0
            for k in NAMES:
                p = params[k]
                p.add_(step[i : i + p.numel()].reshape(p.shape))
                i += p.numel()
        if float(step.abs().div(post.std()).max()) < 1e-6:
            break


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", type=int, default=20)
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("out/posterior_calibration"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT), reentry.prior_cov()
    truth = torch.tensor([math.log(reentry.GAMMA), 0.0, 0.0], dtype=DT)
    z: dict[str, list[list[float]]] = {"hessian": [], "sandwich": []}
    t0 = time.perf_counter()
    for s in range(args.sets):
        y = reentry.simulate_truth(args.runs, seed=args.seed + s).measurements
        model = radar()
        mle(model, y, x0, P0)
        for cov in z:
            post = torchfilt.parameter_posterior(
                model,
                y,
                x0=x0,
                P0=P0,
                parameters=NAMES,
                covariance=cov,  # type: ignore[arg-type]
            )
            z[cov].append(((post.mean - truth) / post.std()).tolist())
        print(f"set {s + 1}/{args.sets}: z (hessian) {[round(v, 2) for v in z['hessian'][-1]]}")
    elapsed = time.perf_counter() - t0
    rows: dict[str, dict[str, list[float]]] = {}
    for cov, zs in z.items():
        Z = torch.tensor(zs, dtype=DT)
        rows[cov] = {
            "rms_z": Z.pow(2).mean(0).sqrt().tolist(),
            "coverage95": (Z.abs() <= 1.96).to(DT).mean(0).tolist(),
        }
    head = f"{'covariance':<10}  " + "  ".join(
        f"{n.split('.')[-1]:>16}" for n in ("log_gamma", "log_gain", "offset")
    )
    lines = [head, "-" * len(head)]
    for cov, r in rows.items():
        cells = "  ".join(
            f"{a:>6.2f} ({c:4.0%})   " for a, c in zip(r["rms_z"], r["coverage95"], strict=True)
        )
        lines.append(f"{cov:<10}  {cells}")
    table = "\n".join(lines)
    print(f"\nRMS z-score (95% interval coverage) over {args.sets} sets of {args.runs} runs")
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    out = {
        "sets": args.sets,
        "runs": args.runs,
        "seed": args.seed,
        "names": list(NAMES),
        "rows": rows,
        "z": z,
        "table": table,
        "seconds": elapsed,
        "environment": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "load_average": list(os.getloadavg()),
        },
    }
    tmp = args.out / "results.json.tmp"
    tmp.write_text(json.dumps(out, indent=2), encoding="utf-8")
    tmp.replace(args.out / "results.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
