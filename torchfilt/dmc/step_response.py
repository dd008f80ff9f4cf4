"""Step-response (finite step-response, FSR) models of DMC: MV and measured-DV channels.

Controlled variables (CVs) ``y in R^ny``, manipulated variables (MVs) ``u in R^nu`` and measured
disturbances (DVs) ``v in R^nv``. The model is a list of step-response coefficient matrices
``S^u_i (ny x nu)`` and ``S^v_i (ny x nv)``, ``i = 1, 2, ...`` (``S_0 = 0``: every channel is strictly
proper), with the superposition

    y(k) = sum_{i >= 1} S^u_i du(k - i) + sum_{i >= 1} S^v_i dv(k - i),

written in the prediction form DMC uses (spec section 1, eq. (2) and (5) of the paper):

    y^fr(k+p|k) - y^fr(k+p|k-1) = S^u_{p+1} du(k-1) + S^v_p dv(k),    p >= 0,

where ``du(k-1) = u(k-1) - u(k-2)`` is the last move and ``dv(k) = v(k) - v(k-1)`` the disturbance change
measured at time ``k``. Beyond the stored coefficients each CV follows its settling rule:

* stable CV:       ``S_{L+j} = S_L``                         for ``j >= 0``;
* integrating CV:  ``S_{L+j} = S_L + j (S_L - S_{L-1})``      (the slope ``R = S_L - S_{L-1}`` settled).

The model horizon ``N`` is what a realisation uses: stable CVs take ``S_1..S_N``, integrating CVs
``S_1..S_{N+1}``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from torchfilt.dmc.transfer import TransferEntry, _positive_int, as_entry
from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.models import LinearModel, StateSpaceModel

__all__ = ["DiscreteModel", "StepResponseModel"]


@runtime_checkable
class DiscreteModel(Protocol):
    """The interface :meth:`StepResponseModel.from_simulation` simulates steps through.

    ``step`` maps the state and the held inputs to the next state; ``output`` maps a state to the CVs.
    Both must broadcast over leading dimensions (a batch of simulations runs at once).

        x_{k+1} = step(x_k, w_k),   y_k = output(x_k),   w = [u; v]  (MVs first, then DVs)
    """

    def step(self, x: Tensor, w: Tensor) -> Tensor:
        """Next state.

        Args:
            x: states ``x_k``, shape ``(..., n)``.
            w: held inputs ``w_k = [u; v]``, shape ``(..., nu + nv)``.

        Returns:
            ``x_{k+1}``, shape ``(..., n)``.
        """
        ...

    def output(self, x: Tensor) -> Tensor:
        """CVs of a state.

        Args:
            x: states ``x_k``, shape ``(..., n)``.

        Returns:
            ``y_k``, shape ``(..., ny)``.
        """
        ...


class _FunctionPair:
    def __init__(
        self, step: Callable[[Tensor, Tensor], Tensor], output: Callable[[Tensor], Tensor]
    ):
        self._step, self._output = step, output

    def step(self, x: Tensor, w: Tensor) -> Tensor:
        return self._step(x, w)

    def output(self, x: Tensor) -> Tensor:
        return self._output(x)


class _StateSpaceAdapter:
    """Uses the predictive means of a :class:`~torchfilt.models.StateSpaceModel` (noise ignored)."""

    def __init__(self, model: StateSpaceModel) -> None:
        meas = model.measurement
        if isinstance(meas, LinearModel) and meas.D is not None:
            raise ModelError(
                "model: the measurement has a feed-through matrix D (y_k depends on u_k); a "
                "step-response model needs strictly proper channels (S_0 = 0)"
            )
        self.model = model

    def step(self, x: Tensor, w: Tensor) -> Tensor:
        out = self.model.transition.predict(x.unsqueeze(-2), w.unsqueeze(-2)).mean
        return out.squeeze(-2)

    def output(self, x: Tensor) -> Tensor:
        return self.model.measurement.predict(x.unsqueeze(-2), None).mean.squeeze(-2)


def _as_discrete_model(model: Any) -> DiscreteModel:
    if isinstance(model, StateSpaceModel):
        return _StateSpaceAdapter(model)
    if isinstance(model, tuple) and len(model) == 2 and all(callable(f) for f in model):
        return _FunctionPair(model[0], model[1])
    if isinstance(model, DiscreteModel):
        return model
    raise InputTypeError(
        "model must be a torchfilt StateSpaceModel, an object with step(x, w) and output(x) "
        f"methods (DiscreteModel), or a pair (step, output) of callables; got {type(model).__name__}"
    )


def _extend(S: Tensor, count: int, integrating: Tensor) -> Tensor:
    """``S_1..S_count`` from ``S_1..S_L`` (``(L, ny, k)``) by the per-CV settling rules."""
    L = S.shape[0]
    if count <= L:
        return S[:count]
    extra = torch.arange(1, count - L + 1, dtype=S.dtype, device=S.device)[:, None, None]
    prev = S[-2] if L >= 2 else torch.zeros_like(S[-1])
    slope = torch.where(integrating[:, None], S[-1] - prev, torch.zeros_like(S[-1]))
    return torch.cat([S, S[-1] + extra * slope], dim=0)


@dataclass(frozen=True, eq=False)
class StepResponseModel:
    """Step-response model with MV and measured-DV channels and a per-CV layout.

    Build one with :meth:`from_transfer_functions`, :meth:`from_arrays` or :meth:`from_simulation`.

    Attributes:
        Su: MV step-response coefficients ``S^u_1..S^u_L``, shape ``(L, ny, nu)``.
        Sv: DV step-response coefficients ``S^v_1..S^v_L``, shape ``(L, ny, nv)`` (``nv`` may be 0).
        integrating: which CVs are integrating (use the integrating layout), shape ``(ny,)`` bool.
        horizon: model horizon ``N`` (stable CVs use ``S_1..S_N``, integrating ones ``S_1..S_{N+1}``).
        dt: sampling period ``T`` (informational; ``None`` if unknown).
    """

    Su: Tensor
    Sv: Tensor
    integrating: Tensor
    horizon: int
    dt: float | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        Su: Tensor | Any,
        Sv: Tensor | Any | None = None,
        *,
        integrating: Sequence[bool] | Tensor | None = None,
        horizon: int | None = None,
        dt: float | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> StepResponseModel:
        """A model from measured step-response arrays.

        Args:
            Su: MV coefficients ``S^u_1..S^u_L``, shape ``(L, ny, nu)``.
            Sv: DV coefficients ``S^v_1..S^v_L``, shape ``(L, ny, nv)``, or ``None`` for no DVs.
            integrating: per-CV flag, shape ``(ny,)``; default all stable.
            horizon: model horizon ``N``; default ``L`` if every CV is stable, else ``L - 1`` (so an
                integrating CV's ``S_{N+1}`` is the last measured coefficient).
            dt: sampling period.
            dtype: floating dtype of the stored coefficients.

        Returns:
            The model.

        Raises:
            ShapeError: wrong ranks, or ``Sv``/``integrating`` inconsistent with ``Su``.
            InputError: non-finite coefficients or a horizon below 1.
        """
        Su_t = torch.as_tensor(Su, dtype=dtype)
        if Su_t.dim() != 3:
            raise ShapeError(f"Su: expected shape (L, ny, nu), got {tuple(Su_t.shape)}")
        L, ny, nu = Su_t.shape
        if L < 1 or ny < 1 or nu < 1:
            raise ShapeError(f"Su: every dimension of (L, ny, nu) must be >= 1, got {(L, ny, nu)}")
        if Sv is None:
            Sv_t = Su_t.new_zeros(L, ny, 0)
        else:
            Sv_t = torch.as_tensor(Sv, dtype=dtype)
            if Sv_t.dim() != 3:
                raise ShapeError(f"Sv: expected shape (L, ny, nv), got {tuple(Sv_t.shape)}")
            if Sv_t.shape[:2] != (L, ny):
                raise ShapeError(
                    f"Sv: expected shape ({L}, {ny}, nv) to match Su's (L, ny) = ({L}, {ny}), "
                    f"got {tuple(Sv_t.shape)}"
                )
        for name, S in (("Su", Su_t), ("Sv", Sv_t)):
            if not bool(torch.isfinite(S).all()):
                raise InputError(f"{name} contains non-finite coefficients")
        if integrating is None:
            integ = torch.zeros(ny, dtype=torch.bool)
        else:
            integ = torch.as_tensor(integrating, dtype=torch.bool).reshape(-1)
            if integ.shape != (ny,):
                raise ShapeError(
                    f"integrating: expected {ny} flags (one per CV), got shape {tuple(integ.shape)}"
                )
        if horizon is None:
            horizon = L - 1 if bool(integ.any()) and L >= 2 else L
        horizon = _positive_int(horizon, "horizon")
        if dt is not None and not dt > 0:
            raise InputError(f"dt (sampling period) must be positive, got {dt}")
        return cls(Su_t, Sv_t, integ, int(horizon), None if dt is None else float(dt))

    @classmethod
    def from_transfer_functions(
        cls,
        Gu: Sequence[Sequence[TransferEntry | int | None]],
        Gv: Sequence[Sequence[TransferEntry | int | None]] | None = None,
        *,
        dt: float,
        horizon: int,
        integrating: Sequence[bool] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> StepResponseModel:
        """A model from transfer-function matrices of FOPDT / IPDT entries, sampled exactly.

        ``S_i = s(i T)`` with the closed forms of :mod:`torchfilt.dmc.transfer` (exact for the
        zero-order-hold discretisation, fractional dead times included). ``horizon + 1``
        coefficients are computed, so an integrating CV's ``S_{N+1}`` is exact too.

        Args:
            Gu: MV channels, ``ny`` rows of ``nu`` entries (:class:`FOPDT`, :class:`IPDT`, or
                ``None``/``0`` for no coupling).
            Gv: DV channels, ``ny`` rows of ``nv`` entries, or ``None``.
            dt: sampling period ``T`` (same time unit as the time constants and dead times).
            horizon: model horizon ``N``.
            integrating: per-CV layout override, shape ``(ny,)``. Default: a CV is integrating when
                any entry of its row (MV or DV) is an :class:`IPDT`. A stable CV may be put in the
                integrating layout (the paper's section 3.2 does so); the reverse raises.
            dtype: floating dtype.

        Returns:
            The model, with ``L = horizon + 1`` coefficients.

        Raises:
            InputError: a non-positive ``dt`` or ``horizon``, or the stable layout asked for a CV
                with an integrating entry.
            InputTypeError: ``Gu`` or ``Gv`` not a list of rows of entries.
            ShapeError: ragged rows, ``Gu`` and ``Gv`` with different numbers of rows, or
                ``integrating`` without one flag per CV.
        """
        if not dt > 0:
            raise InputError(f"dt (sampling period) must be positive, got {dt}")
        horizon = _positive_int(horizon, "horizon")
        ent_u = _entries(Gu, "Gu")
        ny = len(ent_u)
        ent_v = _entries(Gv, "Gv") if Gv is not None else [[] for _ in range(ny)]
        if len(ent_v) != ny:
            raise ShapeError(f"Gv has {len(ent_v)} rows but Gu has {ny}; both need one row per CV")
        t = dt * torch.arange(1, horizon + 2, dtype=dtype)

        def sample(rows: list[list[TransferEntry | None]]) -> Tensor:
            cols = len(rows[0]) if rows else 0
            S = torch.zeros(horizon + 1, ny, cols, dtype=dtype)
            for i, row in enumerate(rows):
                for j, e in enumerate(row):
                    if e is not None:
                        S[:, i, j] = e.step(t)
            return S

        natural = [
            any(e is not None and e.integrating for e in ent_u[i] + ent_v[i]) for i in range(ny)
        ]
        if integrating is None:
            integ = natural
        else:
            integ = [bool(b) for b in integrating]
            if len(integ) != ny:
                raise ShapeError(f"integrating: expected {ny} flags (one per CV), got {len(integ)}")
            wrong = [i for i in range(ny) if natural[i] and not integ[i]]
            if wrong:
                raise InputError(
                    f"integrating: CV(s) {wrong} have integrating (IPDT) entries and cannot use the "
                    "stable layout"
                )
        return cls.from_arrays(
            sample(ent_u), sample(ent_v), integrating=integ, horizon=horizon, dt=dt, dtype=dtype
        )

    @classmethod
    @torch.no_grad()
    def from_simulation(
        cls,
        model: DiscreteModel
        | StateSpaceModel
        | tuple[Callable[..., Tensor], Callable[..., Tensor]],
        x0: Tensor,
        w0: Tensor,
        *,
        nu: int,
        horizon: int,
        integrating: Sequence[bool] | None = None,
        amplitude: float | Tensor = 1.0,
        dt: float | None = None,
    ) -> StepResponseModel:
        """A model identified by simulating unit steps through a (learned) discrete-time model.

            x_{k+1} = step(x_k, w_k),  y_k = output(x_k),  w = [u; v]

        All ``nu + nv`` step experiments and a baseline run with the inputs held at ``w0`` are
        simulated as one batch from ``x0``; ``S_i = (y_i^{step j} - y_i^{base}) / amplitude_j``.
        Subtracting the baseline makes the result exact for a linear model even when ``x0`` is not an
        equilibrium; for a nonlinear model it is the response around that trajectory (pick a small
        ``amplitude`` for a local linearisation).

        Args:
            model: a :class:`~torchfilt.models.StateSpaceModel` (its transition and measurement
                means; the measurement is called without inputs), an object with ``step``/``output``
                (:class:`DiscreteModel`), or a pair ``(step, output)`` of callables.
            x0: initial state, shape ``(n,)``.
            w0: operating-point inputs ``[u; v]``, shape ``(nu + nv,)``.
            nu: number of MVs (the first ``nu`` entries of ``w``); the rest are DVs.
            horizon: model horizon ``N``; ``N + 1`` coefficients are simulated.
            integrating: per-CV layout, shape ``(ny,)``; default all stable.
            amplitude: step size, a scalar or one per input, shape ``(nu + nv,)``.
            dt: sampling period (informational).

        Returns:
            The identified model with ``L = horizon + 1`` coefficients.

        Raises:
            ShapeError: ``x0``/``w0``/``nu`` inconsistent, or the model returns wrong shapes.
            ModelError: a linear measurement with a feed-through matrix ``D`` (not strictly proper).
            InputError: a non-positive ``horizon``, or an amplitude that is zero or not finite.
        """
        dm = _as_discrete_model(model)
        x0 = torch.as_tensor(x0)
        w0 = torch.as_tensor(w0)
        if not x0.is_floating_point():
            x0 = x0.to(torch.float64)
        w0 = w0.to(x0.dtype)
        if x0.dim() != 1:
            raise ShapeError(f"x0: expected shape (n,), got {tuple(x0.shape)}")
        if w0.dim() != 1:
            raise ShapeError(f"w0: expected shape (nu + nv,), got {tuple(w0.shape)}")
        nw = w0.shape[0]
        if not 1 <= nu <= nw:
            raise ShapeError(f"nu = {nu} must lie in 1..{nw} (the length of w0)")
        horizon = _positive_int(horizon, "horizon")
        amp = torch.as_tensor(amplitude, dtype=x0.dtype).expand(nw)
        if not bool((amp != 0).all() & torch.isfinite(amp).all()):
            raise InputError("amplitude must be finite and non-zero for every input")
        w = w0.expand(nw + 1, nw).clone()
        w[1:] += torch.diag(amp)
        x = x0.expand(nw + 1, -1).clone()
        ys = []
        for _ in range(horizon + 1):
            x = dm.step(x, w)
            if x.shape != (nw + 1, x0.shape[0]):
                raise ShapeError(
                    f"model step returned shape {tuple(x.shape)}; expected {(nw + 1, x0.shape[0])}"
                )
            y = dm.output(x)
            if y.dim() != 2 or y.shape[0] != nw + 1:
                raise ShapeError(
                    f"model output returned shape {tuple(y.shape)} for states {tuple(x.shape)}; "
                    "expected (batch, ny)"
                )
            ys.append(y)
        Y = torch.stack(ys)  # (L, nw + 1, ny)
        S = ((Y[:, 1:] - Y[:, :1]) / amp[:, None]).permute(0, 2, 1)  # (L, ny, nw)
        return cls.from_arrays(
            S[..., :nu],
            S[..., nu:],
            integrating=integrating,
            horizon=horizon,
            dt=dt,
            dtype=x0.dtype,
        )

    # ------------------------------------------------------------------ properties
    @property
    def ny(self) -> int:
        """Number of CVs."""
        return int(self.Su.shape[1])

    @property
    def nu(self) -> int:
        """Number of MVs."""
        return int(self.Su.shape[2])

    @property
    def nv(self) -> int:
        """Number of measured DVs."""
        return int(self.Sv.shape[2])

    @property
    def dtype(self) -> torch.dtype:
        """The coefficients' dtype."""
        return self.Su.dtype

    def coefficients(self, count: int, channel: str = "u") -> Tensor:
        """``S_1..S_count`` of the horizon-``N`` model, MV (``"u"``) or DV (``"v"``) channels.

        This is the model every realisation and the controller use: a stable CV holds ``S_N`` from
        ``i = N`` on, an integrating CV extrapolates linearly from ``S_{N+1}`` with the slope
        ``R = S_{N+1} - S_N``. Stored coefficients beyond that are ignored; if fewer than ``N + 1``
        are stored the stored ones are extended by the same rules first.

        Args:
            count: number of coefficients (``>= 1``).
            channel: ``"u"`` or ``"v"``.

        Returns:
            Coefficients, shape ``(count, ny, nu)`` or ``(count, ny, nv)``.

        Raises:
            InputError: ``channel`` is neither ``"u"`` nor ``"v"``, or ``count < 1``.
        """
        if channel not in ("u", "v"):
            raise InputError(f"channel must be 'u' or 'v', got {channel!r}")
        if count < 1:
            raise InputError(f"count must be >= 1, got {count}")
        N = self.horizon
        S = _extend(self.Su if channel == "u" else self.Sv, N + 1, self.integrating)[: N + 1]
        stable = torch.cat([S[:N], S[N - 1 : N]], dim=0)  # S_{N+1} := S_N
        S = torch.where(self.integrating[None, :, None], S, stable)
        return _extend(S, count, self.integrating)

    def steady_gain(self, channel: str = "u") -> Tensor:
        """Steady-state gain ``S_N`` (stable CVs) or settled slope ``S_{N+1} - S_N`` (integrating).

        Args:
            channel: ``"u"`` (MVs) or ``"v"`` (DVs).

        Returns:
            The gains, shape ``(ny, nu)`` or ``(ny, nv)``.

        Raises:
            InputError: ``channel`` is neither ``"u"`` nor ``"v"``.
        """
        S = self.coefficients(self.horizon + 1, channel)
        return torch.where(self.integrating[:, None], S[-1] - S[-2], S[-2])

    def with_layout(self, integrating: Sequence[bool] | Tensor) -> StepResponseModel:
        """The same coefficients with another per-CV layout (e.g. a stable CV in the integrating one).

        Args:
            integrating: the per-CV layout flags, shape ``(ny,)``.

        Returns:
            The new model.
        """
        return StepResponseModel.from_arrays(
            self.Su,
            self.Sv,
            integrating=integrating,
            horizon=self.horizon,
            dt=self.dt,
            dtype=self.dtype,
        )


def _entries(G: Any, name: str) -> list[list[TransferEntry | None]]:
    if isinstance(G, str | bytes) or not isinstance(G, Sequence):
        raise InputTypeError(f"{name} must be a list of rows (one per CV), got {type(G).__name__}")
    rows: list[list[TransferEntry | None]] = []
    width = None
    for i, row in enumerate(G):
        if isinstance(row, str | bytes) or not isinstance(row, Sequence):
            raise InputTypeError(
                f"{name}[{i}] must be a row (list) of entries, got {type(row).__name__}"
            )
        if width is None:
            width = len(row)
        elif len(row) != width:
            raise ShapeError(
                f"{name} is ragged: row 0 has {width} entries but row {i} has {len(row)}"
            )
        rows.append([as_entry(e, f"{name}[{i}][{j}]") for j, e in enumerate(row)])
    if not rows or width == 0:
        raise ShapeError(f"{name} must have at least one row and one column")
    return rows
