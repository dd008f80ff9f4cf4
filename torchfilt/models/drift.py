"""Slowly drifting sensors as extra states: ``y_j = h_j(x) + b_i``, ``b`` a first-order Gauss-Markov
process.

A sensor whose error drifts slowly (a bias that wanders over minutes) cannot be described by a
white measurement noise ``R``: its errors do not average out over repeated measurements, so a
filter that treats them as white is over-confident, and a likelihood fit without a drift state
explains the drift as process noise of the measured state and follows the sensor. The standard
remedy is to estimate the drift: :func:`with_sensor_drift` appends one state per drifting channel,

    b_{k+1} = a b_k + e_k,   a = exp(-dt / tau),   e_k ~ N(0, sd^2 (1 - a^2)),

(stationary standard deviation ``sd``, time constant ``tau``), adds it to the channel's
measurement, and makes ``tau`` and ``sd`` learnable (log parametrisations: both span orders of
magnitude, and an optimiser step then changes them by a factor, not by an amount), so that
:func:`torchfilt.calibrate` fits them by the filter likelihood together with the variance scales.
The drift is only identifiable when the dynamics predict the measured state (from other sensors
or inputs): otherwise a drift and a change of the state explain the data equally well.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction
from torchfilt.models.functional import StateSpaceModel


class _LogPositive(nn.Module):
    """A positive vector ``exp(raw)``."""

    def __init__(self, init: Tensor) -> None:
        super().__init__()
        if not bool(torch.isfinite(init).all()) or bool((init <= 0).any()):
            raise InputError(f"initial values must be finite and positive, got {init.tolist()}")
        self.raw = nn.Parameter(init.log())

    def forward(self) -> Tensor:
        return self.raw.exp()


__all__ = ["DriftMeasurement", "DriftModel", "DriftTransition", "with_sensor_drift"]


def _block(a: Tensor | None, b: Tensor) -> Tensor:
    """Block-diagonal ``[[a, 0], [0, b]]`` for ``a (..., n, n)`` (``None``: zeros ``n = 0``)."""
    if a is None:
        return b
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    n, k = a.shape[-1], b.shape[-1]
    out = a.new_zeros(*batch, n + k, n + k)
    out[..., :n, :n] = a
    out[..., n:, n:] = b
    return out


class DriftTransition(ConditionalModel):
    """``[f(x), a b]`` with noise ``blockdiag(Q_f, sd^2 (1 - a^2))``."""

    def __init__(
        self, base: ConditionalModel, n: int, k: int, tau: _LogPositive, sd: _LogPositive, dt: float
    ) -> None:
        super().__init__()
        self.base, self.n, self.k, self.dt = base, n, k, float(dt)
        self.tau, self.sd = tau, sd
        self.out_dim = self.in_dim = n + k

    def decay(self) -> Tensor:
        return torch.exp(-self.dt / self.tau())

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        p = self.base.predict(x[..., : self.n], u)
        a = self.decay().to(x.dtype)
        mean = torch.cat([p.mean, a * x[..., self.n :]], -1)
        zeros = x.new_zeros(*x.shape[:-1], self.k)
        var = None if p.var is None else torch.cat([p.var, zeros], -1)
        cov = None
        if p.cov is not None:
            cov = _block(p.cov, torch.diag_embed(zeros))
        return Prediction(mean, var, cov)

    def predict_mean(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        a = self.decay().to(x.dtype)
        return torch.cat([self.base.predict_mean(x[..., : self.n], u), a * x[..., self.n :]], -1)

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        a = self.decay()
        own = torch.diag(self.sd().pow(2) * (1 - a * a))
        base = self.base.noise_cov(step)
        if base is None:
            base = own.new_zeros(self.n, self.n)
        return _block(base.to(own), own)

    @property
    def time_varying_noise(self) -> bool:
        return self.base.time_varying_noise


class DriftMeasurement(ConditionalModel):
    """``h(x) + S b`` with ``S`` the selection of the drifting channels."""

    _sel: Tensor

    def __init__(self, base: ConditionalModel, n: int, channels: Sequence[int]) -> None:
        super().__init__()
        self.base, self.n = base, n
        self.out_dim, self.in_dim = base.out_dim, n + len(channels)
        sel = torch.zeros(base.out_dim, len(channels))
        for i, c in enumerate(channels):
            sel[c, i] = 1.0
        self.register_buffer("_sel", sel, persistent=False)

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        p = self.base.predict(x[..., : self.n], u)
        bias = x[..., self.n :] @ self._sel.to(x.dtype).mT
        return Prediction(p.mean + bias, p.var, p.cov)

    def predict_mean(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        bias = x[..., self.n :] @ self._sel.to(x.dtype).mT
        return self.base.predict_mean(x[..., : self.n], u) + bias

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        return self.base.noise_cov(step)

    @property
    def time_varying_noise(self) -> bool:
        return self.base.time_varying_noise


class DriftModel(StateSpaceModel):
    """A state-space model whose last ``k`` states are sensor drifts (see the module docstring).

    Attributes:
        base_state_dim: ``n``, the states of the original model (the first ``n``).
        channels: the drifting measurement channels, in the order of the drift states.
    """

    def __init__(
        self,
        base: StateSpaceModel,
        channels: Sequence[int],
        tau: _LogPositive,
        sd: _LogPositive,
        dt: float,
    ) -> None:
        n = base.state_dim
        super().__init__(
            DriftTransition(base.transition, n, len(channels), tau, sd, dt),
            DriftMeasurement(base.measurement, n, channels),
        )
        self.base_state_dim = n
        self.channels = list(channels)

    @property
    def time_constant(self) -> Tensor:
        """The drifts' time constants ``(k,)``."""
        assert isinstance(self.transition, DriftTransition)
        return self.transition.tau()

    @property
    def drift_sd(self) -> Tensor:
        """The drifts' stationary standard deviations ``(k,)``."""
        assert isinstance(self.transition, DriftTransition)
        return self.transition.sd()

    def drift_parameters(self) -> list[nn.Parameter]:
        """The learnable drift parameters (``log tau`` and ``log sd``)."""
        assert isinstance(self.transition, DriftTransition)
        return [*self.transition.tau.parameters(), *self.transition.sd.parameters()]

    def prior(self, x0: Tensor, P0: Tensor) -> tuple[Tensor, Tensor]:
        """The augmented prior: ``[x0, 0]`` and ``blockdiag(P0, diag(sd^2))``.

        Args:
            x0: prior mean of the original states ``(..., n)``.
            P0: their covariance ``(..., n, n)``.
        """
        k = len(self.channels)
        with torch.no_grad():
            sd2 = self.drift_sd.pow(2).to(P0)
        x = torch.cat([x0, x0.new_zeros(*x0.shape[:-1], k)], -1)
        return x, _block(P0, torch.diag(sd2))


def with_sensor_drift(
    model: StateSpaceModel,
    channels: Sequence[int],
    *,
    time_constant: float | Sequence[float],
    sd: float | Sequence[float],
    sample_time: float = 1.0,
    dtype: torch.dtype = torch.float64,
) -> DriftModel:
    """Append a first-order Gauss-Markov drift state to measurement ``channels`` of ``model``.

    Args:
        model: the model (its states stay the first ``n``).
        channels: indices of the drifting measurement channels.
        time_constant: initial time constant(s) ``tau`` of the drifts (in units of
            ``sample_time``), one or one per channel; learnable.
        sd: initial stationary standard deviation(s) of the drifts; learnable.
        sample_time: time between steps.
        dtype: dtype of the parameters.

    Returns:
        A :class:`DriftModel` with ``n + len(channels)`` states; its :meth:`DriftModel.prior`
        extends a prior of the original states.
    """
    if not isinstance(model, StateSpaceModel):
        raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    ch = [int(c) for c in channels]
    m = model.obs_dim
    if not ch or len(set(ch)) != len(ch) or not all(0 <= c < m for c in ch):
        raise InputError(f"channels: need distinct indices in [0, {m}), got {list(channels)}")
    k = len(ch)

    def vec(v: float | Sequence[float], name: str) -> Tensor:
        t = torch.as_tensor(v, dtype=dtype)
        t = t.expand(k).clone() if t.dim() == 0 else t
        if t.shape != (k,):
            raise ShapeError(f"{name}: expected one value or {k}, got shape {tuple(t.shape)}")
        return t

    if not sample_time > 0:
        raise InputError(f"sample_time must be positive, got {sample_time}")
    tau = _LogPositive(vec(time_constant, "time_constant"))
    sdv = _LogPositive(vec(sd, "sd"))
    return DriftModel(model, ch, tau, sdv, sample_time)
