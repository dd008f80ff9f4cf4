"""One recipe whose likelihood stages run data-parallel on Ray actors (``torchfilt train RECIPE
--ray --data-parallel N``, :func:`~torchfilt.pipeline.distributed.train_recipe_data_parallel`):
the calibration stage and the ``states = "none"`` transition stage on two actors of a ``gloo``
group give the bundle of a local run (the sums only change order), a run interrupted after a
stage checkpoint resumes to the bundle of an uninterrupted one, a local resume of such a run is
refused, and the CLI refuses ``--data-parallel`` where it does not apply."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import run_support
import torch

import torchfilt.pipeline.distributed.data_parallel as dp_mod
import torchfilt.pipeline.distributed.group as group_mod
from torchfilt.cli import main as cli_main
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import load_bundle, train_recipe, train_recipe_data_parallel
from torchfilt.training import RunError

#: float64 sums over two ranks instead of one process: the same arithmetic up to summation order
ORDER_RTOL = 1e-9
#: the same through a likelihood-method fit (L-BFGS)
LBFGS_ORDER_RTOL = 1e-7
CAL_ITERS, EVERY = 8, 3


def _close(a: object, b: object, where: str = "", rtol: float = ORDER_RTOL) -> None:
    """Equal structure, floats (and tensors) to ``rtol``, anything else exactly."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _close(a[k], b[k], f"{where}.{k}", rtol)
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{where}[{i}]", rtol)
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=rtol, atol=1e-15, msg=where)
    elif isinstance(a, float) and not isinstance(b, bool):
        assert b == pytest.approx(a, rel=rtol, abs=1e-15), where
    else:
        assert a == b, where


def _metrics(run: Path, stage: str, method: str | None = None) -> list[int]:
    """The iterations ``metrics.jsonl`` records for ``stage`` (and, under ``method = "auto"``
    or ``"both"``, for one ``method``)."""
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    return [
        r["iteration"]
        for r in lines
        if r["stage"] == stage and (method is None or r.get("method") == method)
    ]


@pytest.fixture(scope="module")
def gp_runs(ray_local, tmp_path_factory):
    """The tiny GP recipe (both sides GPs, then calibration) trained locally and by the CLI with
    ``--data-parallel 2`` (4 training recordings: two per actor)."""
    root = tmp_path_factory.mktemp("dp_gp")
    data = run_support.tiny_dataset(root / "data")
    recipe = run_support.write_recipe(
        root / "tiny.toml", data, iters=3, every=EVERY, cal_iters=CAL_ITERS
    )
    local = root / "local"
    train_recipe(recipe, local, progress=False)
    dp = root / "dp"
    args = ["train", str(recipe), "--out", str(dp), "--ray", "--data-parallel", "2", "--quiet"]
    assert cli_main(args) == 0
    return recipe, local, dp


def test_data_parallel_calibration_gives_the_local_bundle(gp_runs, capsys):
    _, local, dp = gp_runs
    assert sorted(p.name for p in dp.iterdir()) == sorted(p.name for p in local.iterdir())
    a, b = load_bundle(local / "model.pt"), load_bundle(dp / "model.pt")
    assert a.keys() == b.keys()
    for k in ("transition", "measurement", "channels", "prior", "dataset", "recipe"):
        _close(a[k], b[k], k)
    _close(a["calibration"], b["calibration"], "calibration")
    _close(a["validation"], b["validation"], "validation")
    # the calibration moved its floors (the scales stay at 1 on these data)
    fit = b["calibration"]["fit"]
    assert fit["iterations"] == CAL_ITERS and fit["log_likelihood"] > fit["initial_log_likelihood"]
    da, db = (json.loads((r / "dataset.json").read_text()) for r in (local, dp))
    assert da == db
    ca, cb = (json.loads((r / "config.json").read_text()) for r in (local, dp))
    assert ca["digest"] == cb["digest"] and "stage_fitters" not in ca
    assert cb["stage_fitters"] == "data-parallel on 2 Ray actors (--data-parallel 2)"
    assert _metrics(dp, "calibrate") == _metrics(local, "calibrate") == list(range(1, 9))
    assert "calibrate: iteration 6/8" in (dp / "train.log").read_text()
    capsys.readouterr()
    assert cli_main(["info", str(dp / "model.pt")]) == 0
    info = _info_lines(capsys.readouterr().out, dp)
    assert cli_main(["info", str(local / "model.pt")]) == 0
    assert info == _info_lines(capsys.readouterr().out, local)
    assert any("CalibratedModel" in ln for ln in info)
    # a run that started data-parallel resumes only so (refused before anything is touched)
    with pytest.raises(RunError, match=r"data-parallel on 2 Ray actors.*resume it the same way"):
        train_recipe(gp_runs[0], dp, resume=True, progress=False)


def _info_lines(text: str, run: Path) -> list[str]:
    """``torchfilt info`` of ``run/model.pt`` without what differs between two runs of one recipe
    (the run directory, the creation time, floats that differ in their last digits)."""
    text = text.replace(str(run), "RUN")
    return [ln for ln in text.splitlines() if not re.search(r"created|\d\.\d{6,}", ln)]


@pytest.mark.slow
def test_interrupted_data_parallel_run_resumes_to_the_same_bundle(gp_runs, monkeypatch):
    """A driver interrupted in the calibration stage after its checkpoint at iteration 3 (as a
    Ctrl-C would): the actors are stopped and their checkpoints kept; a local resume is refused;
    resuming with ``--data-parallel 2`` gives the uninterrupted run's bundle."""
    recipe, _, dp = gp_runs
    real = dp_mod.calibrate_ray

    run = recipe.parent / "killed"
    # interrupted at iteration 5, after the checkpoint at 3
    monkeypatch.setattr(dp_mod, "calibrate_ray", run_support.interrupted_at(real, 5))
    with pytest.raises(KeyboardInterrupt):
        train_recipe_data_parallel(recipe, run, workers=2, progress=False)
    monkeypatch.setattr(dp_mod, "calibrate_ray", real)
    ck = run / "calibrate.ckpt"
    assert sorted(p.name for p in ck.iterdir()) == ["rank0.ckpt", "rank1.ckpt"]
    assert [torch.load(ck / f"rank{r}.ckpt")["iteration"] for r in (0, 1)] == [3, 3]
    assert not (run / "model.pt").exists()
    with pytest.raises(RunError, match=r"data-parallel on 2 Ray actors.*resume it the same way"):
        train_recipe(recipe, run, resume=True, progress=False)
    with pytest.raises(RunError, match=r"resume it the same way, not data-parallel on 1 Ray"):
        train_recipe_data_parallel(recipe, run, workers=1, resume=True, progress=False)
    train_recipe_data_parallel(recipe, run, workers=2, resume=True, progress=False)
    a, b = load_bundle(run / "model.pt"), load_bundle(dp / "model.pt")
    assert a["calibration"] == b["calibration"]
    for side in ("transition", "measurement"):
        _close(a[side], b[side], side)
    assert _metrics(run, "calibrate") == list(range(1, CAL_ITERS + 1))
    assert not ck.exists()
    assert "calibrate: resuming from iteration 3" in (run / "train.log").read_text()


class _LosesRank1At4(group_mod._DriverCallback):
    """The actors' callback, except that rank 1's process exits (a lost machine) at iteration 4."""

    def __call__(self, state):
        import os

        import torch.distributed

        if torch.distributed.get_rank() == 1 and state.iteration == 4:
            os._exit(1)
        return super().__call__(state)


@pytest.mark.slow
def test_lost_actor_is_a_worker_error_and_the_run_resumes(gp_runs, tmp_path, monkeypatch, capsys):
    """Rank 1 of the calibration stage dies after the checkpoint at iteration 3: a WorkerError
    naming the rank and saying how to resume (one line at the CLI, exit 2); ``--resume`` gives
    the uninterrupted run's bundle."""
    import sys

    import ray

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    recipe, _, dp = gp_runs
    run = tmp_path / "lost"
    monkeypatch.setattr(group_mod, "_DriverCallback", _LosesRank1At4)
    args = ["train", str(recipe), "--out", str(run), "--ray", "--data-parallel", "2", "--quiet"]
    capsys.readouterr()
    assert cli_main(args) == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert re.search(
        r"error: calibrate_ray: rank 1 of 2 was lost.*--resume.*--data-parallel 2", err
    )
    monkeypatch.undo()
    assert not (run / "model.pt").exists()
    ck = run / "calibrate.ckpt"
    assert [torch.load(ck / f"rank{r}.ckpt")["iteration"] for r in (0, 1)] == [3, 3]
    assert cli_main([*args, "--resume"]) == 0
    a, b = load_bundle(run / "model.pt"), load_bundle(dp / "model.pt")
    assert a["calibration"] == b["calibration"]
    assert _metrics(run, "calibrate") == list(range(1, CAL_ITERS + 1))


MEASONLY = """
name = "measonly"
seed = 1
states = "none"
[dataset]
path = "{data}"
[measurement]
model = "system:reaction"
[filter]
prior = "system:reaction"
[measurement_only]
# EM alone keeps the module's runs short (method = "both" on the actors: its own test)
method = "em"
iterations = 4
inducing = 6
m_step_iterations = 4
process_noise = 0.01
nominal = {{system = "reaction", k1 = 0.08}}
[train]
checkpoint_every = 2
[calibrate]
enabled = false
"""


@pytest.fixture(scope="module")
def measonly_runs(ray_local, tmp_path_factory):
    """A ``states = "none"`` recipe (EM, 4 iterations, no calibration) trained locally and with
    ``workers=2`` (3 training recordings: two and one)."""
    root = tmp_path_factory.mktemp("dp_measonly")
    data = root / "data"
    simulate_dataset("reaction", data, recordings=4, steps=60, seed=0)
    recipe = root / "measonly.toml"
    recipe.write_text(MEASONLY.format(data=data.as_posix()))
    local = train_recipe(recipe, root / "local", progress=False)
    dp = train_recipe_data_parallel(recipe, root / "dp", workers=2, progress=False)
    return recipe, local, dp


def test_data_parallel_learns_the_local_sensor_noise(ray_local, tmp_path):
    """``learn_measurement_noise = true`` with your own sensor: the actors learn the ``R`` of a
    local run (summation order apart), and the bundles' sensors hold it."""
    simulate_dataset("reaction", tmp_path / "data", recordings=4, steps=60, seed=0)
    text = MEASONLY.format(data=(tmp_path / "data").as_posix()).replace(
        'model = "system:reaction"\n[filter]',
        'model = "run_support:total_pressure"\nR = [0.1]\n[filter]',
    )
    recipe = tmp_path / "r.toml"
    recipe.write_text(text.replace("[train]", "learn_measurement_noise = true\n[train]"))
    a = load_bundle(train_recipe(recipe, tmp_path / "local", progress=False))
    b = load_bundle(train_recipe_data_parallel(recipe, tmp_path / "dp", workers=2, progress=False))
    _close(a["transition"], b["transition"], "transition")
    R = torch.tensor(b["transition"]["fit"]["measurement_R"], dtype=torch.float64)
    assert abs(float(R) - 0.1) > 1e-3  # it moved from its start
    torch.testing.assert_close(
        a["measurement"]["R"], b["measurement"]["R"], rtol=ORDER_RTOL, atol=0
    )
    torch.testing.assert_close(b["measurement"]["R"].to(torch.float64), R, rtol=1e-12, atol=0)


def test_data_parallel_measurement_only_stage_gives_the_local_bundle(measonly_runs, capsys):
    """``states = "none"``: the EM of the transition stage on two actors learns the transition
    of the local run."""
    _, local, dp = measonly_runs
    a, b = load_bundle(local), load_bundle(dp)
    _close(a["transition"], b["transition"], "transition")
    _close(a["validation"], b["validation"], "validation")
    assert a["calibration"] is None and b["calibration"] is None
    fit = b["transition"]["fit"]
    assert fit["method"] == "em" and fit["iterations"] == 4
    assert fit["log_likelihood"] > fit["initial_log_likelihood"]
    assert _metrics(dp.parent, "transition") == [1, 2, 3, 4]
    assert not (dp.parent / "transition.ckpt").exists()
    capsys.readouterr()
    assert cli_main(["info", str(dp)]) == 0
    assert "learned from: measurements alone (method em" in capsys.readouterr().out


@pytest.fixture(scope="module")
def both_runs(ray_local, tmp_path_factory):
    """The ``states = "none"`` recipe with ``method = "both"`` trained locally and with
    ``workers=2``."""
    root = tmp_path_factory.mktemp("dp_both")
    simulate_dataset("reaction", root / "data", recordings=4, steps=60, seed=0)
    text = MEASONLY.format(data=(root / "data").as_posix()).replace(
        'method = "em"', 'method = "both"\nlr = 0.5'
    )
    recipe = root / "r.toml"
    recipe.write_text(text)
    local = train_recipe(recipe, root / "local", progress=False)
    dp = train_recipe_data_parallel(recipe, root / "dp", workers=2, progress=False)
    return recipe, local, dp


def test_data_parallel_compares_both_methods_like_a_local_run(both_runs):
    """``method = "both"`` on two actors: EM and the likelihood method each data-parallel, the
    two compared on the validation recordings (whole on every actor), the same one kept as in a
    local run, with the same record, metrics and learned transition (summation order apart)."""
    _, local, dp = both_runs
    a, b = load_bundle(local), load_bundle(dp)
    # the likelihood method's L-BFGS line searches carry the order of the sums further (to
    # about 4e-9 relative here) than EM's closed steps
    _close(a["transition"], b["transition"], "transition", rtol=LBFGS_ORDER_RTOL)
    compared = b["transition"]["fit"]["compared"]
    assert [c["method"] for c in compared] == ["em", "likelihood"]
    assert all(c["basis"] == "validation" and c["score"] is not None for c in compared)
    for c in compared:
        assert _metrics(dp.parent, "transition", c["method"]) == list(range(1, c["iterations"] + 1))
    assert not (dp.parent / "transition.ckpt").exists()


def test_data_parallel_takes_accelerate_like_a_local_run(ray_local, tmp_path):
    """``[measurement_only] accelerate = true`` reaches the actors' EM (the stage's fitter took
    no such keyword before: a TypeError inside the stage): the bundle equals a local run's."""
    simulate_dataset("reaction", tmp_path / "data", recordings=4, steps=60, seed=0)
    text = MEASONLY.format(data=(tmp_path / "data").as_posix())
    recipe = tmp_path / "r.toml"
    recipe.write_text(text.replace("\niterations = 4", "\niterations = 2\naccelerate = true", 1))
    a = load_bundle(train_recipe(recipe, tmp_path / "local", progress=False))
    b = load_bundle(train_recipe_data_parallel(recipe, tmp_path / "dp", workers=2, progress=False))
    _close(a["transition"], b["transition"], "transition", rtol=LBFGS_ORDER_RTOL)
    assert b["transition"]["fit"]["options"]["accelerate"] is True


@pytest.mark.slow
def test_interrupted_comparison_resumes_to_the_same_bundle(both_runs, monkeypatch):
    """A data-parallel ``method = "both"`` run killed in its second method (the likelihood
    method's iteration 3, after its checkpoint at 2; EM done) resumes each method from its own
    files to the bundle and metrics of the uninterrupted run."""
    from torchfilt.training import LikelihoodState

    recipe, _, dp = both_runs
    real = dp_mod.fit_measurement_only_ray

    def killed(*args, **kwargs):
        inner = kwargs["callback"]

        def cb(state):
            inner(state)
            if isinstance(state, LikelihoodState) and state.iteration == 3:
                raise KeyboardInterrupt

        return real(*args, **{**kwargs, "callback": cb})

    run = recipe.parent / "killed"
    monkeypatch.setattr(dp_mod, "fit_measurement_only_ray", killed)
    with pytest.raises(KeyboardInterrupt):
        train_recipe_data_parallel(recipe, run, workers=2, progress=False)
    monkeypatch.setattr(dp_mod, "fit_measurement_only_ray", real)
    ck = run / "transition.ckpt"
    saved = {
        m: [torch.load(ck / f"rank{r}.{m}.ckpt")["iteration"] for r in (0, 1)]
        for m in ("em", "likelihood")
    }
    assert saved == {"em": [4, 4], "likelihood": [2, 2]}
    train_recipe_data_parallel(recipe, run, workers=2, resume=True, progress=False)
    a, b = load_bundle(run / "model.pt"), load_bundle(dp)
    _close(a["transition"], b["transition"], "transition")
    for m in ("em", "likelihood"):
        assert _metrics(run, "transition", m) == [1, 2, 3, 4], m
    assert "transition (likelihood): resuming from iteration 2" in (run / "train.log").read_text()
    assert not ck.exists()


@pytest.mark.slow
def test_interrupted_measurement_only_stage_resumes_to_the_same_bundle(measonly_runs, monkeypatch):
    recipe, _, dp = measonly_runs
    real = dp_mod.fit_measurement_only_ray

    run = recipe.parent / "killed"
    # interrupted at iteration 3, after the checkpoint at 2
    monkeypatch.setattr(dp_mod, "fit_measurement_only_ray", run_support.interrupted_at(real, 3))
    with pytest.raises(KeyboardInterrupt):
        train_recipe_data_parallel(recipe, run, workers=2, progress=False)
    monkeypatch.setattr(dp_mod, "fit_measurement_only_ray", real)
    ck = run / "transition.ckpt"
    assert [torch.load(ck / f"rank{r}.ckpt")["iteration"] for r in (0, 1)] == [2, 2]
    assert not (run / "transition.pt").exists()
    train_recipe_data_parallel(recipe, run, workers=2, resume=True, progress=False)
    a, b = load_bundle(run / "model.pt"), load_bundle(dp)
    for k, v in b["transition"]["state"].items():
        va = a["transition"]["state"][k]
        assert torch.equal(va, v) if isinstance(v, torch.Tensor) else va == v, k
    assert a["transition"]["fit"] == b["transition"]["fit"]
    assert _metrics(run, "transition") == [1, 2, 3, 4]
    assert not ck.exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--data-parallel", "2"], r"--data-parallel .*use it with --ray"),
        (["--ray", "--data-parallel", "0"], r"--data-parallel must be a positive integer"),
        (["--ray", "--data-parallel", "2", "--dataset", "d"], r"--data-parallel trains one recipe"),
        (["--ray", "--data-parallel", "2", "SECOND"], r"--data-parallel trains one recipe"),
    ],
)
def test_cli_refuses_data_parallel_where_it_does_not_apply(tmp_path, capsys, extra, message):
    recipe = tmp_path / "r.toml"
    recipe.write_text("name = 'x'\n")
    recipes = [str(recipe)] * (1 + extra.count("SECOND"))
    extra = [e for e in extra if e != "SECOND"]
    capsys.readouterr()
    assert cli_main(["train", *recipes, "--out", str(tmp_path / "run"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("torchfilt train: error: ")
    assert re.search(message, err), err
    assert not (tmp_path / "run").exists()


def test_without_ray_data_parallel_says_how_to_install(tmp_path, capsys, monkeypatch):
    import sys

    from torchfilt.exceptions import MissingDependencyError

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    recipe = tmp_path / "r.toml"
    recipe.write_text("name = 'x'\n")
    with pytest.raises(MissingDependencyError, match=r"pip install 'torchfilt\[distributed\]'"):
        train_recipe_data_parallel(recipe, tmp_path / "run", workers=2)
    capsys.readouterr()
    argv = ["train", str(recipe), "--out", str(tmp_path / "run"), "--ray", "--data-parallel", "2"]
    assert cli_main(argv) == 2
    assert "torchfilt[distributed]" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_actors_import_the_drivers_modules_or_say_which_is_missing(tmp_path, monkeypatch):
    """An actor adds the driver's folders that exist on its machine to ``sys.path`` before it
    unpickles the job (a recipe's own sensor module); a module it still cannot import is a
    MissingDependencyError naming it, not a raw unpickling error."""
    import pickle
    import sys

    from torchfilt.exceptions import MissingDependencyError

    folder = tmp_path / "mods"
    folder.mkdir()
    (folder / "far_sensor.py").write_text("def h(x):\n    return x\n")
    monkeypatch.syspath_prepend(str(folder))
    import far_sensor  # created above

    packed = group_mod._packed({"model": far_sensor.h}, pickle.dumps)
    assert str(folder) in packed[0]
    # an actor: another process, without the module and without its folder on sys.path
    monkeypatch.delitem(sys.modules, "far_sensor")
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(folder)])
    with pytest.raises(MissingDependencyError, match="cannot import module 'far_sensor'"):
        group_mod._unpacked(([], packed[1]))
    job = group_mod._unpacked(packed)  # the driver's folder exists here: found
    assert job["model"](3) == 3 and str(folder) in sys.path


def test_the_ray_fitters_take_every_keyword_the_stages_pass(tmp_path):
    """A local run through spy fitters records what the calibration and ``states = "none"``
    stages pass with every optional key set (``method = "auto"``, ``accelerate``, a learned
    sensor noise, calibration on); the Ray stage fitters' signatures take all of it (a missing
    keyword was a raw ``TypeError`` inside the stage: ``accelerate``). No Ray needed."""
    import inspect

    from torchfilt.pipeline.run_stages import StageFitters
    from torchfilt.training import calibrate, fit_measurement_only

    seen: dict[str, tuple[int, dict]] = {}

    def spy(name, real):
        def fit(*args, **kwargs):
            seen[name] = (len(args), kwargs)
            return real(*args, **kwargs)

        return fit

    simulate_dataset("reaction", tmp_path / "data", recordings=4, steps=40, seed=0)
    text = MEASONLY.format(data=(tmp_path / "data").as_posix())
    text = text.replace('model = "system:reaction"\n[filter]', 'model = "run_support:total_pressure"\nR = [0.1]\n[filter]')  # fmt: skip
    text = text.replace('method = "em"', 'method = "auto"').replace(
        "\niterations = 4", "\niterations = 2\naccelerate = true\nlearn_measurement_noise = true", 1
    )
    text = text.replace("[calibrate]\nenabled = false", "[calibrate]\niterations = 2")
    recipe = tmp_path / "r.toml"
    recipe.write_text(text)
    local = StageFitters(
        calibrate=spy("calibrate", calibrate),
        measurement_only=spy("measurement_only", fit_measurement_only),
        name="spy",
    )
    train_recipe(recipe, tmp_path / "run", progress=False, fitters=local)
    assert set(seen) == {"calibrate", "measurement_only"}
    assert {"accelerate", "validation", "learn_measurement_noise"} <= set(
        seen["measurement_only"][1]
    )
    ray_fitters = dp_mod.data_parallel_fitters(2)
    for name, (n_args, kwargs) in seen.items():
        inspect.signature(getattr(ray_fitters, name)).bind(*([None] * n_args), **kwargs)
