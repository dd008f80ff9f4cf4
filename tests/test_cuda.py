"""CUDA path: the same filter on the GPU equals the CPU result. Skipped without a CUDA device."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torchfilt
from torchfilt.systems import reentry

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
]


@pytest.mark.parametrize("sqrt", [False, True])
def test_cuda_matches_cpu(sqrt):
    sim = reentry.simulate_truth(64, seed=0)
    kw = dict(x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov())
    cpu = torchfilt.CKF(reentry.model(), sqrt=sqrt).smooth(sim.measurements, **kw)
    gpu = torchfilt.CKF(reentry.model().cuda(), sqrt=sqrt).smooth(
        sim.measurements.cuda(), **{k: v.cuda() for k, v in kw.items()}
    )
    assert gpu.mean.device.type == "cuda"
    ok = torch.isfinite(cpu.filtered.mean).all(-1).all(-1)
    assert torch.allclose(gpu.mean.cpu()[ok], cpu.mean[ok], rtol=1e-6, atol=1e-6)


def test_cuda_float32_batch_runs():
    """float32 on the GPU: a few sequences of 1024 may diverge (and say so), the rest run."""
    sim = reentry.simulate_truth(1024, seed=1, dtype=torch.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.DivergenceWarning)
        res = torchfilt.CKF(reentry.model(dtype=torch.float32).cuda()).filter(
            sim.measurements.cuda(),
            x0=torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float32, device="cuda"),
            P0=reentry.prior_cov(torch.float32).cuda(),
        )
    assert res.mean.shape == (1024, reentry.STEPS, 3)
    assert torch.isfinite(res.mean).all(-1).all(-1).float().mean() > 0.95


@pytest.mark.parametrize("compile_", [False, True])
@pytest.mark.parametrize("sqrt", [False, True])
def test_graphed_filter_matches_eager(sqrt, compile_):
    """A CUDA-graph replay gives the eager CUDA result (float64), on new data and with a mask."""
    sim = reentry.simulate_truth(256, seed=2)
    y = sim.measurements.cuda()
    x0 = torch.tensor(reentry.PRIOR_MEAN, device="cuda")
    P0 = reentry.prior_cov().cuda()
    model = reentry.model().cuda()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
        graphed = torchfilt.CKF(model, sqrt=sqrt, compile=compile_).graphed(y, x0=x0, P0=P0)
    y2 = reentry.simulate_truth(256, seed=3).measurements.cuda()
    mask = torch.rand(y2.shape, generator=torch.Generator().manual_seed(0)).cuda() > 0.2
    for data, m in ((y, None), (y2, mask)):
        with warnings.catch_warnings():  # the odd diverging sequence is excluded below
            warnings.simplefilter("ignore", torchfilt.DivergenceWarning)
            warnings.simplefilter("ignore", torchfilt.exceptions.NumericsWarning)
            ref = torchfilt.CKF(model, sqrt=sqrt).filter(data, x0=x0, P0=P0, mask=m)
            got = graphed.filter(data, mask=m)
        ok = torch.isfinite(ref.mean).all(-1).all(-1) & torch.isfinite(got.mean).all(-1).all(-1)
        assert ok.float().mean() > 0.9
        torch.testing.assert_close(got.mean[ok], ref.mean[ok], rtol=1e-7, atol=1e-6)
        torch.testing.assert_close(got.cov[ok], ref.cov[ok], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(got.log_likelihood[ok], ref.log_likelihood[ok])
    with pytest.raises(torchfilt.exceptions.ShapeError, match="captured for shape"):
        graphed.filter(y[:10])


def test_cli_filter_with_a_gp_bundle_on_cuda_matches_cpu(tmp_path):
    """`torchfilt filter --device cuda` with a learned (GP) bundle gives the CPU estimates."""
    from torchfilt.cli import main
    from torchfilt.io.estimates import read_estimates
    from torchfilt.io.synth import simulate_dataset

    data = tmp_path / "data"
    simulate_dataset("reaction", data, recordings=6, steps=30, seed=0)
    recipe = tmp_path / "tiny.toml"
    recipe.write_text(
        f'name = "tiny"\nseed = 3\n[dataset]\npath = "{data.as_posix()}"\n'
        "[transition]\nincrement = true\niterations = 20\n[measurement]\niterations = 20\n"
    )
    run = tmp_path / "run"
    assert main(["train", str(recipe), "--out", str(run), "--quiet"]) == 0
    recs = sorted(str(p) for p in data.glob("rec_*.csv"))
    for dev in ("cpu", "cuda"):
        args = ["filter", "--model", str(run / "model.pt"), *recs, "--out", str(tmp_path / dev)]
        assert main([*args, "--smooth", "--device", dev]) == 0
    for p in recs:
        for kind in ("filtered", "smoothed"):
            name = f"{Path(p).stem}.{kind}.csv"
            cpu = read_estimates(tmp_path / "cpu" / name)
            gpu = read_estimates(tmp_path / "cuda" / name)
            np.testing.assert_allclose(gpu.mean, cpu.mean, rtol=1e-8, atol=1e-10)
            np.testing.assert_allclose(gpu.cov, cpu.cov, rtol=1e-6, atol=1e-12)
