"""The corrected Lee-Morari-Garcia realisation gives the same predictions as ours (the paper's claim),
on stable, integrating and mixed plants."""

import pytest
import torch

from torchfilt.dmc import (
    FOPDT,
    IPDT,
    LMGPredictor,
    OpenLoopPredictor,
    StepResponseModel,
    lmg_realization,
    realize,
    steady_gain,
)

D = torch.float64
#: Relative agreement of the two filters' predictions (both gains come from separate DARE solves
#: converged to ~1e-13; the predictions are O(10-100)).
PRED_RTOL = 1e-9
#: Structural identities of the realisations hold exactly (sums of a few coefficients).
EXACT_TOL = 1e-12


def model(layout, N=12):
    rows_u = {
        False: [FOPDT(2.0, 4.0, 1.5), FOPDT(-1.0, 2.0, 0.6)],
        True: [IPDT(0.2, 2.0, 1.2), IPDT(-0.1, 1.0, 0.3)],
    }
    rows_v = {False: [FOPDT(0.5, 3.0, 0.5)], True: [IPDT(0.05, 2.0, 0.0)]}
    return StepResponseModel.from_transfer_functions(
        [rows_u[i] for i in layout], [rows_v[i] for i in layout], dt=1.0, horizon=N
    )


LAYOUTS = {"stable": (False, False), "integrating": (True, True), "mixed": (True, False)}


@pytest.mark.parametrize("layout", list(LAYOUTS.values()), ids=list(LAYOUTS))
def test_lmg_structure_is_a_transform_of_ours(layout):
    m = model(layout)
    ours, lmg = realize(m), lmg_realization(m)
    T = lmg.embedding
    assert T is not None and T.shape == (lmg.state_dim, ours.state_dim)
    torch.testing.assert_close(lmg.A @ T, T @ ours.A, rtol=0, atol=EXACT_TOL)
    torch.testing.assert_close(lmg.B, T @ ours.B, rtol=0, atol=EXACT_TOL)
    torch.testing.assert_close(lmg.Bv, T @ ours.Bv, rtol=0, atol=EXACT_TOL)
    torch.testing.assert_close(lmg.H @ T, ours.H, rtol=0, atol=0)


@pytest.mark.parametrize("layout", list(LAYOUTS.values()), ids=list(LAYOUTS))
@pytest.mark.parametrize("qY", [0.5, 0.01])
def test_lmg_and_ours_give_identical_predictions(layout, qY):
    m = model(layout)
    ours = OpenLoopPredictor(m, Q_Y=qY, Q_y=1.0)
    lmg = LMGPredictor(m, Q_Y=qY, Q_y=1.0)
    g = torch.Generator().manual_seed(7)
    T = 150
    y = 3.0 * torch.randn(T, 2, generator=g, dtype=D)  # measurements unrelated to the model
    du = torch.randn(T, 2, generator=g, dtype=D)
    dv = torch.randn(T, 1, generator=g, dtype=D)
    a, b = ours.run(y, du, dv), lmg.run(y, du, dv)
    scale = a.predictions.abs().max()
    assert scale > 10.0
    torch.testing.assert_close(b.predictions, a.predictions, rtol=0, atol=PRED_RTOL * scale)
    # the LMG state maps onto ours: x_LMG = T x_ours at every step
    T_map = lmg.realization.embedding
    torch.testing.assert_close(b.states, a.states @ T_map.mT, rtol=0, atol=PRED_RTOL * scale)


def test_independent_xp_noise_is_a_different_filter():
    """Without the paper's parameter setting (x_p given its own independent noise) the predictions
    differ: the equality above is not automatic."""
    m = model((True, True))
    lmg_real = lmg_realization(m)
    n = lmg_real.state_dim
    K_indep = steady_gain(lmg_real, 0.5 * torch.eye(n, dtype=D), torch.eye(2, dtype=D))
    other = LMGPredictor(m, gain=K_indep)
    ours = OpenLoopPredictor(m, Q_Y=0.5, Q_y=1.0)
    g = torch.Generator().manual_seed(8)
    y = torch.randn(60, 2, generator=g, dtype=D)
    diff = (other.run(y).predictions - ours.run(y).predictions).abs().max()
    assert diff > 1e-2
