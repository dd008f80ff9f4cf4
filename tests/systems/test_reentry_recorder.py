"""The re-entry training-data recorder: exact size, sane targets, coverage of the prior."""

from __future__ import annotations

import pytest
import torch
from gp_support import one_thread

from torchfilt.systems import reentry

pytestmark = pytest.mark.usefixtures("one_thread")
__all__ = ["one_thread"]

SAMPLES = 600


@pytest.fixture(scope="module")
def record():
    return reentry.record_training_data(SAMPLES, seed=3)


def test_exact_count_and_shapes(record):
    assert record.pairs == SAMPLES
    assert len(record.states) == len(record.measurements)
    for s, y in zip(record.states, record.measurements, strict=True):
        assert s.shape[1] == 3 and y.shape == (s.shape[0], 1) and s.shape[0] >= 2


def test_every_recorded_step_is_the_true_dynamics_and_sane(record):
    for s in record.states:
        assert bool(torch.isfinite(s).all())
        assert bool((s[:, 0] >= 0).all()) and bool((s[:, 1] >= 0).all())
        assert bool((s[:, 1] <= reentry.MAX_VELOCITY).all())
        torch.testing.assert_close(reentry.transition(s[:-1]), s[1:], rtol=0, atol=0)


def test_initial_states_cover_the_prior(record):
    x0 = record.initial
    sd = x0.std(0)
    want = torch.tensor(reentry.PRIOR_COV_DIAG, dtype=torch.float64).sqrt()
    torch.testing.assert_close(sd, want, rtol=0.25, atol=0)  # a few hundred draws
    assert float((x0[:, 2] < 0).double().mean()) > 0.3  # negative ballistic coefficients included
    assert sum(record.rejected.values()) > 0  # ... and their blow-ups were cut off


def test_measurements_are_range_plus_100ft_noise(record):
    s = torch.cat(record.states)
    y = torch.cat(record.measurements)
    resid = y - reentry.measurement(s)
    assert abs(float(resid.std()) - 100.0) < 10.0
    assert abs(float(resid.mean())) < 10.0


def test_reproducible_and_seeded():
    a = reentry.record_training_data(50, seed=1)
    b = reentry.record_training_data(50, seed=1)
    c = reentry.record_training_data(50, seed=2)
    assert all(torch.equal(p, q) for p, q in zip(a.states, b.states, strict=True))
    assert not torch.equal(a.states[0], c.states[0])
    with pytest.raises(ValueError, match="positive"):
        reentry.record_training_data(0)
