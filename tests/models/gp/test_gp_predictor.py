"""The frozen predictor against GPyTorch (exact settings) and against the GP formulas in NumPy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gp_support import DT, one_thread, query_points, smooth_data

from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.models.gp.kernels import KERNELS, correlation, scaled_sq_dist

pytestmark = pytest.mark.usefixtures("one_thread")
__all__ = ["one_thread"]

#: Frozen predictor vs GPyTorch (both exact, float64, well-conditioned: noise ~ 1e-3 relative).
MATCH_RTOL = 1e-8
MATCH_ATOL = 1e-10
#: SVGP: GPyTorch adds its jitter in slightly different places (1e-6 relative in K_uu).
SPARSE_ATOL = 1e-8
#: Against NumPy's independent evaluation of the same formulas.
NUMPY_RTOL = 1e-8
ITERS = 25


@pytest.fixture(scope="module")
def data():
    return smooth_data(80)


def _fit(data, **kw):
    x, y = data
    return GPMeasurement.fit(x, y, iterations=ITERS, progress=False, **kw)


def _assert_matches(model, xq, atol=MATCH_ATOL):
    with torch.no_grad():
        ours = model.predict(xq)
        ref = model.predict_gpytorch(xq)
    torch.testing.assert_close(ours.mean, ref.mean, rtol=MATCH_RTOL, atol=atol)
    if ref.cov is not None:
        torch.testing.assert_close(ours.cov, ref.cov, rtol=MATCH_RTOL, atol=atol)
    else:
        torch.testing.assert_close(ours.var, ref.var, rtol=MATCH_RTOL, atol=atol)


@pytest.mark.parametrize("kernel", sorted(KERNELS))
def test_kernels_match_gpytorch(kernel):
    import gpytorch

    g = torch.Generator().manual_seed(3)
    a, b = torch.randn(7, 3, generator=g, dtype=DT), torch.randn(5, 3, generator=g, dtype=DT)
    ls = torch.tensor([0.7, 1.3, 2.1], dtype=DT)
    nu = KERNELS[kernel]
    k = (
        gpytorch.kernels.RBFKernel(ard_num_dims=3)
        if nu is None
        else gpytorch.kernels.MaternKernel(nu=nu, ard_num_dims=3)
    ).to(DT)
    k.lengthscale = ls
    ref = k(a, b).to_dense().detach()
    ours = correlation(scaled_sq_dist((a / ls)[None], (b / ls)[None]), kernel)[0]
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("kernel", ["rbf", "matern32", "matern52"])
def test_frozen_exact_equals_gpytorch_exact(data, kernel):
    model = _fit(data, kernel=kernel, variance="exact")
    assert model.variance_forms == [("exact", None)]
    _assert_matches(model, query_points())


def test_unfrozen_predict_is_gpytorch_exact(data):
    model = _fit(data).unfreeze()
    xq = query_points()
    with torch.no_grad():
        a = model.predict(xq)
        b = model.predict_gpytorch(xq)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.var, b.var)


def test_frozen_equals_numpy_formulas(data):
    """Independent reference: K*(K + s2 I)^-1 (y - c) and k** - K*(K + s2 I)^-1 K*^T in NumPy."""
    x, y = data
    model = _fit(data, variance="exact")
    xq = query_points()
    with torch.no_grad():
        ours = model.predict(xq)
    grp = model.groups[0]
    h = grp.hyperparameters()
    ist, tst = model.input_std, model.target_std
    X = ((x - ist.shift) / ist.scale).numpy()
    Xq = ((xq - ist.shift) / ist.scale).numpy()
    Y = ((y - tst.shift) / tst.scale).numpy()
    for j in range(2):
        ls = h["lengthscale"][j].numpy()
        s2f, s2n, c = float(h["outputscale"][j]), float(h["noise"][j]), float(h["constant"][j])

        def k(a, b, ls=ls, s2f=s2f):
            d2 = (((a[:, None, :] - b[None, :, :]) / ls) ** 2).sum(-1)
            return s2f * np.exp(-0.5 * d2)

        Kh = k(X, X) + s2n * np.eye(len(X))
        Ks = k(Xq, X)
        mean = c + Ks @ np.linalg.solve(Kh, Y[:, j] - c)
        var = s2f - np.einsum("ij,ji->i", Ks, np.linalg.solve(Kh, Ks.T)) + s2n
        sc, sh = float(tst.scale[j]), float(tst.shift[j])
        np.testing.assert_allclose(ours.mean[:, j].numpy(), mean * sc + sh, rtol=NUMPY_RTOL)
        np.testing.assert_allclose(ours.var[:, j].numpy(), var * sc * sc, rtol=NUMPY_RTOL)


def test_multitask_frozen_equals_gpytorch(data):
    model = _fit(data, structure="multitask", num_latents=2, variance="exact")
    xq = query_points()
    _assert_matches(model, xq)
    cov = model.predict(xq).cov
    assert cov is not None and cov.shape == (9, 2, 2)
    assert bool((torch.linalg.eigvalsh(cov) > 0).all())
    assert float(cov[:, 0, 1].abs().max()) > 0  # correlated outputs


def test_sparse_frozen_equals_gpytorch(data):
    model = _fit(data, structure="sparse", num_inducing=20, batch_size=40)
    assert model.variance_forms == [("sparse", None)]
    _assert_matches(model, query_points(), atol=SPARSE_ATOL)


def test_lowrank_variance_is_conservative_and_converges(data):
    model = _fit(data, variance="exact")
    xq = torch.cat([query_points(), data[0][:20]])
    with torch.no_grad():
        exact = model.predict(xq).var
        errs = []
        for r in (4, 16, 40, 80):
            model.freeze("lowrank", rank=r)
            low = model.predict(xq).var
            assert bool((low >= exact * (1 - 1e-10)).all()), f"rank {r} below exact"
            errs.append(float(((low - exact) / exact).max()))
    assert errs == sorted(errs, reverse=True)
    assert errs[-1] < 1e-8  # full rank: exact


def test_auto_picks_a_rank_within_tolerance():
    """A noisy 1-D sensor: a small rank suffices; the chosen form meets its tolerance."""
    g = torch.Generator().manual_seed(5)
    x = torch.rand(200, 2, generator=g, dtype=DT) * 4
    y = torch.sin(x[:, :1]) + 0.1 * torch.randn(200, 1, generator=g, dtype=DT)
    model = GPMeasurement.fit(x, y, inputs=[0], iterations=ITERS, progress=False)
    form, rank = model.variance_forms[0]
    assert form == "lowrank" and rank is not None and rank <= 64
    xq = torch.rand(50, 2, generator=g, dtype=DT) * 4
    with torch.no_grad():
        auto = model.predict(xq).var
        exact = model.freeze("exact").predict(xq).var
    assert float(((auto - exact) / exact).abs().max()) < 0.05


def test_predictor_gradients_match_finite_differences(data):
    model = _fit((data[0][:30], data[1][:30]))
    for variance in ("exact", "lowrank"):
        model.freeze(variance, rank=10)

        def fn(z, model=model):
            p = model.predict(z)
            return p.mean, p.var

        z = query_points(3).requires_grad_(True)
        assert torch.autograd.gradcheck(fn, (z,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("batch", [(), (4,), (3, 2)])
def test_batched_equals_looped_and_chunked(data, batch):
    model = _fit(data)
    g = torch.Generator().manual_seed(7)
    x = torch.randn(*batch, 5, 2, generator=g, dtype=DT)
    with torch.no_grad():
        full = model.predict(x)
        flat = x.reshape(-1, 5, 2)
        loop = [model.predict(flat[i]) for i in range(flat.shape[0])]
        model.freeze(chunk_size=3)
        chunked = model.predict(x)
    assert full.mean.shape == (*batch, 5, 2) and full.var.shape == (*batch, 5, 2)
    torch.testing.assert_close(
        full.mean.reshape(-1, 5, 2), torch.stack([p.mean for p in loop]), rtol=1e-12, atol=1e-12
    )
    torch.testing.assert_close(chunked.var, full.var, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "options",
    [
        dict(variance="exact"),
        dict(variance="lowrank", rank=8),
        dict(structure="multitask", num_latents=2, variance="exact"),
        dict(structure="sparse", num_inducing=20, batch_size=40),
        dict(inputs=[[0], [1]]),
    ],
    ids=["exact", "lowrank", "multitask", "sparse", "per-output-inputs"],
)
def test_predict_mean_equals_predict(data, options):
    """The mean-only path (what the constrained CKF's solver calls) is the full prediction's mean,
    frozen and chunked, batched, and unfrozen (GPyTorch)."""
    model = _fit(data, **options)
    g = torch.Generator().manual_seed(8)
    x = torch.randn(3, 7, 2, generator=g, dtype=DT)
    with torch.no_grad():
        for chunk in (128, 4):
            model.freeze(**{**model._freeze_opts, "chunk_size": chunk})
            assert torch.equal(model.predict_mean(x), model.predict(x).mean)
        model.unfreeze()
        torch.testing.assert_close(model.predict_mean(x), model.predict(x).mean, rtol=0, atol=0)


def test_predict_mean_with_prior_mean_and_increment():
    g = torch.Generator().manual_seed(9)
    x = torch.randn(50, 2, generator=g, dtype=DT)
    x_next = torch.stack([0.9 * x[:, 0], torch.sin(x[:, 1])], -1)
    opts = dict(iterations=ITERS, progress=False)
    xq = torch.randn(6, 2, generator=g, dtype=DT)
    for f in (
        GPTransition.fit(x, None, x_next, increment=True, **opts),
        GPTransition.fit(x, None, x_next, prior_mean=lambda x: 0.8 * x, **opts),
    ):
        with torch.no_grad():
            assert torch.equal(f.predict_mean(xq), f.predict(xq).mean)


def test_float32_predictor_is_close_to_float64(data):
    model = _fit(data, variance="exact")
    xq = query_points()
    with torch.no_grad():
        ref = model.predict(xq)
        model.predictor.to(torch.float32)
        low = model.predict(xq.float())
    assert low.mean.dtype == torch.float32
    torch.testing.assert_close(low.mean.double(), ref.mean, rtol=1e-3, atol=1e-3)


def test_transition_with_inputs_and_constant_output():
    """``x3`` constant in the data: in increment form it gets no GP, zero variance."""
    g = torch.Generator().manual_seed(2)
    x = torch.randn(60, 3, generator=g, dtype=DT)
    u = torch.randn(60, 1, generator=g, dtype=DT)
    x_next = torch.stack([0.9 * x[:, 0] + u[:, 0], torch.tanh(x[:, 1]), x[:, 2]], -1)
    x_next[:, :2] += 0.01 * torch.randn(60, 2, generator=g, dtype=DT)
    f = GPTransition.fit(x, u, x_next, increment=True, iterations=ITERS, progress=False)
    assert f.config.constant_outputs == (2,)
    xq = torch.randn(4, 3, generator=g, dtype=DT)
    uq = torch.randn(4, 1, generator=g, dtype=DT)
    with torch.no_grad():
        p = f.predict(xq, uq)
        q = f.predict_gpytorch(xq, uq)
    assert torch.equal(p.mean[:, 2], xq[:, 2]) and bool((p.var[:, 2] == 0).all())
    torch.testing.assert_close(p.mean, q.mean, rtol=1e-8, atol=1e-10)
    with pytest.raises(ValueError, match="u"):
        f.predict(xq)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_frozen_predictor_on_cuda_matches_cpu(data):
    model = _fit(data, variance="exact")
    xq = query_points()
    with torch.no_grad():
        cpu = model.predict(xq)
        model.to("cuda")
        gpu = model.predict(xq.cuda())
    torch.testing.assert_close(gpu.mean.cpu(), cpu.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(gpu.var.cpu(), cpu.var, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize(
    "options, entries_per_point",
    [
        (dict(variance="exact"), lambda S: 2 * S),  # one block of 2 outputs x S points
        (dict(inputs=[[0], [1]]), lambda S: 2 * S),  # two blocks of 1 output x S points
        (dict(structure="multitask", num_latents=2, variance="exact"), lambda S: 2 * S * 2**2),
    ],
    ids=["exact", "per-output-inputs", "multitask"],
)
def test_automatic_chunk_size(data, monkeypatch, options, entries_per_point):
    """By default a chunk holds as many points as keep its kernel rows under CHUNK_ENTRIES (at
    least CHUNK_SIZE), and the chunked predictions equal one chunk's."""
    import torchfilt.models.gp.predictor as predictor

    model = _fit(data, **options)
    S = int(data[0].shape[0])  # training points
    g = torch.Generator().manual_seed(10)
    x = torch.randn(700, 2, generator=g, dtype=DT)
    with torch.no_grad():
        model.freeze(**{**model._freeze_opts, "chunk_size": None})
        assert model.predictor.chunk_size == max(128, 2**21 // entries_per_point(S))
        whole = model.predict(x)
        monkeypatch.setattr(predictor, "CHUNK_ENTRIES", 300 * entries_per_point(S))
        model.freeze(**{**model._freeze_opts, "chunk_size": None})
        assert model.predictor.chunk_size == 300  # three chunks of 300, 300 and 100 points
        chunked = model.predict(x)
        monkeypatch.setattr(predictor, "CHUNK_ENTRIES", 1)
        model.freeze(**{**model._freeze_opts, "chunk_size": None})
        assert model.predictor.chunk_size == 128  # the floor
    torch.testing.assert_close(chunked.mean, whole.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(chunked.var, whole.var, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("options", [dict(variance="lowrank", rank=8), dict(variance="auto")])
def test_outputs_fitted_on_their_own_rows_run_as_one_stacked_block(data, options):
    """Outputs with missing rows of their own become one block each; the low-rank blocks run
    stacked (padded points, zero weights), with the same predictions and gradients as the
    blocks one by one."""
    from torchfilt.models.gp.blocks import _IndependentBlock

    x, y = data
    y = y.clone()
    y[::3, 0] = float("nan")  # each output on its own rows: two groups
    y[1::4, 1] = float("nan")
    model = GPMeasurement.fit(x, y, iterations=ITERS, progress=False, **options)
    pred = model.predictor
    assert len(pred.blocks) == 2
    stacked = [b for b in pred.runs if isinstance(b, _IndependentBlock) and b.form != "exact"]
    if options["variance"] == "lowrank":
        assert len(pred.runs) == 1 and stacked
    g = torch.Generator().manual_seed(11)
    z = torch.randn(40, 2, generator=g, dtype=DT).requires_grad_(True)
    got = pred(z)
    parts = [b(z) for b in pred.blocks]  # the blocks one by one, in output order
    idx = torch.cat([b.outputs for b in pred.blocks]).argsort()
    want_mean = torch.cat([p[0] for p in parts], 1)[:, idx]
    want_var = torch.cat([p[1] for p in parts], 1)[:, idx]
    torch.testing.assert_close(got.mean, want_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.var, want_var, rtol=1e-12, atol=1e-12)
    (g1,) = torch.autograd.grad((got.mean.sum() + got.var.sum()), z)
    (g2,) = torch.autograd.grad((want_mean.sum() + want_var.sum()), z)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12)
    cached = type(pred).from_cache(pred.cache())
    torch.testing.assert_close(cached(z.detach()).var, got.var.detach(), rtol=1e-12, atol=1e-12)
