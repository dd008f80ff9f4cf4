"""The training pipeline: recipes, run directories, resume after a kill, bundles, end to end."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import run_support
import torch

import torchfilt
from torchfilt.cli import main as cli_main
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import BUNDLE_SCHEMA, load_bundle, load_model, load_recipe, train_recipe
from torchfilt.training import BundleError, RecipeError, RunError

ROOT = Path(__file__).resolve().parents[2]
#: resumed and uninterrupted runs execute the same float64 arithmetic: they agree to round-off
RESUME_RTOL = 1e-10


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    simulate_dataset("reaction", root, recordings=6, steps=30, seed=0)
    return root


def write_recipe(
    path: Path, data: Path, iters: int = 20, every: int = 5, cal_iters: int = 12
) -> Path:
    return run_support.write_recipe(path, data, iters=iters, every=every, cal_iters=cal_iters)


def gp_tensors(bundle: dict) -> dict[str, torch.Tensor]:
    out = {}
    for side in ("transition", "measurement"):
        for k, v in bundle[side]["state"]["state_dict"].items():
            out[f"{side}.{k}"] = v
    return out


def test_end_to_end_train_filter_evaluate(tmp_path, tiny_data, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data)
    run = tmp_path / "run"
    assert cli_main(["train", str(recipe), "--out", str(run), "--quiet"]) == 0
    for f in (
        "config.json",
        "dataset.json",
        "metrics.jsonl",
        "validation.json",
        "model.pt",
        "train.log",
    ):
        assert (run / f).is_file(), f
    assert not (run / "checkpoint.pt").exists()
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["iteration"]) for r in lines if r["stage"] != "calibrate"] == [
        (s, i) for s in ("transition", "measurement") for i in range(1, 21)
    ]
    cal_lines = [r["iteration"] for r in lines if r["stage"] == "calibrate"]
    assert cal_lines == list(range(1, len(cal_lines) + 1)) and cal_lines
    assert "lengthscale" in " ".join(lines[0]["hyperparameters"])
    # each stage logs its estimated remaining time once, after its first iterations
    log_text = (run / "train.log").read_text()
    for stage in ("transition", "measurement"):
        estimates = [x for x in log_text.splitlines() if f"{stage}: about " in x]
        assert len(estimates) == 1 and "s left at most" in estimates[0], stage
    dlog = json.loads((run / "dataset.json").read_text())
    assert len(dlog["fingerprint"]["files"]) == 6 and dlog["split"]["test"] == ["rec_005"]
    val = json.loads((run / "validation.json").read_text())
    assert set(val) >= {"transition", "measurement"} and len(val["transition"]["rmse"]) == 2
    assert set(val["filter"]) == {"uncalibrated", "calibrated"}
    assert {"nis_mean", "nees_mean", "coverage95"} <= set(val["filter"]["calibrated"])
    bundle = load_bundle(run / "model.pt")
    assert bundle["dataset"] == dlog["fingerprint"] and bundle["schema"] == BUNDLE_SCHEMA
    # the learned model filters the held-out recording about as well as the true model
    test = sorted(str(p) for p in tiny_data.glob("rec_005.csv"))
    learned = torchfilt.pipeline.filter_recordings(run / "model.pt", test, tmp_path / "est_gp")
    true = torchfilt.pipeline.filter_recordings("system:reaction", test, tmp_path / "est_true")
    r_gp = learned["recordings"][0]["filtered_metrics"]["rmse"]
    r_true = true["recordings"][0]["filtered_metrics"]["rmse"]
    assert all(a < 3.0 * b + 0.05 for a, b in zip(r_gp, r_true, strict=True)), (r_gp, r_true)
    model = load_model(run / "model.pt")
    assert isinstance(model.transition, torchfilt.CalibratedModel)
    assert isinstance(model.transition.base, torchfilt.GPTransition)
    cal = bundle["calibration"]
    assert torch.allclose(
        model.transition.scale, torch.tensor(cal["transition"]["scale"], dtype=torch.float64)
    )
    assert min(cal["transition"]["scale"] + cal["measurement"]["scale"]) >= 1.0  # inflate only
    capsys.readouterr()
    assert cli_main(["info", str(run / "model.pt")]) == 0
    info = capsys.readouterr().out
    assert "CalibratedModel" in info and '"calibration"' in info and '"scale"' in info


def _wait_for(path: Path, proc: subprocess.Popen, log: Path, timeout: float = 120.0) -> None:
    t0 = time.time()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"training exited early: {log.read_text()}")
        if time.time() - t0 > timeout:
            proc.kill()
            raise AssertionError("no checkpoint appeared")
        time.sleep(0.01)


def test_resume_after_kill_reaches_the_same_model(tmp_path, tiny_data):
    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data, iters=150, every=5)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    killed = tmp_path / "killed"
    cmd = [sys.executable, "-m", "torchfilt", "train", str(recipe), "--out", str(killed), "--quiet"]
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, env=env, stderr=err, stdout=subprocess.DEVNULL)
        _wait_for(killed / "checkpoint.pt", proc, log)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "model.pt").exists(), "the run finished before it could be killed"
    with pytest.raises(RunError, match="already holds a run"):
        train_recipe(recipe, killed, progress=False)
    torch.set_num_threads(1)
    train_recipe(recipe, killed, resume=True, progress=False)
    fresh = tmp_path / "fresh"
    train_recipe(recipe, fresh, progress=False)
    a, b = gp_tensors(load_bundle(killed / "model.pt")), gp_tensors(load_bundle(fresh / "model.pt"))
    assert a.keys() == b.keys()
    for k in a:
        assert torch.allclose(a[k], b[k], rtol=RESUME_RTOL, atol=0), k
    assert (
        load_bundle(killed / "model.pt")["calibration"]
        == load_bundle(fresh / "model.pt")["calibration"]
    )
    lines = [json.loads(x) for x in (killed / "metrics.jsonl").read_text().splitlines()]
    keys = [(r["stage"], r["iteration"]) for r in lines if r["stage"] != "calibrate"]
    assert keys == [(s, i) for s in ("transition", "measurement") for i in range(1, 151)]


def test_resume_after_kill_during_calibration_equals_uninterrupted(
    tmp_path, tiny_data, monkeypatch
):
    """A run killed in the calibration stage resumes from its checkpoint to the same bundle."""
    import torchfilt.pipeline.run_stages as run_mod

    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data, iters=10, every=3)
    fresh = tmp_path / "fresh"
    train_recipe(recipe, fresh, progress=False)
    real = run_mod.calibrate
    killed = tmp_path / "killed"
    # interrupted at iteration 8, after the checkpoint at 6
    monkeypatch.setattr(run_mod, "calibrate", run_support.interrupted_at(real, 8))
    with pytest.raises(KeyboardInterrupt):
        train_recipe(recipe, killed, progress=False)
    assert (killed / "calibrate.ckpt").is_file() and not (killed / "model.pt").exists()
    monkeypatch.setattr(run_mod, "calibrate", real)
    train_recipe(recipe, killed, resume=True, progress=False)
    a, b = load_bundle(killed / "model.pt"), load_bundle(fresh / "model.pt")
    assert a["calibration"] == b["calibration"]
    assert not (killed / "calibrate.ckpt").exists()
    lines = [json.loads(x) for x in (killed / "metrics.jsonl").read_text().splitlines()]
    its = [r["iteration"] for r in lines if r["stage"] == "calibrate"]
    assert its == list(range(1, a["calibration"]["fit"]["iterations"] + 1))


def test_calibration_can_be_switched_off(tmp_path, tiny_data):
    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data, iters=3, every=3)
    recipe.write_text(recipe.read_text().replace("[calibrate]\n", "[calibrate]\nenabled = false\n"))
    run = tmp_path / "run"
    train_recipe(recipe, run, progress=False)
    assert load_bundle(run / "model.pt")["calibration"] is None
    assert isinstance(load_model(run / "model.pt").transition, torchfilt.GPTransition)
    assert set(json.loads((run / "validation.json").read_text())["filter"]) == {"uncalibrated"}


def test_resume_refuses_changes(tmp_path, tiny_data):
    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data, iters=3, every=1)
    run = tmp_path / "run"
    with pytest.raises(RunError, match="no run to resume"):
        train_recipe(recipe, run, resume=True, progress=False)
    train_recipe(recipe, run, progress=False)
    write_recipe(recipe, tiny_data, iters=4, every=1)
    with pytest.raises(RunError, match="recipe changed"):
        train_recipe(recipe, run, resume=True, progress=False)


class Evil:
    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


def test_tampered_foreign_and_corrupted_bundles_are_refused(tmp_path):
    marker = tmp_path / "pwned"
    evil = {"schema": BUNDLE_SCHEMA, "transition": Evil(str(marker))}
    torch.save(evil, tmp_path / "evil.pt")
    with pytest.raises(BundleError, match="refused: the file contains Python objects"):
        load_bundle(tmp_path / "evil.pt")
    assert not marker.exists()
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(BundleError, match="not a torchfilt model bundle"):
        load_bundle(tmp_path / "foreign.pt")
    raw = (tmp_path / "foreign.pt").read_bytes()
    (tmp_path / "trunc.pt").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(BundleError, match="not a readable torchfilt model bundle"):
        load_bundle(tmp_path / "trunc.pt")
    (tmp_path / "text.pt").write_text("hello")
    with pytest.raises(BundleError, match="not a readable"):
        load_bundle(tmp_path / "text.pt")
    with pytest.raises(BundleError, match="model bundle not found"):
        load_bundle(tmp_path / "missing.pt")
    assert cli_main(["info", str(tmp_path / "evil.pt")]) == 2


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "[dataset]\npath='x'\n[transition]\nitertions=3\n[measurement]\n",
            r"unknown key\(s\) \['itertions'\] in \[transition\]",
        ),
        ("[transition]\n[measurement]\n", r"\[dataset\] needs 'path'"),
        ("[dataset]\npath='x'\n[measurement]\n", r"missing \[transition\] table"),
        ("[dataset]\npath='x'\n[transition]\nmodel='reentry'\n[measurement]\n", "model must be"),
        (
            "[dataset]\npath='x'\n[transition]\n[measurement]\n[train]\ndtype='float16'\n",
            "dtype must be",
        ),
        (
            "[dataset]\npath='x'\n[transition]\nprior_mean='reentry'\n[measurement]\n",
            "prior_mean must be a table",
        ),
        ("colour = 1\n", r"unknown key\(s\) \['colour'\] in \[top level\]"),
        (
            "[dataset]\npath='x'\n[transition]\nkernel='nosuch'\n[measurement]\n",
            r"\[transition\] kernel must be \"rbf\", \"matern52\"",
        ),
        ("[dataset]\npath='x'\n[transition]\n[measurement]\niterations=0\n", "iterations must be"),
        ("[dataset]\npath='x'\n[transition]\nlr=-1\n[measurement]\n", r"lr must be a number > 0"),
        ("[dataset]\npath='x'\n[transition]\nincrement='yes'\n[measurement]\n", "increment"),
        ("[dataset]\npath='x'\n[transition]\n[measurement]\n[train]\nthreads=0\n", "threads"),
        ("seed = 1.5\n[dataset]\npath='x'\n[transition]\n[measurement]\n", "seed must be"),
        ("[dataset\n", "not valid TOML"),
    ],
)
def test_recipe_errors_name_the_key(tmp_path, text, message):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(RecipeError, match=message):
        load_recipe(p)


def test_recipe_kernels_are_the_gp_kernels():
    from torchfilt.models.gp.kernels import KERNELS
    from torchfilt.pipeline.recipe import KERNELS as RECIPE_KERNELS

    assert set(RECIPE_KERNELS) == set(KERNELS)


@pytest.mark.parametrize("path", sorted((ROOT / "trainers").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_recipes_are_valid(path):
    r = load_recipe(path)
    ds = torchfilt.load_dataset(r.dataset)
    names = ds.manifest.names("state") + ds.manifest.names("input")
    for side in ("transition", "measurement"):
        for name in getattr(r, side).get("inputs", []):
            assert name in names, f"{path.name}: [{side}] input {name!r} is not a channel"
    assert ds.split("train") and ds.split("test")


def test_calibration_refits_gp_noises_into_the_bundle(tmp_path, tiny_data):
    """``[calibrate] gp = "noise"``: the bundle holds the GPs with the refitted noises (not the
    ones of the stage files), `info` shows them, and the loaded model predicts with them."""
    recipe = write_recipe(tmp_path / "tiny.toml", tiny_data, iters=3, every=3, cal_iters=4)
    recipe.write_text(recipe.read_text().replace("[calibrate]\n", '[calibrate]\ngp = "noise"\n'))
    run = tmp_path / "run"
    train_recipe(recipe, run, progress=False)
    b = load_bundle(run / "model.pt")
    stage = torch.load(run / "transition.pt", weights_only=True)
    cal = b["calibration"]
    assert "models" not in cal and cal["fit"]["options"]["gp"] == "noise"
    logged = cal["gp_hyperparameters"]
    assert set(logged) == {"transition", "measurement"}
    before = torchfilt.GPTransition.from_state(stage["state"]).noise_variance
    model = load_model(run / "model.pt")
    after = model.transition.base.noise_variance
    assert not torch.allclose(before, after)
    assert torch.allclose(after, torch.tensor(logged["transition"]["noise"], dtype=after.dtype))
    # a run resumed after the calibration stage (bundle lost) takes the refitted GPs from
    # calibration.pt: the same bundle models
    (run / "model.pt").unlink()
    train_recipe(recipe, run, resume=True, progress=False)
    again = load_bundle(run / "model.pt")
    assert again["calibration"] == cal
    for k, v in b["transition"]["state"]["state_dict"].items():
        assert torch.equal(v, again["transition"]["state"]["state_dict"][k]), k
