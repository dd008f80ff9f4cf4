"""Offline filtering of recording files, evaluation, and the CLI commands around them."""

import json

import matplotlib
import numpy as np
import pytest
import torch

matplotlib.use("Agg")

from torchfilt import CKF, LinearGaussianModel
from torchfilt.cli import main
from torchfilt.io import Channel, Recording, write_recording
from torchfilt.io.estimates import read_estimates
from torchfilt.pipeline import ModelSpec, evaluate_outputs, filter_recordings

D = torch.float64


@pytest.fixture
def linear_spec():
    A = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=D)
    B = torch.tensor([[0.0], [0.1]], dtype=D)
    model = LinearGaussianModel(
        A,
        torch.tensor([[1.0, 0.0]], dtype=D),
        0.01 * torch.eye(2, dtype=D),
        torch.tensor([[0.2]], dtype=D),
        B=B,
    )
    return ModelSpec(
        model,
        [("p", "m"), ("v", "m/s")],
        [("pos", "m")],
        [("force", "N")],
        0.1,
        torch.zeros(2, dtype=D),
        torch.eye(2, dtype=D),
        "test:linear",
    )


def write_linear_recordings(tmp_path, lengths, seed=0, truth=True):
    rng = np.random.default_rng(seed)
    paths = []
    for i, T in enumerate(lengths):
        t = np.arange(T) * 0.1
        cols = {
            "p": rng.standard_normal(T),
            "v": rng.standard_normal(T),
            "force": rng.standard_normal(T),
            "pos": rng.standard_normal(T),
        }
        cols["pos"][0] = np.nan
        cols["pos"][3] = np.nan
        chans = [Channel("force", "input"), Channel("pos", "measurement")]
        if truth:
            chans = [Channel("p", "state"), Channel("v", "state"), *chans]
        rec = Recording.from_arrays(t, chans, cols)
        paths.append(tmp_path / f"r{i}.csv")
        write_recording(rec, paths[-1])
    return paths


def test_filter_recordings_matches_direct_filter(tmp_path, linear_spec):
    paths = write_linear_recordings(tmp_path, [12, 9, 12])
    summary = filter_recordings(linear_spec, paths, tmp_path / "out", smooth=True)
    assert [e["rows"] for e in summary["recordings"]] == [12, 9, 12]
    filt = CKF(linear_spec.model)
    for p, e in zip(paths, summary["recordings"], strict=True):
        from torchfilt.io import read_recording

        rec = read_recording(p, linear_spec.channels)
        ref = filt.smooth(
            rec.measurements[1:],
            rec.inputs[:-1],
            x0=linear_spec.prior_mean,
            P0=linear_spec.prior_cov,
        )
        est = read_estimates(tmp_path / "out" / e["filtered"])
        np.testing.assert_allclose(est.mean[1:], ref.filtered.mean.numpy(), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(est.cov[1:], ref.filtered.cov.numpy(), rtol=1e-10, atol=1e-14)
        np.testing.assert_array_equal(est.mean[0], linear_spec.prior_mean.numpy())
        sm = read_estimates(tmp_path / "out" / e["smoothed"])
        np.testing.assert_allclose(sm.mean[1:], ref.mean.numpy(), rtol=1e-12, atol=1e-14)
        assert np.isnan(est.nis[3]) or est.nis_dof[3] == 0  # the missing measurement row


def test_evaluate_outputs_against_numpy(tmp_path, linear_spec):
    paths = write_linear_recordings(tmp_path, [15, 15])
    filter_recordings(linear_spec, paths, tmp_path / "out")
    res = evaluate_outputs(tmp_path / "out")
    errs = []
    for p, e in zip(paths, res["recordings"], strict=True):
        est = read_estimates(tmp_path / "out" / f"{p.stem}.filtered.csv")
        truth = np.loadtxt(p, delimiter=",", skiprows=1, usecols=(1, 2))
        errs.append(est.mean[1:] - truth[1:])
        np.testing.assert_allclose(
            e["rmse"], np.sqrt(((est.mean[1:] - truth[1:]) ** 2).mean(0)), rtol=1e-10
        )
    E = np.concatenate(errs)
    np.testing.assert_allclose(res["pooled"]["rmse"], np.sqrt((E**2).mean(0)), rtol=1e-10)
    assert (
        json.loads((tmp_path / "out" / "evaluation_filtered.json").read_text())["pooled"]["steps"]
        == 28
    )
    with pytest.raises(Exception, match="no smoothed estimates"):
        evaluate_outputs(tmp_path / "out", which="smoothed")


def test_recordings_without_truth_filter_but_do_not_evaluate(tmp_path, linear_spec):
    paths = write_linear_recordings(tmp_path, [10], truth=False)
    summary = filter_recordings(linear_spec, paths, tmp_path / "out")
    assert summary["recordings"][0]["filtered_metrics"] == {}
    with pytest.raises(Exception, match="no recording has logged truth"):
        evaluate_outputs(tmp_path / "out")


def test_cli_simulate_filter_evaluate(tmp_path, capsys):
    ds, out = tmp_path / "ds", tmp_path / "out"
    assert (
        main(
            [
                "simulate",
                "reentry",
                "--out",
                str(ds),
                "--recordings",
                "3",
                "--steps",
                "25",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    recs = sorted(str(p) for p in ds.glob("rec_*.csv"))
    assert len(recs) == 3
    assert (
        main(
            ["filter", "--model", "system:reentry", *recs, "--out", str(out), "--smooth", "--plot"]
        )
        == 0
    )
    assert (out / "rec_000.png").stat().st_size > 10_000
    assert main(["evaluate", str(out), "--smoothed"]) == 0
    text = capsys.readouterr().out
    assert "mean NEES" in text and "altitude: RMSE" in text


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    assert main(["simulate", "nosuch", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown system 'nosuch'" in err and "Traceback" not in err
    assert (
        main(
            [
                "filter",
                "--model",
                "system:reentry",
                str(tmp_path / "missing.csv"),
                "--out",
                str(tmp_path),
            ]
        )
        == 2
    )
    assert "recording not found" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("time,altitude\n0,1\n1,2\n")
    assert main(["filter", "--model", "system:reentry", str(bad), "--out", str(tmp_path)]) == 2
    assert "column 'range'" in capsys.readouterr().err
