"""Learned parameters as uncertain states: a filter that carries the training's parameter error.

A model fitted to a few recordings knows its parameters only up to the curvature of the fit's
likelihood. A filter that takes the point estimate as exact is overconfident wherever the state
is sensitive to those parameters: on re-entry, a drag constant 0.05% off (well inside its
training uncertainty of about 0.4%) makes the CKF's ballistic coefficient three times too
certain. :class:`UncertainParameters` appends the parameters to the state,

    z = [x, theta],   x_k = f(x_{k-1}, u; theta_{k-1}),   theta_k = theta_{k-1},
    y_k = h(x_k, u; theta_k),

with the prior ``theta ~ N(theta_hat, C)`` from the fit (``torchfilt.training.parameter_posterior``:
the inverse Hessian of the negative log-likelihood, or its sandwich form). The filter then
propagates the parameters' uncertainty into the state's covariance and refines them on the new
recording (joint state and parameter estimation). The parameters are the raw (unconstrained)
``nn.Parameter`` values: a ``log_gamma`` is Gaussian in the log.

The maps are evaluated with one parameter value per cubature point by ``torch.func.vmap`` over
``torch.func.functional_call``: their ``forward`` must be plain torch operations (no
``.item()``, no branching on tensor values).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchfilt.exceptions import InputError, ModelError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction
from torchfilt.models.functional import StateSpaceModel
from torchfilt.models.params import CovarianceParameter

__all__ = [
    "ParameterPosterior",
    "UncertainParameters",
    "map_parameters",
    "noise_parameter_names",
]


class ParameterPosterior(NamedTuple):
    """A Gaussian over some of a model's parameters (flattened in the order of ``names``).

    Attributes:
        names: parameter names as in ``model.named_parameters()`` (``"transition._fn.log_gamma"``).
        mean: the flattened values ``(p,)``.
        cov: their covariance ``(p, p)``.
    """

    names: tuple[str, ...]
    mean: Tensor
    cov: Tensor

    def std(self) -> Tensor:
        """Standard deviations ``(p,)``."""
        return self.cov.diagonal().clamp_min(0.0).sqrt()


def noise_parameter_names(model: torch.nn.Module) -> set[str]:
    """Names of the parameters that belong to a learnable noise covariance (``Q``, ``R``)."""
    out: set[str] = set()
    for prefix, mod in model.named_modules():
        if isinstance(mod, CovarianceParameter):
            for name, _ in mod.named_parameters():
                out.add(f"{prefix}.{name}" if prefix else name)
    return out


def map_parameters(
    model: StateSpaceModel, names: Sequence[str], arg: str
) -> dict[str, torch.nn.Parameter]:
    """The named parameters of a model's maps, in the order given: the check that
    :func:`~torchfilt.training.parameter_posterior` and :class:`UncertainParameters` share.

    Args:
        model: the state-space model.
        names: names as in ``model.named_parameters()``.
        arg: the argument's name in error messages.

    Raises:
        InputError: no name, a repeated name, a name that is not a parameter of the model, or
            one of a learnable noise covariance.
    """
    names = list(names)
    if not names:
        raise InputError(f"{arg}: no parameter named")
    if len(set(names)) != len(names):
        raise InputError(f"{arg}: repeated names in {names}")
    named = dict(model.named_parameters())
    noise = noise_parameter_names(model)
    for k in names:
        if k not in named:
            raise InputError(
                f"{arg}: {k!r} is not a parameter of the model (it has {sorted(named)[:8]})"
            )
        if k in noise:
            raise InputError(
                f"{arg}: {k!r} is a noise covariance's parameter; only the maps' parameters "
                "can be carried as states"
            )
        if k.partition(".")[0] not in ("transition", "measurement"):
            raise InputError(f"{arg}: {k!r} is not in the transition or measurement")
    return {k: named[k] for k in names}


class _Slot(NamedTuple):
    name: str  # relative to the side's module
    start: int
    shape: torch.Size


class _WithParameters(ConditionalModel):
    """One side of :class:`UncertainParameters`: the base map evaluated at per-point parameters
    ``theta = z[..., n:]``; the transition also carries ``theta`` over unchanged."""

    def __init__(
        self, base: ConditionalModel, slots: list[_Slot], n: int, p: int, *, carry: bool
    ) -> None:
        super().__init__()
        self.base = base
        self.slots = slots
        self.n, self.p, self.carry = n, p, carry
        self.out_dim = int(base.out_dim) + (p if carry else 0)
        self.in_dim = n + p

    def _evaluate(self, x: Tensor, theta: Tensor, u: Tensor | None) -> Prediction:
        if not self.slots:
            return self.base.predict(x, u)
        lead = torch.broadcast_shapes(
            x.shape[:-1], theta.shape[:-1], *(() if u is None else (u.shape[:-1],))
        )
        xf = x.expand(*lead, x.shape[-1]).reshape(-1, x.shape[-1])
        tf = theta.expand(*lead, self.p).reshape(-1, self.p)
        uf = None if u is None else u.expand(*lead, u.shape[-1]).reshape(-1, u.shape[-1])
        base, slots = self.base, self.slots

        fields: list[bool] = []  # whether var and cov are returned (set when vmap traces one)

        def one(xi: Tensor, ti: Tensor, ui: Tensor | None) -> tuple[Tensor, ...]:
            values = {
                s.name: ti[s.start : s.start + s.shape.numel()].reshape(s.shape) for s in slots
            }
            args = (xi.unsqueeze(0), None if ui is None else ui.unsqueeze(0))
            pred = torch.func.functional_call(base, values, args)
            fields[:] = [pred.var is not None, pred.cov is not None]
            extra = [t[0] for t in (pred.var, pred.cov) if t is not None]
            return (pred.mean[0], *extra)

        fn: Callable[..., Any] = torch.func.vmap(one, in_dims=(0, 0, None if uf is None else 0))
        try:
            outs = fn(xf, tf, uf)
        except RuntimeError as e:
            raise ModelError(
                f"UncertainParameters: the {self.base.__class__.__name__} map cannot be "
                "evaluated with one parameter value per point under torch.func.vmap (its "
                f"forward must be plain torch operations: no .item(), no branching on values): {e}"
            ) from e
        has_var, has_cov = fields
        d = int(self.base.out_dim)
        mean = outs[0].reshape(*lead, d)
        var = outs[1].reshape(*lead, d) if has_var else None
        cov = outs[-1].reshape(*lead, d, d) if has_cov else None
        return Prediction(mean, var, cov)

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        xs, theta = x[..., : self.n], x[..., self.n :]
        pred = self._evaluate(xs, theta, u)
        if not self.carry:
            return pred
        mean = torch.cat([pred.mean, theta.expand(*pred.mean.shape[:-1], self.p)], -1)
        var = None
        if pred.var is not None:
            var = torch.cat([pred.var, pred.var.new_zeros(*pred.var.shape[:-1], self.p)], -1)
        cov = None
        if pred.cov is not None:
            cov = _pad(pred.cov, self.p)
        return Prediction(mean, var, cov)

    def noise_cov(self, step: int | None = None) -> Tensor | None:
        noise = self.base.noise_cov(step)
        if noise is None or not self.carry:
            return noise
        return _pad(noise, self.p)

    @property
    def time_varying_noise(self) -> bool:
        return self.base.time_varying_noise


def _pad(cov: Tensor, p: int) -> Tensor:
    """``(..., d, d) -> (..., d + p, d + p)`` with zeros in the new rows and columns."""
    return torch.nn.functional.pad(cov, (0, p, 0, p))


class UncertainParameters(StateSpaceModel):
    """A state-space model whose state carries some of its own parameters: ``z = [x, theta]``.

    Filter it like any model, from :meth:`prior`; :meth:`state_marginal` gives back the state's
    part. See the module docstring.

    Args:
        model: the fitted model (its parameter values are not changed).
        posterior: the Gaussian over some of ``model``'s parameters (its names must be parameters
            of ``model.transition`` or ``model.measurement``, not of a learnable noise).

    Attributes:
        state_dim: ``n + p``; ``base_state_dim`` is ``n``.

    Raises:
        InputError: ``model`` or ``posterior`` of the wrong type, a name that is no parameter of
            the model's maps, or a posterior that is not finite, symmetric and positive definite.
        ShapeError: the posterior's ``mean`` is not ``(p,)`` or its ``cov`` not ``(p, p)`` for
            the ``p`` values its names hold.
    """

    def __init__(self, model: StateSpaceModel, posterior: ParameterPosterior) -> None:
        if not isinstance(model, StateSpaceModel):
            raise InputError(f"model must be a StateSpaceModel, got {type(model).__name__}")
        if not isinstance(posterior, ParameterPosterior):
            raise InputError(
                f"posterior must be a ParameterPosterior, got {type(posterior).__name__}"
            )
        named = map_parameters(model, posterior.names, "posterior.names")
        slots: dict[str, list[_Slot]] = {"transition": [], "measurement": []}
        start = 0
        for name in posterior.names:
            side, _, rel = name.partition(".")
            shape = named[name].shape
            slots[side].append(_Slot(rel, start, shape))
            start += shape.numel()
        p = start
        mean, cov = posterior.mean, posterior.cov
        if mean.shape != (p,) or cov.shape != (p, p):
            raise ShapeError(
                f"posterior: {p} parameter values named, so mean must be ({p},) and cov ({p}, {p}); "
                f"got {tuple(mean.shape)} and {tuple(cov.shape)}"
            )
        if not bool(torch.isfinite(mean).all() & torch.isfinite(cov).all()):
            raise InputError("posterior: mean and cov must be finite")
        if not torch.allclose(cov, cov.mT, rtol=1e-8, atol=0.0):
            raise InputError("posterior.cov: not symmetric")
        if int(torch.linalg.cholesky_ex(cov).info) != 0:
            raise InputError("posterior.cov: not positive definite")
        n = model.state_dim
        super().__init__(
            _WithParameters(model.transition, slots["transition"], n, p, carry=True),
            _WithParameters(model.measurement, slots["measurement"], n, p, carry=False),
        )
        self.base_state_dim = n
        self.posterior = posterior

    def prior(self, x0: Tensor, P0: Tensor) -> tuple[Tensor, Tensor]:
        """The joint prior ``(z0, Pz0)``: the state's prior with the parameters' mean and
        covariance appended (independent of the state a priori).

        Args:
            x0: the state's prior mean, shape ``(..., n)``.
            P0: the state's prior covariance, shape ``(..., n, n)``.

        Returns:
            ``z0`` of shape ``(..., n + p)`` and ``Pz0`` of shape ``(..., n + p, n + p)``.

        Raises:
            ShapeError: ``x0`` is not ``(..., n)`` or ``P0`` not ``(..., n, n)``.
        """
        n = self.base_state_dim
        if x0.shape[-1:] != (n,) or P0.shape[-2:] != (n, n):
            raise ShapeError(
                f"x0, P0: expected (..., {n}) and (..., {n}, {n}), got {tuple(x0.shape)} and "
                f"{tuple(P0.shape)}"
            )
        mean = self.posterior.mean.to(x0)
        cov = self.posterior.cov.to(P0)
        p = int(mean.shape[0])
        z0 = torch.cat([x0, mean.expand(*x0.shape[:-1], p)], -1)
        Pz = _pad(P0, p)
        Pz[..., n:, n:] = cov
        return z0, Pz

    def state_marginal(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        """The state's part of a joint estimate.

        Args:
            mean: joint means, shape ``(..., n + p)``.
            cov: joint covariances, shape ``(..., n + p, n + p)``.

        Returns:
            The state's means, shape ``(..., n)``, and covariances, shape ``(..., n, n)``.
        """
        n = self.base_state_dim
        return mean[..., :n], cov[..., :n, :n]

    def parameter_marginal(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        """The parameters' part of a joint estimate.

        Args:
            mean: joint means, shape ``(..., n + p)``.
            cov: joint covariances, shape ``(..., n + p, n + p)``.

        Returns:
            The parameters' means, shape ``(..., p)``, and covariances, shape ``(..., p, p)``.
        """
        n = self.base_state_dim
        return mean[..., n:], cov[..., n:, n:]
