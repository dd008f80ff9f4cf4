"""Learning from measurements alone, beside the same model trained with states.

2A -> B (``torchfilt.systems.reaction``) from total pressure only. The learned model is an
:class:`~torchfilt.models.InducingTransition` on a *nominal* physics model (the textbook Euler step
with a guessed rate constant ``k1 = K1_NOMINAL``, half the true one) with a learnable linear
correction, a GP residual on ``M`` inducing points, learnable ``Q`` and ``R``, and the known
measurement map ``PA + PB`` (the gauge). It is trained three ways on the same training recordings:

* ``states``: with the logged states (maximum likelihood of the transitions ``x_{t-1} -> x_t``);
* ``em``: from the measurements alone by EM with the cubature RTS smoother;
* ``likelihood``: from the measurements alone by the filter's innovation likelihood;

and every model, with the true model and the nominal (textbook) one, is run by the CKF on the same
held-out recordings from the papers' prior ``N([5, 5], 36 I)``. Reported: filtering RMSE over all
states and steps, mean NEES (n = 2: consistent 2), 95% coverage (mean over states), the held-out
log predictive density of the measurements per measurement, and the training time.

Not done yet (see the README): re-entry and Plaza2.

    python scripts/reproduce_measurement_only.py --out scripts/results/cpu-2026-12-01-measonly
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import torch
from matplotlib.figure import Figure

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json

import torchfilt
from torchfilt.models import DiagonalCovariance, InducingTransition, StateSpaceModel
from torchfilt.systems import reaction

DT = torch.float64
K1_NOMINAL = 0.08
INDUCING = 8


def nominal_step(x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
    return reaction.transition(x, k1=K1_NOMINAL)


def nominal_model() -> StateSpaceModel:
    Q = torch.diag(torch.tensor(reaction.Q_DIAG, dtype=DT))
    R = torch.tensor([[reaction.R_VAR]], dtype=DT)
    return StateSpaceModel(nominal_step, reaction.measurement, Q=Q, R=R)


def learnable(cloud: torch.Tensor) -> StateSpaceModel:
    f = InducingTransition(
        2, INDUCING, nominal=nominal_step, outputscale=1e-4, lengthscale=2.0, dtype=DT
    )
    f.init_inducing(cloud)
    return StateSpaceModel(
        f,
        reaction.measurement,
        Q=DiagonalCovariance(torch.full((2,), 1e-3, dtype=DT)),
        R=DiagonalCovariance(torch.full((1,), 0.05, dtype=DT)),
    )


def fit_with_states(
    model: StateSpaceModel, states: torch.Tensor, y: torch.Tensor, iterations: int
) -> None:
    """Maximum likelihood of the logged transitions under the model's transition density, and
    ``R`` from the residuals of the known measurement map."""
    xa, xb = states[:, :-1].reshape(-1, 1, 2), states[:, 1:].reshape(-1, 1, 2)
    with torch.no_grad():
        r2 = (y - reaction.measurement(states)).pow(2).mean()
        model.measurement.noise_param.raw.copy_(r2.log().reshape(1))  # type: ignore[union-attr]
    params = [p for n, p in model.named_parameters() if not n.startswith("measurement")]
    opt = torch.optim.LBFGS(params, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        pred = model.transition.predict(xa)
        cov = model.transition.noise_cov() + torch.diag_embed(pred.var)  # type: ignore[operator]
        d = torch.distributions.MultivariateNormal(pred.mean, cov)
        loss = -d.log_prob(xb).mean()
        loss.backward()
        return loss

    opt.step(closure)  # type: ignore[arg-type]


def evaluate(model: StateSpaceModel, test: Any) -> dict[str, float]:
    x0, P0 = reaction.prior_mean("paper", DT), reaction.prior_cov(DT)
    with torch.no_grad():
        res = torchfilt.CKF(model).filter(test.measurements, x0=x0, P0=P0)
    x = test.states
    ok = torch.isfinite(res.mean).all(-1).all(-1)
    err = res.mean[ok] - x[ok]
    nees = torchfilt.nees(x[ok], res.mean[ok], res.cov[ok])
    cov = torchfilt.coverage(x[ok], res.mean[ok], res.cov[ok])
    return {
        "rmse": float(err.pow(2).mean().sqrt()),
        "rmse_last80": float(err[:, 20:].pow(2).mean().sqrt()),
        "nees": float(nees.mean()),
        "coverage95": float(cov.mean()),
        "log_predictive_density": float(res.log_likelihood[ok].sum()) / int(ok.sum() * x.shape[1]),
        "finite_runs": int(ok.sum()),
    }


# ----------------------------------------------------------------------------------- linear
LIN_A = torch.tensor([[0.8, 0.4], [-0.4, 0.6]], dtype=DT)
LIN_Q = torch.tensor([[0.2, 0.05], [0.05, 0.3]], dtype=DT)
LIN_R = torch.tensor([[0.05, 0.0], [0.0, 0.1]], dtype=DT)
LIN_H = torch.eye(2, dtype=DT)


def linear_case(train_runs: int, test_runs: int, seed: int, iterations: int) -> dict[str, Any]:
    """A linear-Gaussian system with the full gauge (H = I known): every state is pinned."""
    from torchfilt.models import CholeskyCovariance, LinearGaussianModel, LinearModel

    true = LinearGaussianModel(LIN_A, LIN_H, LIN_Q, LIN_R)
    x0, P0 = torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)
    g = torch.Generator().manual_seed(seed + 10)
    tr = torchfilt.simulate(true, 100, x0, batch_shape=(train_runs,), generator=g)
    te = torchfilt.simulate(true, 100, x0, batch_shape=(test_runs,), generator=g)
    A0 = torch.tensor([[0.5, 0.2], [-0.1, 0.4]], dtype=DT)
    rows: dict[str, dict[str, Any]] = {
        "true model": {**_evaluate(true, te, x0, P0), "train_s": 0.0}
    }
    t0 = time.perf_counter()
    xa, xb = tr.states[:, :-1].reshape(-1, 2), tr.states[:, 1:].reshape(-1, 2)
    A_ls = torch.linalg.lstsq(xa, xb).solution.mT
    Q_ls = torch.cov((xb - xa @ A_ls.mT).mT)
    e = tr.measurements.reshape(-1, 2) - tr.states.reshape(-1, 2)
    st = LinearGaussianModel(A_ls, LIN_H, Q_ls, torch.cov(e.mT))
    rows["trained with states"] = {**_evaluate(st, te, x0, P0), "train_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    em = torchfilt.fit_measurement_only(
        LinearGaussianModel(A0, LIN_H, 0.3 * torch.eye(2, dtype=DT), torch.eye(2, dtype=DT)),
        tr.measurements,
        x0=x0,
        P0=P0,
        known_channels=[0, 1],
        method="em",
        iterations=iterations,
    )
    rows["measurements only (em)"] = {
        **_evaluate(em.model, te, x0, P0),
        "train_s": time.perf_counter() - t0,
    }
    f = InducingTransition(2, 0, linear=A0, dtype=DT)
    f.bias.requires_grad_(False)
    h = LinearModel(LIN_H, CholeskyCovariance(torch.eye(2, dtype=DT)), name="measurement")
    lm = StateSpaceModel(f, h, Q=CholeskyCovariance(0.3 * torch.eye(2, dtype=DT)))
    t0 = time.perf_counter()
    torchfilt.fit_measurement_only(
        lm,
        tr.measurements,
        x0=x0,
        P0=P0,
        known_channels=[0, 1],
        method="likelihood",
        iterations=10,
    )
    rows["measurements only (likelihood)"] = {
        **_evaluate(lm, te, x0, P0),
        "train_s": time.perf_counter() - t0,
    }
    return rows


def _evaluate(
    model: StateSpaceModel, test: Any, x0: torch.Tensor, P0: torch.Tensor
) -> dict[str, float]:
    with torch.no_grad():
        res = torchfilt.CKF(model).filter(test.measurements, x0=x0, P0=P0)
    x = test.states
    return {
        "rmse": float((res.mean - x).pow(2).mean().sqrt()),
        "nees": float(torchfilt.nees(x, res.mean, res.cov).mean()),
        "coverage95": float(torchfilt.coverage(x, res.mean, res.cov).mean()),
        "log_predictive_density": float(res.log_likelihood.sum()) / x.shape[0] / x.shape[1],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/measurement_only"))
    ap.add_argument("--train-runs", type=int, default=8)
    ap.add_argument("--test-runs", type=int, default=50)
    ap.add_argument("--em-iterations", type=int, default=40)
    ap.add_argument("--likelihood-iterations", type=int, default=15)
    ap.add_argument("--m-step-iterations", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    train = reaction.simulate_truth(args.train_runs, start="paper", seed=args.seed + 1)
    test = reaction.simulate_truth(args.test_runs, start="paper", seed=args.seed + 2)
    x0, P0 = reaction.prior_mean("paper", DT), reaction.prior_cov(DT)
    rows: dict[str, dict[str, Any]] = {}
    rows["true model"] = {**evaluate(reaction.model(DT), test), "train_s": 0.0}
    nominal = nominal_model()
    rows[f"textbook (k1 = {K1_NOMINAL})"] = {**evaluate(nominal, test), "train_s": 0.0}

    # with states
    t0 = time.perf_counter()
    m_states = learnable(train.states.reshape(-1, 2))
    fit_with_states(m_states, train.states, train.measurements, iterations=200)
    rows["GP, trained with states"] = {
        **evaluate(m_states, test),
        "train_s": time.perf_counter() - t0,
    }

    # measurement only: the inducing inputs start on the nominal model's smoothed states
    with torch.no_grad():
        sm = torchfilt.rts_smooth(torchfilt.CKF(nominal).filter(train.measurements, x0=x0, P0=P0))
    cloud = sm.mean.reshape(-1, 2)
    fits: dict[str, Any] = {}
    for method, iters in (("em", args.em_iterations), ("likelihood", args.likelihood_iterations)):
        torch.manual_seed(args.seed)
        model = learnable(cloud)
        t0 = time.perf_counter()
        fit = torchfilt.fit_measurement_only(
            model,
            train.measurements,
            x0=x0,
            P0=P0,
            known_channels=[0],
            method=method,  # type: ignore[arg-type]
            iterations=iters,
            m_step_iterations=args.m_step_iterations,
        )
        fits[method] = {
            "log_likelihood": fit.log_likelihood,
            "iterations": fit.iterations,
            "stopped": fit.stopped,
        }
        rows[f"GP, measurements only ({method})"] = {
            **evaluate(fit.model, test),
            "train_s": time.perf_counter() - t0,
        }

    headers = [
        "model",
        "RMSE",
        "RMSE steps 20+",
        "mean NEES",
        "95% cov.",
        "held-out LPD",
        "train s",
    ]
    body = [
        [
            k,
            v["rmse"],
            v["rmse_last80"],
            v["nees"],
            v["coverage95"],
            v["log_predictive_density"],
            v["train_s"],
        ]
        for k, v in rows.items()
    ]
    text = table(headers, body)
    print("2A -> B, from total pressure only (held-out runs, CKF from N([5, 5], 36 I))")
    print(text)
    state_rmse = rows["GP, trained with states"]["rmse"]
    best = min(rows[f"GP, measurements only ({m})"]["rmse"] for m in ("em", "likelihood"))
    best_nees = min(
        (rows[f"GP, measurements only ({m})"] for m in ("em", "likelihood")),
        key=lambda r: r["rmse"],
    )["nees"]
    targets = {
        "rmse_within_1.5x_of_state_trained": best <= 1.5 * state_rmse,
        "nees_in_[1,4]": 1.0 <= best_nees <= 4.0,
    }
    print("targets:", targets)

    lin = linear_case(args.train_runs, args.test_runs, args.seed, 200)
    lin_text = table(
        ["model", "RMSE", "mean NEES", "95% cov.", "held-out LPD", "train s"],
        [
            [k, v["rmse"], v["nees"], v["coverage95"], v["log_predictive_density"], v["train_s"]]
            for k, v in lin.items()
        ],
    )
    print("\nlinear-Gaussian n = 2, H = I known (full gauge), measurements only vs with states")
    print(lin_text)
    write_json(
        args.out / "results.json",
        {
            "system": "reaction 2A -> B, start 'paper'",
            "k1_nominal": K1_NOMINAL,
            "inducing": INDUCING,
            "train_runs": args.train_runs,
            "test_runs": args.test_runs,
            "seed": args.seed,
            "rows": rows,
            "fits": fits,
            "targets": targets,
            "table": text,
            "linear_full_gauge": {"rows": lin, "table": lin_text},
            "environment": environment(),
        },
    )
    fig = Figure(figsize=(6, 3.5))
    ax = fig.add_subplot()
    names = list(rows)
    ax.barh(names, [rows[k]["rmse"] for k in names])
    ax.set_xlabel("filtering RMSE (held-out)")
    ax.set_title("2A -> B from total pressure only")
    fig.tight_layout()
    fig.savefig(args.out / "reaction_rmse.png", dpi=120)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
