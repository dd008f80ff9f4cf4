"""A ``states = "none"`` recipe without ``process_noise`` tries one pilot start per scale of
``PILOT_NOISE_SCALES`` on the default process noise, scores each by its filter log-likelihood on
the validation recordings, logs each and keeps the best; the bundle's training record lists them.
Reference: each candidate's score recomputed from public parts (pilot CKF, InducingTransition,
CKF on the validation recordings)."""

from __future__ import annotations

import math

import pytest
import torch

import torchfilt
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import CholeskyCovariance, InducingTransition, StateSpaceModel
from torchfilt.pipeline import load_bundle, train_recipe
from torchfilt.pipeline.run_stages import PILOT_NOISE_SCALES
from torchfilt.systems import get_system

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


def test_pilot_starts_are_scored_on_held_out_data_and_the_best_kept(tmp_path) -> None:
    data = tmp_path / "data"
    simulate_dataset("reaction", data, recordings=6, steps=50, seed=2)
    recipe = tmp_path / "r.toml"
    recipe.write_text(RECIPE.format(data=data.as_posix()))
    b = load_bundle(train_recipe(recipe, tmp_path / "run", progress=False))
    cands = b["transition"]["fit"]["candidates"]
    assert [c["process_noise_scale"] for c in cands] == list(PILOT_NOISE_SCALES)
    ds = torchfilt.load_dataset(data)
    train, val = ds.split("train"), ds.split("validation")
    assert val
    ref = [_candidate_score(train, val, s) for s in PILOT_NOISE_SCALES]
    for c, r in zip(cands, ref, strict=True):
        assert c["on"] == "held-out"
        assert c["score"] == pytest.approx(r, rel=1e-9)
    best = max(range(len(ref)), key=lambda i: ref[i])
    assert [c["chosen"] for c in cands] == [i == best for i in range(len(ref))]
    assert len({round(r, 6) for r in ref if math.isfinite(r)}) == len(ref)  # the choice matters
    log = (tmp_path / "run" / "train.log").read_text()
    assert log.count("transition: candidate start") == len(PILOT_NOISE_SCALES)
    assert f"transition: starting from candidate {best + 1}" in log
