import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
import torch

import torchfilt
from torchfilt.plots import plot_errors, plot_estimates, plot_nis
from torchfilt.systems import reentry


@pytest.fixture(scope="module")
def run():
    sim = reentry.simulate_truth(1, seed=0, steps=20)
    sm = torchfilt.CKF(reentry.model()).smooth(
        sim.measurements[0], x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov()
    )
    return sim, sm


def test_plot_estimates_with_truth_has_error_column(run, tmp_path):
    sim, sm = run
    fig = plot_estimates(
        sm, truth=sim.states[0], state_names=["a", "v", "b"], units=["ft", "ft/s", None]
    )
    axes = fig.get_axes()
    assert len(axes) == 6
    err_ax = axes[1]
    label = [t.get_text() for t in err_ax.get_legend().get_texts()][-1]
    err = (sm.mean[:, 0] - sim.states[0, :, 0]).abs()
    band = 1.959963984540054 * sm.cov[:, 0, 0].sqrt()
    assert f"{float((err <= band).double().mean()):.0%} inside" in label
    assert axes[0].get_ylabel() == "a [ft]"
    fig.savefig(tmp_path / "est.png")
    assert (tmp_path / "est.png").stat().st_size > 10_000


def test_plot_estimates_rejects_batches(run):
    _, sm = run
    batched = sm.filtered._replace(mean=sm.filtered.mean[None], cov=sm.filtered.cov[None])
    with pytest.raises(ValueError, match="one sequence"):
        plot_estimates(batched)


def test_plot_nis_band_fraction(run):
    _, sm = run
    fig = plot_nis(sm.filtered)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    value, dof = torchfilt.nis(sm.filtered)
    assert (dof == 1).all()
    lo, hi = (float(torchfilt.numerics.chi2_quantile(p, 1)) for p in (0.025, 0.975))
    frac = float(((value >= lo) & (value <= hi)).double().mean())
    assert any(f"{frac:.0%} inside" in s for s in labels)


def test_plot_errors_counts_failed_runs():
    e = np.ones((4, 10, 2))
    e[1, 5:] = np.nan
    fig = plot_errors({"good": np.ones((4, 10, 2)), "bad": e})
    texts = [t.get_text() for t in fig.get_axes()[0].get_legend().get_texts()]
    assert texts == ["good", "bad (1/4 runs failed)"]
    with pytest.raises(ValueError, match="share"):
        plot_errors({"a": np.ones((2, 10, 2)), "b": np.ones((2, 9, 2))})
