"""A ``states = "none"`` recipe with ``[measurement_only] method = "both"``: EM, then the
likelihood method, from the same start, the better validation log-likelihood kept; the train log
and the bundle say which and why; a run killed in the second fit resumes to the identical
bundle. ``method = "auto"`` runs the second only where EM stalls: here EM ends at its budget, and
its run is the ``method = "em"`` run with the comparison's record. The data and recipe are those of test_training_measurement_only.py (the 2A -> B
reaction, its states removed), whose ``fresh`` run (method = "em") is the reference for EM's
part."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
import torch
from test_training_measurement_only import _assert_same_learned_model, data, fresh, write

import torchfilt
from torchfilt.cli import main as cli_main
from torchfilt.pipeline import load_bundle, train_recipe
from torchfilt.pipeline.run_stages import StageFitters
from torchfilt.systems import get_system
from torchfilt.training import LikelihoodState

__all__ = ["data", "fresh"]  # the fixtures, shared

#: the recipe with method = "both" (both methods take their own keys)
AUTO = 'method = "both"\nlr = 0.5\niterations = 6'


def _auto(path: Path, data: Path, method: str = "both") -> Path:
    recipe = write(path, data)
    text = AUTO.replace('"both"', f'"{method}"')
    recipe.write_text(recipe.read_text().replace('method = "em"\niterations = 6', text, 1))
    return recipe


@pytest.fixture(scope="module")
def auto_run(tmp_path_factory, data) -> Path:
    root = tmp_path_factory.mktemp("auto_run")
    return train_recipe(_auto(root / "r.toml", data), root / "run", progress=False)


def _score(bundle: dict[str, Any], data: Path) -> float:
    """The validation log-likelihood of the bundle's uncalibrated transition, independently:
    the CKF over the validation recordings from the system's prior."""
    from torchfilt.pipeline.bundle import build_side

    spec = get_system("reaction")
    model = torchfilt.StateSpaceModel(
        build_side(bundle["transition"], "transition"), spec.model().measurement
    )
    ds = torchfilt.load_dataset(data, require_finite=("input",), optional=("state",))
    ckf = torchfilt.CKF(model)
    with torch.no_grad():
        return sum(
            float(
                ckf.filter(
                    r.measurements[1:], x0=spec.prior_mean(), P0=spec.prior_cov()
                ).log_likelihood
            )
            for r in ds.split("validation")
        )


def test_auto_keeps_the_better_method_and_says_so(auto_run, fresh, data, capsys):
    b = load_bundle(auto_run)
    fit = b["transition"]["fit"]
    compared = fit["compared"]
    assert [c["method"] for c in compared] == ["em", "likelihood"]
    assert all(c["basis"] == "validation" for c in compared)
    kept = [c for c in compared if c["kept"]]
    assert len(kept) == 1 and fit["method"] == kept[0]["method"]
    assert kept[0]["score"] == max(c["score"] for c in compared)
    # EM's part is the method = "em" run's fit (EM does not use the validation recordings)
    em = load_bundle(fresh)["transition"]["fit"]
    assert compared[0]["log_likelihood"] == pytest.approx(em["log_likelihood"], rel=1e-10)
    # the kept score is the validation log-likelihood of the bundle's learned transition
    assert kept[0]["score"] == pytest.approx(_score(b, data), rel=1e-9)
    log = (auto_run.parent / "train.log").read_text()
    assert "method both: EM, then the likelihood method, from the same start" in log
    assert "transition: method both: em: validation log-likelihood" in log
    assert f"transition: method both: {fit['method']}: validation log-likelihood" in log
    assert ", kept" in log and "transition (likelihood): iteration" in log
    lines = [json.loads(x) for x in (auto_run.parent / "metrics.jsonl").read_text().splitlines()]
    for m in ("em", "likelihood"):
        its = [r["iteration"] for r in lines if r.get("method") == m]
        assert its == list(
            range(1, next(c for c in compared if c["method"] == m)["iterations"] + 1)
        )
    assert not list(auto_run.parent.glob("transition*.ckpt"))
    assert cli_main(["info", str(auto_run)]) == 0
    info = capsys.readouterr().out
    assert f"learned from: measurements alone (method {fit['method']}," in info
    assert "compared:     em, validation log-likelihood" in info
    assert "compared:     likelihood, validation log-likelihood" in info and ", kept" in info


def test_auto_killed_in_the_likelihood_fit_resumes_to_the_identical_bundle(
    auto_run, data, tmp_path, monkeypatch
):
    import torchfilt.pipeline.run_stages as run_mod

    real = run_mod.fit_measurement_only

    def killed(*args: Any, **kwargs: Any) -> Any:
        inner = kwargs["callback"]

        def cb(state: Any) -> None:
            inner(state)
            if isinstance(state, LikelihoodState) and state.iteration == 3:
                raise KeyboardInterrupt

        return real(*args, **{**kwargs, "callback": cb})

    recipe = _auto(tmp_path / "r.toml", data)
    run = tmp_path / "killed"
    monkeypatch.setattr(run_mod, "fit_measurement_only", killed)
    with pytest.raises(KeyboardInterrupt):
        train_recipe(recipe, run, progress=False)
    assert (run / "transition.em.ckpt").is_file() and (run / "transition.likelihood.ckpt").is_file()
    monkeypatch.setattr(run_mod, "fit_measurement_only", real)
    train_recipe(recipe, run, resume=True, progress=False)
    _assert_same_learned_model(load_bundle(run / "model.pt"), load_bundle(auto_run))
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    fit = load_bundle(auto_run)["transition"]["fit"]
    for c in fit["compared"]:
        its = [r["iteration"] for r in lines if r.get("method") == c["method"]]
        assert its == list(range(1, c["iterations"] + 1))
    assert "transition (likelihood): resuming from iteration" in (run / "train.log").read_text()
    assert math.isfinite(fit["log_likelihood"])


@pytest.mark.parametrize("method", ["both", "auto"])
def test_other_fitters_are_asked_for_the_recipes_method(auto_run, fresh, data, tmp_path, method):
    """Fitters of their own (Ray data-parallel's) are asked for ``"both"`` and ``"auto"`` as the
    recipe says, with the validation recordings the methods are compared on; the run ends with
    the bundle of a local run (``"both"``: ``auto_run``; ``"auto"``: EM's, with the record)."""
    asked: list[tuple[str, int]] = []

    def fitter(*args: Any, **kwargs: Any) -> Any:
        asked.append((kwargs["method"], len(kwargs["validation"])))
        return torchfilt.fit_measurement_only(*args, **kwargs)

    fitters = StageFitters(measurement_only=fitter, name="ray")
    recipe = _auto(tmp_path / "r.toml", data, method)
    b = load_bundle(train_recipe(recipe, tmp_path / "run", progress=False, fitters=fitters))
    n_val = len(torchfilt.load_dataset(data, require_finite=("input",), optional=("state",)).split("validation"))  # fmt: skip
    assert asked == [(method, n_val)] and n_val > 0
    log = (tmp_path / "run" / "train.log").read_text()
    assert f"learning from measurements alone ({method}," in log
    assert "EM alone" not in log
    want = load_bundle(auto_run if method == "both" else fresh)
    if method == "both":
        _assert_same_learned_model(b, want)
        assert b["transition"]["fit"]["compared"] == want["transition"]["fit"]["compared"]
    else:
        assert (
            b["transition"]["fit"]["log_likelihood"] == want["transition"]["fit"]["log_likelihood"]
        )
        assert [c["method"] for c in b["transition"]["fit"]["compared"]] == ["em", "likelihood"]


def test_checkpoint_iterations_of_a_data_parallel_comparison(tmp_path):
    """A data-parallel ``"auto"``/``"both"`` fit keeps one file per process and method in
    ``transition.ckpt``: each method resumes from the lowest iteration its processes saved,
    and neither is read as the other's (nor as a one-method fit's)."""
    from torchfilt.pipeline.run_stages import _transition_iterations

    folder = tmp_path / "transition.ckpt"
    folder.mkdir()
    for name, it in {"rank0.em": 3, "rank1.em": 2, "rank0.likelihood": 5, "rank1.likelihood": 7}.items():  # fmt: skip
        torch.save({"iteration": it}, folder / f"{name}.ckpt")
    assert _transition_iterations(tmp_path) == {"": 0, "em": 2, "likelihood": 5}
    for r, it in ((0, 4), (1, 6)):  # a one-method data-parallel fit
        torch.save({"iteration": it}, folder / f"rank{r}.ckpt")
    assert _transition_iterations(tmp_path) == {"": 4, "em": 2, "likelihood": 5}
    local = tmp_path / "local"
    local.mkdir()
    torch.save({"iteration": 9}, local / "transition.likelihood.ckpt")
    assert _transition_iterations(local) == {"": 0, "em": 0, "likelihood": 9}


def test_auto_keeps_an_em_that_did_not_stall(fresh, data, tmp_path):
    b = load_bundle(
        train_recipe(_auto(tmp_path / "r.toml", data, "auto"), tmp_path / "run", progress=False)
    )
    fit = b["transition"]["fit"]
    em = load_bundle(fresh)["transition"]
    assert fit["method"] == "em" and fit["log_likelihood"] == em["fit"]["log_likelihood"]
    for k, v in em["state"].items():
        got = b["transition"]["state"][k]
        assert torch.equal(got, v) if isinstance(v, torch.Tensor) else got == v, k
    assert "not stalled" in fit["compared"][1]["skipped"] and fit["compared"][1]["score"] is None
    log = (tmp_path / "run" / "train.log").read_text()
    assert 'method auto: EM, then the likelihood method if EM stops with "no improvement"' in log
    assert "transition: method auto: likelihood: not fitted: EM ended 'iterations'" in log
