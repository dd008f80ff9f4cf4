"""``fit_em(compile=...)``: a non-linear model's filter runs compiled, and the fit is the eager one.

The compiled time loop fuses operations, so its rounding differs from the eager loop's: the
first E-step's likelihood agrees to rounding, and after a few EM iterations (each an L-BFGS
M-step that amplifies rounding a little) the fits agree far below anything the data can tell
apart.
"""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

import torchfilt
from torchfilt.exceptions import InputError
from torchfilt.models import CholeskyCovariance, LinearGaussianModel
from torchfilt.optim import StoppingOptions
from torchfilt.systems import reaction
from torchfilt.training import fit_em

D = torch.float64
#: the first E-step's log-likelihood, compiled against eager: rounding of one filter run
FIRST_RTOL = 1e-10
#: after three EM iterations: relative difference of the log-likelihood and of the parameters
FIT_RTOL = 1e-6


class _Transition(nn.Module):
    """The 2A -> B Euler step with a learnable rate constant (a user's model)."""

    def __init__(self, k1: float) -> None:
        super().__init__()
        self.k1 = nn.Parameter(torch.tensor(k1, dtype=D))

    def forward(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        return reaction.transition(x, k1=self.k1)


def _problem() -> tuple[torchfilt.StateSpaceModel, dict[str, Tensor]]:
    sim = reaction.simulate_truth(3, steps=60, seed=0)
    model = torchfilt.StateSpaceModel(
        _Transition(0.8 * reaction.K1),
        reaction.measurement,
        Q=CholeskyCovariance(4 * torch.diag(torch.tensor(reaction.Q_DIAG, dtype=D))),
        R=CholeskyCovariance(torch.tensor([[2 * reaction.R_VAR]], dtype=D)),
    )
    return model, dict(y=sim.measurements, x0=reaction.prior_mean(), P0=reaction.prior_cov())


def _fit(compile: bool | str) -> torchfilt.training.EMFit:
    model, d = _problem()
    return fit_em(
        model, d["y"], x0=d["x0"], P0=d["P0"], known_channels=[0], iterations=3,
        stopping=StoppingOptions(tol=0.0, rtol=0.0), compile=compile,  # type: ignore[arg-type]
    )  # fmt: skip


@pytest.mark.slow
def test_compiled_em_equals_eager() -> None:
    eager, compiled = _fit(False), _fit("loop")
    assert compiled.initial_log_likelihood == pytest.approx(
        eager.initial_log_likelihood, rel=FIRST_RTOL
    )
    assert compiled.iterations == eager.iterations
    assert compiled.log_likelihood == pytest.approx(eager.log_likelihood, rel=FIT_RTOL)
    assert compiled.log_likelihood > compiled.initial_log_likelihood  # the fit did move
    for (name, a), (_, b) in zip(
        eager.model.named_parameters(), compiled.model.named_parameters(), strict=True
    ):
        a, b = a.detach(), b.detach()
        if a.numel():
            assert torch.allclose(b, a, rtol=FIT_RTOL, atol=FIT_RTOL * float(a.abs().max())), name


@pytest.mark.parametrize("bad", ["fast", 1.0, None])
def test_invalid_compile_is_an_input_error(bad: object) -> None:
    model, d = _problem()
    with pytest.raises(InputError, match="compile"):
        fit_em(model, d["y"], x0=d["x0"], P0=d["P0"], known_channels=[0], compile=bad)  # type: ignore[arg-type]


def test_compile_leaves_a_linear_models_exact_em_alone() -> None:
    """A linear-Gaussian model's E-step is the exact Kalman smoother: ``compile`` changes
    nothing (bit-identical), and nothing is compiled."""
    g = torch.Generator().manual_seed(0)
    y = torch.randn(2, 40, 1, generator=g, dtype=D).cumsum(-2)

    def fit(compile: bool | str) -> float:
        model = LinearGaussianModel(
            torch.eye(1, dtype=D), torch.eye(1, dtype=D), torch.eye(1, dtype=D),
            torch.eye(1, dtype=D),
        )  # fmt: skip
        return fit_em(
            model, y, x0=torch.zeros(1, dtype=D), P0=torch.eye(1, dtype=D), known_channels=[0],
            iterations=3, compile=compile,  # type: ignore[arg-type]
        ).log_likelihood  # fmt: skip

    assert fit("loop") == fit(False)
