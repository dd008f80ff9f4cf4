"""A ``states = "none"`` recipe without ``process_noise`` tries one pilot start per scale of
``PILOT_NOISE_SCALES`` on the default process noise and a linear-EM start, scores each by its filter log-likelihood on
the validation recordings, logs each and keeps the best; the bundle's training record lists them.
Reference: each candidate's score recomputed from public parts (pilot CKF, InducingTransition,
subspace_start, fit_em, CKF on the validation recordings)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

import torchfilt
from torchfilt.filters import kalman_smoother
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import (
    CholeskyCovariance,
    InducingTransition,
    LinearGaussianModel,
    StateSpaceModel,
    subspace_start,
)
from torchfilt.pipeline import load_bundle, train_recipe
from torchfilt.pipeline.linear_start import linear_em_start
from torchfilt.pipeline.run_stages import PILOT_NOISE_SCALES
from torchfilt.systems import get_system
from torchfilt.training import fit_em

DT = torch.float64
INDUCING = 4
RECIPE = f"""
name = "starts"
seed = 0
states = "none"
[dataset]
path = "{{data}}"
[measurement]
model = "system:reaction"
[filter]
prior = "system:reaction"
[measurement_only]
iterations = 1
inducing = {INDUCING}
m_step_iterations = 2
[calibrate]
enabled = false
"""


def _candidate_score(train: list, val: list, scale: float) -> float:
    spec = get_system("reaction")
    h = spec.model().measurement
    m0, P0 = spec.prior_mean(), spec.prior_cov()
    q0 = scale * 1e-2 * P0.diagonal()
    pilot = torchfilt.CKF(StateSpaceModel(InducingTransition(2, 0), h, Q=torch.diag(q0)))
    X = torch.cat([pilot.filter(r.measurements[1:], x0=m0, P0=P0).mean for r in train])
    X = X[torch.isfinite(X).all(-1)]
    f = InducingTransition(2, INDUCING, lengthscale=X.std(0), outputscale=q0)
    f.init_inducing(X)
    model = StateSpaceModel(f, h, Q=CholeskyCovariance(torch.diag(q0)))
    with torch.no_grad():
        return sum(
            float(torchfilt.CKF(model).filter(r.measurements[1:], x0=m0, P0=P0).log_likelihood)
            for r in val
        )


def _linear_candidate_score(train: list, val: list) -> float:
    """The linear-EM candidate rebuilt from public parts: the sensor's ``H`` (linear: its
    Jacobian), N4SID in its gauge with 6 and with 12 block rows, the better of 20 EM iterations (``fit_em``'s default for a linear model:
    SQUAREM cycles) with ``H`` and ``R`` fixed, a GP transition
    starting exactly at it on the smoothed states, scored by the CKF on the validation data."""
    spec = get_system("reaction")
    h = spec.model().measurement
    m0, P0 = spec.prior_mean(), spec.prior_cov()
    x = m0.reshape(1, 1, 2)
    J = torch.autograd.functional.jacobian(lambda z: h.predict(z, None).mean, x).reshape(-1, 2)
    R = h.noise_cov().reshape(1, 1)
    ys = [r.measurements[1:] - (h.predict(x, None).mean.reshape(-1) - J @ m0) for r in train]
    crude = LinearGaussianModel(torch.eye(2, dtype=DT), J, torch.diag(1e-2 * P0.diagonal()), R)
    fits = []
    for rows in (6, 12):  # the default block rows for 2 states and 1 output, and twice that
        sub = subspace_start(crude, ys, known_channels=[0], block_rows=rows).model
        start = LinearGaussianModel(sub.A, J, sub.transition.noise_cov(), R)
        fits.append(
            fit_em(start, ys, x0=m0, P0=P0, known_channels=[0], fixed=("H", "R"), iterations=20)
        )
    lin = max(fits, key=lambda f: f.log_likelihood)  # the higher likelihood after the EM
    X = torch.cat([kalman_smoother(lin.model, y, x0=m0, P0=P0).mean for y in ys])
    f = InducingTransition.from_linear(
        lin.model.A, inducing=INDUCING, states=X, lengthscale=X.std(0)
    )
    model = StateSpaceModel(f, h, Q=CholeskyCovariance(lin.model.transition.noise_cov()))
    with torch.no_grad():
        return sum(
            float(torchfilt.CKF(model).filter(r.measurements[1:], x0=m0, P0=P0).log_likelihood)
            for r in val
        )


def test_pilot_starts_are_scored_on_held_out_data_and_the_best_kept(tmp_path) -> None:
    data = tmp_path / "data"
    simulate_dataset("reaction", data, recordings=6, steps=50, seed=2)
    recipe = tmp_path / "r.toml"
    recipe.write_text(RECIPE.format(data=data.as_posix()))
    b = load_bundle(train_recipe(recipe, tmp_path / "run", progress=False))
    cands = b["transition"]["fit"]["candidates"]
    pilots = [c for c in cands if c["start"] == "pilot"]
    assert [c["process_noise_scale"] for c in pilots] == list(PILOT_NOISE_SCALES)
    ds = torchfilt.load_dataset(data)
    train, val = ds.split("train"), ds.split("validation")
    assert val
    ref = [_candidate_score(train, val, s) for s in PILOT_NOISE_SCALES]
    ref.append(_linear_candidate_score(train, val))  # the linear-EM candidate, after the pilots
    assert [c["start"] for c in cands] == ["pilot"] * len(PILOT_NOISE_SCALES) + ["linear EM"]
    for c, r in zip(cands, ref, strict=True):
        assert c["on"] == "held-out"
        assert c["score"] == pytest.approx(r, rel=1e-9)
    best = max(range(len(ref)), key=lambda i: ref[i])
    assert [c["chosen"] for c in cands] == [i == best for i in range(len(ref))]
    assert len({round(r, 6) for r in ref if math.isfinite(r)}) == len(ref)  # the choice matters
    log = (tmp_path / "run" / "train.log").read_text()
    assert log.count("transition: candidate start") == len(PILOT_NOISE_SCALES)
    assert log.count("transition: linear-EM candidate") == 1
    assert f"transition: starting from candidate {best + 1}" in log
    # the fit used its whole budget (RECIPE: 1 iteration): the log says so, and how to fit longer
    assert (
        "transition: stopped at its budget of 1 iteration, not converged (a new run with a "
        "larger [measurement_only] iterations fits longer; --resume keeps the recipe as it is)"
        in log
    )


def test_linear_candidate_starts_exactly_at_the_linear_fit(tmp_path) -> None:
    """The linear-EM candidate's GP model has the linear fit's likelihood (CKF of the GP model,
    recording by recording, against the EM's exact Kalman likelihood); with a missing
    measurement it starts from the random walk instead of N4SID (which needs complete data)."""
    simulate_dataset("reaction", tmp_path / "data", recordings=4, steps=40, seed=3)
    train = torchfilt.load_dataset(tmp_path / "data").split("train")
    spec = get_system("reaction")
    h = spec.model().measurement
    m0, P0 = spec.prior_mean(), spec.prior_cov()
    kw = dict(n=2, nu=0, m0=m0, P0=P0, q0=1e-2 * P0.diagonal(), inducing=INDUCING, known=[0])
    lin = linear_em_start(h, train, dtype=DT, **kw)  # type: ignore[arg-type]
    assert lin is not None and lin.record["from"] == "N4SID"
    # N4SID with the default block rows (6) and twice that, the higher likelihood after EM kept
    tried = lin.record["block_rows_tried"]
    assert [t["block_rows"] for t in tried] == [6, 12]
    kept = max(tried, key=lambda t: t["log_likelihood"])
    assert lin.record["block_rows"] == kept["block_rows"]
    assert lin.record["linear_log_likelihood"] == kept["log_likelihood"]
    with torch.no_grad():
        ll = sum(
            float(torchfilt.CKF(lin.model).filter(r.measurements[1:], x0=m0, P0=P0).log_likelihood)
            for r in train
        )
    assert ll == pytest.approx(lin.record["linear_log_likelihood"], rel=1e-8)
    ys = [r.measurements.clone() for r in train]
    ys[0][5, 0] = math.nan
    recs = [SimpleNamespace(measurements=y, inputs=None) for y in ys]
    gappy = linear_em_start(h, recs, dtype=DT, **kw)  # type: ignore[arg-type]
    assert gappy is not None and gappy.record["from"] == "random walk"
    assert math.isfinite(gappy.record["linear_log_likelihood"])


def test_the_log_says_why_a_stage_fit_ended() -> None:
    """A budget, an EM stall (with what to try), and the other stops as they are."""
    from torchfilt.pipeline.run_stages import _ended

    assert _ended("iterations", 30, "calibrate") == (
        "stopped at its budget of 30 iterations, not converged (a new run with a larger "
        "[calibrate] iterations fits longer; --resume keeps the recipe as it is)"
    )
    stall = _ended("no improvement", 2, "measurement_only")
    assert stall.startswith("no improvement after 2 iterations: no EM step raised")
    assert 'method = "likelihood" may go further' in stall
    assert 'method = "auto" runs both' in stall
    assert _ended("converged", 1, "measurement_only") == "converged after 1 iteration"
    assert _ended("early stopping", 15, "calibrate") == "early stopping after 15 iterations"
