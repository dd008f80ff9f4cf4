"""Verified, fast model bundles: checksum, range checks, stored predictor caches, the time column,
and bundles of the earlier schema."""

from __future__ import annotations

import hashlib
import io
import json
import re

import numpy as np
import pytest
import torch
from run_support import tiny_bundle, tiny_dataset, write_recipe

from torchfilt import GPMeasurement, GPTransition
from torchfilt.cli import main
from torchfilt.exceptions import BundleError, OutputError
from torchfilt.models.gp.model import GPModel
from torchfilt.pipeline import (
    BUNDLE_SCHEMA,
    load_bundle,
    load_model,
    save_bundle,
    train_recipe,
    upgrade_bundle,
)
from torchfilt.pipeline.bundle import LEGACY_SCHEMA, UnverifiedBundleWarning

#: a model rebuilt from its stored cache predicts what the trained model predicts; the exact
#: form's Cholesky factor is recomputed from the same numbers, so they agree to round-off
CACHE_RTOL = 1e-9
CACHE_ATOL = 1e-12
#: byte offsets checked by the flip test: every header byte plus this many spread over the file
SPREAD_OFFSETS = 400


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return tiny_bundle(tmp_path_factory.mktemp("bundle"))


def write_raw(path, payload: dict, *, digest: str | None = None) -> None:
    """A schema-2 bundle written independently of save_bundle (no value checks on the way)."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    data = buf.getvalue()
    digest = hashlib.sha256(data).hexdigest() if digest is None else digest
    path.write_bytes(f"{BUNDLE_SCHEMA} sha256={digest}\n".encode() + data)


# ------------------------------------------------------------------------------ integrity
def test_bundle_starts_with_its_checksum(bundle):
    raw = bundle.read_bytes()
    header, payload = raw.split(b"\n", 1)
    assert header == f"{BUNDLE_SCHEMA} sha256={hashlib.sha256(payload).hexdigest()}".encode()


def test_any_flipped_byte_is_refused(bundle, tmp_path):
    raw = bundle.read_bytes()
    header_len = raw.index(b"\n") + 1
    rng = np.random.default_rng(0)
    offsets = sorted(
        set(range(header_len)) | set(rng.integers(header_len, len(raw), SPREAD_OFFSETS).tolist())
    )
    offsets.append(len(raw) - 1)
    bad = tmp_path / "bad.pt"
    for off in offsets:
        for flip in (0x01, 0x80):
            b = bytearray(raw)
            b[off] ^= flip
            bad.write_bytes(bytes(b))
            with pytest.raises(BundleError, match=re.escape(str(bad))):
                load_bundle(bad)
    assert len(offsets) > SPREAD_OFFSETS // 2


@pytest.mark.parametrize("edit", ["truncate", "append", "drop_header"])
def test_truncated_extended_or_headless_bundle_is_refused(bundle, tmp_path, edit):
    raw = bundle.read_bytes()
    header_len = raw.index(b"\n") + 1
    data = {
        "truncate": raw[:-1],
        "append": raw + b"\0",
        "drop_header": raw[header_len:],  # a bare payload claims schema 2 without a checksum
    }[edit]
    bad = tmp_path / "bad.pt"
    bad.write_bytes(data)
    with pytest.raises(BundleError, match=re.escape(str(bad))) as info:
        load_bundle(bad)
    assert "checksum" in str(info.value)


# ------------------------------------------------------------------------------ value checks
def _edit_gp(b: dict, key: str, value) -> None:
    b["transition"]["state"]["state_dict"][key] = value


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda b: _edit_gp(b, "target_std.scale", torch.zeros(2, dtype=torch.float64)), "scale"),
        (
            lambda b: (
                b["transition"]["state"]["state_dict"]["groups.0.train_y"]
                .view(-1)[:1]
                .fill_(float("nan"))
            ),
            "not finite",
        ),
        (lambda b: b.update(sample_time=float("inf")), "sample_time"),
        (lambda b: b.update(sample_time=0.0), "sample_time"),
        (lambda b: b["prior"]["cov"].fill_diagonal_(-1.0), "positive semi-definite"),
        (lambda b: b["prior"].update(mean=torch.zeros(5, dtype=torch.float64)), "do not match"),
        (
            lambda b: b["measurement"]["state"]["frozen"]["blocks"][0]["args"][
                "lengthscale"
            ].neg_(),
            "lengthscale",
        ),
        (lambda b: b.update(time_column=""), "time_column"),
    ],
)
def test_edited_values_are_refused_with_a_valid_checksum(bundle, tmp_path, edit, message):
    b = load_bundle(bundle)
    edit(b)
    bad = tmp_path / "edited.pt"
    write_raw(bad, b)
    with pytest.raises(BundleError, match=message) as info:
        load_bundle(bad)
    assert str(bad) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(BundleError, match=message):
        save_bundle(tmp_path / "never.pt", b)
    assert not (tmp_path / "never.pt").exists()


def test_unknown_future_schema_is_refused(bundle, tmp_path):
    raw = bundle.read_bytes().replace(b"torchfilt.bundle/2", b"torchfilt.bundle/9", 1)
    (tmp_path / "future.pt").write_bytes(raw)
    with pytest.raises(BundleError, match=r"torchfilt\.bundle/9 is not readable"):
        load_bundle(tmp_path / "future.pt")


# ------------------------------------------------------------------------------ caches
def _predict(side, x: torch.Tensor, u: torch.Tensor | None = None):
    p = side.predict(x, u)
    return p.mean, p.var if p.var is not None else p.cov


def test_load_model_does_not_refit(bundle, monkeypatch):
    def no_freeze(self, *args, **kwargs):
        raise AssertionError("load_model chose the variance form again")

    monkeypatch.setattr(GPModel, "freeze", no_freeze)
    model = load_model(bundle)
    # both sides are calibrated GPs: the wrappers hold the frozen GPs
    assert model.transition.base.frozen and model.measurement.base.frozen


def test_cached_model_predicts_as_a_refrozen_one(bundle):
    b = load_bundle(bundle)
    model = load_model(bundle)
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(7, 2, generator=gen, dtype=torch.float64)
    for role, cls in (("transition", GPTransition), ("measurement", GPMeasurement)):
        state = {**b[role]["state"], "frozen": None}  # no cache: freeze from scratch
        ref = cls.from_state(state)
        got = _predict(getattr(model, role), x)
        want = _predict(ref, x)
        for g, w in zip(got, want, strict=True):
            torch.testing.assert_close(g, w, rtol=CACHE_RTOL, atol=CACHE_ATOL)


@pytest.mark.parametrize(
    "options",
    [
        {"variance": "exact"},
        {"variance": "lowrank", "rank": 8},
        {"structure": "multitask"},
        {"structure": "sparse", "num_inducing": 16, "batch_size": 64},
    ],
    ids=["exact", "lowrank", "multitask", "sparse"],
)
def test_state_round_trip_keeps_every_variance_form(options):
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(60, 2, generator=gen, dtype=torch.float64)
    y = torch.stack([torch.sin(x[:, 0]), x[:, 1] * x[:, 0]], -1)
    y = y + 0.05 * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    model = GPMeasurement.fit(x, y, iterations=5, progress=False, **options)
    state = torch.load(_saved(model.to_state()), weights_only=True)
    again = GPMeasurement.from_state(state)
    assert again.variance_forms == model.variance_forms
    z = torch.randn(9, 2, generator=gen, dtype=torch.float64)
    for g, w in zip(_predict(again, z), _predict(model, z), strict=True):
        torch.testing.assert_close(g, w, rtol=CACHE_RTOL, atol=CACHE_ATOL)


def _saved(obj) -> io.BytesIO:
    buf = io.BytesIO()
    torch.save(obj, buf)
    buf.seek(0)
    return buf


# ------------------------------------------------------------------------------ legacy bundles
def test_schema_1_bundle_loads_with_a_warning(bundle, tmp_path):
    b = load_bundle(bundle)
    b["schema"] = LEGACY_SCHEMA
    for role in ("transition", "measurement"):
        b[role]["state"].pop("frozen")
    b.pop("time_column")
    torch.save(b, tmp_path / "old.pt")
    with pytest.warns(UnverifiedBundleWarning, match="no checksum"):
        model = load_model(tmp_path / "old.pt")
    x = torch.rand(4, 2, dtype=torch.float64)
    for g, w in zip(
        _predict(model.transition, x), _predict(load_model(bundle).transition, x), strict=True
    ):
        torch.testing.assert_close(g, w, rtol=CACHE_RTOL, atol=CACHE_ATOL)
    new = upgrade_bundle(tmp_path / "old.pt", tmp_path / "new.pt")
    assert new.read_bytes().startswith(BUNDLE_SCHEMA.encode())
    assert load_bundle(new)["time_column"] == "time"
    fast = load_model(new)  # no warning: verified, with caches
    assert fast.transition.base.frozen
    for g, w in zip(_predict(fast.transition, x), _predict(model.transition, x), strict=True):
        torch.testing.assert_close(g, w, rtol=CACHE_RTOL, atol=CACHE_ATOL)
    with pytest.raises(OutputError, match="exists"):
        upgrade_bundle(tmp_path / "old.pt", new)


# ------------------------------------------------------------------------------ time column
def test_bundle_remembers_the_time_column(tmp_path, capsys):
    data = tiny_dataset(tmp_path / "data", recordings=5, steps=20)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["time"]["name"] = "t"
    (data / "manifest.json").write_text(json.dumps(manifest))
    for f in data.glob("rec_*.csv"):
        text = f.read_text()
        assert text.startswith("time,")
        f.write_text("t," + text[len("time,") :])
    bundle = train_recipe(write_recipe(tmp_path / "t.toml", data), tmp_path / "run", progress=False)
    assert load_bundle(bundle)["time_column"] == "t"
    out = tmp_path / "est"
    assert (
        main(["filter", "--model", str(bundle), str(data / "rec_004.csv"), "--out", str(out)]) == 0
    )
    assert main(["evaluate", str(out)]) == 0
    assert main(["info", str(bundle)]) == 0
    text = capsys.readouterr().out
    assert "mean NEES" in text and "time column:  t\n" in text
