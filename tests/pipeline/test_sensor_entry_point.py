"""``[measurement] model = "package.module:function"``: a user's own sensor as the known
measurement model (the gauge) of a ``states = "none"`` recipe. The reference: the same sensor as
the built-in ``system:reaction`` measurement trains the identical transition; the bundle records
the entry point and its module file's SHA-256, and a changed file is refused on load and on
``--resume``; a bad entry point is a RecipeError naming the file, the table and the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from run_support import sensor_module

from torchfilt.exceptions import BundleError, RecipeError, RunError
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import load_bundle, load_model, train_recipe
from torchfilt.systems import get_system

R_VAR = float(get_system("reaction").model().measurement.noise_cov()[0, 0])

RECIPE = """
name = "sensor"
seed = 1
states = "none"
[dataset]
path = "{data}"
[measurement]
{measurement}
[filter]
prior = "system:reaction"
[measurement_only]
iterations = 2
inducing = 4
m_step_iterations = 3
process_noise = 0.01
[calibrate]
enabled = false
"""

SENSOR = '''
import torch

def total_pressure(x):
    """PA + PB: (..., 2) -> (..., 1)."""
    return x.sum(-1, keepdim=True)

def wrong_shape(x):
    return x

NOT_A_FUNCTION = 3
'''


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sensor_data")
    simulate_dataset("reaction", root, recordings=4, steps=60, seed=0)
    return root


@pytest.fixture
def sensor(tmp_path, monkeypatch) -> tuple[str, Path]:
    """A fresh sensor module (a new name per test: no import cache between tests)."""
    return sensor_module(tmp_path, SENSOR, "user_sensor", monkeypatch)


def _recipe(path: Path, data: Path, measurement: str) -> Path:
    path.write_text(RECIPE.format(data=data.as_posix(), measurement=measurement))
    return path


def test_entry_point_sensor_trains_like_the_builtin_one(data, sensor, tmp_path) -> None:
    name, src = sensor
    ep = _recipe(tmp_path / "ep.toml", data, f'model = "{name}:total_pressure"\nR = [{R_VAR!r}]')
    builtin = _recipe(tmp_path / "builtin.toml", data, 'model = "system:reaction"')
    b_ep = load_bundle(train_recipe(ep, tmp_path / "ep", progress=False))
    b_sys = load_bundle(train_recipe(builtin, tmp_path / "sys", progress=False))
    m = b_ep["measurement"]
    assert m["kind"] == "entry_point" and m["entry_point"] == f"{name}:total_pressure"
    import hashlib

    assert m["sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()
    for k, v in b_sys["transition"]["state"].items():
        if isinstance(v, torch.Tensor):
            torch.testing.assert_close(b_ep["transition"]["state"][k], v, rtol=1e-10, atol=1e-12)
    model = load_model(tmp_path / "ep" / "model.pt")
    x = torch.tensor([[3.0, 1.5]], dtype=torch.float64)
    assert torch.allclose(model.measurement.predict(x).mean, x.sum(-1, keepdim=True))
    assert torch.allclose(model.measurement.noise_cov(), torch.tensor([[R_VAR]]).double())
    # a resume with the same sensor goes through; a changed sensor is refused on resume and load
    train_recipe(ep, tmp_path / "ep", resume=True, progress=False)
    src.write_text(SENSOR.replace("x.sum(-1, keepdim=True)", "2 * x.sum(-1, keepdim=True)"))
    with pytest.raises(RunError, match="sensor module"):
        train_recipe(ep, tmp_path / "ep", resume=True, progress=False)
    with pytest.raises(BundleError, match="changed since the bundle was trained"):
        load_model(tmp_path / "ep" / "model.pt")


@pytest.mark.parametrize(
    ("measurement", "match"),
    [
        ('model = "no_such_module_xyz:h"\nR = [0.1]', r"\[measurement\] model.*cannot import"),
        ('model = "{name}:missing"\nR = [0.1]', r"\[measurement\] model.*no attribute 'missing'"),
        ('model = "{name}:wrong_shape"\nR = [0.1]', r"\[measurement\] model.*shape \(1, 2\)"),
        ('model = "{name}:NOT_A_FUNCTION"\nR = [0.1]', r"\[measurement\] model.*expected a func"),
        ('model = "{name}:total_pressure"', r"\[measurement\] R: .*is a function"),
        ('model = "{name}:total_pressure"\nR = [0.1, 0.2]', r"\[measurement\] R .*shape \(2, 2\)"),
        ('model = "{name}:total_pressure"\nR = [-1.0]', r"\[measurement\] R .*positive definite"),
    ],
)
def test_bad_entry_points_name_the_file_table_and_key(
    data, sensor, tmp_path, measurement, match
) -> None:
    name, _ = sensor
    path = _recipe(tmp_path / "bad.toml", data, measurement.format(name=name))
    with pytest.raises(RecipeError, match=match) as info:
        train_recipe(path, tmp_path / "run", progress=False)
    assert str(path) in str(info.value)
    assert not (tmp_path / "run").exists()


def test_R_is_only_for_an_entry_point(data, tmp_path) -> None:
    path = _recipe(tmp_path / "r.toml", data, 'model = "system:reaction"\nR = [0.1]')
    with pytest.raises(RecipeError, match=r"unknown key\(s\) \['R'\] in \[measurement\]"):
        train_recipe(path, tmp_path / "run", progress=False)
