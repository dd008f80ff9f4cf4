"""Evidence for a follow-up, not a library feature: where measurement-only EM stops with
``"no improvement"`` (the CKF's approximate E-step finds no M-step that raises the filter
likelihood), what does the likelihood method add when it starts from EM's end?

The cases and their settings are those of ``scripts/reproduce_measurement_only.py`` (re-entry
from ranges only, 8 training runs, 100 test runs; 2A -> B from the total pressure, 8 / 50, the
GP residual on the textbook model and the grey-box ``k1``). Every fit here uses
``noise_scale="none"`` (all training runs, no held-out scaling), so the rows compare the fits
themselves: EM alone (its defaults otherwise), the likelihood method alone, and EM followed by
the likelihood method from EM's model (its ``iterations`` budget again).

Run from a checkout: ``PYTHONPATH=. python
scripts/results/cpu-2026-12-05-em-then-likelihood/em_then_likelihood.py --out OUT.json``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # scripts/
import reproduce_measurement_only as rmo

import torchfilt
from torchfilt.optim import OptimizerOptions
from torchfilt.systems import reaction, reentry

DT = torch.float64


def _fit(
    model: Any, y: Any, x0: Any, P0: Any, method: str, iterations: int, lr: float | None
) -> Any:
    return torchfilt.fit_measurement_only(
        model, y, x0=x0, P0=P0, known_channels=[0], method=method,  # type: ignore[arg-type]
        iterations=iterations, noise_scale="none",
        optimizer=OptimizerOptions("lbfgs", lr=lr) if method == "likelihood" else None,
    )  # fmt: skip


def _three(
    build: Any, y: Any, x0: Any, P0: Any, score: Any, em_its: int, lf_its: int, lr: float | None
) -> dict[str, Any]:
    """EM alone, the likelihood method alone, EM then the likelihood method: scored rows."""
    out: dict[str, Any] = {}
    torch.manual_seed(0)
    t0 = time.perf_counter()
    em = _fit(build(), y, x0, P0, "em", em_its, None)
    t_em = time.perf_counter() - t0
    out["em"] = {**score(em.model), "stopped": em.stopped, "iterations": em.iterations,
                 "log_likelihood": em.log_likelihood, "train_s": t_em}  # fmt: skip
    t0 = time.perf_counter()
    lf = _fit(em.model, y, x0, P0, "likelihood", lf_its, lr)
    out["em, then likelihood"] = {**score(lf.model), "stopped": lf.stopped,
                                  "iterations": lf.iterations, "log_likelihood": lf.log_likelihood,
                                  "train_s": t_em + time.perf_counter() - t0}  # fmt: skip
    torch.manual_seed(0)
    t0 = time.perf_counter()
    alone = _fit(build(), y, x0, P0, "likelihood", lf_its, lr)
    out["likelihood"] = {**score(alone.model), "stopped": alone.stopped,
                         "iterations": alone.iterations, "log_likelihood": alone.log_likelihood,
                         "train_s": time.perf_counter() - t0}  # fmt: skip
    for k, r in out.items():
        print(f"  {k:<22} RMSE {r.get('rmse', r.get('rmse_altitude')):10.4g}  NEES "
              f"{r['nees']:8.3g}  LPD {r['log_predictive_density']:8.4f}  {r['stopped']} after "
              f"{r['iterations']}  LL {r['log_likelihood']:.2f}  {r['train_s']:.0f} s", flush=True)  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    result: dict[str, Any] = {}
    # re-entry (the script's lr: the gain's gradient is 1e5 times the offset's)
    train = reentry.simulate_truth(8, seed=11)
    test = reentry.simulate_truth(100, seed=12)
    x0, P0 = torch.tensor(reentry.PRIOR_MEAN, dtype=DT), reentry.prior_cov()
    print("re-entry, ranges only (true model RMSE altitude 210.8, NEES 3.74)")
    result["reentry"] = _three(
        rmo.radar_model, train.measurements, x0, P0,
        lambda m: rmo.radar_evaluate(m, test), 30, 30, 0.01,
    )  # fmt: skip
    # 2A -> B
    train = reaction.simulate_truth(8, start="paper", seed=1)
    test = reaction.simulate_truth(50, start="paper", seed=2)
    x0, P0 = reaction.prior_mean("paper", DT), reaction.prior_cov(DT)
    with torch.no_grad():
        sm = torchfilt.filters.rts_smooth(
            torchfilt.CKF(rmo.nominal_model()).filter(train.measurements, x0=x0, P0=P0)
        )
    cloud = sm.mean.reshape(-1, 2)
    print("2A -> B GP residual (state-trained GP RMSE 0.371)")
    result["reaction GP residual"] = _three(
        lambda: rmo.learnable(cloud), train.measurements, x0, P0,
        lambda m: rmo.evaluate(m, test), 40, 15, None,
    )  # fmt: skip
    print("2A -> B grey-box k1 (state-trained RMSE 0.385)")
    result["reaction grey-box k1"] = _three(
        rmo.grey_box, train.measurements, x0, P0, lambda m: rmo.evaluate(m, test), 40, 15, None
    )
    args.out.write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
