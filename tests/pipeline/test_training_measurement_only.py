"""The training pipeline with ``states = "none"``: a recipe that learns the transition from
measurements alone (run directory, resume after a kill, calibration, bundle, ``torchfilt info``,
``torchfilt filter``), its refusals, and the ``"inducing"`` bundle entry's checks.

The data are the 2A -> B reaction (n = 2 states, one total-pressure sensor, the known
``system:reaction`` measurement model as the gauge), with every state value removed from the
training recordings: two lose their state columns, one has them all NaN. The reference for the
learned transition is an independent construction from public parts (a pilot CKF with the nominal
callable, ``InducingTransition``, ``fit_measurement_only``) on the same measurements.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from run_support import interrupted_at

import torchfilt
from torchfilt.cli import main as cli_main
from torchfilt.exceptions import DataError
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import CholeskyCovariance, InducingTransition, StateSpaceModel
from torchfilt.pipeline import load_bundle, load_model, load_recipe, train_recipe
from torchfilt.pipeline.bundle import build_side, check_bundle
from torchfilt.pipeline.recipe import Recipe
from torchfilt.systems import get_system
from torchfilt.training import BundleError, RecipeError, fit_measurement_only

DT = torch.float64
#: the pipeline and the direct call run the same float64 arithmetic
REFERENCE_RTOL = 1e-10
ITERATIONS, INDUCING, M_STEP, Q0, K1 = 6, 6, 5, 0.01, 0.08

RECIPE = f"""
name = "measonly"
seed = 1
states = "none"
[dataset]
path = "{{data}}"
[measurement]
model = "system:reaction"
[filter]
prior = "system:reaction"
[measurement_only]
# the EM route (the default, "auto": tests/pipeline/test_training_method_auto.py)
method = "em"
iterations = {ITERATIONS}
inducing = {INDUCING}
m_step_iterations = {M_STEP}
process_noise = {Q0}
nominal = {{{{system = "reaction", k1 = {K1}}}}}
[train]
checkpoint_every = 2
[calibrate]
iterations = 4
"""


def _strip_states(root: Path, split: str = "train") -> None:
    """Remove every state value of a split: drop the columns, or write NaN (the second file)."""
    man = json.loads((root / "manifest.json").read_text())
    train = [r["file"] for r in man["recordings"] if r["split"] == split]
    for k, name in enumerate(train):
        p = root / name
        with p.open() as fh:
            rows = list(csv.reader(fh))
        idx = {rows[0].index("PA"), rows[0].index("PB")}
        if k == 1:
            out = [rows[0]] + [
                ["nan" if i in idx else v for i, v in enumerate(r)] for r in rows[1:]
            ]
        else:
            out = [[v for i, v in enumerate(r) if i not in idx] for r in rows]
        with p.open("w", newline="") as fh:
            csv.writer(fh).writerows(out)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("measonly_data")
    simulate_dataset("reaction", root, recordings=4, steps=100, seed=0)
    _strip_states(root)
    return root


def write(path: Path, data: Path, text: str = RECIPE) -> Path:
    path.write_text(text.format(data=data.as_posix()))
    return path


@pytest.fixture(scope="module")
def fresh(tmp_path_factory, data) -> Path:
    root = tmp_path_factory.mktemp("measonly_run")
    recipe = write(root / "r.toml", data)
    return train_recipe(recipe, root / "run", progress=False)


def _train_split(data: Path) -> list:
    ds = torchfilt.load_dataset(data, require_finite=("input",), optional=("state",))
    return ds.split("train")


def test_training_split_has_no_states_and_logged_recipes_still_refuse_it(data, tmp_path):
    train = _train_split(data)
    assert len(train) == 3 and all(bool(r.states.isnan().all()) for r in train)
    logged = RECIPE.replace('states = "none"\n', "").split("[measurement_only]")[0]
    logged = logged.replace("[dataset]", "[transition]\n[dataset]")
    with pytest.raises(DataError, match=r"rec_000\.csv, column 'PA'.*missing column"):
        train_recipe(write(tmp_path / "logged.toml", data, logged), tmp_path / "r", progress=False)


def test_states_none_run_writes_a_bundle_that_loads_and_filters(fresh, data, tmp_path, capsys):
    run = fresh.parent
    for f in ("config.json", "dataset.json", "metrics.jsonl", "transition.pt", "calibration.pt"):
        assert (run / f).is_file(), f
    assert not (run / "transition.ckpt").exists() and not (run / "checkpoint.pt").exists()
    b = load_bundle(fresh)
    entry = b["transition"]
    assert entry["kind"] == "inducing" and entry["nominal"] == {"system": "reaction", "k1": K1}
    assert entry["state"]["inducing_inputs"].shape == (INDUCING, 2)
    fit = entry["fit"]
    assert fit["method"] == "em" and fit["known_channels"] == ["pressure"]
    assert fit["log_likelihood"] > fit["initial_log_likelihood"]
    assert b["recipe"]["states"] == "none" and b["measurement"] == {
        "kind": "system",
        "system": "reaction",
    }
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    tr = [r for r in lines if r["stage"] == "transition"]
    assert [r["iteration"] for r in tr] == list(range(1, fit["iterations"] + 1))
    assert tr[-1]["log_likelihood"] == pytest.approx(fit["log_likelihood"], rel=1e-12)
    # the validation recording logs states: the one-step and NEES figures are evaluation only
    val = json.loads((run / "validation.json").read_text())
    assert "transition" in val and "nees_mean" in val["filter"]["calibrated"]
    model = load_model(fresh)
    assert isinstance(model.transition, torchfilt.CalibratedModel)
    assert isinstance(model.transition.base.base, InducingTransition)
    assert not any(p.requires_grad for p in model.transition.base.parameters())
    rec = sorted(str(p) for p in data.glob("rec_003.csv"))
    capsys.readouterr()
    assert cli_main(["filter", *rec, "--model", str(fresh), "--out", str(tmp_path / "est")]) == 0
    assert (tmp_path / "est" / "rec_003.filtered.csv").is_file()
    assert cli_main(["info", str(fresh)]) == 0
    info = capsys.readouterr().out
    assert "learned from: measurements alone (method em, known channels pressure" in info
    assert "CalibratedModel" in info


def _reference_model(train: list) -> StateSpaceModel:
    """The recipe's initial model built from public parts, independently of the pipeline."""
    spec = get_system("reaction")
    g = spec.nominal_transition(k1=K1)
    h = spec.model().measurement
    m0, P0 = spec.prior_mean(), spec.prior_cov()
    q0 = torch.full((2,), Q0, dtype=DT)
    pilot = torchfilt.CKF(StateSpaceModel(g, h, Q=torch.diag(q0)))
    X = torch.cat([pilot.filter(r.measurements[1:], x0=m0, P0=P0).mean for r in train])
    X = X[torch.isfinite(X).all(-1)]
    f = InducingTransition(2, INDUCING, nominal=g, lengthscale=X.std(0), outputscale=q0)
    f.init_inducing(X)
    return StateSpaceModel(f, h, Q=CholeskyCovariance(torch.diag(q0)))


def test_learned_transition_is_the_direct_fit_and_beats_the_initial_model(fresh, data):
    train = _train_split(data)
    spec = get_system("reaction")
    ys = [r.measurements[1:] for r in train]
    model = _reference_model(train)
    start = copy.deepcopy(model)
    fit = fit_measurement_only(
        model,
        ys,
        x0=spec.prior_mean(),
        P0=spec.prior_cov(),
        known_channels=[0],
        method="em",
        iterations=ITERATIONS,
        m_step_iterations=M_STEP,
        learn_measurement_noise=False,
        noise_scale="none",  # as the pipeline's stage fits
    )
    st = load_bundle(fresh)["transition"]["state"]
    f = fit.model.transition
    for name in ("linear", "bias", "inducing_inputs", "inducing_outputs", "log_lengthscale"):
        torch.testing.assert_close(st[name], getattr(f.base, name), rtol=REFERENCE_RTOL, atol=0)
    torch.testing.assert_close(st["Q"], f.noise_cov(), rtol=REFERENCE_RTOL, atol=1e-14)

    # the bundle's (uncalibrated) transition filters the training measurements better than the
    # initial model
    def loglik(m: StateSpaceModel) -> float:
        ckf = torchfilt.CKF(m)
        with torch.no_grad():
            return sum(
                float(ckf.filter(y, x0=spec.prior_mean(), P0=spec.prior_cov()).log_likelihood)
                for y in ys
            )

    learned = StateSpaceModel(
        build_side(load_bundle(fresh)["transition"], "transition"), spec.model().measurement
    )
    assert loglik(learned) > loglik(start) + 10
    assert loglik(learned) == pytest.approx(fit.log_likelihood, rel=1e-9)


def _assert_same_learned_model(a: dict, b: dict) -> None:
    """Two bundles hold the same learned transition (bit for bit), fit record and calibration."""
    for k, v in b["transition"]["state"].items():
        va = a["transition"]["state"][k]
        assert torch.equal(va, v) if isinstance(v, torch.Tensor) else va == v, k
    assert a["transition"]["fit"] == b["transition"]["fit"]
    assert a["calibration"] == b["calibration"]


def test_killed_run_resumes_to_the_identical_bundle(fresh, data, tmp_path, monkeypatch):
    import torchfilt.pipeline.run_stages as run_mod

    real = run_mod.fit_measurement_only

    recipe = write(tmp_path / "r.toml", data)
    run = tmp_path / "killed"
    # interrupted at iteration 3, after the checkpoint at 2
    monkeypatch.setattr(run_mod, "fit_measurement_only", interrupted_at(real, 3))
    with pytest.raises(KeyboardInterrupt):
        train_recipe(recipe, run, progress=False)
    assert (run / "transition.ckpt").is_file() and not (run / "transition.pt").exists()
    monkeypatch.setattr(run_mod, "fit_measurement_only", real)
    train_recipe(recipe, run, resume=True, progress=False)
    a, b = load_bundle(run / "model.pt"), load_bundle(fresh)
    _assert_same_learned_model(a, b)
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    its = [r["iteration"] for r in lines if r["stage"] == "transition"]
    assert its == list(range(1, b["transition"]["fit"]["iterations"] + 1))
    assert not (run / "transition.ckpt").exists()


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            'model = "system:reaction"\n[filter]',
            "iterations = 3\n[filter]",
            r'\[measurement\]: with states = "none" the measurement model must be known',
        ),
        ('prior = "system:reaction"', 'prior = "data"', r'\[filter\] prior = "data"'),
        ('prior = "system:reaction"', "", r'\[filter\] prior = "data"'),
        (
            'prior = "system:reaction"',
            "prior = false",
            r"prior must be 'data', 'system:NAME'.*False",
        ),
        ('method = "em"', 'method = "gradient"', r"\[measurement_only\] method"),
        ("iterations = 6", "window = 50\niterations = 6", r"\['window'\]: not an option of"),
        ("[dataset]", "[transition]\nkernel = 'rbf'\n[dataset]", r"\[transition\] \['kernel'\]"),
        ("iterations = 4", 'iterations = 4\ngp = "noise"', r'\[calibrate\] gp = "noise"'),
        ('states = "none"\n', "", r"\[measurement_only\] applies only with states"),
        ("inducing = 6", "inducing = -1", "inducing must be an integer >= 0"),
    ],
)
def test_recipe_refusals_name_the_key(tmp_path, data, old, new, message):
    text = RECIPE.replace(old, new, 1)
    assert text != RECIPE
    if 'states = "none"' not in text:
        text = text.replace("[dataset]", "[transition]\n[dataset]")
    with pytest.raises(RecipeError, match=message):
        load_recipe(write(tmp_path / "bad.toml", data, text))


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "iterations = 6",
            'known_channels = ["pressur"]\niterations = 6',
            r"known_channels: unknown measurement channel.*'pressur'",
        ),
        ('model = "system:reaction"', 'model = "system:nosuch"', r"\[measurement\] model: unknown"),
        ("k1 = 0.08", "kk = 0.08", r"\[measurement_only\] nominal: .*bad nominal-model param"),
        ('model = "system:reaction"', 'model = "system:reentry"', r"maps 3 states to 1"),
        ("process_noise = 0.01", "process_noise = [0.1, 0.1, 0.1]", "3 values for 2 states"),
    ],
)
def test_refusals_against_the_dataset(tmp_path, data, old, new, message):
    text = RECIPE.replace(old, new, 1)
    assert text != RECIPE
    with pytest.raises(RecipeError, match=message):
        train_recipe(write(tmp_path / "bad.toml", data, text), tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


def test_refusal_of_a_recipe_built_in_code(tmp_path, data):
    r = Recipe(
        path=None,
        name="code",
        seed=0,
        dataset=data,
        transition={},
        measurement={"iterations": 3},
        filter={"prior": "system:reaction"},
        states="none",
    )
    with pytest.raises(RecipeError, match=r"\[measurement\]: with states"):
        train_recipe(r, tmp_path / "r", progress=False)


def test_cli_train_refuses_a_bad_recipe_in_one_line(tmp_path, data, capsys):
    text = RECIPE.replace('prior = "system:reaction"', 'prior = "data"')
    recipe = write(tmp_path / "bad.toml", data, text)
    assert cli_main(["train", str(recipe), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "[filter] prior" in err and "bad.toml" in err


@pytest.mark.parametrize(
    ("edit", "where"),
    [
        (
            lambda s: s.update(inducing_outputs=torch.zeros(2, 5, dtype=DT)),
            "transition.state.inducing_outputs",
        ),
        (lambda s: s["Q"].fill_(float("nan")), "transition.state.Q"),
        (lambda s: s.update(Q=-torch.eye(2, dtype=DT)), "transition.state.Q"),
        (lambda s: s.pop("linear"), "transition.state.linear"),
        (lambda s: s.update(state_dim=3), "transition.state.state_dim"),
        (lambda s: s["floor"].fill_(-1.0), "transition.state.floor"),
        (lambda s: s.update(jitter="x"), "transition.state.jitter"),
    ],
)
def test_malformed_inducing_entry_is_refused(fresh, edit, where):
    b = load_bundle(fresh)
    bad = copy.deepcopy(b)
    edit(bad["transition"]["state"])
    with pytest.raises(BundleError, match=rf"model\.pt: invalid value in {where}"):
        check_bundle(bad, fresh)
    check_bundle(b, fresh)  # the original passes
    b["measurement"] = {**b["transition"]}
    with pytest.raises(BundleError, match="kind 'inducing' is a transition"):
        check_bundle(b, fresh)


def _add_input(src: Path, dst: Path) -> Path:
    """``src`` with an input channel ``valve`` (a sine) added to every recording."""
    dst.mkdir()
    man = json.loads((src / "manifest.json").read_text())
    man["channels"].append({"name": "valve", "role": "input", "unit": ""})
    (dst / "manifest.json").write_text(json.dumps(man))
    for rec in man["recordings"]:
        with (src / rec["file"]).open() as fh:
            rows = list(csv.reader(fh))
        out = [[*rows[0], "valve"]] + [
            [*r, repr(math.sin(0.3 * k))] for k, r in enumerate(rows[1:])
        ]
        with (dst / rec["file"]).open("w", newline="") as fh:
            csv.writer(fh).writerows(out)
    return dst


def test_likelihood_method_with_inputs(tmp_path, data):
    """``method = "likelihood"`` (windows, Adam) on a dataset with an input channel and no
    states in the validation split either: the transition takes ``[x; u]``, the fit raises the
    likelihood, the state-based validation figures are skipped, the bundle filters."""
    with_u = _add_input(data, tmp_path / "data_u")
    _strip_states(with_u, "validation")
    text = (
        RECIPE.replace("m_step_iterations = 5\n", "")
        .replace(
            'method = "em"\niterations = 6', 'method = "likelihood"\noptimizer = "adam"\nlr = 0.002'
        )
        .replace("inducing = 6", "inducing = 4\nwindow = 50\nburn_in = 5\niterations = 4")
        .replace("iterations = 4\n", 'iterations = 4\nknown_channels = ["pressure"]\n', 1)
        .replace("[calibrate]\niterations = 4", "[calibrate]\nenabled = false")
    )
    bundle = train_recipe(
        write(tmp_path / "r.toml", with_u, text), tmp_path / "run", progress=False
    )
    b = load_bundle(bundle)
    st, fit = b["transition"]["state"], b["transition"]["fit"]
    assert (
        st["input_dim"] == 1
        and st["linear"].shape == (2, 3)
        and st["inducing_inputs"].shape == (4, 3)
    )
    assert fit["method"] == "likelihood" and fit["iterations"] == 4
    assert fit["log_likelihood"] > fit["initial_log_likelihood"]
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in lines if r["stage"] == "transition"] == [1, 2, 3, 4]
    val = json.loads((tmp_path / "run" / "validation.json").read_text())
    assert val["one_step"].startswith("skipped") and "transition" not in val
    assert "nis_mean" in val["filter"]["uncalibrated"]
    assert "nees_mean" not in val["filter"]["uncalibrated"]
    summary = torchfilt.pipeline.filter_recordings(
        bundle, [with_u / "rec_003.csv"], tmp_path / "est"
    )
    assert summary["recordings"][0]["finite"]


@pytest.mark.slow
def test_sigkilled_run_resumes_to_the_uninterrupted_bundle(data, tmp_path):
    """A real SIGKILL of ``torchfilt train`` during the measurement-only stage: ``--resume``
    continues from the last checkpoint to the bundle of an uninterrupted run."""
    text = RECIPE.replace(f"iterations = {ITERATIONS}", "iterations = 40", 1)
    recipe = write(tmp_path / "r.toml", data, text)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "torchfilt", "train", str(recipe), "--out", str(run), "--quiet"]
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, env=env, stderr=err, stdout=subprocess.DEVNULL)
        t0 = time.time()
        while not (run / "transition.ckpt").exists():
            assert proc.poll() is None, f"training exited early: {log.read_text()}"
            assert time.time() - t0 < 120, "no checkpoint appeared"
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not (run / "transition.pt").exists(), "the stage finished before it could be killed"
    torch.set_num_threads(1)
    train_recipe(recipe, run, resume=True, progress=False)
    ref = train_recipe(recipe, tmp_path / "fresh", progress=False)
    _assert_same_learned_model(load_bundle(run / "model.pt"), load_bundle(ref))


def test_a_recipe_built_in_code_with_a_partial_calibrate_table(tmp_path, data):
    """``calibrate={"iterations": 2}`` gets the other keys' defaults (it used to hit a
    KeyError deep in the stage); a wrong key is a RecipeError naming it."""
    base = load_recipe(write(tmp_path / "r.toml", data))

    def in_code(calibrate: dict) -> Recipe:
        return Recipe(
            path=None,
            name="code",
            seed=1,
            dataset=data,
            transition={},
            measurement=dict(base.measurement),
            filter=dict(base.filter),
            states="none",
            measurement_only={**base.measurement_only, "iterations": 2},
            calibrate=calibrate,
        )

    bundle = load_bundle(train_recipe(in_code({"iterations": 2}), tmp_path / "ok", progress=False))
    assert bundle["calibration"]["fit"]["iterations"] <= 2
    config = json.loads((tmp_path / "ok" / "config.json").read_text())
    assert config["recipe"]["calibrate"]["window"] == base.calibrate["window"]
    with pytest.raises(RecipeError, match=r"unknown key\(s\) \['iters'\] in \[calibrate\]"):
        train_recipe(in_code({"iters": 2}), tmp_path / "bad", progress=False)
    assert not (tmp_path / "bad").exists()


def _boolean_key_runs(tmp_path, data, key: str, override: dict) -> tuple[list[object], str]:
    """Train the recipe without ``[measurement_only] key`` and with ``key = true``, through a
    fitter that records the ``key`` it was passed (``"absent"`` when not) and runs with
    ``override``; check the key's parsed value, and that ``key = false`` keeps the digest of a
    recipe without it while ``true`` changes it (a key added later). The recorded values and
    the recipe text without the key."""
    from torchfilt.pipeline.run_stages import StageFitters

    seen: list[object] = []

    def fitter(*args, **kwargs):
        seen.append(kwargs.get(key, "absent"))
        return fit_measurement_only(*args, **{**kwargs, **override, "iterations": 1})

    text = RECIPE.replace("[calibrate]\niterations = 4", "[calibrate]\nenabled = false")
    for flag, expected in (("", False), (f"{key} = true\n", True)):
        recipe = write(
            tmp_path / f"r{expected}.toml", data, text.replace("[train]", f"{flag}[train]", 1)
        )
        assert load_recipe(recipe).measurement_only[key] is expected
        train_recipe(
            recipe, tmp_path / f"run{expected}", progress=False,
            fitters=StageFitters(measurement_only=fitter, name="recording"),
        )  # fmt: skip
    off = write(tmp_path / "off.toml", data, text.replace("[train]", f"{key} = false\n[train]"))
    digests = {load_recipe(p).digest() for p in (tmp_path / "rFalse.toml", off)}
    assert len(digests) == 1 and load_recipe(tmp_path / "rTrue.toml").digest() not in digests
    assert key not in load_recipe(off).resolved()["measurement_only"]
    return seen, text


def test_recipe_compile_reaches_the_transition_fit(tmp_path, data):
    """``[measurement_only] compile = true`` is passed to the fitter as ``compile=True``
    (default ``False``); a value that is not a boolean is a RecipeError naming the key."""
    seen, text = _boolean_key_runs(tmp_path, data, "compile", {"compile": False})
    assert seen == [False, True]
    bad = write(tmp_path / "bad.toml", data, text.replace("[train]", 'compile = "yes"\n[train]'))
    with pytest.raises(RecipeError, match="compile"):
        load_recipe(bad)


def test_recipe_accelerate_reaches_the_transition_fit(tmp_path, data):
    """``[measurement_only] accelerate = true`` reaches the fitter as ``accelerate=True`` (and
    is not passed at its default); it belongs to method "em" alone, and leaves the digest of a
    recipe without it unchanged."""
    seen, text = _boolean_key_runs(tmp_path, data, "accelerate", {})
    assert seen == ["absent", True]
    lik = (
        text.replace("[train]", "accelerate = true\n[train]")
        .replace(f"m_step_iterations = {M_STEP}\n", "")
        .replace('method = "em"', 'method = "likelihood"')
    )
    bad = write(tmp_path / "lik.toml", data, lik)
    with pytest.raises(RecipeError, match=r"\['accelerate'\]: not an option of method"):
        load_recipe(bad)
