"""Subspace identification of a linear-Gaussian model from input-output data (N4SID).

The combined deterministic-stochastic N4SID of Van Overschee & De Moor (1994; *Subspace
Identification for Linear Systems*, 1996, algorithm 1 of ch. 4) on block Hankel matrices with
``i`` block rows, the recordings' columns side by side:

1. the oblique projection ``O_i = Y_f /_{U_f} W_p`` of the future outputs on the past inputs and
   outputs ``W_p`` along the future inputs, by least squares;
2. its SVD ``O_i = U S V^T``: the order ``n`` is the number of dominant singular values (see
   :func:`subspace_order`) and the extended observability matrix is
   ``Gamma_i = [C; C A; ...; C A^{i-1}] = U_1 S_1^{1/2}``;
3. ``C`` its first block row and ``A`` from its shift invariance (least squares), as in MOESP
   (for a plant known to be stable, ``stable=True`` re-estimates an unstable ``A`` with the
   shifted matrix padded by zeros, which keeps its eigenvalues in the unit disc);
4. ``B``, ``D'`` and each recording's initial state by linear least squares on all outputs
   given ``A, C`` (the output is linear in them).

This gives the predictor form ``s_{k+1} = A s_k + B u_k``, ``y_k = C s_k + D' u_k``; torchfilt's
convention ``x_t = A x_{t-1} + B u_t``, ``y_t = H x_t + D u_t`` is the same system with
``s_t = x_{t-1}``, so ``H = C A^{-1}`` and ``D = D' - H B``. The noise covariances ``Q`` and
``R`` (independent, as in :class:`~torchfilt.models.LinearGaussianModel`) are matched to the
sample output autocovariances of the stochastic part ``Lambda_j = H A^j Sigma H^T + [j=0] R``
(``Sigma = A Sigma A^T + Q``) by linear least squares, then projected onto the positive
definite cone. The prior of each recording is its least-squares initial state and the stationary
state covariance. The estimate is consistent (it tends to the true system, up to a change of
state coordinates, as the data grow) but not efficient: it is a start for EM or a likelihood fit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.models.functional import StateSpaceModel
from torchfilt.models.linear import LinearGaussianModel, linear_system

__all__ = [
    "SubspaceFit",
    "SubspaceOrder",
    "default_block_rows",
    "subspace_identify",
    "subspace_order",
    "subspace_start",
]

f64 = torch.float64


class SubspaceFit(NamedTuple):
    """A model identified by :func:`subspace_identify`.

    Attributes:
        model: the :class:`~torchfilt.models.LinearGaussianModel` (float64).
        x0: prior mean of ``x_{-1}`` per recording, ``(R, n)``.
        P0: prior covariance ``(n, n)`` (the stationary state covariance).
        singular_values: of the oblique projection, ``(i m,)`` (see :func:`subspace_order`).
    """

    model: LinearGaussianModel
    x0: Tensor
    P0: Tensor
    singular_values: Tensor


class SubspaceOrder(NamedTuple):
    """The order suggested by :func:`subspace_order`.

    Attributes:
        singular_values: of the oblique projection, descending, ``(i m,)``.
        suggested: the order at the largest gap of the log singular values.
    """

    singular_values: Tensor
    suggested: int


def _series(x: Tensor | Sequence[Tensor] | None, name: str) -> list[Tensor] | None:
    """The recordings ``(T_i, d)`` of ``x (..., T, d)`` or of a list, in float64."""
    if x is None:
        return None
    if any(isinstance(r, Tensor) and r.is_complex() for r in ([x] if isinstance(x, Tensor) else x)):
        raise InputTypeError(f"{name}: expected real data, got a complex tensor")
    if isinstance(x, Tensor):
        if x.dim() < 2:
            raise ShapeError(f"{name}: expected shape (..., T, d), got {tuple(x.shape)}")
        return list(x.detach().to(f64).reshape(-1, *x.shape[-2:]).unbind(0))
    out = []
    for k, r in enumerate(x):
        if not isinstance(r, Tensor) or r.dim() != 2:
            raise ShapeError(f"{name}[{k}]: expected a tensor of shape (T, d)")
        out.append(r.detach().to(f64))
    if not out:
        raise InputError(f"{name}: no recording")
    return out


def _data(
    y: Tensor | Sequence[Tensor], u: Tensor | Sequence[Tensor] | None, block_rows: int
) -> tuple[list[Tensor], list[Tensor]]:
    ys = _series(y, "y")
    assert ys is not None
    us = _series(u, "u")
    if us is None:
        us = [r.new_zeros(r.shape[0], 0) for r in ys]
    if len(us) != len(ys):
        raise ShapeError(f"u: {len(us)} recordings, y has {len(ys)}")
    for k, (a, b) in enumerate(zip(ys, us, strict=True)):
        if a.shape[0] != b.shape[0]:
            raise ShapeError(f"u[{k}]: {b.shape[0]} steps, y[{k}] has {a.shape[0]}")
        if not (bool(torch.isfinite(a).all()) and bool(torch.isfinite(b).all())):
            raise InputError(f"y[{k}] or u[{k}]: subspace identification needs complete data")
    if block_rows < 1:
        raise InputError(f"block_rows must be at least 1, got {block_rows}")
    if max(r.shape[0] for r in ys) < 2 * block_rows + 2:
        raise InputError(
            f"y: the recordings are too short for block_rows={block_rows} "
            f"(need at least {2 * block_rows + 2} steps)"
        )
    return ys, us


def _hankel(x: Tensor, rows: int) -> Tensor:
    """Block Hankel matrix ``(rows d, T - rows + 1)`` of ``x (T, d)``."""
    j = x.shape[0] - rows + 1
    return x.mT.unfold(1, j, 1).permute(1, 0, 2).reshape(rows * x.shape[1], j)


def _oblique(Yf: Tensor, Wp: Tensor, Uf: Tensor) -> Tensor:
    """``Yf /_{Uf} Wp``: the part of the least-squares fit of ``Yf`` on ``[Wp; Uf]`` along ``Wp``."""
    Z = torch.cat([Wp, Uf], 0)
    coef = torch.linalg.lstsq(Z.mT, Yf.mT, driver="gelsd").solution  # (rows Z, rows Yf)
    return coef[: Wp.shape[0]].mT @ Wp


def _projection(ys: list[Tensor], us: list[Tensor], i: int) -> Tensor:
    """The oblique projection ``O_i`` over the recordings long enough."""
    m, p = ys[0].shape[1], us[0].shape[1]
    Yh = torch.cat([_hankel(y, 2 * i) for y in ys if y.shape[0] >= 2 * i + 1], 1)
    Uh = torch.cat(
        [_hankel(u, 2 * i) for u, y in zip(us, ys, strict=True) if y.shape[0] >= 2 * i + 1], 1
    )
    Wp = torch.cat([Uh[: i * p], Yh[: i * m]], 0)
    O_i = _oblique(Yh[i * m :], Wp, Uh[i * p :])
    return O_i


def default_block_rows(order: int | None, outputs: int) -> int:
    """The block rows ``i`` :func:`subspace_identify` uses when none are given: 10 without an
    order, else ``max(2 ceil(order / outputs) + 2, order + 1, 5)``."""
    return 10 if order is None else max(2 * math.ceil(order / outputs) + 2, order + 1, 5)


def subspace_order(
    y: Tensor | Sequence[Tensor],
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    block_rows: int = 10,
    max_order: int | None = None,
) -> SubspaceOrder:
    """Suggest the state dimension from the singular values of the oblique projection.

    Args:
        y: measurements ``(..., T, m)`` or a list of ``(T_i, m)`` (complete, no NaN).
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None``.
        block_rows: block rows ``i`` of the Hankel matrices (the order can be at most ``i m``).
        max_order: the largest order considered (default ``i m - 1``).

    Returns:
        A :class:`SubspaceOrder`: the singular values and the order at their largest
        logarithmic gap.

    Raises:
        InputError: missing data, recordings too short, or a bad ``block_rows``.
        ShapeError: ``y`` and ``u`` of mismatched shapes.
    """
    ys, us = _data(y, u, block_rows)
    O_i = _projection(ys, us, block_rows)
    s = torch.linalg.svdvals(O_i)
    top = s.shape[0] - 1 if max_order is None else min(max_order, s.shape[0] - 1)
    if top < 1:
        raise InputError(f"max_order must be at least 1, got {max_order}")
    logs = torch.log(s.clamp_min(s[0] * torch.finfo(f64).eps))
    gaps = logs[:top] - logs[1 : top + 1]
    return SubspaceOrder(s, int(gaps.argmax()) + 1)


def _lyap(A: Tensor, Q: Tensor) -> Tensor:
    """``Sigma = A Sigma A^T + Q`` (stable ``A``)."""
    n = A.shape[0]
    vec = torch.linalg.solve(torch.eye(n * n, dtype=f64) - torch.kron(A, A), Q.reshape(-1))
    return vec.reshape(n, n)


def _sym_basis(d: int) -> list[Tensor]:
    out = []
    for a in range(d):
        for b in range(a, d):
            E = torch.zeros(d, d, dtype=f64)
            E[a, b] = E[b, a] = 1.0
            out.append(E)
    return out


def _psd(S: Tensor, floor: float) -> Tensor:
    w, V = torch.linalg.eigh(0.5 * (S + S.mT))
    out = (V * w.clamp_min(floor)) @ V.mT
    return 0.5 * (out + out.mT)


def _noise(A: Tensor, H: Tensor, res: list[Tensor], lags: int) -> tuple[Tensor, Tensor]:
    """``Q, R`` matched to the output autocovariances of the stochastic residuals ``res``."""
    n, m = A.shape[0], H.shape[0]
    lam: list[Tensor] = []
    for j in range(lags + 1):
        num = torch.zeros(m, m, dtype=f64)
        cnt = 0
        for r in res:
            if r.shape[0] > j:
                num = num + r[j:].mT @ r[: r.shape[0] - j]
                cnt += r.shape[0] - j
        lam.append(num / cnt)
    target = torch.cat([x.reshape(-1) for x in lam])
    floor = 1e-8 * float(torch.diagonal(lam[0]).mean())
    if float(torch.linalg.eigvals(A).abs().max()) >= 1.0:
        # no stationary covariance: the residuals are all measurement noise
        return torch.eye(n, dtype=f64) * floor, _psd(lam[0], floor)
    powers = [torch.linalg.matrix_power(A, j) for j in range(lags + 1)]
    cols = []
    for E in _sym_basis(n):
        Sig = _lyap(A, E)
        cols.append(torch.cat([(H @ Pj @ Sig @ H.mT).reshape(-1) for Pj in powers]))
    for E in _sym_basis(m):
        cols.append(torch.cat([E.reshape(-1)] + [torch.zeros(m * m, dtype=f64)] * lags))
    M = torch.stack(cols, -1)
    theta = torch.linalg.lstsq(M, target.unsqueeze(-1), driver="gelsd").solution.squeeze(-1)
    bq = len(cols) - m * (m + 1) // 2
    Q = (theta[:bq, None, None] * torch.stack(_sym_basis(n))).sum(0)
    R = (theta[bq:, None, None] * torch.stack(_sym_basis(m))).sum(0)
    return _psd(Q, floor), _psd(R, floor)


def _input_maps(
    A: Tensor, C: Tensor, ys: list[Tensor], us: list[Tensor]
) -> tuple[Tensor, Tensor, Tensor, list[Tensor]]:
    """``B, D'`` and the initial states of ``s_{t+1} = A s_t + B u_t``, ``y_t = C s_t + D' u_t``
    by least squares on every output (linear in them given ``A, C``), and the residuals."""
    n, m, p, R = A.shape[0], C.shape[0], us[0].shape[1], len(ys)
    lengths = [y.shape[0] for y in ys]
    T = max(lengths)
    U = torch.zeros(R, T, p, dtype=f64)  # zero inputs past a recording's end change nothing
    for k, u in enumerate(us):
        U[k, : u.shape[0]] = u
    eye_n, eye_m = torch.eye(n, dtype=f64), torch.eye(m, dtype=f64)
    # Psi_t = sum_{j<t} u_j^T (x) A^{t-1-j} (R, n, n p): y_t's regressor on vec(B) is C Psi_t,
    # all recordings at once; u_t^T (x) I is (eye[i, j] u_b) at [i, b n + j]
    Psi = torch.zeros(R, n, n * p, dtype=f64)
    Ak = eye_n
    regB, regD, regX = [], [], []
    for t in range(T):
        regB.append(C @ Psi)
        regD.append((eye_m[None, :, None, :] * U[:, t, None, :, None]).reshape(R, m, p * m))
        regX.append(C @ Ak)
        Psi = A @ Psi + (eye_n[None, :, None, :] * U[:, t, None, :, None]).reshape(R, n, p * n)
        Ak = A @ Ak
    RB, RD, RX = torch.stack(regB, 1), torch.stack(regD, 1), torch.stack(regX, 0)  # (R, T, m, .)
    rows, targets = [], []
    for k, y in enumerate(ys):
        Tk = lengths[k]
        x0_part = torch.zeros(Tk, m, n * R, dtype=f64)
        x0_part[..., k * n : (k + 1) * n] = RX[:Tk]
        rows.append(torch.cat([RB[k, :Tk], RD[k, :Tk], x0_part], -1).reshape(Tk * m, -1))
        targets.append(y.reshape(-1))
    X, Y = torch.cat(rows, 0), torch.cat(targets, 0)
    theta = torch.linalg.lstsq(X, Y.unsqueeze(-1), driver="gelsd").solution.squeeze(-1)
    fitted = X @ theta
    B = theta[: n * p].reshape(p, n).mT  # column-major vec
    D = theta[n * p : n * p + m * p].reshape(p, m).mT
    x0 = theta[n * p + m * p :].reshape(R, n)
    res, off = [], 0
    for y in ys:
        k = y.numel()
        res.append(y - fitted[off : off + k].reshape(y.shape))
        off += k
    return B, D, x0, res


def _shift_invariance(Gam: Tensor, m: int, *, stable: bool) -> Tensor:
    """``A`` from ``Gamma_{2:} = Gamma_{:-1} A`` by least squares, for ``Gamma`` ``(i m, n)``.

    With ``stable`` and an estimate with an eigenvalue on or outside the unit circle: ``A``
    from ``Gamma A = [Gamma_{2:}; 0]`` instead. For an eigenpair ``A v = lambda v``,
    ``|lambda| |Gamma v| = |P [Gamma_{2:} v; 0]| <= |Gamma_{2:} v| <= |Gamma v|`` (``P`` the
    projection onto the range of ``Gamma``), so ``|lambda| <= 1`` (Maciejowski 1995).
    """
    A = torch.linalg.lstsq(Gam[:-m], Gam[m:], driver="gelsd").solution
    if stable and float(torch.linalg.eigvals(A).abs().max()) >= 1.0:
        shifted = torch.cat([Gam[m:], Gam.new_zeros(m, Gam.shape[-1])], 0)
        A = torch.linalg.lstsq(Gam, shifted, driver="gelsd").solution
    return A


def subspace_identify(
    y: Tensor | Sequence[Tensor],
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    order: int,
    block_rows: int | None = None,
    feedthrough: bool = False,
    stable: bool = False,
) -> SubspaceFit:
    """Identify a linear-Gaussian model of order ``order`` by N4SID (see the module docstring).

    Args:
        y: measurements ``(..., T, m)`` or a list of ``(T_i, m)`` (complete, no NaN).
        u: inputs ``(..., T, nu)``, a list of ``(T_i, nu)``, or ``None`` (no input).
        order: the state dimension ``n`` (see :func:`subspace_order`).
        block_rows: block rows ``i`` of the Hankel matrices (default from ``order`` and ``m``;
            more rows: less bias, more cost).
        feedthrough: estimate the feed-through ``D`` (else the model has none).
        stable: for a plant known to be stable: when the shift-invariance estimate of ``A``
            has an eigenvalue on or outside the unit circle, estimate it again with ``m`` zero
            rows appended to the shifted observability matrix (Maciejowski 1995), whose
            eigenvalues lie inside it (on it only in degenerate cases). The price is a bias
            towards zero (on the robot-arm log the slowest pole moved from 0.994 to 0.954),
            which EM or a likelihood fit removes;
            a stable estimate is kept as it is. Default ``False``: the estimate as it comes.

    Returns:
        A :class:`SubspaceFit` in float64: the model (``B`` only with inputs, ``D`` only with
        ``feedthrough``), the prior mean per recording ``(R, n)`` and covariance ``(n, n)``.

    Raises:
        InputError: missing data, recordings too short, or a bad ``order`` or ``block_rows``.
        ShapeError: ``y`` and ``u`` of mismatched shapes.
        ModelError: the identified transition matrix is singular (no ``H = C A^{-1}``).
    """
    ys0 = _series(y, "y")
    assert ys0 is not None
    m = ys0[0].shape[1]
    i = default_block_rows(order, m) if block_rows is None else block_rows
    ys, us = _data(ys0, u, i)
    p = us[0].shape[1]
    if not 1 <= order <= i * m - 1:
        raise InputError(f"order must be in 1..{i * m - 1} for block_rows={i}, got {order}")
    n = order
    O_i = _projection(ys, us, i)
    Uo, s, _ = torch.linalg.svd(O_i, full_matrices=False)
    Gam = Uo[:, :n] * s[:n].sqrt()  # extended observability matrix [C; C A; ...]
    A = _shift_invariance(Gam, m, stable=stable)
    C = Gam[:m]
    Bp, Dp, x0s, res = _input_maps(A, C, ys, us)
    if float(torch.linalg.svdvals(A).min()) <= 1e-12 * float(torch.linalg.svdvals(A).max()):
        raise ModelError("subspace_identify: the identified A is singular; try another order")
    if feedthrough or p == 0:
        H = torch.linalg.solve(A.mT, C.mT).mT
    else:  # no feed-through: also H B = D' (least squares on both)
        AB = torch.cat([A, Bp], -1)
        H = torch.linalg.lstsq(AB.mT, torch.cat([C, Dp], -1).mT, driver="gelsd").solution.mT
    B = Bp if p > 0 else None
    D = Dp - H @ Bp if (feedthrough and p > 0) else None
    Q, R = _noise(A, H, res, i)
    stable = float(torch.linalg.eigvals(A).abs().max()) < 1.0
    P0 = _lyap(A, Q) if stable else Q.clone()
    P0 = 0.5 * (P0 + P0.mT)
    model = LinearGaussianModel(A, H, Q, R, B, D)
    return SubspaceFit(model, x0s, P0, s)


def _gauge(H_s: Tensor, H_u: Tensor) -> Tensor:
    """An invertible ``M`` with ``H_s M = H_u`` on the known rows (``x' = M^{-1} x``)."""
    n = H_s.shape[1]
    Zs = torch.linalg.svd(H_s, full_matrices=True)[2][torch.linalg.matrix_rank(H_s) :].mT
    Wu = torch.linalg.svd(H_u, full_matrices=True)[2][torch.linalg.matrix_rank(H_u) :]
    if Zs.shape[1] != Wu.shape[0]:
        raise ModelError(
            "subspace_start: the known rows of H have another rank in the identified model; "
            "the gauge cannot be matched"
        )
    M = torch.linalg.pinv(H_s) @ H_u + Zs @ Wu
    assert M.shape == (n, n)
    return M


def subspace_start(
    model: StateSpaceModel,
    y: Tensor | Sequence[Tensor],
    u: Tensor | Sequence[Tensor] | None = None,
    *,
    known_channels: Sequence[int],
    block_rows: int | None = None,
    stable: bool = False,
) -> SubspaceFit:
    """A subspace start for a linear EM or likelihood fit, in the gauge of ``model``.

    Identifies a model of ``model``'s state dimension by :func:`subspace_identify` (with a
    feed-through when ``model`` has one) and changes its state coordinates so that the rows of
    ``H`` of ``known_channels`` equal ``model``'s (the gauge of
    :func:`~torchfilt.training.check_gauge`); the likelihood is unchanged by the change of
    coordinates. Then ``fit_em(start.model, y, u, x0=start.x0, P0=start.P0,
    known_channels=...)`` refines it.

    Args:
        model: the linear model to be fitted (:func:`~torchfilt.models.linear_system` returns
            its matrices); only its dimensions, ``D``'s presence and the known rows of ``H``
            are used.
        y: measurements ``(..., T, m)`` or a list of ``(T_i, m)`` (complete, no NaN).
        u: inputs ``(..., T, nu)``, a list, or ``None``.
        known_channels: the channels whose rows of ``H`` are known.
        block_rows: of :func:`subspace_identify`.
        stable: of :func:`subspace_identify` (for a plant known to be stable).

    Returns:
        A :class:`SubspaceFit` whose model's known rows of ``H`` are ``model``'s (float64).

    Raises:
        ModelError: ``model`` is not linear, or the gauge cannot be matched.
        InputError: as :func:`subspace_identify`, or a channel out of range.
    """
    sys = linear_system(model)
    if sys is None:
        raise ModelError("subspace_start: the model is not linear (linear_system returns None)")
    known = sorted(int(c) for c in known_channels)
    m = sys.H.shape[-2]
    if not known or any(not 0 <= c < m for c in known):
        raise InputError(f"known_channels: expected indices in 0..{m - 1}, got {known}")
    fit = subspace_identify(
        y,
        u,
        order=sys.A.shape[-1],
        block_rows=block_rows,
        feedthrough=sys.D is not None,
        stable=stable,
    )
    est = fit.model
    M = _gauge(est.H[known], sys.H.detach().to(f64)[known])

    def inv(x: Tensor) -> Tensor:
        return torch.linalg.solve(M, x)

    A, H = inv(est.A @ M), est.H @ M
    H[known] = sys.H.detach().to(f64)[known]
    Q = inv(inv(est.transition.noise_cov()).mT)  # type: ignore[arg-type]
    B = None if est.B is None else inv(est.B)
    out = LinearGaussianModel(A, H, 0.5 * (Q + Q.mT), est.measurement.noise_cov(), B, est.D)  # type: ignore[arg-type]
    P0 = inv(inv(fit.P0).mT)
    return SubspaceFit(out, inv(fit.x0.mT).mT, 0.5 * (P0 + P0.mT), fit.singular_values)
