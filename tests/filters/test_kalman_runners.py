"""The Kalman runners (sequential, fast, Riccati) against each other and against the independent
NumPy reference, and the one Gaussian log-likelihood term against scipy."""

import numpy as np
import pytest
import scipy.stats
import torch
from conftest import random_spd

from torchfilt.numerics import gaussian_log_prob

TOL = 1e-10


def _logpdf(e, S, o):
    if not o.any():
        return 0.0
    return scipy.stats.multivariate_normal(np.zeros(int(o.sum())), S[np.ix_(o, o)]).logpdf(e[o])


@pytest.mark.parametrize("library", [False, True])
@pytest.mark.parametrize("layout", ["per_residual", "shared", "per_step_shared"])
def test_gaussian_log_prob_matches_scipy(layout, library):
    """log N(e; 0, S) over the observed components (the others: a unit row and column in the
    factor and a zero residual), for one factor per residual and for factors shared by the batch
    (solved as columns of one solve)."""
    rng = np.random.default_rng(11)
    T, B, m = 4, 70, 3
    lead = {"per_residual": (T, B), "shared": (), "per_step_shared": (T, 1)}[layout]
    count = int(np.prod(lead)) if lead else 1
    S = np.stack([random_spd(rng, m) for _ in range(count)]).reshape(*lead, m, m)
    e = rng.standard_normal((T, B, m))
    Sfull = np.broadcast_to(S, (T, B, m, m))
    want = np.array(
        [[_logpdf(e[t, b], Sfull[t, b], np.ones(m, bool)) for b in range(B)] for t in range(T)]
    )
    got = gaussian_log_prob(
        torch.tensor(e), torch.linalg.cholesky(torch.tensor(S)), library=library
    )
    np.testing.assert_allclose(got.numpy(), want, rtol=TOL, atol=TOL)
    # missing components: masked factor per residual and the observed count
    obs = rng.random((T, B, m)) > 0.3
    want = np.array(
        [[_logpdf(e[t, b], Sfull[t, b], obs[t, b]) for b in range(B)] for t in range(T)]
    )
    Sm = Sfull * (obs[..., :, None] * obs[..., None, :]) + np.eye(m) * (1.0 - obs)[..., None, :]
    L = torch.linalg.cholesky(torch.tensor(Sm))
    got = gaussian_log_prob(torch.tensor(e * obs), L, torch.tensor(obs).sum(-1), library=library)
    np.testing.assert_allclose(got.numpy(), want, rtol=TOL, atol=TOL)


# ------------------------------------------------------------------------------ the runners
KEEP = frozenset({"mean", "cov", "predicted_mean", "predicted_cov", "log_likelihood"})
BATCH = 3


def _problem(varying, missing, prior, T, seed=5):
    """A model with inputs (time-varying Q when ``varying``), ``BATCH`` sequences, NaN or mask
    missing data, one P0 per sequence or shared."""
    from linear_support import make_problem, t64

    from torchfilt import LinearGaussianModel
    from torchfilt.models import TimeVarying

    p = make_problem(seed, T=T, missing=0.0)
    rng = np.random.default_rng(seed + 1)
    Q = p["Q"] * np.linspace(0.5, 2.0, T)[:, None, None] if varying else p["Q"]
    model = LinearGaussianModel(
        t64(p["A"]),
        t64(p["H"]),
        TimeVarying(t64(Q)) if varying else t64(Q),
        t64(p["R"]),
        B=t64(p["B"]),
    )
    y = np.nan_to_num(p["y"])[None] + rng.standard_normal((BATCH, T, p["y"].shape[-1]))
    obs = np.ones(y.shape, bool)
    if missing != "complete":
        obs = rng.random(y.shape) > 0.25
        obs[:, 3] = False  # a step with nothing observed
    if missing == "nan":
        y = np.where(obs, y, np.nan)
    x0 = rng.standard_normal((BATCH, p["m0"].shape[0]))
    P0 = p["P0"] * (rng.uniform(0.25, 4.0, (BATCH, 1, 1)) if prior == "per_sequence" else 1.0)
    want = [
        kalman_filter_ref(p, Q, y[b], x0[b], P0 if P0.ndim == 2 else P0[b], obs[b])
        for b in range(BATCH)
    ]
    mask = torch.tensor(obs) if missing == "mask" else None
    kw = dict(x0=t64(x0), P0=t64(P0), mask=mask)
    return model, (t64(y), t64(p["u"])), kw, want


def kalman_filter_ref(p, Q, y, x0, P0, obs):
    from reference import kalman_filter

    return kalman_filter(p["A"], p["H"], Q, p["R"], y, x0, P0, B=p["B"], u=p["u"], obs=obs)


def _runs(model, args, kw):
    """Every runner that can serve the recording, by name, with its kept outputs."""
    from torchfilt.filters import kalman_runners as runners
    from torchfilt.filters.kalman import linear_steps, measurement_terms

    data, steps = linear_steps(model, *args, **kw)
    out = {
        "sequential": runners._run(data, steps, sqrt=False, keep=KEEP, inplace=True),
        "sequential-sqrt": runners._run(data, steps, sqrt=True, keep=KEEP, inplace=False),
        "fast": runners._run_fast(data, steps, keep=KEEP, inplace=True),
        "fast-autograd-layout": runners._run_fast(data, steps, keep=KEEP, inplace=False),
    }
    Bc = runners._covariance_batch(data, steps)
    if Bc is not None:
        out["riccati"] = runners._run_riccati(data, steps, keep=KEEP, Bc=Bc)
    shape = {"mean": 1, "predicted_mean": 1, "cov": 2, "predicted_cov": 2}
    for res in out.values():
        assert res is not None
        if "log_likelihood" not in res:  # the sequential runner leaves it to the measurement terms
            ll = measurement_terms(data, steps, res["predicted_mean"], res["predicted_cov"])[3]
            res["log_likelihood"] = ll
        for k, tail in shape.items():
            res[k] = res[k].expand(*data.batch, data.y.shape[-2], *res[k].shape[-tail:])
    return out


def _close(a, b, what):
    a, b = np.asarray(a), np.asarray(b)
    scale = max(1.0, float(np.abs(b).max()))
    assert np.abs(a - b).max() <= TOL * scale, f"{what}: max diff {np.abs(a - b).max():.2e}"


@pytest.mark.parametrize("T", [15, 400], ids=["short", "converged_tail"])
@pytest.mark.parametrize("prior", ["shared", "per_sequence"])
@pytest.mark.parametrize("missing", ["complete", "nan", "mask"])
@pytest.mark.parametrize("varying", [False, True], ids=["invariant", "time_varying"])
def test_runners_equal_the_reference_and_the_sequential_steps(varying, missing, prior, T):
    """Each runner equals the sequential runner of the pure steps and the NumPy reference:
    means, covariances, predicted moments and the log-likelihood, float64, to 1e-10."""
    model, args, kw, want = _problem(varying, missing, prior, T)
    runs = _runs(model, args, kw)
    if missing == "complete" and (prior == "shared" or not varying):
        assert "riccati" in runs
    base = runs["sequential"]
    fields = ("mean", "cov", "predicted_mean", "predicted_cov")
    for name, res in runs.items():
        for k in (*fields, "log_likelihood"):
            _close(res[k], base[k], f"{name} {k} vs the sequential steps")
        for b in range(BATCH):
            ref = want[b]
            for i, k in enumerate(fields):
                _close(res[k][b], ref[i], f"{name} {k} vs the reference")
            _close(res["log_likelihood"][b], ref[4], f"{name} log-likelihood vs the reference")


@pytest.mark.parametrize("execution", ["kalman-riccati", "kalman-fast", "kalman-sequential"])
def test_the_plan_forces_each_runner(monkeypatch, execution):
    """A plan naming a runner runs it through run_exact; the in-loop log-likelihood (large
    results) gives the same value."""
    from torchfilt.filters import kalman_runners as runners
    from torchfilt.filters.kalman import linear_steps
    from torchfilt.filters.plan import ExecutionPlan

    model, args, kw, want = _problem(False, "complete", "shared", 60)
    data, steps = linear_steps(model, *args, **kw)
    for vector in (True, False):
        if not vector:
            monkeypatch.setattr(runners, "_VECTOR_LL_BYTES", 0)
        keep = frozenset({"mean", "log_likelihood"})  # summed inside the sequential loop
        out = runners.run_exact(
            data, steps, keep, ExecutionPlan("kalman", execution, inplace=vector)
        )
        assert out is not None
        for b in range(BATCH):
            _close(out["log_likelihood"][b], want[b][4], f"{execution} log-likelihood")
            _close(out["mean"][b], want[b][0], f"{execution} mean")
