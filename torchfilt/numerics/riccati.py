"""The filter-form discrete algebraic Riccati equation (DARE) and the steady-state Kalman gain.

For the linear time-invariant model

    x_{k+1} = A x_k + w_k,   w_k ~ N(0, Q)
    y_k     = C x_k + v_k,   v_k ~ N(0, R)

the steady-state one-step *predicted* covariance ``Sigma = lim Cov(x_k | y_{1:k-1})`` solves

    Sigma = A [Sigma - Sigma C^T (C Sigma C^T + R)^{-1} C Sigma] A^T + Q,

and the steady-state (filter) gain is ``K = Sigma C^T (C Sigma C^T + R)^{-1}``. A stabilising solution
(the one with ``A (I - K C)`` stable) exists and is unique when ``(A, C)`` is detectable and
``(A, Q^{1/2})`` is stabilisable. Both conditions are checked with the Popov-Belevitch-Hautus (PBH)
rank test on every eigenvalue of ``A`` on or outside the unit circle. A failure raises
:class:`~torchfilt.exceptions.NotDetectableError` naming the mode; garbage is never returned.

The equation is solved by ``scipy.linalg.solve_discrete_are`` (Laub's generalised Schur method) on
the dual pair ``(A^T, C^T)``, one problem at a time over a batch, followed by one Newton (Kleinman)
refinement step (kept only where it lowers the residual). Its only caller in the library
computes one gain per predictor on small float64 CPU problems, so a batched hand-written solver bought
nothing there; the result is detached (not differentiable). Around it this module keeps what scipy
does not do: the PBH checks that turn a non-detectable or non-stabilisable pair into a clear error
before solving, and a check of the Riccati residual and of closed-loop stability after.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.linalg
import torch
from torch import Tensor

from torchfilt.exceptions import InputError, NotDetectableError, ShapeError
from torchfilt.numerics.dtypes import check_real_tensor
from torchfilt.numerics.linalg import psd_solve, symmetrize

__all__ = ["SteadyStateKalman", "check_detectable", "solve_dare", "steady_state_kalman"]

#: Eigenvalues with ``|lambda| >= 1 - UNIT_CIRCLE_MARGIN`` are treated as marginal or unstable
#: and must pass the PBH test. Nilpotent shift chains (as in step-response realisations) have
#: eigenvalues that rounding scatters on a circle of radius ``eps**(1/N)``, well inside this margin.
UNIT_CIRCLE_MARGIN = 1e-6
#: A PBH matrix whose smallest singular value is below ``PBH_RTOL * scale`` is rank deficient.
PBH_RTOL = 1e-9
#: Relative residual of the Riccati equation accepted from the solver.
RESIDUAL_RTOL = 1e-8
#: Relative asymmetry tolerated in ``Q`` and ``R``.
SYMMETRY_RTOL = 1e-10


class SteadyStateKalman(NamedTuple):
    """Steady-state Kalman filter of a linear time-invariant model.

    Attributes:
        gain: filter gain ``K = Sigma C^T (C Sigma C^T + R)^{-1}``, shape ``(..., n, m)``.
        pred_cov: steady-state predicted covariance ``Sigma``, shape ``(..., n, n)``.
        filt_cov: steady-state filtered covariance ``(I - K C) Sigma``, shape ``(..., n, n)``.
        innov_cov: innovation covariance ``C Sigma C^T + R``, shape ``(..., m, m)``.
    """

    gain: Tensor
    pred_cov: Tensor
    filt_cov: Tensor
    innov_cov: Tensor


def _check_square(M: Tensor, name: str, n: int | None = None) -> None:
    if M.dim() < 2 or M.shape[-1] != M.shape[-2] or (n is not None and M.shape[-1] != n):
        want = "(..., n, n)" if n is None else f"(..., {n}, {n})"
        raise ShapeError(f"{name}: expected a square matrix {want}, got {tuple(M.shape)}")


def _check_inputs(A: Tensor, C: Tensor, Q: Tensor, R: Tensor) -> tuple[Tensor, ...]:
    for name, M in (("A", A), ("C", C), ("Q", Q), ("R", R)):
        if not isinstance(M, Tensor):
            raise InputError(f"{name} must be a torch.Tensor, got {type(M).__name__}")
        check_real_tensor(M, name)
        if not bool(torch.isfinite(M).all()):
            raise InputError(f"{name} contains non-finite entries")
    _check_square(A, "A")
    n = A.shape[-1]
    if C.dim() < 2 or C.shape[-1] != n:
        raise ShapeError(f"C: expected shape (..., m, {n}), got {tuple(C.shape)}")
    m = C.shape[-2]
    _check_square(Q, "Q", n)
    _check_square(R, "R", m)
    for name, M in (("Q", Q), ("R", R)):
        scale = M.abs().amax().clamp_min(1.0)
        if not torch.allclose(M, M.mT, rtol=0.0, atol=float(scale) * SYMMETRY_RTOL):
            raise InputError(f"{name} is not symmetric")
    ev_r = torch.linalg.eigvalsh(symmetrize(R))
    if bool((ev_r[..., 0] <= 0).any()):
        raise InputError(
            f"R must be positive definite; smallest eigenvalue {float(ev_r[..., 0].min()):.3e}"
        )
    ev_q = torch.linalg.eigvalsh(symmetrize(Q))
    qscale = ev_q[..., -1].abs().clamp_min(torch.finfo(Q.dtype).tiny)
    if bool((ev_q[..., 0] < -math.sqrt(torch.finfo(Q.dtype).eps) * qscale).any()):
        raise InputError(
            f"Q must be positive semi-definite; smallest eigenvalue {float(ev_q[..., 0].min()):.3e}"
        )
    dtype = torch.promote_types(torch.promote_types(A.dtype, C.dtype), Q.dtype)
    dtype = torch.promote_types(dtype, R.dtype)
    try:
        batch = torch.broadcast_shapes(A.shape[:-2], C.shape[:-2], Q.shape[:-2], R.shape[:-2])
    except RuntimeError:
        desc = ", ".join(
            f"{k} {tuple(M.shape[:-2])}" for k, M in zip("ACQR", (A, C, Q, R), strict=True)
        )
        raise ShapeError(f"batch shapes do not broadcast: {desc}") from None
    return tuple(M.to(dtype).expand(*batch, *M.shape[-2:]) for M in (A, C, Q, R))


def _psd_sqrt(M: Tensor) -> Tensor:
    evals, evecs = torch.linalg.eigh(symmetrize(M))
    return evecs * evals.clamp_min(0.0).sqrt().unsqueeze(-2)


def _pbh_failures(A: Tensor, B: Tensor, *, columns: bool) -> list[complex]:
    """Eigenvalues ``lambda`` of ``A`` with ``|lambda| >= 1 - margin`` where the PBH matrix loses rank.

    ``columns=False`` tests ``[lambda I - A; B]`` (observability of the mode through ``B``);
    ``columns=True`` tests ``[lambda I - A, B]`` (controllability of the mode from ``B``).
    """
    n = A.shape[-1]
    evals = torch.linalg.eigvals(A)
    scale = max(float(torch.linalg.matrix_norm(A, ord=2)), float(B.abs().amax()), 1.0)
    eye = torch.eye(n, dtype=evals.dtype)
    Ac, Bc = A.to(evals.dtype), B.to(evals.dtype)
    bad: list[complex] = []
    seen: list[complex] = []
    for lam in evals.tolist():
        if abs(lam) < 1.0 - UNIT_CIRCLE_MARGIN:
            continue
        if any(abs(lam - s) <= math.sqrt(PBH_RTOL) for s in seen):
            continue  # a cluster (defective eigenvalue) is tested once
        seen.append(lam)
        P = lam * eye - Ac
        stacked = torch.cat([P, Bc], dim=-1 if columns else -2)
        smin = float(torch.linalg.svdvals(stacked)[n - 1])
        if smin <= PBH_RTOL * scale:
            bad.append(lam)
    return bad


def _fmt(lams: list[complex]) -> str:
    out = []
    for lam in lams[:4]:
        out.append(f"{lam.real:.6g}" if abs(lam.imag) < 1e-12 else f"{lam:.6g}")
    return ", ".join(out) + (" ..." if len(lams) > 4 else "")


def check_detectable(A: Tensor, C: Tensor, Q: Tensor | None = None) -> None:
    """Raise if ``(A, C)`` is not detectable or ``(A, Q^{1/2})`` is not stabilisable.

    PBH test: every eigenvalue ``lambda`` of ``A`` with ``|lambda| >= 1`` (within
    :data:`UNIT_CIRCLE_MARGIN`) must satisfy ``rank [lambda I - A; C] = n`` (the mode is seen by the
    measurements) and, when ``Q`` is given, ``rank [lambda I - A, Q^{1/2}] = n`` (the mode is excited
    by the process noise, so the steady-state filter keeps correcting it).

    Args:
        A: transition matrices, shape ``(..., n, n)``.
        C: measurement matrices, shape ``(..., m, n)``.
        Q: optional process-noise covariances, shape ``(..., n, n)``.

    Raises:
        NotDetectableError: naming the offending eigenvalues and, for a batch, the batch index.
    """
    n = A.shape[-1]
    batch = torch.broadcast_shapes(A.shape[:-2], C.shape[:-2], () if Q is None else Q.shape[:-2])
    Af = A.expand(*batch, n, n).reshape(-1, n, n)
    Cf = C.expand(*batch, *C.shape[-2:]).reshape(-1, *C.shape[-2:])
    Qf = None if Q is None else Q.expand(*batch, n, n).reshape(-1, n, n)
    for i in range(Af.shape[0]):
        where = f" (batch index {i})" if Af.shape[0] > 1 else ""
        bad = _pbh_failures(Af[i], Cf[i], columns=False)
        if bad:
            raise NotDetectableError(
                f"(A, C) is not detectable{where}: the mode(s) with eigenvalue {_fmt(bad)} of A "
                "lie on or outside the unit circle and are not observed through C (PBH rank test "
                "[lambda I - A; C] fails). No steady-state Kalman gain exists; add a measured "
                "state that sees these modes (e.g. the y(k|k) block of a step-response realisation)"
            )
        if Qf is not None:
            bad = _pbh_failures(Af[i], _psd_sqrt(Qf[i]), columns=True)
            if bad:
                raise NotDetectableError(
                    f"(A, Q^(1/2)) is not stabilisable{where}: the mode(s) with eigenvalue "
                    f"{_fmt(bad)} of A lie on or outside the unit circle and receive no process "
                    "noise (PBH rank test [lambda I - A, Q^(1/2)] fails). No stabilising "
                    "steady-state gain exists; give these modes process noise in Q"
                )


def solve_dare(
    A: Tensor,
    C: Tensor,
    Q: Tensor,
    R: Tensor,
    *,
    check: bool = True,
) -> Tensor:
    """Stabilising solution of the filter-form DARE (by ``scipy.linalg.solve_discrete_are`` and one
    Newton refinement step).

        Sigma = A [Sigma - Sigma C^T (C Sigma C^T + R)^{-1} C Sigma] A^T + Q

    (equal to ``scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)``, refined to a residual at
    rounding level).

    Args:
        A: transition matrices, shape ``(..., n, n)``.
        C: measurement matrices, shape ``(..., m, n)``.
        Q: process-noise covariances (PSD), shape ``(..., n, n)``.
        R: measurement-noise covariances (PD), shape ``(..., m, m)``.
        check: run the PBH detectability/stabilisability test first and verify the result
            (residual and closed-loop stability) afterwards.

    Returns:
        ``Sigma``, symmetric PSD, shape ``(..., n, n)`` (leading shapes broadcast).

    Raises:
        NotDetectableError: ``(A, C)`` not detectable or ``(A, Q^{1/2})`` not stabilisable, or the
            solver found no stabilising solution.
        ShapeError: inconsistent shapes (the message names the argument).
        InputError: a matrix that is not a real float tensor, has non-finite entries, or ``Q`` or
            ``R`` not symmetric, ``R`` not positive definite or ``Q`` not positive semi-definite.
    """
    A, C, Q, R = _check_inputs(A, C, Q, R)
    if check:
        check_detectable(A, C, Q)
    Sigma = _scipy_dare(A, C, Q, R)
    if check:
        _verify(A, C, Q, R, Sigma)
    return Sigma


def _scipy_dare(A: Tensor, C: Tensor, Q: Tensor, R: Tensor) -> Tensor:
    n, m = A.shape[-1], C.shape[-2]
    batch = A.shape[:-2]
    As = A.detach().reshape(-1, n, n).cpu().double().numpy()
    Cs = C.detach().reshape(-1, m, n).cpu().double().numpy()
    Qs = symmetrize(Q.detach()).reshape(-1, n, n).cpu().double().numpy()
    Rs = symmetrize(R.detach()).reshape(-1, m, m).cpu().double().numpy()
    out = []
    for i in range(As.shape[0]):
        try:
            X = scipy.linalg.solve_discrete_are(As[i].T, Cs[i].T, Qs[i], Rs[i])
        except (np.linalg.LinAlgError, ValueError) as err:
            where = f" (batch index {i})" if As.shape[0] > 1 else ""
            raise NotDetectableError(
                f"the Riccati equation has no stabilising solution{where}: {err} (a mode on the "
                "unit circle is undetectable or receives no process noise, within numerical "
                "precision)"
            ) from None
        out.append(_newton_refine(As[i], Cs[i], Qs[i], Rs[i], 0.5 * (X + X.T)))
    return torch.as_tensor(np.stack(out), dtype=A.dtype, device=A.device).reshape(*batch, n, n)


def _dare_residual(
    A: np.ndarray, C: np.ndarray, Q: np.ndarray, R: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``F(X) = A X A^T - L S L^T + Q - X`` (``S = C X C^T + R``, ``L = A X C^T S^{-1}``, the
    predictor gain) and the closed loop ``A - L C``."""
    S = C @ X @ C.T + R
    L = np.linalg.solve(S, C @ X @ A.T).T
    F = A @ X @ A.T - L @ S @ L.T + Q - X
    return 0.5 * (F + F.T), A - L @ C


def _newton_refine(
    A: np.ndarray, C: np.ndarray, Q: np.ndarray, R: np.ndarray, X: np.ndarray
) -> np.ndarray:
    """One Newton (Kleinman) step on a DARE solution, kept only if it lowers the residual.

    The Newton correction ``D`` solves the Stein equation ``Acl D Acl^T - D + F(X) = 0`` with the
    closed loop ``Acl = A - L C`` (stable at the stabilising solution); in this correction form the
    Stein solver's error scales with ``F(X)``, not with ``X``. scipy's generalised-Schur solution
    loses accuracy with the condition of the problem (relative residual 1e-10 and gain error
    ~1e-8 on 300-state step-response realisations); one step brings the residual to rounding.
    """
    F, Acl = _dare_residual(A, C, Q, R, X)
    if not (np.isfinite(F).all() and np.isfinite(Acl).all()):
        return X
    try:
        D = scipy.linalg.solve_discrete_lyapunov(Acl, F)
    except (np.linalg.LinAlgError, ValueError):
        return X  # a singular Stein equation: keep the solver's answer (_verify judges it)
    X1 = X + 0.5 * (D + D.T)
    F1, _ = _dare_residual(A, C, Q, R, X1)
    if np.isfinite(F1).all() and np.linalg.norm(F1) < np.linalg.norm(F):
        return X1
    return X


def _gain(Sigma: Tensor, C: Tensor, R: Tensor) -> tuple[Tensor, Tensor]:
    S = symmetrize(C @ Sigma @ C.mT + R)
    K = psd_solve(S, C @ Sigma, name="innovation covariance").mT
    return K, S


def _verify(A: Tensor, C: Tensor, Q: Tensor, R: Tensor, Sigma: Tensor) -> None:
    K, _ = _gain(Sigma, C, R)
    n = A.shape[-1]
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    rhs = A @ ((eye - K @ C) @ Sigma) @ A.mT + Q
    res = torch.linalg.matrix_norm(rhs - Sigma) / torch.linalg.matrix_norm(Sigma).clamp_min(1.0)
    if bool((res > RESIDUAL_RTOL).any()):
        raise NotDetectableError(
            f"the DARE solution has relative residual {float(res.max()):.2e}; the equation has no "
            "stabilising solution within numerical precision"
        )
    rho = torch.linalg.eigvals(A - A @ K @ C).abs().amax(-1)
    if bool((rho >= 1.0).any()):
        raise NotDetectableError(
            f"the steady-state filter is not stable (closed-loop spectral radius "
            f"{float(rho.max()):.6f}); (A, C) is not detectable or (A, Q^(1/2)) not stabilisable"
        )


def steady_state_kalman(
    A: Tensor,
    C: Tensor,
    Q: Tensor,
    R: Tensor,
    *,
    check: bool = True,
) -> SteadyStateKalman:
    """Steady-state Kalman filter: DARE solution, gain and covariances.

    Model and equation as in the module docstring; the filter built from the result is

        x^-_k = A x_{k-1} (+ known inputs),   x_k = x^-_k + K (y_k - C x^-_k).

    Args:
        A: transition matrices, shape ``(..., n, n)``.
        C: measurement matrices, shape ``(..., m, n)``.
        Q: process-noise covariances (PSD), shape ``(..., n, n)``.
        R: measurement-noise covariances (PD), shape ``(..., m, m)``.
        check: PBH test before and verification after (see :func:`solve_dare`).

    Returns:
        A :class:`SteadyStateKalman` with ``gain (..., n, m)`` and the covariances.

    Raises:
        NotDetectableError: no stabilising solution (non-detectable or non-stabilisable pair).
        ShapeError: inconsistent shapes (the message names the argument).
        InputError: invalid matrices, as in :func:`solve_dare`.
    """
    A, C, Q, R = _check_inputs(A, C, Q, R)
    if check:
        check_detectable(A, C, Q)
    Sigma = _scipy_dare(A, C, Q, R)
    if check:
        _verify(A, C, Q, R, Sigma)
    K, S = _gain(Sigma, C, R)
    n = A.shape[-1]
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    P = symmetrize((eye - K @ C) @ Sigma)
    return SteadyStateKalman(K, Sigma, P, S)
