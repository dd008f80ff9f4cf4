"""CUDA path: the same filter on the GPU equals the CPU result. Skipped without a CUDA device.

Every path the filter can pick on CUDA is here (eager, ``compile="step"``, the ``compile="loop"``
while-loop and its chunked fallback under autograd, the CUDA graph, the constrained filter, the
exact Kalman runners sequential and parallel-in-time, the GP predictor exact and sparse, and a
calibration gradient), each against the same run on the CPU in float64. Public API only.
"""

import copy
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from gp_support import smooth_data
from linear_support import make_problem, t64

import torchfilt
from torchfilt import CKF, CalibratedModel, ConstrainedCKF, LinearGaussianModel, StateSpaceModel
from torchfilt.exceptions import ModelError
from torchfilt.filters import kalman_filter, kalman_smoother
from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.systems import reaction, reentry
from torchfilt.training.likelihood import step_log_likelihood

#: the device under test (the CPU run is the reference)
DEV = torch.device("cuda")
#: CPU against GPU, float64: the same computation in a different operation order
GPU_RTOL = GPU_ATOL = 1e-6

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


def _linear(p, device):
    """The linear-Gaussian model of a ``make_problem`` problem on ``device``."""
    return LinearGaussianModel(*(t64(p[k]).to(device) for k in ("A", "H", "Q", "R")))


def _close(got, want, rtol=GPU_RTOL, atol=GPU_ATOL):
    torch.testing.assert_close(got.detach().cpu(), want.detach(), rtol=rtol, atol=atol)


@pytest.fixture()
def _fresh_compiler():
    """Each compiled test traces from scratch (as in tests/filters/test_compile_loop.py)."""
    torch.compiler.reset()
    yield
    torch.compiler.reset()


@pytest.mark.usefixtures("_fresh_compiler")
@pytest.mark.parametrize(
    ("compile_", "execution"),
    [(False, "eager"), ("step", "compiled-step"), ("loop", "compiled-loop")],
    ids=["eager", "step", "loop"],
)
def test_cubature_paths_on_cuda_match_cpu(compile_, execution):
    """The CKF on a linear model (kept on the cubature path): eager, per-step compiled and the
    compiled while-loop on the GPU give the CPU's eager result."""
    p = make_problem(21, n=3, m=2, T=12)
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    y = t64(p["y"])
    cpu = CKF(_linear(p, "cpu")).filter(y, path="cubature", **kw)
    gpu = CKF(_linear(p, DEV), compile=compile_).filter(
        y.to(DEV), path="cubature", **{k: v.to(DEV) for k, v in kw.items()}
    )
    assert gpu.mean.device.type == "cuda"
    if compile_:
        assert gpu.numerics.execution == execution
    _close(gpu.mean, cpu.mean)
    _close(gpu.cov, cpu.cov)
    _close(gpu.log_likelihood, cpu.log_likelihood)


@pytest.mark.usefixtures("_fresh_compiler")
def test_compiled_loop_under_autograd_runs_chunks_on_cuda():
    """Under autograd ``compile="loop"`` runs compiled chunks; their gradient on the GPU is the
    CPU's eager gradient."""
    p = make_problem(11, n=2, m=1, T=6)

    def grad(device, compile_):
        A = t64(p["A"]).to(device).requires_grad_()
        rest = (t64(p[k]).to(device) for k in ("H", "Q", "R"))
        res = CKF(LinearGaussianModel(A, *rest), compile=compile_).filter(
            t64(p["y"]).to(device),
            x0=t64(p["m0"]).to(device),
            P0=t64(p["P0"]).to(device),
            path="cubature",
        )
        res.log_likelihood.backward()
        return A.grad, res

    want, _ = grad("cpu", False)
    got, res = grad(DEV, "loop")
    assert res.numerics.execution == "compiled-chunks"
    _close(got, want)


def test_constrained_filter_on_cuda_matches_cpu_and_graphed_refuses():
    """The constrained CKF runs on the GPU with the CPU's result; a CUDA graph of it is refused
    with a message that says why."""
    sim = reaction.simulate_truth(runs=4, seed=0)
    kw = dict(x0=reaction.prior_mean(), P0=reaction.prior_cov())
    gkw = {k: v.to(DEV) for k, v in kw.items()}
    box = dict(lower=[0.0, 0.0], upper=[100.0, 100.0])
    cpu = ConstrainedCKF(reaction.model(), **box).filter(sim.measurements, **kw)
    filt = ConstrainedCKF(reaction.model().to(DEV), **box)
    gpu = filt.filter(sim.measurements.to(DEV), **gkw)
    assert gpu.mean.device.type == "cuda"
    assert (gpu.mean >= 0).all() and (gpu.mean <= 100).all()
    _close(gpu.mean, cpu.mean)
    _close(gpu.cov, cpu.cov)
    _close(gpu.log_likelihood, cpu.log_likelihood)
    with pytest.raises(ModelError, match="cannot be captured into a CUDA graph") as err:
        filt.graphed(sim.measurements.to(DEV), **gkw)
    assert "NDDR solver decides on the host" in str(err.value)


@pytest.mark.parametrize("parallel", [False, True], ids=["sequential", "parallel"])
def test_exact_kalman_on_cuda_matches_cpu(parallel):
    """The closed-form Kalman filter and RTS smoother, sequential and parallel-in-time."""
    p = make_problem(5, n=3, m=2, T=40, missing=0.0)
    kw = dict(x0=t64(p["m0"]), P0=t64(p["P0"]))
    gkw = {k: v.to(DEV) for k, v in kw.items()}
    y = t64(p["y"])
    cpu_f = kalman_filter(_linear(p, "cpu"), y, parallel=parallel, **kw)
    gpu_f = kalman_filter(_linear(p, DEV), y.to(DEV), parallel=parallel, **gkw)
    assert gpu_f.mean.device.type == "cuda"
    _close(gpu_f.mean, cpu_f.mean)
    _close(gpu_f.cov, cpu_f.cov)
    _close(gpu_f.log_likelihood, cpu_f.log_likelihood)
    cpu_s = kalman_smoother(_linear(p, "cpu"), y, parallel=parallel, **kw)
    gpu_s = kalman_smoother(_linear(p, DEV), y.to(DEV), parallel=parallel, **gkw)
    _close(gpu_s.mean, cpu_s.mean)
    _close(gpu_s.cov, cpu_s.cov)


@pytest.mark.parametrize(
    "opts",
    [dict(variance="exact"), dict(structure="sparse", num_inducing=20, batch_size=40)],
    ids=["exact", "sparse"],
)
def test_gp_predictor_on_cuda_matches_cpu(opts):
    """The frozen GP predictor, exact (cached Cholesky) and sparse (SVGP), on the GPU."""
    x, y = smooth_data(80)
    model = GPMeasurement.fit(x, y, iterations=25, progress=False, **opts)
    xq = 1.5 * torch.randn(9, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        cpu = model.predict(xq)
        model.to(DEV)  # in place (an SVGP's cache cannot be deep-copied)
        gpu = model.predict(xq.to(DEV))
    assert gpu.mean.device.type == "cuda"
    # as tests/models/gp/test_gp_predictor.py's CUDA test
    _close(gpu.mean, cpu.mean, rtol=1e-9, atol=1e-9)
    _close(gpu.var, cpu.var, rtol=1e-7, atol=1e-9)


def test_calibration_gradient_on_cuda_matches_cpu():
    """The gradient of the filter likelihood with respect to the calibration parameters of both
    GP sides (what ``torchfilt.calibrate`` follows) is the CPU's."""
    log = reentry.record_training_data(60, seed=0)
    fit = dict(iterations=10, subset=None, progress=False)
    f = GPTransition.fit(log.states, increment=True, seed=0, **fit)
    h = GPMeasurement.fit(log.states, log.measurements, inputs=[0], **fit)
    sim = reentry.simulate_truth(4, steps=20, seed=1)

    def grads(device):
        cf, ch = (CalibratedModel(copy.deepcopy(m), min_scale=1.0).to(device) for m in (f, h))
        params = [cf.log_scale, cf.log_floor, ch.log_scale, ch.log_floor]
        res = CKF(StateSpaceModel(cf, ch)).filter(
            sim.measurements.to(device),
            x0=torch.tensor(reentry.PRIOR_MEAN, device=device),
            P0=reentry.prior_cov().to(device),
        )
        loss = step_log_likelihood(res)[..., 5:].sum()
        return loss, torch.autograd.grad(loss, params)

    want_loss, want = grads("cpu")
    got_loss, got = grads(DEV)
    assert torch.isfinite(want_loss)
    _close(got_loss, want_loss)
    for g, w in zip(got, want, strict=True):
        _close(g, w)
