"""Fitting GP models: noise floor, input selection, missing data, options, errors, checkpoints."""

from __future__ import annotations

import io

import pytest
import torch
from gp_support import DT, one_thread, query_points, smooth_data

from torchfilt.exceptions import InputError, ModelError, ShapeError
from torchfilt.models.gp import FitState, GPMeasurement, GPModel, GPTransition
from torchfilt.models.gp.noise import GPYTORCH_FLOOR
from torchfilt.optim import OptimizerOptions

pytestmark = pytest.mark.usefixtures("one_thread")
__all__ = ["one_thread"]

ITERS = 30
#: A learned noise standard deviation within 25 % of the truth (S = 300 points, 1-D).
NOISE_SD_RTOL = 0.25
#: SVGP (30 inducing points) on 400 noisy points (noise sd 0.05): RMSE against the true function.
SPARSE_RMSE = 0.1


def _range_sensor(S: int = 300, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Radar-like range: ``sqrt(M^2 + (x1 - H)^2) + v`` with sd(v) = 100 ft, range spread ~4e4 ft."""
    g = torch.Generator().manual_seed(seed)
    x1 = 2e4 + 2.8e5 * torch.rand(S, generator=g, dtype=DT)
    x2 = 2e4 * torch.rand(S, generator=g, dtype=DT)
    x = torch.stack([x1, x2], -1)
    y = torch.sqrt(1e10 + (x1 - 1e5) ** 2).unsqueeze(-1)
    return x, y + 100.0 * torch.randn(S, 1, generator=g, dtype=DT)


def test_noise_floor_from_data_recovers_small_sensor_noise():
    x, y = _range_sensor()
    adam = OptimizerOptions("adam", lr=0.1)
    h = GPMeasurement.fit(x, y, inputs=[0], iterations=150, optimizer=adam, progress=False)
    sd = float(h.noise_variance.sqrt())
    assert abs(sd - 100.0) < NOISE_SD_RTOL * 100.0, sd
    floor_sd = float(torch.tensor(h.config.noise_floor).sqrt())
    gpytorch_floor_sd = GPYTORCH_FLOOR**0.5 * float(h.target_std.scale)
    assert floor_sd < 50.0 < gpytorch_floor_sd  # the stock floor would forbid 100 ft


def test_user_noise_floor_and_fixed_noise():
    x, y = _range_sensor(120)
    h = GPMeasurement.fit(x, y, inputs=[0], noise_floor=250.0**2, iterations=ITERS, progress=False)
    assert float(h.noise_variance) >= 250.0**2 * (1 - 1e-9)
    h2 = GPMeasurement.fit(x, y, inputs=[0], noise=80.0**2, iterations=ITERS, progress=False)
    torch.testing.assert_close(
        h2.noise_variance, torch.tensor([6400.0], dtype=DT), rtol=1e-10, atol=0
    )


def test_input_selection_ignores_other_inputs():
    x, y = _range_sensor(100)
    h = GPMeasurement.fit(x, y, inputs=[0], iterations=ITERS, progress=False)
    a = x[:5].clone()
    b = a.clone()
    b[:, 1] += 1e6  # far outside the training range along the unused input
    with torch.no_grad():
        pa, pb = h.predict(a), h.predict(b)
    assert torch.equal(pa.mean, pb.mean) and torch.equal(pa.var, pb.var)


def test_per_output_input_selection_and_missing_measurements():
    x, y = smooth_data(90)
    y = y.clone()
    y[::3, 1] = float("nan")  # output 1 missing every third step
    h = GPMeasurement.fit(
        x, y, inputs=[[0, 1], [0, 1]], iterations=ITERS, progress=False, variance="exact"
    )
    # different observed rows -> two groups; each trains on its own observed rows
    assert [g.outputs for g in h.config.groups] == [(0,), (1,)]
    assert [grp.num_points for grp in h.groups] == [90, 60]
    h2 = GPMeasurement.fit(
        x, y[:, :1].repeat(1, 2), inputs=[[0], [1]], iterations=ITERS, progress=False
    )
    assert [g.features for g in h2.config.groups] == [(0,), (1,)]
    with torch.no_grad():
        p, q = h.predict(query_points()), h.predict_gpytorch(query_points())
    torch.testing.assert_close(p.var, q.var, rtol=1e-6, atol=1e-10)


def test_increment_and_prior_mean_forms():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(70, 2, generator=g, dtype=DT)

    def f_true(x, u=None):
        return torch.stack([x[..., 0] + 0.1 * torch.sin(x[..., 1]), 0.95 * x[..., 1]], -1)

    def f_nominal(x, u=None):
        return torch.stack([x[..., 0], 0.9 * x[..., 1]], -1)  # wrong, but close

    xn = f_true(x) + 1e-3 * torch.randn(70, 2, generator=g, dtype=DT)
    inc = GPTransition.fit(x, None, xn, increment=True, iterations=ITERS, progress=False)
    res = GPTransition.fit(x, None, xn, prior_mean=f_nominal, iterations=ITERS, progress=False)
    # the residual targets are what the GP standardised
    torch.testing.assert_close(inc.target_std.shift, (xn - x).mean(0), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(
        res.target_std.shift, (xn - f_nominal(x)).mean(0), rtol=1e-12, atol=1e-14
    )
    xq = 0.5 * query_points(6)
    with torch.no_grad():
        for model in (inc, res):
            err = (model.predict(xq).mean - f_true(xq)).abs().max()
            assert float(err) < 0.05
    with pytest.raises(ValueError, match="exclusive"):
        GPTransition.fit(x, None, xn, increment=True, prior_mean=f_nominal, progress=False)


def test_recordings_do_not_cross_boundaries():
    # two recordings far apart: a pair across the boundary would be a ~100-unit jump
    g = torch.Generator().manual_seed(8)
    r1 = (0.05 * torch.randn(21, 2, generator=g, dtype=DT)).cumsum(0)
    r2 = 100.0 + (0.05 * torch.randn(21, 2, generator=g, dtype=DT)).cumsum(0)
    f = GPTransition.fit([r1, r2], increment=True, iterations=5, progress=False)
    grp = f.groups[0]
    assert grp.num_points == 40
    increments = f.target_std.inverse(grp.train_y.T)
    want = torch.cat([r1.diff(dim=0), r2.diff(dim=0)])
    torch.testing.assert_close(increments, want, rtol=1e-12, atol=1e-12)
    batched = GPTransition.fit(torch.stack([r1, r2]), increment=True, iterations=5, progress=False)
    assert torch.equal(batched.groups[0].train_x, grp.train_x)


def test_bad_input_errors_name_the_argument():
    x, y = smooth_data(20)
    with pytest.raises(ShapeError, match="x_next"):
        GPTransition.fit(x, None, x[:, :1])
    with pytest.raises(ShapeError, match="x_next"):
        GPTransition.fit(x, None, x[:10])
    bad = x.clone()
    bad[3, 0] = float("nan")
    with pytest.raises(ValueError, match="x contains 1 non-finite"):
        GPTransition.fit(bad, None, x)
    with pytest.raises(ValueError, match="u contains"):
        GPTransition.fit(x, bad, x)
    with pytest.raises(ValueError, match="at least"):
        GPTransition.fit(x[:3], None, x[:3])
    ymiss = y.clone()
    ymiss[2:, 1] = float("nan")
    with pytest.raises(ValueError, match=r"y\[:, 1\]: 2 observed"):
        GPMeasurement.fit(x, ymiss)
    with pytest.raises(ValueError, match="infinite"):
        GPMeasurement.fit(x, y.masked_fill(y > 1, float("inf")))
    with pytest.raises(ValueError, match="inputs"):
        GPMeasurement.fit(x, y, inputs=[5])
    with pytest.raises(InputError, match="unexpected keyword"):
        GPMeasurement.fit(x, y, iterationz=3)
    with pytest.raises(ModelError, match="prior_mean"):
        GPTransition.fit(x, None, x, prior_mean=lambda x: x[..., :1].repeat(1, 3), progress=False)
    with pytest.raises(ShapeError, match="u"):
        GPTransition.fit([x], [x[:5]])
    h = GPMeasurement.fit(x, y, iterations=2, progress=False)
    with pytest.raises(ShapeError, match="x: expected shape"):
        h.predict(torch.zeros(4, 3, dtype=DT))


def test_progress_and_callback():
    x, y = smooth_data(30)
    seen: list[FitState] = []
    stream = io.StringIO()

    def cb(state: FitState) -> bool:
        seen.append(state)
        return state.iteration == 7  # stop early

    from torchfilt.models.gp import optimize

    original = optimize.Progress.__init__

    def patched(self, label, total, stream_=None):
        original(self, label, total, stream)

    optimize.Progress.__init__ = patched  # type: ignore[method-assign]
    try:
        GPMeasurement.fit(x, y, iterations=20, callback=cb, progress=True)
    finally:
        optimize.Progress.__init__ = original  # type: ignore[method-assign]
    assert [s.iteration for s in seen] == list(range(1, 8))
    assert seen[-1].iterations == 20 and all(torch.isfinite(torch.tensor(s.loss)) for s in seen)
    text = stream.getvalue()
    assert "GPMeasurement: iteration 2/20" in text and "iteration 7/20" in text
    hp = seen[-1].hyperparameters()
    assert set(hp) >= {"noise", "outputscale", "lengthscale.0", "lengthscale.1"}


def test_progress_silenced(capsys):
    x, y = smooth_data(30)
    GPMeasurement.fit(x, y, iterations=3, progress=False)
    assert capsys.readouterr().err == ""
    GPMeasurement.fit(x, y, iterations=3)
    assert "iteration 3/3" in capsys.readouterr().err


def test_resume_from_checkpoint_equals_uninterrupted(tmp_path):
    x, y = smooth_data(40)
    straight = GPMeasurement.fit(x, y, iterations=8, progress=False)
    ckpts = {}

    def keep(state: FitState) -> None:
        if state.iteration == 4:
            ckpts["c"] = state.checkpoint()

    GPMeasurement.fit(x, y, iterations=8, callback=keep, progress=False)
    path = tmp_path / "ckpt.pt"
    torch.save(ckpts["c"], path)
    ckpt = torch.load(path, weights_only=True)
    resumed = GPMeasurement.fit(x, y, iterations=8, resume=ckpt, progress=False)
    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12, msg=k)
    with pytest.raises(ValueError, match="different data"):
        GPMeasurement.fit(x + 1, y, iterations=8, resume=ckpt, progress=False)


def test_state_round_trip_weights_only(tmp_path):
    x, y = smooth_data(40)
    for kw in ({}, {"structure": "multitask"}, {"structure": "sparse", "num_inducing": 10}):
        h = GPMeasurement.fit(x, y, iterations=5, progress=False, **kw)
        path = tmp_path / "m.pt"
        torch.save(h.to_state(), path)
        back = GPModel.from_state(torch.load(path, weights_only=True))
        assert isinstance(back, GPMeasurement) and back.variance_forms == h.variance_forms
        xq = query_points()
        with torch.no_grad():
            a, b = h.predict(xq), back.predict(xq)
        assert torch.equal(a.mean, b.mean)


def test_prior_mean_must_be_reattached(tmp_path):
    x, _ = smooth_data(30)

    def nominal(x, u=None):
        return 0.9 * x

    f = GPTransition.fit(x, None, 0.95 * x, prior_mean=nominal, iterations=3, progress=False)
    state = f.to_state()
    with pytest.raises(ValueError, match="prior_mean"):
        GPTransition.from_state(state)
    back = GPTransition.from_state(state, prior_mean=nominal)
    with torch.no_grad():
        assert torch.equal(back.predict(x[:4]).mean, f.predict(x[:4]).mean)
    with pytest.raises(ValueError, match="holds a GPTransition"):
        GPMeasurement.from_state(state)


def test_sparse_elbo_training_reduces_loss_and_fits():
    x, y = smooth_data(400, noise_sd=0.05)
    h = GPMeasurement.fit(
        x, y, structure="sparse", num_inducing=30, batch_size=100, iterations=150, progress=False
    )
    assert h.history[-1] < h.history[0]
    xq = x[:100]  # inside the data
    f = torch.stack([torch.sin(xq[:, 0]) + 0.5 * xq[:, 1], xq[:, 0] * xq[:, 1]], -1)
    with torch.no_grad():
        err = (h.predict(xq).mean - f).pow(2).mean().sqrt()
    assert float(err) < SPARSE_RMSE


def test_subset_training_conditions_on_all_rows():
    x, y = smooth_data(120)
    h = GPMeasurement.fit(x, y, subset=40, iterations=10, progress=False)
    assert h.groups[0].num_points == 120
    assert h.groups[0].gp.train_inputs[0].shape[-2] == 120


def test_fixed_hyperparameters_are_bit_identical():
    """``fixed=`` holds a GP hyperparameter exactly while the others train; an unknown name is
    an InputError naming it."""
    x, y = smooth_data(40)
    name = "groups.0.gp.covar_module.base_kernel.raw_lengthscale"
    free = GPMeasurement.fit(x, y, iterations=0, progress=False)
    start = dict(free.named_parameters())[name].detach().clone()
    noise = dict(free.named_parameters())["groups.0.likelihood.noise_covar.raw_noise"]
    noise0 = noise.detach().clone()
    free.optimize(iterations=10, progress=False, fixed=[name])
    assert torch.equal(dict(free.named_parameters())[name].detach(), start)
    assert not torch.equal(noise.detach(), noise0)
    with pytest.raises(InputError, match=r"fixed: 'groups\.9' is no parameter"):
        free.optimize(iterations=2, progress=False, fixed=["groups.9"])
