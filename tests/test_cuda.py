"""CUDA path: the same filter on the GPU equals the CPU result. Skipped without a CUDA device."""

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
    sim = reentry.simulate_truth(1024, seed=1, dtype=torch.float32)
    res = torchfilt.CKF(reentry.model(dtype=torch.float32).cuda()).filter(
        sim.measurements.cuda(),
        x0=torch.tensor(reentry.PRIOR_MEAN, dtype=torch.float32, device="cuda"),
        P0=reentry.prior_cov(torch.float32).cuda(),
    )
    assert res.mean.shape == (1024, reentry.STEPS, 3)
    assert torch.isfinite(res.mean).all(-1).all(-1).float().mean() > 0.95
