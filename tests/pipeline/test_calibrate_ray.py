"""Data-parallel fits on Ray (``calibrate_ray``, ``fit_measurement_only_ray``): two actors in a
``gloo`` group, each with half of the recordings, give the fit of one process on all of them;
a finished job resumes from the actors' checkpoints to the same result."""

from __future__ import annotations

import sys

import pytest
import ray
import torch

import torchfilt
from torchfilt.exceptions import InputError, WorkerError
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import CheckpointOptions, OptimizerOptions, WindowOptions
from torchfilt.pipeline import calibrate_ray, fit_measurement_only_ray
from torchfilt.systems import pendulum
from torchfilt.training.likelihood import Sequences

DT = torch.float64
OPTIONS = dict(
    sides=("transition",),
    # every window: one process and two then optimise the same objective (with calibrate's
    # default subsets each process draws its own windows: unbiased, but not the same steps)
    windows=WindowOptions(window=40, burn_in=5, per_iteration=None),
    iterations=12,
    optimizer=OptimizerOptions(lr=0.2),
)


@pytest.fixture(scope="module")
def data():
    """Pendulum recordings with 100x the model's process noise: calibration must inflate Q."""
    g = torch.Generator().manual_seed(0)
    sim = torchfilt.simulate(
        pendulum.model(qc=30.0, R=0.001), 80, torch.tensor([1.0, 0.0], dtype=DT), batch_shape=(6,),
        generator=g,
    )  # fmt: skip
    return pendulum.model(R=0.001), Sequences(sim.measurements), torch.tensor([1.0, 0.0], dtype=DT)


def test_two_actors_calibrate_like_one_process(ray_local, data, tmp_path):
    model, seqs, x0 = data
    P0 = 0.1 * torch.eye(2, dtype=DT)
    local = torchfilt.calibrate(model, seqs, x0=x0, P0=P0, **OPTIONS)
    dist = calibrate_ray(
        model, seqs, x0=x0, P0=P0, workers=2, checkpoint=tmp_path / "ck", **OPTIONS
    )
    a, b = local.parameters["transition"], dist.parameters["transition"]
    assert torch.allclose(torch.tensor(a["scale"]), torch.tensor(b["scale"]), rtol=1e-9)
    assert torch.allclose(torch.tensor(a["floor"]), torch.tensor(b["floor"]), rtol=1e-9)
    assert abs(local.fit.log_likelihood - dist.fit.log_likelihood) <= 1e-9 * abs(
        local.fit.log_likelihood
    )
    assert dist.fit.measurements == local.fit.measurements
    # the fit moved (the model's Q is far too small)
    assert local.fit.log_likelihood > local.fit.initial_log_likelihood + 10
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == ["rank0.ckpt", "rank1.ckpt"]
    # resuming a finished job from its checkpoints gives the same result
    again = calibrate_ray(
        model,
        seqs,
        x0=x0,
        P0=P0,
        workers=2,
        checkpoint=CheckpointOptions(tmp_path / "ck", resume=True),
        **OPTIONS,
    )
    assert again.parameters == dist.parameters


def test_calibrate_ray_refuses(ray_local, data):
    model, seqs, x0 = data
    P0 = torch.eye(2, dtype=DT)
    with pytest.raises(InputError, match="workers"):
        calibrate_ray(model, seqs, x0=x0, P0=P0, workers=0)
    with pytest.raises(InputError, match="at most 6"):
        calibrate_ray(model, seqs, x0=x0, P0=P0, workers=7)
    with pytest.raises(InputError, match="has 2 CPUs"):
        calibrate_ray(model, seqs, x0=x0, P0=P0, workers=3)
    with pytest.raises(InputError, match="timeout"):
        calibrate_ray(model, seqs, x0=x0, P0=P0, timeout=0)
    with pytest.raises(InputError, match="method"):
        fit_measurement_only_ray(model, seqs, x0=x0, P0=P0, known_channels=[0], method="mle")


def _scalar_recordings(seed: int, steps: int) -> torch.Tensor:
    """Four recordings ``(4, steps, 1)`` of ``x' = 0.9 x + w``, ``y = x + v`` (sd 0.5, 0.3)."""
    g = torch.Generator().manual_seed(seed)
    x, ys = torch.zeros(4, 1, dtype=DT), []
    for _ in range(steps):
        x = 0.9 * x + 0.5 * torch.randn(4, 1, generator=g, dtype=DT)
        ys.append(x + 0.3 * torch.randn(4, 1, generator=g, dtype=DT))
    return torch.stack(ys, 1)


def _scalar_model() -> torchfilt.StateSpaceModel:
    """That system with ``Q`` and ``R`` unknown (both start at 1); ``h`` known: the gauge."""
    Q, R = ScalarCovariance(1.0, 1, dtype=DT), ScalarCovariance(1.0, 1, dtype=DT)
    return torchfilt.StateSpaceModel(lambda x, u: 0.9 * x, lambda x, u: x, Q=Q, R=R)


def test_measurement_only_on_two_actors_equals_one_process(ray_local):
    """Unknown Q and R of a scalar linear system, from measurements alone (gauge: h known)."""
    y = _scalar_recordings(1, 50)
    model = _scalar_model
    # the workers cannot import this test module: send its functions by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

    kw = dict(
        x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), known_channels=[0], iterations=3
    )
    local = torchfilt.fit_measurement_only(model(), y, method="likelihood", **kw).model
    res = fit_measurement_only_ray(model(), Sequences(y), workers=2, **kw)
    assert res.noise_scale is not None  # "auto": 10 held-out steps of each of 4 recordings

    def noises(m: torchfilt.StateSpaceModel) -> torch.Tensor:
        with torch.no_grad():
            return torch.stack(
                [m.transition.noise_cov().reshape(()), m.measurement.noise_cov().reshape(())]
            )

    want, got = noises(local), noises(res.model)
    assert torch.allclose(got, want, rtol=1e-8, atol=0), (got, want)
    assert not torch.allclose(want, torch.ones(2, dtype=DT), rtol=1e-2)  # the fit moved


@pytest.mark.slow
def test_compiled_likelihood_on_two_actors_equals_one_eager_process(ray_local, tmp_path):
    """``compile=True`` reaches each actor's filter (one compiled step, forward and backward):
    the data-parallel fit equals one eager process on all recordings."""
    y = _scalar_recordings(2, 40)
    model = _scalar_model
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    kw = dict(
        x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), known_channels=[0], iterations=2
    )
    local = torchfilt.fit_measurement_only(model(), y, method="likelihood", **kw)
    res = fit_measurement_only_ray(
        model(), Sequences(y), workers=2, compile=True, checkpoint=tmp_path / "ckpt", **kw
    )
    assert res.log_likelihood == pytest.approx(local.log_likelihood, rel=1e-9)
    for a, b in zip(res.model.parameters(), local.model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=0)


#: the iteration at whose end rank 1's process exits in the interrupted EM below
KILL_AT = 3
#: the collectives' timeout there: the whole test took 81 s on two cores shared with other jobs
#: and two busy loops (``yes``), of which one collective is a small part, so a slow but live rank
#: never counts as stuck; a lost rank is reported as soon as it dies, whatever the timeout
LOST_ACTOR_TIMEOUT = 600.0


def _exit_on_rank_1(state) -> None:
    """A callback that kills rank 1's actor process (as a lost machine would) at ``KILL_AT``."""
    import os

    import torch.distributed

    if torch.distributed.get_rank() == 1 and state.iteration == KILL_AT:
        os._exit(1)


def test_em_on_two_actors_survives_a_lost_actor(ray_local, tmp_path):
    """``fit_measurement_only_ray(method="em")`` whose rank 1 dies mid-fit: a WorkerError naming
    the rank (its death is seen by the driver, not waited out: the collectives' timeout is far
    longer than the test); the same call with ``resume=True`` completes and equals the EM of one
    process on all recordings (which the data-parallel EM equals). Nothing depends on timing:
    the collectives' timeout only bounds a hang, and a loaded machine stays far within it."""
    import ddp_support

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    y = ddp_support.em_data(ddp_support.EM_LENGTHS)
    kw = dict(ddp_support.EM_KW, method="em", iterations=6)
    local = torchfilt.fit_measurement_only(ddp_support.em_linear(), y, **kw)
    ck = tmp_path / "ck"
    ray_kw = dict(kw, workers=2, checkpoint=ck, timeout=LOST_ACTOR_TIMEOUT)
    with pytest.raises(WorkerError, match=r"rank 1 of 2 was lost.*resume=True"):
        fit_measurement_only_ray(
            ddp_support.em_linear(), Sequences(y), callback=_exit_on_rank_1, **ray_kw
        )
    done = [torch.load(ck / f"rank{r}.ckpt", weights_only=True)["iteration"] for r in (0, 1)]
    assert max(done) < kw["iterations"]
    ray_kw["checkpoint"] = CheckpointOptions(ck, resume=True)
    res = fit_measurement_only_ray(ddp_support.em_linear(), Sequences(y), **ray_kw)
    got, want = ddp_support.linear_values(res.model), ddp_support.linear_values(local.model)
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-12), (got, want)
    ll = [h["log_likelihood"] for h in res.history]
    assert ll == pytest.approx([h["log_likelihood"] for h in local.history], rel=1e-10)
    assert local.log_likelihood > local.detail.initial_log_likelihood + 10  # the fit moved
    # noise_scale="auto" scales here (tails of 12, 9, 12, 10 steps), alike in both
    assert res.noise_scale is not None and local.noise_scale is not None
    assert res.noise_scale.scale == local.noise_scale.scale


def _sleep_on_rank_1(state) -> None:
    """A callback that makes rank 1 miss the next collective (a hung worker)."""
    import time

    import torch.distributed

    if torch.distributed.get_rank() == 1 and state.iteration == 2:
        time.sleep(120)


@pytest.mark.slow
def test_hung_actor_fails_after_the_timeout_and_a_foreign_checkpoint_is_refused(
    ray_local, tmp_path
):
    """A rank that does not reach a collective: a WorkerError naming it once the others have
    waited ``timeout`` seconds; a rank's own TorchfiltError (checkpoints of another fit) is
    raised as it is."""
    import time

    import ddp_support

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    y = ddp_support.em_data(ddp_support.EM_LENGTHS)
    kw = dict(ddp_support.EM_KW, method="em", iterations=4, workers=2, checkpoint=tmp_path / "ck")
    t0 = time.perf_counter()
    with pytest.raises(
        WorkerError, match=r"rank 1 of 2 did not reach a collective within timeout=3 s"
    ):
        fit_measurement_only_ray(
            ddp_support.em_linear(), Sequences(y), callback=_sleep_on_rank_1, timeout=3.0, **kw
        )
    assert time.perf_counter() - t0 < 60
    with pytest.raises(torchfilt.exceptions.RunError, match="another fit") as info:
        kw["checkpoint"] = CheckpointOptions(tmp_path / "ck", resume=True)
        fit_measurement_only_ray(ddp_support.em_linear(), Sequences(y[:3]), **kw)
    assert not isinstance(info.value, WorkerError)


def test_held_out_noise_scale_on_two_actors_equals_one_process(ray_local):
    """``noise_scale="held-out"``: each actor holds out its recordings' tails, the scores are
    summed, and every actor chooses what one process on all recordings chooses."""
    y = _scalar_recordings(1, 50)
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    kw = dict(
        x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), known_channels=[0], iterations=3,
        method="likelihood", noise_scale="held-out", holdout=0.3,
    )  # fmt: skip
    local = torchfilt.fit_measurement_only(_scalar_model(), y, **kw)
    res = fit_measurement_only_ray(_scalar_model(), Sequences(y), workers=2, **kw)
    assert local.noise_scale is not None and res.noise_scale is not None
    assert res.noise_scale.scale == local.noise_scale.scale
    assert res.noise_scale.held_out == local.noise_scale.held_out == 4 * 15
    for (s, a), (_, b) in zip(res.noise_scale.scores, local.noise_scale.scores, strict=True):
        assert a == pytest.approx(b, rel=1e-8), s


@pytest.mark.parametrize("method", ["both", "auto"])
def test_both_methods_on_two_actors_equal_one_process(ray_local, method):
    """``method="both"`` and ``"auto"`` on two actors: each runs EM and (``"both"``) the
    likelihood method from the same start, the held-out scores summed over the actors, and
    keeps what one process on all recordings keeps (the held-out split: the tails of every
    recording in both)."""
    y = _scalar_recordings(1, 50)
    model = _scalar_model
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    kw = dict(
        x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), known_channels=[0], iterations=3,
        method=method,
    )  # fmt: skip
    local = torchfilt.fit_measurement_only(model(), y, **kw)
    res = fit_measurement_only_ray(model(), Sequences(y), workers=2, **kw)
    assert [c["method"] for c in local.compared] == ["em", "likelihood"]
    fitted = [c for c in local.compared if "score" in c and "skipped" not in c]
    assert len(fitted) == (2 if method == "both" else 1)
    for a, b in zip(res.compared, local.compared, strict=True):
        assert a["method"] == b["method"] and a["kept"] == b["kept"]
        assert a["score"] == pytest.approx(b["score"], rel=1e-8)
    assert res.method == local.method
    for a, b in zip(res.model.parameters(), local.model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=0)


def test_accelerated_em_on_two_actors_equals_one_process(ray_local):
    """``accelerate=True`` (SQUAREM cycles over EM's gradient M-steps) reaches the actors: two
    take the steps of one process on all recordings (the cycles' extrapolation and its
    safeguard use the summed likelihood)."""
    y = _scalar_recordings(3, 40)
    model = _scalar_model
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    kw = dict(
        x0=torch.zeros(1, dtype=DT), P0=torch.eye(1, dtype=DT), known_channels=[0], iterations=2,
        method="em", accelerate=True, m_step_iterations=3, noise_scale="none",
    )  # fmt: skip
    local = torchfilt.fit_measurement_only(model(), y, **kw)
    res = fit_measurement_only_ray(model(), Sequences(y), workers=2, **kw)
    e_steps = [h["e_steps"] for h in local.history]
    assert e_steps[-1] > local.iterations  # the cycles ran (more E-steps than iterations)
    assert [h["e_steps"] for h in res.history] == e_steps
    assert res.log_likelihood == pytest.approx(local.log_likelihood, rel=1e-9)
    for a, b in zip(res.model.parameters(), local.model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=0)
