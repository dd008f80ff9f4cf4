"""The held-out scale of a learned model's process noise (torchfilt.training.noise_scale), against
the textbook Kalman filter of tests/reference.py, and fit_measurement_only(noise_scale=...)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from linear_support import make_problem, t64
from reference import kalman_filter

import torchfilt
from torchfilt.exceptions import InputError
from torchfilt.models import (
    CholeskyCovariance,
    LinearGaussianModel,
    StateSpaceModel,
    TimeVarying,
)
from torchfilt.training import Sequences, fit_measurement_only
from torchfilt.training.noise_scale import (
    AUTO_MIN_HELD_OUT,
    INFLATE_SCALES,
    NOISE_SCALES,
    held_out_noise_scale,
    scales_by_default,
    split_held_out,
    split_tails,
    with_process_noise_scale,
)

DT = torch.float64


def _simulate(p, runs, T, seed):
    """``runs`` recordings ``(runs, T, m)`` of the problem's system, no inputs, none missing."""
    rng = np.random.default_rng(seed)
    A, H, Q, R = p["A"], p["H"], p["Q"], p["R"]
    n, m = A.shape[0], H.shape[0]
    y = np.empty((runs, T, m))
    for r in range(runs):
        x = rng.multivariate_normal(p["m0"], p["P0"])
        for t in range(T):
            x = A @ x + rng.multivariate_normal(np.zeros(n), Q)
            y[r, t] = H @ x + rng.multivariate_normal(np.zeros(m), R)
    return y


def _linear(p, q_factor=1.0):
    return LinearGaussianModel(t64(p["A"]), t64(p["H"]), q_factor * t64(p["Q"]), t64(p["R"]))


def test_scaled_models_filter_as_the_scaled_noise():
    """A plain model's wrapped transition filters as the same model built with s Q; a linear
    model's Q is s Q (float64, 1e-12)."""
    p = make_problem(0, T=30, missing=0.0)
    A, H, Q, R = (t64(p[k]) for k in ("A", "H", "Q", "R"))
    y = t64(_simulate(p, 2, 30, seed=1))
    x0, P0 = t64(p["m0"]), t64(p["P0"])

    def plain(Qm):
        return StateSpaceModel(lambda x, u=None: x @ A.mT, lambda x, u=None: x @ H.mT, Q=Qm, R=R)

    scaled = with_process_noise_scale(plain(Q), 2.5)
    assert with_process_noise_scale(plain(Q), 1.0) is not scaled
    assert not any(p.requires_grad for p in scaled.transition.parameters())
    # the wrapper's scale is fixed; the wrapped transition's own parameters are left alone
    learnable = StateSpaceModel(
        lambda x, u=None: x @ A.mT, lambda x, u=None: x @ H.mT, Q=CholeskyCovariance(Q), R=R
    )
    wrapped = with_process_noise_scale(learnable, 2.5)
    assert all(p.requires_grad for p in learnable.parameters())
    assert sum(p.requires_grad for p in wrapped.transition.parameters()) == sum(
        1 for _ in learnable.transition.parameters()
    )
    got = torchfilt.CKF(scaled).filter(y, x0=x0, P0=P0)
    want = torchfilt.CKF(plain(2.5 * Q)).filter(y, x0=x0, P0=P0)
    torch.testing.assert_close(got.mean, want.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.cov, want.cov, rtol=1e-12, atol=1e-12)
    lin = with_process_noise_scale(_linear(p), 2.5)
    assert isinstance(lin, LinearGaussianModel)
    torch.testing.assert_close(lin.transition.noise_cov(), 2.5 * Q, rtol=0, atol=0)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InputError, match="scale"):
            with_process_noise_scale(_linear(p), bad)


def test_tail_scores_are_the_reference_likelihood_of_the_tails():
    """Each scale's score is the textbook Kalman filter's log-likelihood of the held-out tail
    (the whole recording's less its head's); the best is their maximum, the choice the largest
    scale within 1.92 nats of it (margin 0: the best)."""
    p = make_problem(2, T=10, missing=0.0)
    y = _simulate(p, 3, 40, seed=3)
    model = _linear(p, 0.25)  # Q four times too small
    data = Sequences(t64(y), None, t64(p["m0"]), t64(p["P0"]))
    heads, whole, starts = split_tails(model, data, 0.25, dtype=DT)
    assert starts == [30, 30, 30]
    assert [tuple(h.shape) for h in heads.y] == [(30, 2)] * 3
    torch.testing.assert_close(heads.y[1], t64(y[1, :30]), rtol=0, atol=0)
    choice = held_out_noise_scale(model, whole, starts, dtype=DT)
    assert choice.held_out == 3 * 10 * 2
    for s, score in choice.scores:
        want = 0.0
        for r in range(3):
            args = (p["A"], p["H"], 0.25 * s * p["Q"], p["R"])
            full = kalman_filter(*args, y[r], p["m0"], p["P0"])[-1]
            head = kalman_filter(*args, y[r, :30], p["m0"], p["P0"])[-1]
            want += full - head
        assert score == pytest.approx(want, rel=1e-10), s
    best = max(choice.scores, key=lambda sv: sv[1])
    within = [s for s, v in choice.scores if v >= best[1] - 1.92]
    assert choice.best == best[0] and choice.scale == max(within) > best[0]
    assert choice.log_likelihood == dict(choice.scores)[choice.scale]
    strict = held_out_noise_scale(model, whole, starts, dtype=DT, margin=0.0)
    assert strict.scale == strict.best == best[0]
    with pytest.raises(InputError, match="margin"):
        held_out_noise_scale(model, whole, starts, dtype=DT, margin=-1.0)
    with pytest.raises(InputError, match="scales"):
        held_out_noise_scale(model, whole, starts, dtype=DT, scales=[2.0, 1.0])


def test_held_out_recordings_recover_a_process_noise_too_small():
    """With Q a quarter of the truth, long held-out recordings find the best scale at 4 and
    choose one within a step of the grid of it."""
    p = make_problem(4, T=10, missing=0.0)
    y = _simulate(p, 8, 300, seed=5)
    model = _linear(p, 0.25)
    choice = held_out_noise_scale(model, Sequences(t64(y), None, t64(p["m0"]), t64(p["P0"])))
    assert choice.best == 4.0
    assert 4.0 <= choice.scale <= 4 * math.sqrt(2)
    assert len(choice.scores) == len(NOISE_SCALES)


def test_data_parallel_choice_is_the_choice_on_all_recordings():
    """Two processes, each with its own recordings and an all_reduce that sums in the other's
    scores, choose as one process with all recordings."""
    p = make_problem(6, T=10, missing=0.0)
    y = t64(_simulate(p, 4, 50, seed=7))
    model = _linear(p, 0.5)
    prior = (t64(p["m0"]), t64(p["P0"]))

    def part(rows, all_reduce=None):
        return held_out_noise_scale(
            model, Sequences(y[rows], None, *prior), [40] * len(rows), all_reduce=all_reduce
        )

    other = part([2, 3])
    flat_other = torch.tensor([v for _, v in other.scores] + [float(other.held_out)], dtype=DT)

    def all_reduce(t):
        t.add_(flat_other)

    got = part([0, 1], all_reduce)
    want = part([0, 1, 2, 3])
    assert (got.scale, got.best) == (want.scale, want.best)
    assert got.held_out == want.held_out == 4 * 10 * 2
    for (s, a), (_, b) in zip(got.scores, want.scores, strict=True):
        assert a == pytest.approx(b, rel=1e-12), s


def test_split_tails_refuses_bad_holdouts():
    p = make_problem(0, T=10, missing=0.0)
    model = _linear(p)
    data = Sequences(t64(_simulate(p, 1, 4, seed=0)), None, t64(p["m0"]), t64(p["P0"]))
    for bad in (0.0, 1.0, 1.5, -0.1, True):
        with pytest.raises(InputError, match="holdout"):
            split_tails(model, data, bad, dtype=DT)
    with pytest.raises(InputError, match="holdout"):  # 4 steps: 0.2 of them is no step
        split_tails(model, data, 0.2, dtype=DT)


def test_fit_measurement_only_fits_the_heads_then_scales():
    """noise_scale="held-out": the fit sees the heads only (the same fit as on them with "none"),
    its model carries the scale chosen on the tails, from 1 up; with validation= it fits on all
    of y."""
    p = make_problem(8, T=10, missing=0.0)
    y = t64(_simulate(p, 2, 60, seed=9))
    x0, P0 = t64(p["m0"]), t64(p["P0"])
    kw = dict(x0=x0, P0=P0, known_channels=[0, 1], iterations=3, method="em")
    fit = fit_measurement_only(_linear(p, 0.3), y, noise_scale="held-out", holdout=0.25, **kw)
    heads = fit_measurement_only(_linear(p, 0.3), y[:, :45], noise_scale="none", **kw)
    assert fit.noise_scale is not None and heads.noise_scale is None
    assert fit.noise_scale.held_out == 2 * 15 * 2
    assert [s for s, _ in fit.noise_scale.scores] == list(INFLATE_SCALES)  # 1 and up only
    data = Sequences(y, None, x0, P0)
    want = held_out_noise_scale(heads.model, data, [45, 45], dtype=DT, scales=INFLATE_SCALES)
    assert fit.noise_scale.scale == want.scale
    assert fit.log_likelihood == pytest.approx(heads.log_likelihood, rel=1e-12)
    Qh = heads.model.transition.noise_cov()
    torch.testing.assert_close(fit.model.transition.noise_cov(), fit.noise_scale.scale * Qh)
    val = t64(_simulate(p, 2, 60, seed=10))
    fv = fit_measurement_only(_linear(p, 0.3), y, noise_scale="held-out", validation=val, **kw)
    whole = fit_measurement_only(_linear(p, 0.3), y, noise_scale="none", **kw)
    assert fv.log_likelihood == pytest.approx(whole.log_likelihood, rel=1e-12)
    assert fv.noise_scale is not None and fv.noise_scale.held_out == 2 * 60 * 2
    with pytest.raises(InputError, match="noise_scale"):
        fit_measurement_only(_linear(p), y, noise_scale="validation", **kw)  # type: ignore[arg-type]


def test_auto_scales_when_held_out_data_can_be_scored():
    """noise_scale="auto" (the default) is "held-out" with at least 30 held-out steps, or with
    validation=; else, with a fixed Q, or for a model whose noise cannot be scaled, "none"."""
    p = make_problem(8, T=10, missing=0.0)
    x0, P0 = t64(p["m0"]), t64(p["P0"])
    kw = dict(x0=x0, P0=P0, known_channels=[0, 1], iterations=3, method="em")
    long = t64(_simulate(p, 2, 80, seed=11))  # 2 x 16 held-out steps: 32
    auto = fit_measurement_only(_linear(p, 0.3), long, **kw)
    held = fit_measurement_only(_linear(p, 0.3), long, noise_scale="held-out", **kw)
    assert auto.noise_scale == held.noise_scale and auto.noise_scale is not None
    torch.testing.assert_close(
        auto.model.transition.noise_cov(), held.model.transition.noise_cov(), rtol=0, atol=0
    )
    short = long[:, :70]  # 2 x 14 held-out steps: 28
    for kwargs in ({}, {"fixed": ("Q",)}):
        got = fit_measurement_only(_linear(p, 0.3), short, **kwargs, **kw)
        want = fit_measurement_only(_linear(p, 0.3), short, noise_scale="none", **kwargs, **kw)
        assert got.noise_scale is None and got.log_likelihood == want.log_likelihood
    fixed_q = fit_measurement_only(_linear(p, 0.3), long, fixed=("Q",), **kw)
    assert fixed_q.noise_scale is None
    val = fit_measurement_only(_linear(p, 0.3), short, validation=long, **kw)
    assert val.noise_scale is not None and val.noise_scale.held_out == 2 * 80 * 2
    with pytest.raises(InputError, match="holdout"):  # refused whether or not it is used
        fit_measurement_only(_linear(p), short, noise_scale="none", holdout=1.0, **kw)


def test_auto_rule_counts_held_out_steps_over_processes():
    """scales_by_default: the held-out steps of every process count (a fake all_reduce doubling
    them); a subclass of StateSpaceModel with its own structure, or a fixed transition
    parameter, is left unscaled."""
    p = make_problem(8, T=10, missing=0.0)
    model = _linear(p)
    data = Sequences(t64(_simulate(p, 1, 100, seed=12)))  # 20 held-out steps

    def doubled(t):
        t.mul_(2)

    assert 20 < AUTO_MIN_HELD_OUT <= 40
    assert not scales_by_default(model, data, 0.2, validation=False)
    assert scales_by_default(model, data, 0.2, validation=False, all_reduce=doubled)
    assert scales_by_default(model, data, 0.2, validation=True)
    assert not scales_by_default(model, data, 0.2, validation=True, fixed=("transition.A",))

    class Custom(StateSpaceModel):
        pass

    custom = Custom(model.transition, model.measurement)
    assert not scales_by_default(custom, data, 0.2, validation=True)
    # a time-varying Q cannot be wrapped (CalibratedModel refuses it): plain or linear, left
    Qt = torch.stack([t64(p["Q"]) * (1 + 0.1 * k) for k in range(100)])
    varying = LinearGaussianModel(t64(p["A"]), t64(p["H"]), TimeVarying(Qt), t64(p["R"]))
    plain = StateSpaceModel(varying.transition, varying.measurement)
    for m in (varying, plain):
        assert not scales_by_default(m, data, 0.2, validation=True)
    assert scales_by_default(StateSpaceModel(model.transition, model.measurement), data, 0.2,
                             validation=True)  # fmt: skip


def test_five_or_more_recordings_hold_out_whole_ones():
    """With 6 recordings the fit sees the first 5 (the same fit as on them with "none") and
    every step of the sixth is scored; the split keeps the recordings' own priors."""
    p = make_problem(8, T=10, missing=0.0)
    x0, P0 = t64(p["m0"]), t64(p["P0"])
    y = t64(_simulate(p, 6, 20, seed=13))
    data = Sequences(y, None, x0, P0)
    train, scored, starts = split_held_out(_linear(p), data, 0.2, dtype=DT)
    assert starts is None and len(train.y) == 5 and len(scored.y) == 1
    torch.testing.assert_close(scored.y[0], y[5], rtol=0, atol=0)
    kw = dict(x0=x0, P0=P0, known_channels=[0, 1], iterations=3, method="em")
    fit = fit_measurement_only(_linear(p, 0.3), y, noise_scale="held-out", **kw)
    first = fit_measurement_only(_linear(p, 0.3), y[:5], noise_scale="none", **kw)
    assert fit.log_likelihood == pytest.approx(first.log_likelihood, rel=1e-12)
    assert fit.noise_scale is not None and fit.noise_scale.held_out == 20 * 2
    scored = Sequences(y[5:], None, x0, P0)
    want = held_out_noise_scale(first.model, scored, None, dtype=DT, scales=INFLATE_SCALES)
    assert fit.noise_scale.scale == want.scale
    for (s, a), (_, b) in zip(fit.noise_scale.scores, want.scores, strict=True):
        assert a == pytest.approx(b, rel=1e-12), s
    assert len(split_held_out(_linear(p), Sequences(y[:4], None, x0, P0), 0.2, dtype=DT)[0].y) == 4
