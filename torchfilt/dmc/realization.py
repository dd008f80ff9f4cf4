"""State-space realisations of a step-response model (spec section 2).

Every realisation here is written in one form, the one the open-loop prediction filter runs:

    X(k) = A X(k-1) + B du(k-1) + Bv dv(k) + w(k-1),    w ~ N(0, Q_Y)
    y(k) = H X(k) + e(k),                                e ~ N(0, Q_y)

**Ours (Xie, Ding & Chen 2016).** The state of CV ``j`` is its free-response prediction vector
``[y_j(k|k), y_j(k+1|k), ..., y_j(k+L_j-1|k)]`` with ``L_j = N + 1`` (stable layout) or ``N + 2``
(integrating layout); the state stacks the CVs one after another (CV-major order, so a mixed plant
simply has blocks of different lengths). Per CV, ``A = M`` and ``B = M [0; S_1; ...; S_{L-1}]``,
``Bv = [0; S^v_1; ...; S^v_{L-1}]`` (paper eq. (6), (14)), ``H`` picks the first element, and

    stable      M^s: block row i (0..L-2) has 1 in column i+1; the last row has 1 in column L-1
    integrating M^r: as M^s except the last row, which is [0 ... 0 -1 2] (linear extrapolation)

With ``Q_Y = q I`` this is the paper's realisation up to a permutation of the state (the paper orders
it time-major, ``[y(k|k); y(k+1|k); ...]`` with ``ny``-blocks), so the filter and its predictions are
the same.

**Lee, Morari & Garcia (1994), with the corrections of the paper's section 2.** The state of CV ``j``
is ``[y_j(k|k), ..., y_j(k+L_j-1|k), x_p,j]``: the prediction vector with a shift whose last row
*repeats* the last element, plus the state ``x_p`` that carries the tail:

    y(k+i|k)     = y(k+i|k-1) + S^u_{i+1} du(k-1) + S^v_i dv(k),           i = 0..L-2   (eq. 24/26)
    y(k+L-1|k)   = y(k+L-2|k-1) + S^u_L du(k-1) + x_p(k-1) + S^v_{L-1} dv(k)             (eq. 25/27)
    x_p(k)       = a_p x_p(k-1) + R^u du(k-1) + R^v dv(k)                                (eq. 22/30)

with ``R = S_{N+1} - S_N`` (zero for a stable CV), ``a_p = 1`` for an integrating CV (``x_p`` is
the settled slope ``R^u u(k-2) + R^v v(k-1)``) and ``a_p = 0`` for a stable one (``x_p = 0``).
The measured disturbance enters through the known ``dv(k)`` directly: the paper's
``x_v(k-1) = dv(k)`` with ``C_v x_v(k-1) = R^v dv(k)``. Both realisations describe the same free response: with ``T`` the map
``x_p = y(k+L-1|k) - y(k+L-2|k)`` (integrating) or ``x_p = 0`` (stable) appended to the identity,
``A_LMG T = T M``, ``B_LMG = T B`` and ``Bv_LMG = T Bv``; a filter on the LMG form with
``Q_LMG = T Q_Y T^T`` gives identical predictions (:class:`~torchfilt.dmc.LMGPredictor`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.dmc.transfer import _positive_int
from torchfilt.exceptions import InputTypeError

__all__ = ["Realization", "lmg_realization", "realize"]


class Realization(NamedTuple):
    """Matrices of a step-response realisation (see the module docstring for the equations).

    Attributes:
        A: transition, shape ``(n, n)``.
        B: MV-move input matrix (acts on ``du(k-1)``), shape ``(n, nu)``.
        Bv: DV-change input matrix (acts on ``dv(k)``), shape ``(n, nv)``.
        H: measurement matrix, shape ``(ny, n)``.
        pred_index: state index of ``y_j(k+i|k)`` at ``[i - 1, j]``, ``i = 1..N``, shape ``(N, ny)``.
        blocks: ``(start, length)`` of each CV's block of the state (block-diagonal structure).
        horizon: model horizon ``N``.
        integrating: per-CV layout flags, shape ``(ny,)``.
        embedding: for the LMG form, the map ``T`` from our state to this one, shape ``(n, n_ours)``;
            ``None`` for ours.
    """

    A: Tensor
    B: Tensor
    Bv: Tensor
    H: Tensor
    pred_index: Tensor
    blocks: tuple[tuple[int, int], ...]
    horizon: int
    integrating: Tensor
    embedding: Tensor | None = None

    @property
    def state_dim(self) -> int:
        """The state dimension ``n``."""
        return int(self.A.shape[-1])


def _shift(L: int, integrating: bool, dtype: torch.dtype) -> Tensor:
    M = torch.diag(torch.ones(L - 1, dtype=dtype), 1)
    if integrating:
        M[-1, -2], M[-1, -1] = -1.0, 2.0
    else:
        M[-1, -1] = 1.0
    return M


def _measurement(
    blocks: list[tuple[int, int]], N: int, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """``H`` picking the first element of each CV block, and the index of ``y_j(k+i|k)``."""
    n = sum(L for _, L in blocks)
    H = torch.zeros(len(blocks), n, dtype=dtype)
    for j, (s, _) in enumerate(blocks):
        H[j, s] = 1.0
    offsets = torch.tensor([s for s, _ in blocks])
    return H, offsets[None, :] + torch.arange(1, N + 1)[:, None]


def _check_horizon(model: StepResponseModel, horizon: int | None) -> int:
    if not isinstance(model, StepResponseModel):
        raise InputTypeError(f"model must be a StepResponseModel, got {type(model).__name__}")
    return model.horizon if horizon is None else _positive_int(horizon, "horizon")


def _with_horizon(model: StepResponseModel, N: int) -> StepResponseModel:
    if N == model.horizon:
        return model
    return StepResponseModel(model.Su, model.Sv, model.integrating, N, model.dt)


def realize(model: StepResponseModel, horizon: int | None = None) -> Realization:
    """Our realisation (stable / integrating layout per CV, CV-major state).

    Args:
        model: the step-response model (its ``integrating`` flags choose each CV's layout).
        horizon: model horizon ``N``; default ``model.horizon``.

    Returns:
        A :class:`Realization` with ``n = sum_j L_j`` states, ``L_j = N + 1`` or ``N + 2``.

    Raises:
        InputTypeError: ``model`` is not a :class:`StepResponseModel`.
        InputError: ``horizon`` is not a positive integer.
    """
    N = _check_horizon(model, horizon)
    model = _with_horizon(model, N)
    dtype = model.dtype
    Su = model.coefficients(N + 1, "u")  # (N+1, ny, nu)
    Sv = model.coefficients(N + 1, "v")
    zu = Su.new_zeros(1, model.nu)
    zv = Sv.new_zeros(1, model.nv)
    As, Bs, Bvs, blocks, start = [], [], [], [], 0
    for j in range(model.ny):
        integ = bool(model.integrating[j])
        L = N + 2 if integ else N + 1
        M = _shift(L, integ, dtype)
        As.append(M)
        Bs.append(M @ torch.cat([zu, Su[: L - 1, j, :]], dim=0))
        Bvs.append(torch.cat([zv, Sv[: L - 1, j, :]], dim=0))
        blocks.append((start, L))
        start += L
    A = torch.block_diag(*As)
    H, pred_index = _measurement(blocks, N, A.dtype)
    return Realization(
        A, torch.cat(Bs), torch.cat(Bvs), H, pred_index, tuple(blocks), N, model.integrating
    )


def lmg_realization(model: StepResponseModel, horizon: int | None = None) -> Realization:
    """The Lee-Morari-Garcia (1994) realisation with the paper's section-2 corrections.

    Args:
        model: the step-response model.
        horizon: model horizon ``N``; default ``model.horizon``.

    Returns:
        A :class:`Realization` with ``n = sum_j (L_j + 1)`` states (prediction vector plus ``x_p``
        per CV) and ``embedding`` ``T`` (``x_LMG = T x_ours``) set.

    Raises:
        InputTypeError: ``model`` is not a :class:`StepResponseModel`.
        InputError: ``horizon`` is not a positive integer.
    """
    N = _check_horizon(model, horizon)
    model = _with_horizon(model, N)
    dtype = model.dtype
    Su = model.coefficients(N + 2, "u")  # S_1..S_{N+2}
    Sv = model.coefficients(N + 1, "v")
    Sv0 = torch.cat([Sv.new_zeros(1, model.ny, model.nv), Sv], dim=0)  # S^v_0..S^v_{N+1}
    As, Bs, Bvs, Ts, blocks, start = [], [], [], [], [], 0
    for j in range(model.ny):
        integ = bool(model.integrating[j])
        L = N + 2 if integ else N + 1
        n = L + 1  # prediction vector + x_p
        A = torch.zeros(n, n, dtype=dtype)
        B = torch.zeros(n, model.nu, dtype=dtype)
        Bv = torch.zeros(n, model.nv, dtype=dtype)
        for i in range(L - 1):  # eq. (24)/(26): shift, i = 0..L-2
            A[i, i + 1] = 1.0
            B[i] = Su[i, j]  # S_{i+1}
            Bv[i] = Sv0[i, j]  # S^v_i
        A[L - 1, L - 1] = 1.0  # eq. (25)/(27): the last element is repeated ...
        A[L - 1, L] = 1.0  # ... plus x_p(k-1)
        B[L - 1] = Su[L - 1, j]  # S_L
        Bv[L - 1] = Sv0[L - 1, j]  # S^v_{L-1}
        A[L, L] = 1.0 if integ else 0.0  # eq. (22)/(30): A_p
        B[L] = Su[N, j] - Su[N - 1, j]  # R^u = S_{N+1} - S_N (zero for a stable CV)
        Bv[L] = Sv0[N + 1, j] - Sv0[N, j]  # C_v x_v(k-1) = R^v dv(k), R^v = S^v_{N+1} - S^v_N
        T = torch.zeros(n, L, dtype=dtype)
        T[:L] = torch.eye(L, dtype=dtype)
        if integ:
            T[L, L - 1], T[L, L - 2] = 1.0, -1.0
        As.append(A)
        Bs.append(B)
        Bvs.append(Bv)
        Ts.append(T)
        blocks.append((start, n))
        start += n
    A = torch.block_diag(*As)
    H, pred_index = _measurement(blocks, N, A.dtype)
    return Realization(
        A,
        torch.cat(Bs),
        torch.cat(Bvs),
        H,
        pred_index,
        tuple(blocks),
        N,
        model.integrating,
        torch.block_diag(*Ts),
    )
