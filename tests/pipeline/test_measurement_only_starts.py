"""A ``states = "none"`` recipe without ``process_noise`` tries one pilot start per scale of
``PILOT_NOISE_SCALES`` on the default process noise and a linear-EM start, scores each by its filter log-likelihood on
the validation recordings, logs each and keeps the best; the bundle's training record lists them.
Reference: each candidate's score recomputed from public parts (pilot CKF, InducingTransition,
subspace_start, fit_em, CKF on the validation recordings)."""

from __future__ import annotations

import contextlib
import io
import math
from types import SimpleNamespace

import pytest
import torch

import torchfilt
from torchfilt.cli import main as cli_main
from torchfilt.filters import kalman_filter, kalman_smoother
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
        for stable in (False, True):  # as estimated, and stabilised where it has to be
            sub = subspace_start(crude, ys, known_channels=[0], block_rows=rows, stable=stable)
            start = LinearGaussianModel(sub.model.A, J, sub.model.transition.noise_cov(), R)
            fits.append(
                fit_em(start, ys, x0=m0, P0=P0, known_channels=[0], fixed=("H", "R"), iterations=20)
            )
            if float(torch.linalg.eigvals(sub.model.A).abs().max()) < 1:
                break
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
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["info", str(tmp_path / "run" / "model.pt")]) == 0
    kept = cands[best]
    words = (
        f"pilot (process noise {kept['process_noise_scale']} x the default)"
        if kept["start"] == "pilot"
        else f"linear EM from N4SID ({kept['block_rows']} block rows"
        + (", stabilised)" if kept["stabilised"] else ")")
    )
    assert (
        f"  start:        candidate {best + 1} of {len(cands)}, {words}, held-out "
        f"log-likelihood {ref[best]:.6g}" in out.getvalue()
    )
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
    # N4SID with the default block rows (6) and twice that, each stabilised too where its
    # estimate has a pole on or outside the unit circle; the higher likelihood after EM kept
    tried = lin.record["block_rows_tried"]
    J = torch.tensor([[1.0, 0.0]], dtype=DT)  # the reaction sensor's first state, linearised
    ys = [r.measurements[1:] for r in train]
    crude = LinearGaussianModel(torch.eye(2, dtype=DT), J, torch.eye(2, dtype=DT), h.noise_cov())
    expected = []
    for rows in (6, 12):
        A = subspace_start(crude, ys, known_channels=[0], block_rows=rows).model.A
        expected.append((rows, False))
        if float(torch.linalg.eigvals(A).abs().max()) >= 1:
            expected.append((rows, True))
    assert [(t["block_rows"], t["stabilised"]) for t in tried] == expected
    assert len(expected) == 3  # this data: the 6-row estimate is unstable, the 12-row one not
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


def _unstable_plant(seed: int) -> tuple[list[SimpleNamespace], LinearGaussianModel]:
    """Two recordings of 150 steps of a 2-state plant with a pole at 1.02 (and 0.6), its first
    state measured with noise variance 1e-2 (row 0: the prior's time, no measurement)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.tensor([[1.02, 0.1], [0.0, 0.6]], dtype=DT)
    H = torch.tensor([[1.0, 0.0]], dtype=DT)
    true = LinearGaussianModel(A, H, 1e-2 * torch.eye(2, dtype=DT), 1e-2 * torch.eye(1, dtype=DT))
    recs = []
    for _ in range(2):
        x, ys = torch.zeros(2, dtype=DT), [torch.full((1,), math.nan, dtype=DT)]
        for _ in range(150):
            x = A @ x + 0.1 * torch.randn(2, generator=g, dtype=DT)
            ys.append(H @ x + 0.1 * torch.randn(1, generator=g, dtype=DT))
        recs.append(SimpleNamespace(measurements=torch.stack(ys), inputs=None))
    return recs, true


def _kalman_ll(model: LinearGaussianModel, recs: list, m0, P0) -> float:
    with torch.no_grad():
        return sum(
            float(kalman_filter(model, r.measurements[1:], x0=m0, P0=P0).log_likelihood.sum())
            for r in recs
        )


def test_linear_start_tries_the_stabilised_n4sid_and_keeps_the_likelier() -> None:
    """On a plant with a pole outside the unit circle N4SID's estimate is unstable: the start
    tries it as estimated and stabilised, at both block rows, and keeps the higher likelihood
    after the EM (the likelihood decides, not a rule). With ``stable``
    (a plant said to be stable) only the stabilised starts are tried, and one whose EM leaves
    the unit circle is kept as it was before the EM: its recorded likelihood is the start's own
    (an independent Kalman filter of the stabilised N4SID model)."""
    recs, true = _unstable_plant(seed=5)
    m0, P0 = torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT)
    kw = dict(n=2, nu=0, m0=m0, P0=P0, q0=1e-2 * P0.diagonal(), inducing=INDUCING, known=[0])
    lin = linear_em_start(true.measurement, recs, dtype=DT, **kw)  # type: ignore[arg-type]
    assert lin is not None
    tried = lin.record["block_rows_tried"]
    assert [(t["block_rows"], t["stabilised"]) for t in tried] == [
        (6, False), (6, True), (12, False), (12, True)
    ]  # fmt: skip
    kept = max(tried, key=lambda t: t["log_likelihood"])
    assert lin.record["linear_log_likelihood"] == kept["log_likelihood"]
    assert lin.record["stabilised"] is kept["stabilised"]
    assert not any("unstable_after_em" in t for t in tried)  # without stable: EM goes where it may
    # a plant said to be stable: the stabilised starts alone
    st = linear_em_start(true.measurement, recs, dtype=DT, stable=True, **kw)  # type: ignore[arg-type]
    assert st is not None
    tried = st.record["block_rows_tried"]
    assert [(t["block_rows"], t["stabilised"]) for t in tried] == [(6, True), (12, True)]
    assert all("unstable_after_em" in t for t in tried)  # the data pull A outside: kept as started
    assert all(t["unstable_after_em"] >= 1 for t in tried)
    assert st.record["em_iterations"] == 0
    ys = [r.measurements[1:] for r in recs]
    H, R = true.H, true.measurement.noise_cov()
    crude = LinearGaussianModel(torch.eye(2, dtype=DT), H, 1e-2 * torch.eye(2, dtype=DT), R)
    for t in tried:
        sub = subspace_start(crude, ys, known_channels=[0], block_rows=t["block_rows"], stable=True)
        A = sub.model.A
        assert float(torch.linalg.eigvals(A).abs().max()) < 1
        start = LinearGaussianModel(A, H, sub.model.transition.noise_cov(), R)
        assert t["log_likelihood"] == pytest.approx(_kalman_ll(start, recs, m0, P0), rel=1e-9)
    # the GP model starts exactly at the kept linear model (CKF of the GP, Kalman of the linear)
    with torch.no_grad():
        ll = sum(
            float(torchfilt.CKF(st.model).filter(r.measurements[1:], x0=m0, P0=P0).log_likelihood)
            for r in recs
        )
    assert ll == pytest.approx(st.record["linear_log_likelihood"], rel=1e-8)


def test_the_log_names_the_stabilised_start() -> None:
    """The log line of the linear-EM candidate names the kept start and every one tried."""
    from torchfilt.pipeline.run_stages import _linear_source

    record = {
        "from": "N4SID", "block_rows": 10, "stabilised": True,
        "block_rows_tried": [
            {"block_rows": 10, "stabilised": False, "log_likelihood": -99.2589},
            {"block_rows": 10, "stabilised": True, "log_likelihood": 403.334},
            {"block_rows": 20, "stabilised": True, "log_likelihood": 54.2419,
             "unstable_after_em": 1.00445},
        ],
    }  # fmt: skip
    assert _linear_source(record) == (
        "N4SID (10 block rows, stabilised; after the EM from 10: -99.2589, 10 stabilised: "
        "403.334, 20 stabilised: 54.2419 (kept as started: the EM's spectral radius 1.004))"
    )
    assert _linear_source({"from": "random walk"}) == "random walk"


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


def test_recipe_stable_reaches_the_linear_start(tmp_path, monkeypatch) -> None:
    """``[measurement_only] stable = true`` is passed to the linear-EM start (default
    ``False``), leaves the digest of a recipe without it unchanged at ``false``, and is a
    RecipeError naming the key beside a given ``process_noise`` or a nominal model (which
    replace the linear-EM start)."""
    import torchfilt.pipeline.run_stages as stages
    from torchfilt.exceptions import RecipeError
    from torchfilt.pipeline import load_recipe

    seen: list[bool] = []

    def spy(*args, **kwargs):
        seen.append(kwargs["stable"])
        return linear_em_start(*args, **kwargs)

    monkeypatch.setattr(stages, "linear_em_start", spy)
    data = tmp_path / "data"
    simulate_dataset("reaction", data, recordings=4, steps=40, seed=3)
    base = RECIPE.format(data=data.as_posix())
    texts = {flag: base.replace("[calibrate]", f"{flag}[calibrate]") for flag in ("", "stable = true\n", "stable = false\n")}  # fmt: skip
    paths = {}
    for flag, text in texts.items():
        paths[flag] = tmp_path / f"r{len(paths)}.toml"
        paths[flag].write_text(text)
    for flag in ("", "stable = true\n"):
        b = load_bundle(train_recipe(paths[flag], tmp_path / f"run{len(seen)}", progress=False))
        lin = [c for c in b["transition"]["fit"]["candidates"] if c["start"] == "linear EM"]
        assert len(lin) == 1 and "stabilised" in lin[0]
    assert seen == [False, True]
    digests = [load_recipe(paths[f]).digest() for f in texts]
    assert digests[0] == digests[2] != digests[1]
    for extra in ("process_noise = 0.01\n", 'nominal = {system = "reaction"}\n'):
        bad = tmp_path / "bad.toml"
        bad.write_text(base.replace("[calibrate]", f"stable = true\n{extra}[calibrate]"))
        with pytest.raises(RecipeError, match=r"\[measurement_only\] stable = true acts on"):
            load_recipe(bad)
