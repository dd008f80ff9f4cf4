"""The open-loop prediction module of DMC as a steady-state Kalman filter (spec section 2).

On a realisation (:mod:`torchfilt.dmc.realization`)

    X(k) = A X(k-1) + B du(k-1) + Bv dv(k) + w(k-1),   w ~ N(0, Q_Y)
    y(k) = H X(k) + e(k),                               e ~ N(0, Q_y)

the predictor runs the steady-state filter (paper eq. (8)-(9), (16)-(17))

    X^-(k)   = A X(k-1|k-1) + B du(k-1) + Bv dv(k)
    eps(k)   = y(k) - H X^-(k)           ( = y(k) - y^ol(k|k-1) - S_1 du(k-1) )
    X(k|k)   = X^-(k) + K eps(k)

with ``K`` the gain of the DARE solution (:func:`~torchfilt.numerics.steady_state_kalman`), and hands
the controller ``Y^ol_N(k|k) = [y^ol(k+1|k); ...; y^ol(k+N|k)]``, shape ``(N, ny)``. The classical DMC
prediction with constant output correction is the same recursion with a fixed gain ``K = h``
(:meth:`OpenLoopPredictor.classical`).

Missing measurements follow the library's one rule (:mod:`torchfilt.numerics.missing`, the same as
the CKF's): a non-finite ``y`` component (NaN or +-inf) is missing, that CV is not corrected at that
sample, and its innovation is NaN. Moves, disturbances, states, ``x0`` and the gain must be finite.

Time convention of one step: at sample ``k`` the inputs are the measurement ``y(k)``, the move applied
at the previous sample ``du(k-1) = u(k-1) - u(k-2)``, and the measured disturbance change
``dv(k) = v(k) - v(k-1)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchfilt.dmc.realization import Realization, lmg_realization, realize
from torchfilt.dmc.step_response import StepResponseModel
from torchfilt.exceptions import InputError, ShapeError
from torchfilt.numerics import check_real_tensor, observed, steady_state_kalman

__all__ = ["LMGPredictor", "OpenLoopPredictor", "PredictorRun"]


class PredictorRun(NamedTuple):
    """Result of an offline run over a recording of ``T`` samples.

    Attributes:
        states: filtered states ``X(k|k)``, shape ``(..., T, n)``.
        predictions: ``y^ol(k+i|k)`` at ``[..., k, i - 1, :]``, ``i = 1..N``, shape ``(..., T, N, ny)``.
        innovations: ``eps(k)``, shape ``(..., T, ny)`` (NaN where ``y`` was missing).
    """

    states: Tensor
    predictions: Tensor
    innovations: Tensor


def _as_tensor(value: Any, name: str, dtype: torch.dtype) -> Tensor:
    """``value`` as a tensor of ``dtype`` under the dtype rule (:mod:`torchfilt.numerics.dtypes`)."""
    if isinstance(value, Tensor):
        check_real_tensor(value, name, integers=True)
    try:
        return torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{name}: expected real numbers, got {type(value).__name__}") from None


def _finite(t: Tensor, name: str, why: str = "") -> None:
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} contains non-finite entries{why}")


def _as_cov(value: Any, n: int, name: str, dtype: torch.dtype) -> Tensor:
    t = _as_tensor(value, name, dtype)
    if t.dim() == 0:
        t = t * torch.eye(n, dtype=dtype)
    elif t.dim() == 1:
        if t.shape[0] != n:
            raise ShapeError(
                f"{name}: expected a scalar, ({n},) or ({n}, {n}), got {tuple(t.shape)}"
            )
        t = torch.diag(t)
    elif t.shape != (n, n):
        raise ShapeError(f"{name}: expected a scalar, ({n},) or ({n}, {n}), got {tuple(t.shape)}")
    _finite(t, name)
    if not torch.allclose(t, t.mT):
        raise InputError(f"{name} is not symmetric")
    return t


def _check_model(model: Any) -> None:
    if not isinstance(model, StepResponseModel):
        raise InputError(
            f"model must be a StepResponseModel (e.g. StepResponseModel.from_transfer_functions), "
            f"got {type(model).__name__}"
        )


def _block_diagonal(Q: Tensor, blocks: tuple[tuple[int, int], ...]) -> bool:
    mask = torch.zeros_like(Q, dtype=torch.bool)
    for s, L in blocks:
        mask[s : s + L, s : s + L] = True
    return not bool(Q[~mask].any())


def _is_diagonal(Q: Tensor) -> bool:
    return not bool((Q - torch.diag(Q.diagonal())).any())


def steady_gain(real: Realization, Q_Y: Tensor, Q_y: Tensor) -> Tensor:
    """Steady-state Kalman gain of a realisation.

    When ``Q_Y`` is block-diagonal over the CV blocks and ``Q_y`` diagonal the DARE decouples into one
    small DARE per CV; those are solved as a batch (one per block size), otherwise the full one.

    Args:
        real: the realisation (:func:`~torchfilt.dmc.realize` or
            :func:`~torchfilt.dmc.lmg_realization`).
        Q_Y: state (process) noise covariance, shape ``(n, n)``.
        Q_y: measurement noise covariance, shape ``(ny, ny)``.

    Returns:
        The gain, shape ``(n, ny)``.

    Raises:
        NotDetectableError: from the DARE solver.
    """
    n, ny = real.state_dim, real.H.shape[0]
    if not (_block_diagonal(Q_Y, real.blocks) and _is_diagonal(Q_y)):
        return steady_state_kalman(real.A, real.H, Q_Y, Q_y).gain
    K = Q_Y.new_zeros(n, ny)
    sizes = sorted({L for _, L in real.blocks})
    for size in sizes:
        cvs = [j for j, (_, L) in enumerate(real.blocks) if L == size]
        idx = [torch.arange(real.blocks[j][0], real.blocks[j][0] + size) for j in cvs]
        A = torch.stack([real.A[i][:, i] for i in idx])
        C = torch.stack([real.H[j : j + 1, i] for j, i in zip(cvs, idx, strict=True)])
        Q = torch.stack([Q_Y[i][:, i] for i in idx])
        R = torch.stack([Q_y[j : j + 1, j : j + 1] for j in cvs])
        gains = steady_state_kalman(A, C, Q, R).gain  # (len(cvs), size, 1)
        for g, j, i in zip(gains, cvs, idx, strict=True):
            K[i, j] = g[:, 0]
    return K


class OpenLoopPredictor:
    """DMC open-loop prediction by a steady-state Kalman filter (ours: Xie, Ding & Chen 2016).

    Missing data: a non-finite measurement component (NaN, +-inf) is missing, as in the CKF
    (:mod:`torchfilt.numerics.missing`); that CV is not corrected at that sample. Non-finite moves,
    disturbances, states, ``x0``, gains or covariances are an
    :class:`~torchfilt.exceptions.InputError`.

    Args:
        model: the step-response model; its ``integrating`` flags choose each CV's layout.
        Q_Y: state (process) noise covariance, a scalar (``q I``), the diagonal ``(n,)`` or the
            matrix ``(n, n)`` in the CV-major state order of :func:`~torchfilt.dmc.realize`.
        Q_y: measurement noise covariance, a scalar, ``(ny,)`` or ``(ny, ny)``.
        gain: a fixed gain ``(n, ny)`` instead of the Kalman gain (then ``Q_Y``/``Q_y`` are unused).
        horizon: model horizon ``N``; default ``model.horizon``.

    Raises:
        NotDetectableError: the realisation with these covariances has no stabilising DARE solution.
        InputError: ``model`` is not a :class:`StepResponseModel`, both or neither of ``gain`` and
            the covariances, a non-finite gain, or a covariance that is not real, finite and
            symmetric.
        ShapeError: a gain that is not ``(n, ny)``, or a covariance of the wrong size.

    Example:
        >>> import torch
        >>> from torchfilt.dmc import FOPDT, StepResponseModel, OpenLoopPredictor
        >>> m = StepResponseModel.from_transfer_functions([[FOPDT(2.0, 5.0, 1.5)]], dt=1.0, horizon=30)
        >>> pred = OpenLoopPredictor(m, Q_Y=0.5, Q_y=1.0)
        >>> pred.update(torch.tensor([0.0]), du=torch.tensor([1.0])).shape
        torch.Size([30, 1])
    """

    realization: Realization
    gain: Tensor

    def __init__(
        self,
        model: StepResponseModel,
        Q_Y: float | Tensor | None = None,
        Q_y: float | Tensor | None = None,
        *,
        gain: Tensor | None = None,
        horizon: int | None = None,
    ) -> None:
        _check_model(model)
        self.model = model
        self.realization = self._realizer(model, horizon)
        n, ny = self.realization.state_dim, model.ny
        dtype = model.dtype
        self.Q_Y: Tensor | None = None
        self.Q_y: Tensor | None = None
        if gain is not None:
            if Q_Y is not None or Q_y is not None:
                raise InputError("give either gain or the covariances Q_Y and Q_y, not both")
            K = _as_tensor(gain, "gain", dtype)
            if K.shape != (n, ny):
                raise ShapeError(f"gain: expected shape ({n}, {ny}), got {tuple(K.shape)}")
            _finite(K, "gain")
            self.gain = K
        else:
            if Q_Y is None or Q_y is None:
                raise InputError("give the covariances Q_Y and Q_y (or a fixed gain)")
            self.Q_Y = self._state_cov(_as_cov(Q_Y, self._cov_dim, "Q_Y", dtype))
            self.Q_y = _as_cov(Q_y, ny, "Q_y", dtype)
            self.gain = steady_gain(self.realization, self.Q_Y, self.Q_y)
        self._state = self.initial_state()

    # -------------------------------------------------------------- variants
    _realizer = staticmethod(realize)

    @property
    def _cov_dim(self) -> int:
        return self.realization.state_dim

    def _state_cov(self, Q: Tensor) -> Tensor:
        return Q

    @classmethod
    def classical(
        cls, model: StepResponseModel, h: float | Tensor = 1.0, *, horizon: int | None = None
    ) -> OpenLoopPredictor:
        """Classical DMC prediction: output correction with a constant gain (no Kalman filter).

            Y(k|k) = A Y(k-1|k-1) + B du(k-1) + Bv dv(k) + h eps(k)

        The default ``h = 1`` shifts every prediction of a CV by its whole prediction error, the
        correction of the original (double-layered) DMC.

        Args:
            model: the step-response model.
            h: correction weights, a scalar or a vector with one weight per element of a CV block
                (length ``N + 1`` or ``N + 2``; all CVs must then use the same layout).
            horizon: model horizon ``N``.

        Returns:
            The predictor, with the gain that applies ``h`` to each CV's block.

        Raises:
            InputError: ``model`` is not a :class:`StepResponseModel`, or ``h`` not finite.
            ShapeError: ``h`` is neither a scalar nor one weight per element of each CV block.
        """
        _check_model(model)
        real = cls._realizer(model, horizon)
        K = torch.zeros(real.state_dim, model.ny, dtype=model.dtype)
        h_t = _as_tensor(h, "h", model.dtype)
        _finite(h_t, "h")
        for j, (s, L) in enumerate(real.blocks):
            if h_t.dim() == 0:
                K[s : s + L, j] = h_t
            elif h_t.shape == (L,):
                K[s : s + L, j] = h_t
            else:
                raise ShapeError(
                    f"h: expected a scalar or shape ({L},) for CV {j}, got {tuple(h_t.shape)}"
                )
        return cls(model, gain=K, horizon=horizon)

    # -------------------------------------------------------------- state helpers
    @property
    def error_dynamics(self) -> Tensor:
        """Error dynamics ``(I - K H) A``, shape ``(n, n)``.

        Without noise the estimation error evolves as ``e(k) = (I - K H) A e(k-1)``; the spectral
        radius of this matrix sets how fast a wrong initial estimate is forgotten.
        """
        r = self.realization
        return r.A - self.gain @ (r.H @ r.A)

    @property
    def horizon(self) -> int:
        """The model horizon ``N``."""
        return self.realization.horizon

    @property
    def state_dim(self) -> int:
        """The state dimension ``n`` of the realisation."""
        return self.realization.state_dim

    def initial_state(self, level: float | Tensor = 0.0) -> Tensor:
        """A state at rest: every prediction of CV ``j`` equal to ``level_j`` (zero slope).

        Args:
            level: a scalar or one value per CV, shape ``(ny,)``.

        Returns:
            The state, shape ``(n,)``.

        Raises:
            InputError: ``level`` not finite.
        """
        lv = _as_tensor(level, "level", self.model.dtype)
        _finite(lv, "level")
        lv = lv.expand(self.model.ny)
        x = torch.zeros(self.state_dim, dtype=self.model.dtype)
        for j, (s, L) in enumerate(self.realization.blocks):
            x[s : s + L] = lv[j]
        if self.realization.embedding is not None:  # x_p = 0 at rest
            for s, L in self.realization.blocks:
                x[s + L - 1] = 0.0
        return x

    def predictions(self, state: Tensor) -> Tensor:
        """The open-loop predictions ``Y^ol_N(k|k) = [y^ol(k+1|k); ...; y^ol(k+N|k)]``.

        Args:
            state: states ``X(k|k)``, shape ``(..., n)``.

        Returns:
            The predictions, shape ``(..., N, ny)``.
        """
        return state[..., self.realization.pred_index]

    def current(self, state: Tensor) -> Tensor:
        """The filtered outputs ``y^ol(k|k)``.

        Args:
            state: states ``X(k|k)``, shape ``(..., n)``.

        Returns:
            The outputs, shape ``(..., ny)``.
        """
        return state @ self.realization.H.mT

    # -------------------------------------------------------------- the filter
    def _inputs(
        self, y: Tensor, du: Tensor | None, dv: Tensor | None, *, time: bool
    ) -> tuple[Tensor, Tensor, Tensor]:
        m = self.model
        dtype = m.dtype
        t = "T, " if time else ""
        y = _as_tensor(y, "y", dtype)
        need = 2 if time else 1
        if y.dim() < need or y.shape[-1] != m.ny:
            raise ShapeError(
                f"y: expected shape (..., {t}ny) with ny = {m.ny}, got {tuple(y.shape)}"
            )
        lead = y.shape[:-1]
        if du is None:
            du_t = y.new_zeros(*lead, m.nu)
        else:
            du_t = _as_tensor(du, "du", dtype)
            if du_t.dim() < need or du_t.shape[-1] != m.nu:
                raise ShapeError(
                    f"du: expected shape (..., {t}nu) with nu = {m.nu}, got {tuple(du_t.shape)}"
                )
        if dv is None:
            dv_t = y.new_zeros(*lead, m.nv)
        else:
            dv_t = _as_tensor(dv, "dv", dtype)
            if dv_t.dim() < need or dv_t.shape[-1] != m.nv:
                raise ShapeError(
                    f"dv: expected shape (..., {t}nv) with nv = {m.nv}, got {tuple(dv_t.shape)}"
                )
        if time:
            T = y.shape[-2]
            if T == 0:
                raise ShapeError(
                    f"y: the time dimension T must be at least 1, got {tuple(y.shape)}"
                )
            for name, a in (("du", du_t), ("dv", dv_t)):
                if a.shape[-2] != T:
                    raise ShapeError(f"{name}: has {a.shape[-2]} samples but y has {T}")
        for name, a in (("du", du_t), ("dv", dv_t)):
            _finite(a, name, "; inputs cannot be missing")
        return y, du_t, dv_t

    def _state_arg(self, value: Any, name: str, lead: tuple[torch.Size, ...]) -> Tensor:
        """A state argument ``(..., n)``: finite, and its batch broadcasting with ``lead``."""
        x = _as_tensor(value, name, self.model.dtype)
        if x.dim() < 1 or x.shape[-1] != self.state_dim:
            raise ShapeError(
                f"{name}: expected shape (..., n) with n = {self.state_dim}, got {tuple(x.shape)}"
            )
        _finite(x, name)
        try:
            torch.broadcast_shapes(x.shape[:-1], *lead)
        except RuntimeError:
            raise ShapeError(
                f"{name}: batch shape {tuple(x.shape[:-1])} does not broadcast with the data's "
                f"{', '.join(str(tuple(s)) for s in lead)}"
            ) from None
        return x

    def _advance(self, x: Tensor, y: Tensor, du: Tensor, dv: Tensor) -> tuple[Tensor, Tensor]:
        r = self.realization
        xp = x @ r.A.mT + du @ r.B.mT + dv @ r.Bv.mT
        eps = y - xp @ r.H.mT
        obs = observed(y)  # the missing-data rule: non-finite = missing
        correction = torch.where(obs, eps, torch.zeros_like(eps))
        return xp + correction @ self.gain.mT, torch.where(obs, eps, torch.nan)

    def step(
        self, state: Tensor, y: Tensor, du: Tensor | None = None, dv: Tensor | None = None
    ) -> Tensor:
        """One filter step (pure function; batches over leading dimensions).

        Args:
            state: ``X(k-1|k-1)``, shape ``(..., n)``.
            y: measurement ``y(k)``, shape ``(..., ny)``; a non-finite entry (NaN, +-inf) is
                missing and skips that CV's correction.
            du: last move ``du(k-1)``, shape ``(..., nu)``; ``None`` for no move.
            dv: disturbance change ``dv(k)``, shape ``(..., nv)``; ``None`` for none.

        Returns:
            ``X(k|k)``, shape ``(..., n)``.

        Raises:
            ShapeError: an argument whose shape is not the one given above, or batch shapes that
                do not broadcast.
            InputError: a non-finite state, move or disturbance.
        """
        y, du_t, dv_t = self._inputs(y, du, dv, time=False)
        state = self._state_arg(state, "state", (y.shape[:-1], du_t.shape[:-1], dv_t.shape[:-1]))
        return self._advance(state, y, du_t, dv_t)[0]

    def run(
        self,
        y: Tensor,
        du: Tensor | None = None,
        dv: Tensor | None = None,
        *,
        x0: Tensor | None = None,
    ) -> PredictorRun:
        """Offline run over a whole recording (batched over leading dimensions).

        Row ``k`` of the inputs is sample ``k``: ``y[..., k, :] = y(k)``,
        ``du[..., k, :] = du(k-1)`` (the move applied at the previous sample),
        ``dv[..., k, :] = dv(k)``.

        Args:
            y: measurements, shape ``(..., T, ny)``, ``T >= 1``; a non-finite entry (NaN, +-inf) is
                missing: that CV is not corrected at that sample and its innovation is NaN.
            du: moves, shape ``(..., T, nu)``, or ``None`` (no moves).
            dv: disturbance changes, shape ``(..., T, nv)``, or ``None``.
            x0: state ``X(-1|-1)`` before the first sample, shape ``(..., n)``; default at rest at 0.

        Returns:
            A :class:`PredictorRun` with states ``(..., T, n)``, predictions ``(..., T, N, ny)`` and
            innovations ``(..., T, ny)``.

        Raises:
            ShapeError: an argument whose shape is not the one given above, ``T = 0``, or batch
                shapes that do not broadcast.
            InputError: a non-finite ``x0``, move or disturbance.
        """
        y, du_t, dv_t = self._inputs(y, du, dv, time=True)
        lead = (y.shape[:-2], du_t.shape[:-2], dv_t.shape[:-2])
        x = self.initial_state() if x0 is None else self._state_arg(x0, "x0", lead)
        try:
            torch.broadcast_shapes(*lead)
        except RuntimeError:
            desc = ", ".join(
                f"{k} {tuple(v)}" for k, v in zip(("y", "du", "dv"), lead, strict=True)
            )
            raise ShapeError(f"batch shapes do not broadcast: {desc}") from None
        batch = torch.broadcast_shapes(y.shape[:-2], du_t.shape[:-2], dv_t.shape[:-2], x.shape[:-1])
        T = y.shape[-2]
        x = x.expand(*batch, self.state_dim)
        states, innov = [], []
        for k in range(T):
            x, eps = self._advance(x, y[..., k, :], du_t[..., k, :], dv_t[..., k, :])
            states.append(x)
            innov.append(eps.expand(*batch, self.model.ny))
        X = torch.stack(states, dim=-2)
        return PredictorRun(X, self.predictions(X), torch.stack(innov, dim=-2))

    # -------------------------------------------------------------- online use
    @property
    def state(self) -> Tensor:
        """The current ``X(k|k)`` of the online predictor, shape ``(n,)``."""
        return self._state

    def reset(self, state: Tensor | None = None, *, level: float | Tensor = 0.0) -> None:
        """Restart the online predictor from ``state`` or at rest at ``level``.

        Args:
            state: the new ``X(k|k)``, shape ``(n,)``; ``None`` for a state at rest.
            level: the rest level (when ``state`` is ``None``), a scalar or shape ``(ny,)``.

        Raises:
            ShapeError: ``state`` is not ``(n,)``.
            InputError: ``state`` or ``level`` not finite.
        """
        if state is None:
            self._state = self.initial_state(level)
            return
        s = _as_tensor(state, "state", self.model.dtype)
        if s.shape != (self.state_dim,):
            raise ShapeError(f"state: expected shape ({self.state_dim},), got {tuple(s.shape)}")
        _finite(s, "state")
        self._state = s.clone()

    def update(self, y: Tensor, du: Tensor | None = None, dv: Tensor | None = None) -> Tensor:
        """Online step: consume ``y(k)``, ``du(k-1)``, ``dv(k)``; return the predictions.

        Args:
            y: measurement ``y(k)``, shape ``(ny,)``; a non-finite entry is missing (no correction
                of that CV).
            du: the move applied at the previous sample, shape ``(nu,)``; ``None`` for none.
            dv: disturbance change ``dv(k)``, shape ``(nv,)``; ``None`` for none.

        Returns:
            ``Y^ol_N(k|k)``, shape ``(N, ny)``: row ``i - 1`` is ``y^ol(k+i|k)``.

        Raises:
            ShapeError: ``y``, ``du`` or ``dv`` of the wrong shape.
            InputError: a non-finite move or disturbance.
        """
        y_t = _as_tensor(y, "y", self.model.dtype)
        if y_t.shape != (self.model.ny,):
            raise ShapeError(f"y: expected shape ({self.model.ny},), got {tuple(y_t.shape)}")
        self._state = self.step(self._state, y_t, du, dv)
        return self.predictions(self._state)


class LMGPredictor(OpenLoopPredictor):
    """The Lee-Morari-Garcia (1994) realisation with the paper's section-2 corrections.

    Same filter, on :func:`~torchfilt.dmc.lmg_realization`. ``Q_Y`` is given in *our* state
    coordinates and mapped to the LMG state as ``T Q_Y T^T`` (the paper's parameter setting: ``x_p`` is
    the slope of the prediction tail, so its noise is the difference of the tail noises); the
    predictions then equal :class:`OpenLoopPredictor`'s.

    Args:
        model: the step-response model.
        Q_Y: state noise in our coordinates (scalar, ``(n_ours,)`` or ``(n_ours, n_ours)``).
        Q_y: measurement noise, scalar, ``(ny,)`` or ``(ny, ny)``.
        gain: a fixed gain in LMG coordinates ``(n_lmg, ny)`` instead.
        horizon: model horizon ``N``.

    Raises:
        NotDetectableError: the realisation with these covariances has no stabilising DARE solution.
        InputError: invalid arguments, as for :class:`OpenLoopPredictor`.
        ShapeError: a gain or covariance of the wrong size.
    """

    _realizer = staticmethod(lmg_realization)

    @property
    def _cov_dim(self) -> int:
        T = self.realization.embedding
        assert T is not None
        return int(T.shape[1])

    def _state_cov(self, Q: Tensor) -> Tensor:
        T = self.realization.embedding
        assert T is not None
        return T @ Q @ T.mT
