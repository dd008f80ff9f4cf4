"""``[measurement_only] learn_measurement_noise = true``: a ``states = "none"`` run learns the
noise ``R`` of the user's own sensor (its start: ``[measurement] R``) with the transition.

References: the same fit through the Python API (``fit_measurement_only`` on the pipeline's own
start, the sensor's noise a :class:`~torchfilt.models.DiagonalCovariance`) gives the same ``R``;
a start ten times the simulator's true noise moves towards it; the bundle's measurement side
holds the learned ``R`` (loaded, resumed after a kill, shown by ``torchfilt info``); a recipe that
cannot learn it is a RecipeError naming the keys."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from run_support import interrupted_at, sensor_module

from torchfilt.cli import main
from torchfilt.exceptions import RecipeError
from torchfilt.io import load_dataset
from torchfilt.io.synth import simulate_dataset
from torchfilt.models import DiagonalCovariance
from torchfilt.pipeline import load_bundle, load_model, train_recipe
from torchfilt.pipeline.entry_point import load_entry_point
from torchfilt.pipeline.recipe import load_recipe
from torchfilt.pipeline.run_stages import _measurement_only_model
from torchfilt.systems import get_system
from torchfilt.training import fit_measurement_only

R_TRUE = float(get_system("reaction").model().measurement.noise_cov()[0, 0])
R_START = 10 * R_TRUE

RECIPE = """
name = "learned-noise"
seed = 1
states = "none"
[dataset]
path = "{data}"
[measurement]
model = "{module}:total_pressure"
R = [{r}]
[filter]
prior = "system:reaction"
[measurement_only]
iterations = {iterations}
inducing = 4
m_step_iterations = 5
process_noise = 0.01
learn_measurement_noise = true
[calibrate]
enabled = false
"""

SENSOR = '''
def total_pressure(x):
    """PA + PB: (..., 2) -> (..., 1)."""
    return x.sum(-1, keepdim=True)
'''


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("noise_data")
    simulate_dataset("reaction", root, recordings=5, steps=80, seed=4)
    return root


@pytest.fixture
def module(tmp_path, monkeypatch) -> str:
    return sensor_module(tmp_path, SENSOR, "noisy_sensor", monkeypatch)[0]


def _recipe(path: Path, data: Path, module: str, iterations: int = 8) -> Path:
    path.write_text(
        RECIPE.format(data=data.as_posix(), module=module, r=R_START, iterations=iterations)
    )
    return path


def test_learned_noise_is_the_api_fit_and_the_bundle_keeps_it(data, module, tmp_path) -> None:
    recipe = _recipe(tmp_path / "r.toml", data, module)
    bundle = train_recipe(recipe, tmp_path / "run", progress=False)
    b = load_bundle(bundle)
    learned = torch.tensor(b["transition"]["fit"]["measurement_R"], dtype=torch.float64)
    assert learned.shape == (1, 1)
    # the reference: fit_measurement_only on the pipeline's start and training recordings, the
    # sensor's noise a DiagonalCovariance from the recipe's R
    r = load_recipe(recipe)
    train = load_dataset(data, optional=("state",)).split("train")
    spec = get_system("reaction")
    m0, P0 = spec.prior_mean(), spec.prior_cov()
    h = load_entry_point(
        f"{module}:total_pressure", [R_START], role="measurement", state_dim=2, obs_dim=1,
        learn_R=True,
    )[0]  # fmt: skip
    assert any(isinstance(m, DiagonalCovariance) for m in h.modules())
    start = _measurement_only_model(r, h, train, 2, 0, m0, P0, torch.float64)
    fit = fit_measurement_only(
        start, [rec.measurements[1:] for rec in train], x0=m0, P0=P0, known_channels=[0],
        iterations=8, m_step_iterations=5, noise_scale="none", method="em",
    )  # fmt: skip
    assert torch.allclose(learned, fit.model.measurement.noise_cov().detach(), rtol=1e-8)
    # towards the simulator's noise from ten times it
    assert abs(math.log(float(learned) / R_TRUE)) < 0.5 * math.log(10)
    # the bundle's measurement side holds it: the entry, the loaded model, torchfilt info
    assert torch.allclose(b["measurement"]["R"].to(torch.float64), learned, rtol=1e-12)
    model = load_model(bundle)
    assert torch.allclose(model.measurement.noise_cov().detach(), learned, rtol=1e-12)
    assert not any(p.requires_grad for p in model.measurement.parameters())
    log = (tmp_path / "run" / "train.log").read_text()
    assert "known channels ['pressure'], and the sensor's noise R)" in log
    assert "its noise R learned with the transition" in log


def test_info_shows_the_learned_noise(data, module, tmp_path, capsys) -> None:
    bundle = train_recipe(
        _recipe(tmp_path / "r.toml", data, module, iterations=2), tmp_path / "run", progress=False
    )
    assert main(["info", str(bundle)]) == 0
    out = capsys.readouterr().out
    assert "sensor noise: R learned with the transition" in out
    assert "2 iterations, stopped at its budget, not converged" in out


def test_killed_run_resumes_to_the_same_learned_noise(data, module, tmp_path, monkeypatch):
    import torchfilt.pipeline.run_stages as run_mod

    recipe = _recipe(tmp_path / "r.toml", data, module, iterations=4)
    fresh = load_bundle(train_recipe(recipe, tmp_path / "fresh", progress=False))
    real = run_mod.fit_measurement_only
    run = tmp_path / "killed"
    monkeypatch.setattr(run_mod, "fit_measurement_only", interrupted_at(real, 3))
    with pytest.raises(KeyboardInterrupt):
        train_recipe(recipe, run, progress=False)
    monkeypatch.setattr(run_mod, "fit_measurement_only", real)
    again = load_bundle(train_recipe(recipe, run, resume=True, progress=False))
    assert (
        again["transition"]["fit"]["measurement_R"] == fresh["transition"]["fit"]["measurement_R"]
    )
    assert torch.equal(again["measurement"]["R"], fresh["measurement"]["R"])


@pytest.mark.parametrize(
    ("measurement", "message"),
    [
        ('model = "system:reaction"', "is a built-in"),
        ('model = "{module}:total_pressure"', "needs R|has no R"),
    ],
)
def test_a_noise_that_cannot_be_learned_is_a_recipe_error(
    data, module, tmp_path, measurement, message
) -> None:
    text = RECIPE.format(data=data.as_posix(), module=module, r=R_START, iterations=2).replace(
        f'model = "{module}:total_pressure"\nR = [{R_START}]', measurement.format(module=module)
    )
    recipe = tmp_path / "r.toml"
    recipe.write_text(text)
    with pytest.raises(RecipeError, match=message) as e:
        train_recipe(recipe, tmp_path / "run", progress=False)
    assert "learn_measurement_noise" in str(e.value) or "R" in str(e.value)
