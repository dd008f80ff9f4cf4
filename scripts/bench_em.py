"""One linear EM iteration: the exact-Kalman E-step against the former CKF + generic RTS E-step.

A 4-state, 2-output linear-Gaussian model with one input, 20 recordings x 500 steps, float64, one
thread. Times (median of ``--repeats`` after a warm-up): the E-step of ``fit_em`` on a linear
model (the exact Kalman filter and RTS smoother, :func:`torchfilt.filters.kalman_smoother`), the
former E-step (the CKF's filter and :func:`torchfilt.filters.rts_smooth`, a Python loop over the
steps), the closed-form M-step, and one iteration (M-step + E-step) each way; also the subspace
start (:func:`torchfilt.models.subspace_start`). The two E-steps' smoothed moments are compared
(``max_diff``), so both compute the same thing.

    python scripts/bench_em.py --out out/bench_em
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, timeit, write_json

from torchfilt.cubature import SphericalRadialRule
from torchfilt.filters import CKF
from torchfilt.models import LinearGaussianModel, subspace_start
from torchfilt.training.em_steps import (
    SmoothedPairs,
    _EMProblem,
    _linear_m_step,
    _linear_start,
    smoothed_pairs,
)
from torchfilt.training.likelihood import _recordings


def _problem(
    reps: int, T: int, seed: int = 0
) -> tuple[LinearGaussianModel, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    n, m = 4, 2
    V = np.linalg.qr(rng.standard_normal((n, n)))[0]
    A = V @ np.diag([0.9, 0.7, -0.6, 0.4]) @ V.T
    H = rng.standard_normal((m, n))
    B = np.ones((n, 1))
    Q, R = 0.01 * np.eye(n), 0.01 * np.eye(m)
    u = rng.standard_normal((reps, T, 1))
    y = np.zeros((reps, T, m))
    for k in range(reps):
        x = np.zeros(n)
        for t in range(T):
            x = A @ x + B @ u[k, t] + rng.multivariate_normal(np.zeros(n), Q)
            y[k, t] = H @ x + rng.multivariate_normal(np.zeros(m), R)
    model = LinearGaussianModel(*(torch.tensor(a) for a in (A, H, Q, R, B)))
    return model, torch.tensor(y), torch.tensor(u)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("out/bench_em"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    model, y, u = _problem(args.recordings, args.steps)
    n, f64 = 4, torch.float64
    recs = _recordings(model, y, u, torch.zeros(n, dtype=f64), torch.eye(n, dtype=f64), f64)
    valid = torch.ones(y.shape[0], y.shape[1], dtype=torch.bool)
    lin = _linear_start(model, f64, [0])
    em = _EMProblem(model, lin, [], recs, valid, [0], SphericalRadialRule(), None, True, 1, 0)

    def old_e_step() -> tuple[float, SmoothedPairs]:
        with torch.no_grad():
            res = CKF(em.current(), rule=em.rule).filter(em.Y, em.U, x0=em.X0, P0=em.C0)
            return float(res.log_likelihood.sum()), smoothed_pairs(res, em.X0, em.C0)

    ll_new, sp_new = em.e_step()
    ll_old, sp_old = old_e_step()
    diff = max(float((a - b).abs().max()) for a, b in zip(sp_new, sp_old, strict=True))

    def m_step() -> None:
        _linear_m_step(em.lin, sp_new, em.Y, em.U, em.valid, em.known, True)  # type: ignore[arg-type]

    r = args.repeats
    t_new, t_old = timeit(em.e_step, r), timeit(old_e_step, r)
    t_m = timeit(m_step, r)
    t_start = timeit(lambda: subspace_start(model, y, u, known_channels=[0]), 1, warmup=0)
    rows = [
        ["E-step, exact Kalman (now)", t_new * 1e3],
        ["E-step, CKF + rts_smooth (before)", t_old * 1e3],
        ["M-step (closed form)", t_m * 1e3],
        ["EM iteration now", (t_new + t_m) * 1e3],
        ["EM iteration before", (t_old + t_m) * 1e3],
        ["subspace start (once)", t_start * 1e3],
    ]
    ratio = (t_old + t_m) / (t_new + t_m)
    print(
        f"{args.recordings} recordings x {args.steps} steps, n = 4, m = 2, one input, float64, 1 thread"
    )
    print(table(["what", "ms"], rows))
    print(f"iteration speed-up (before / now): {ratio:.3g}; E-step {t_old / t_new:.3g}")
    print(f"max |difference| of the smoothed moments: {diff:.3g}; log-lik {ll_new - ll_old:.3g}")
    write_json(
        args.out / "bench_em.json",
        {
            "config": vars(args) | {"out": str(args.out)},
            "environment": environment(),
            "ms": {k: v for k, v in rows},
            "iteration_ratio": ratio,
            "e_step_ratio": t_old / t_new,
            "max_diff": diff,
        },
    )


if __name__ == "__main__":
    main()
