"""The closed-form M-step's noise covariances stay positive semi-definite: a difference of
second moments is semi-definite in exact arithmetic but indefinite by cancellation where a
direction has no noise, which the model's noise check refuses (found on a real log, where
``fit_em`` died inside ``LinearGaussianModel`` with "Q is not positive semi-definite")."""

from __future__ import annotations

import torch

from torchfilt.models import LinearGaussianModel
from torchfilt.training.em_steps import SmoothedPairs, _Lin, _linear_m_step, _psd_part

D = torch.float64


def test_psd_part_clips_only_negative_eigenvalues():
    g = torch.Generator().manual_seed(0)
    V = torch.linalg.qr(torch.randn(4, 4, generator=g, dtype=D)).Q
    S = V @ torch.diag(torch.tensor([2e-3, 1e-4, 5e-6, -2e-11], dtype=D)) @ V.mT
    P = _psd_part(S)
    want = V @ torch.diag(torch.tensor([2e-3, 1e-4, 5e-6, 0.0], dtype=D)) @ V.mT
    torch.testing.assert_close(P, want, rtol=0, atol=1e-17)
    assert float(torch.linalg.eigvalsh(P).min()) >= -1e-18
    # a semi-definite matrix comes back as it was, to the last bit
    psd = V @ torch.diag(torch.tensor([2e-3, 1e-4, 5e-6, 0.0], dtype=D).clamp_min(1e-9)) @ V.mT
    psd = (psd + psd.mT) / 2
    assert torch.equal(_psd_part(psd), psd)


def test_noiseless_trajectory_gives_a_q_the_model_accepts():
    """States that follow ``x_t = A x_{t-1}`` exactly (a rotation, no noise): the closed-form
    ``Q`` is zero up to cancellation, with negative eigenvalues of the rounding's size."""
    c, s = torch.cos(torch.tensor(0.3, dtype=D)), torch.sin(torch.tensor(0.3, dtype=D))
    A = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 0.97]], dtype=D)
    x = [torch.tensor([3.0, -1.0, 2.0], dtype=D)]
    for _ in range(200):
        x.append(A @ x[-1])
    X = torch.stack(x).unsqueeze(0)  # (1, 201, 3)
    zero = torch.zeros(1, 200, 3, 3, dtype=D)
    sp = SmoothedPairs(X[:, :-1], zero, X[:, 1:], zero, zero)
    H = torch.tensor([[1.0, 0.0, 0.0]], dtype=D)
    Y = X[:, 1:] @ H.mT + 0.01
    lin = _Lin(torch.eye(3, dtype=D), H, torch.eye(3, dtype=D), torch.eye(1, dtype=D), None, None)
    valid = torch.ones(1, 200, dtype=torch.bool)
    new = _linear_m_step(lin, sp, Y, None, valid, [0], learn_R=True)
    assert float(torch.linalg.eigvalsh(new.Q).min()) >= -1e-18
    assert float(new.Q.abs().max()) < 1e-12  # the noise-free truth, to rounding
    torch.testing.assert_close(new.A, A, rtol=0, atol=1e-9)
    LinearGaussianModel(new.A, new.H, new.Q, new.R)  # accepted by the noise check
