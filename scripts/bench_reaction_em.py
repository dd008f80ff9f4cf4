"""2A -> B EM per-iteration times for any checkout: the same script runs an old API and the new.

Issue 27's row "EM on a nonlinear model, T = 400: at least 5x faster than today" compares
checkouts, and ``bench_learning.py`` needs the current API. This script uses only what both
have: ``fit_em(model, y, x0=, P0=, known_channels=, iterations=)``, with the flat ``tol=`` of
an old checkout or ``stopping=`` of a new one, and ``compile="loop"`` where the checkout has
it. Its model (:func:`problem`: learnable rate constant, ``Q`` and ``R`` as
``CholeskyCovariance``) is also ``bench_learning.py``'s 2A -> B row; 8 recordings x 400 steps,
3 iterations (the third halves its step). Run it with each checkout first on ``PYTHONPATH``,
alternating:

    cd OLD && PYTHONPATH=$PWD python /path/to/scripts/bench_reaction_em.py --out OUT/old1.json
    cd NEW && PYTHONPATH=$PWD python scripts/bench_reaction_em.py --out OUT/new1.json

Prints a table (seconds per iteration) and writes JSON.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _common import environment
from torch import Tensor, nn

import torchfilt
from torchfilt.models import CholeskyCovariance
from torchfilt.systems import reaction
from torchfilt.training import fit_em

D = torch.float64


class Transition(nn.Module):
    """The 2A -> B Euler step with a learnable rate constant."""

    def __init__(self, k1: float) -> None:
        super().__init__()
        self.k1 = nn.Parameter(torch.tensor(k1, dtype=D))

    def forward(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        return reaction.transition(x, k1=self.k1)


def problem(B: int, T: int) -> tuple[torchfilt.StateSpaceModel, dict[str, Tensor]]:
    """The 2A -> B model from ``0.8 K1`` and inflated noises, and ``B`` simulated recordings of
    ``T`` steps with the prior (``y``, ``m0``, ``P0``)."""
    sim = reaction.simulate_truth(B, steps=T, seed=0)
    model = torchfilt.StateSpaceModel(
        Transition(0.8 * reaction.K1),
        reaction.measurement,
        Q=CholeskyCovariance(4 * torch.diag(torch.tensor(reaction.Q_DIAG, dtype=D))),
        R=CholeskyCovariance(torch.tensor([[2 * reaction.R_VAR]], dtype=D)),
    )
    return model, dict(y=sim.measurements, m0=reaction.prior_mean(), P0=reaction.prior_cov())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="JSON file to write")
    ap.add_argument("--cpu", type=int, default=0, help="core to pin to")
    ap.add_argument("--iterations", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    warnings.simplefilter("ignore")
    params = inspect.signature(fit_em).parameters
    if "stopping" in params:
        from torchfilt.optim import StoppingOptions

        stop: dict[str, Any] = {"stopping": StoppingOptions(tol=0.0, rtol=0.0)}
    else:
        stop = {"tol": 0.0}
    modes: list[bool | str] = [False] + (["loop"] if "compile" in params else [])
    warm, dw = problem(1, 10)  # the first L-BFGS imports torch's compiler stack
    fit_em(warm, dw["y"], x0=dw["m0"], P0=dw["P0"], known_channels=[0], iterations=1)
    rows: list[dict[str, Any]] = []
    for mode in modes:
        model, d = problem(8, 400)
        fit = fit_em(
            model, d["y"], x0=d["m0"], P0=d["P0"], known_channels=[0],
            iterations=args.iterations, **stop, **({"compile": mode} if mode else {}),
        )  # fmt: skip
        el = np.diff([0.0] + [r["elapsed"] for r in fit.history]).tolist()
        rows.append({"compile": mode, "per_iteration_s": el, "final": fit.log_likelihood})
        print(f"compile={mode!r}: " + ", ".join(f"{t:.3f}" for t in el), file=sys.stderr)
    print(f"{'compile':>10}  " + "  ".join(f"iter {i + 1:>2}" for i in range(args.iterations)))
    for r in rows:
        print(f"{r['compile']!r:>10}  " + "  ".join(f"{t:7.3f}" for t in r["per_iteration_s"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "torchfilt": str(Path(torchfilt.__file__).parent),
        "rows": rows,
        "environment": environment(),
    }
    args.out.write_text(json.dumps(payload, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
