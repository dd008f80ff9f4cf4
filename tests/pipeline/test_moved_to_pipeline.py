"""Recipes, runs and bundles moved from ``torchfilt.training`` to ``torchfilt.pipeline``; the old
names keep working for one release, each with a ``DeprecationWarning`` naming the new one."""

from __future__ import annotations

import importlib
import sys

import pytest

import torchfilt.pipeline
import torchfilt.pipeline.bundle
import torchfilt.pipeline.recipe
import torchfilt.pipeline.run
import torchfilt.pipeline.run_stages
import torchfilt.training

MOVED = [
    "BUNDLE_SCHEMA",
    "LOCAL_FITTERS",
    "ModelSpec",
    "Recipe",
    "StageFitters",
    "load_bundle",
    "load_model",
    "load_model_spec",
    "load_recipe",
    "save_bundle",
    "train_recipe",
    "upgrade_bundle",
]


@pytest.mark.parametrize("name", MOVED)
def test_old_training_name_warns_and_is_the_pipeline_one(name):
    with pytest.warns(DeprecationWarning, match=rf"torchfilt\.pipeline\.{name}\b"):
        old = getattr(torchfilt.training, name)
    assert old is getattr(torchfilt.pipeline, name)


@pytest.mark.parametrize("module", ["recipe", "run", "bundle"])
def test_old_training_module_warns_and_re_exports(module, monkeypatch):
    monkeypatch.delitem(sys.modules, f"torchfilt.training.{module}", raising=False)
    with pytest.warns(DeprecationWarning, match=rf"use torchfilt\.pipeline\.{module}\b"):
        old = importlib.import_module(f"torchfilt.training.{module}")
    new = importlib.import_module(f"torchfilt.pipeline.{module}")
    assert old.__all__ == new.__all__
    for name in new.__all__:
        assert getattr(old, name) is getattr(new, name), name


def test_old_run_module_reaches_the_stage_helpers(monkeypatch):
    """``torchfilt.training.run`` stands in for the three modules it became."""
    monkeypatch.delitem(sys.modules, "torchfilt.training.run", raising=False)
    with pytest.deprecated_call():
        old = importlib.import_module("torchfilt.training.run")
    assert old.calibrate is torchfilt.pipeline.run_stages.calibrate
    assert old._calibrate_stage is torchfilt.pipeline.run_stages._calibrate_stage
    assert old._check_measurement_only is torchfilt.pipeline.run_checks._check_measurement_only
    assert old.train_recipe is torchfilt.pipeline.run.train_recipe
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = old.nothing


def test_top_level_names_come_from_the_pipeline():
    import torchfilt

    for name in ("load_bundle", "load_model", "train_recipe"):
        assert getattr(torchfilt, name) is getattr(torchfilt.pipeline, name)


def test_unknown_training_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = torchfilt.training.nothing


def test_progress_bar_moved_to_io():
    """``torchfilt.training.progress`` still imports, with a ``DeprecationWarning`` naming
    ``torchfilt.io.progress``, and its bar is ``torchfilt.io.progress``'s."""
    from torchfilt.io.progress import ProgressBar

    sys.modules.pop("torchfilt.training.progress", None)
    with pytest.warns(DeprecationWarning, match=r"torchfilt\.io\.progress"):
        from torchfilt.training.progress import ProgressBar as Old

    assert Old is ProgressBar
