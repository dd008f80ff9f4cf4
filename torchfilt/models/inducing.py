"""A sparse-GP transition whose inducing inputs *and* inducing outputs are parameters.

Trained from measurements alone there are no target states to condition a GP on. This model
treats the unknown targets as parameters: ``M`` inducing inputs ``Z (M, D)`` (``D = n + nu``: the
state and the input) and, for every state component ``j``, the values ``U_j (M,)`` that the
residual ``r_j = f_j - (W z + b)_j`` takes there. Its prediction at ``z = [x; u]`` is the GP
conditional given those values (Snelson & Ghahramani 2006; the "inducing-output" form of
Turner, Deisenroth & Rasmussen 2010 and Ialongo et al. 2019):

    mean_j(z) = (W z + b)_j + k(z, Z) K_ZZ^{-1} U_j
    var_j(z)  = s_j (1 - c(z, Z) C_ZZ^{-1} c(Z, z)) + floor_j

with one shared ARD correlation ``c`` (RBF) and per-output scales ``s_j``: deterministic, so a
Gaussian filter moment-matches it through its cubature points, and every quantity has a gradient.
Far from the inducing inputs the mean falls back to the linear part and the variance grows to
``s_j``: the model says where it has not seen data.

``inducing=0`` (no inducing points) is the plain linear transition ``W z + b``. A ``nominal``
physics model ``g(x, u)`` (a textbook model with guessed constants) can stand under it all: the
mean is then ``g(x, u) + W z + b + GP``, with ``W`` starting at zero, so training starts from the
physics and learns its error.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, InputTypeError, ModelError, ShapeError
from torchfilt.models.base import ConditionalModel, Prediction
from torchfilt.models.functional import StateSpaceModel
from torchfilt.models.linear import LinearGaussianModel
from torchfilt.models.params import CholeskyCovariance
from torchfilt.numerics import safe_cholesky

__all__ = [
    "LOG_LENGTHSCALE_BOUNDS",
    "LOG_OUTPUTSCALE_BOUNDS",
    "NEGLIGIBLE_OUTPUTSCALE",
    "InducingTransition",
]

#: The range the log-lengthscales are clamped to where the model is evaluated: a fit that pushes
#: them further (a step of a line search) stays in the finite region of the likelihood (the
#: correlations neither underflow to an all-zero kernel nor saturate to a constant one).
LOG_LENGTHSCALE_BOUNDS = (-10.0, 10.0)
#: The range of the log output variances ``log s_j`` where the model is evaluated (the lower end
#: leaves the negligible start of :meth:`InducingTransition.from_linear` inside it).
LOG_OUTPUTSCALE_BOUNDS = (-60.0, 20.0)
#: The default initial output variance of :meth:`InducingTransition.from_linear`: small enough
#: that the model's likelihood is the linear model's to float64 precision, inside
#: :data:`LOG_OUTPUTSCALE_BOUNDS`, so the fit can raise it.
NEGLIGIBLE_OUTPUTSCALE = 1e-14


class InducingTransition(ConditionalModel):
    """``x_t = W [x_{t-1}; u_t] + b + GP residual | (Z, U)``, all parameters learnable.

    Args:
        state_dim: ``n``.
        inducing: initial inducing inputs ``(M, n + nu)`` (``M = 0``: linear only), or an int
            ``M`` (then ``Z`` starts at zero and must be set before use, e.g. with
            :meth:`init_inducing`).
        input_dim: ``nu`` (0: no inputs).
        linear: initial ``W``, shape ``(n, n + nu)`` (default ``[I, 0]``: a random walk; ``0``
            with a ``nominal`` model).
        bias: initial ``b``, shape ``(n,)`` (default 0).
        lengthscale: initial lengthscales, a float or ``(n + nu,)``.
        outputscale: initial GP variances ``s_j``, a float or ``(n,)``.
        floor: a fixed variance floor added to ``var`` (float or ``(n,)``, default 0).
        jitter: added to the diagonal of ``C_ZZ``.
        nominal: a fixed physics model ``g(x, u)``, ``(..., n) -> (..., n)``, added to the mean.
        dtype: parameter dtype.

    Raises:
        InputError: a non-positive ``state_dim``, negative ``input_dim`` or ``inducing``, a
            ``nominal`` that is not callable, or a non-positive scale or negative floor.
        ShapeError: ``inducing``, ``linear`` or ``bias`` of the wrong shape.
    """

    floor: Tensor

    def __init__(
        self,
        state_dim: int,
        inducing: Tensor | int = 0,
        *,
        input_dim: int = 0,
        linear: Tensor | None = None,
        bias: Tensor | None = None,
        lengthscale: float | Tensor = 1.0,
        outputscale: float | Tensor = 0.1,
        floor: float | Tensor = 0.0,
        jitter: float = 1e-6,
        nominal: Callable[[Tensor, Tensor | None], Tensor] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if state_dim < 1:
            raise InputError(f"state_dim must be at least 1, got {state_dim}")
        if input_dim < 0:
            raise InputError(f"input_dim must be non-negative, got {input_dim}")
        n, D = int(state_dim), int(state_dim) + int(input_dim)
        self.out_dim, self.in_dim, self.input_dim = n, n, int(input_dim)
        if isinstance(inducing, int):
            if inducing < 0:
                raise InputError(f"inducing: the number of inducing points is {inducing} < 0")
            Z = torch.zeros(inducing, D, dtype=dtype)
        else:
            Z = torch.as_tensor(inducing, dtype=dtype).detach().clone()
            if Z.dim() != 2 or Z.shape[-1] != D:
                raise ShapeError(f"inducing: expected shape (M, {D}), got {tuple(Z.shape)}")
        M = int(Z.shape[0])
        if nominal is not None and not callable(nominal):
            raise InputError(f"nominal must be callable, got {type(nominal).__name__}")
        self.nominal = nominal
        if linear is None and nominal is not None:
            W = torch.zeros(n, D, dtype=dtype)
        elif linear is None:
            W = torch.cat([torch.eye(n, dtype=dtype), torch.zeros(n, D - n, dtype=dtype)], -1)
        else:
            W = torch.as_tensor(linear, dtype=dtype).detach().clone()
            if W.shape != (n, D):
                raise ShapeError(f"linear: expected shape ({n}, {D}), got {tuple(W.shape)}")
        b = torch.zeros(n, dtype=dtype) if bias is None else torch.as_tensor(bias, dtype=dtype)
        if b.shape != (n,):
            raise ShapeError(f"bias: expected shape ({n},), got {tuple(b.shape)}")
        ls = torch.as_tensor(lengthscale, dtype=dtype).expand(D).clone()
        sc = torch.as_tensor(outputscale, dtype=dtype).expand(n).clone()
        fl = torch.as_tensor(floor, dtype=dtype).expand(n).clone()
        if bool((ls <= 0).any()) or bool((sc <= 0).any()) or bool((fl < 0).any()):
            raise InputError("lengthscale and outputscale must be positive and floor non-negative")
        if not (math.isfinite(jitter) and jitter >= 0):
            raise InputError(f"jitter must be finite and non-negative, got {jitter}")
        self.jitter = float(jitter)
        self.linear = nn.Parameter(W)
        self.bias = nn.Parameter(b.detach().clone())
        self.inducing_inputs = nn.Parameter(Z)
        self.inducing_outputs = nn.Parameter(torch.zeros(n, M, dtype=dtype))
        self.log_lengthscale = nn.Parameter(ls.log())
        self.log_outputscale = nn.Parameter(sc.log())
        self.register_buffer("floor", fl)

    @classmethod
    def from_linear(
        cls,
        A: Tensor,
        B: Tensor | None = None,
        *,
        inducing: int = 0,
        states: Tensor | None = None,
        inputs: Tensor | None = None,
        lengthscale: float | Tensor = 1.0,
        outputscale: float | Tensor | None = None,
    ) -> InducingTransition:
        """Start a GP transition from a linear model (e.g. one identified from the data by
        :func:`~torchfilt.training.fit_em` on a :class:`~torchfilt.models.LinearGaussianModel`):
        ``W = [A, B]``, ``b = 0``, the GP residual at zero mean and, by default, a negligible
        output variance (:data:`NEGLIGIBLE_OUTPUTSCALE`), so that the model (with the linear
        model's ``Q`` and ``R``, see :meth:`model_from_linear`) starts at the linear model's
        likelihood, also far from the inducing inputs.

        Args:
            A: ``(n, n)``.
            B: ``(n, nu)`` or ``None``.
            inducing: number of inducing points ``M``.
            states: ``(N, n)`` states to place the inducing inputs on (required when ``M > 0``),
                e.g. the smoothed means of the linear model.
            inputs: ``(N, nu)`` inputs aligned with ``states``.
            lengthscale: initial lengthscales, a float or ``(n + nu,)``.
            outputscale: initial GP variances ``s_j``, a float or ``(n,)`` (default
                :data:`NEGLIGIBLE_OUTPUTSCALE`: the linear model exactly, to float64 precision).

        Returns:
            The transition (frozen nothing: every parameter learnable).

        Raises:
            ShapeError: ``A`` not square or ``B`` not ``(n, nu)``.
            InputError: ``inducing > 0`` without ``states``.
        """
        A = torch.as_tensor(A)
        if A.dim() != 2 or A.shape[0] != A.shape[1]:
            raise ShapeError(f"A: expected a square matrix (n, n), got {tuple(A.shape)}")
        n = int(A.shape[0])
        if B is not None:
            B = torch.as_tensor(B, dtype=A.dtype)
            if B.dim() != 2 or B.shape[0] != n:
                raise ShapeError(f"B: expected shape ({n}, nu), got {tuple(B.shape)}")
        W = A if B is None else torch.cat([A, B], -1)
        if inducing > 0 and states is None:
            raise InputError("states: needed to place the inducing inputs when inducing > 0")
        f = cls(
            n,
            inducing,
            input_dim=int(W.shape[-1]) - n,
            linear=W.detach(),
            lengthscale=lengthscale,
            outputscale=NEGLIGIBLE_OUTPUTSCALE if outputscale is None else outputscale,
            dtype=A.dtype,
        )
        if inducing > 0 and states is not None:
            f.init_inducing(states, inputs)
        return f

    @classmethod
    def model_from_linear(
        cls,
        linear: LinearGaussianModel,
        *,
        inducing: int = 0,
        states: Tensor | None = None,
        inputs: Tensor | None = None,
        lengthscale: float | Tensor = 1.0,
        outputscale: float | Tensor | None = None,
    ) -> StateSpaceModel:
        """A state-space model with a GP transition that starts exactly at a linear-Gaussian
        model: the transition of :meth:`from_linear` on ``A`` (and ``B``), the full process noise
        ``Q`` as a learnable :class:`~torchfilt.models.CholeskyCovariance`, and the linear
        model's measurement side (a copy: ``H``, ``D`` and the full ``R``, as learnable as they
        are in ``linear``; fitting the new model leaves ``linear`` as it is). Its filter
        likelihood equals the linear model's Kalman likelihood.

        Args:
            linear: the linear model (e.g. :func:`~torchfilt.training.fit_em`'s result).
            inducing: number of inducing points ``M``.
            states: ``(N, n)`` states to place the inducing inputs on (required when ``M > 0``).
            inputs: ``(N, nu)`` inputs aligned with ``states``.
            lengthscale: initial lengthscales, a scalar or shape ``(n + nu,)``.
            outputscale: initial GP variances, a scalar or shape ``(n,)`` (default negligible,
                see :meth:`from_linear`).

        Returns:
            The :class:`~torchfilt.models.StateSpaceModel`.

        Raises:
            InputTypeError: ``linear`` is not a :class:`~torchfilt.models.LinearGaussianModel`.
            ModelError: ``linear`` has a time-varying ``Q``.
        """
        if not isinstance(linear, LinearGaussianModel):
            raise InputTypeError(
                f"linear: expected a LinearGaussianModel, got {type(linear).__name__}"
            )
        Q = linear.transition.noise_cov()
        if Q is None or linear.transition.time_varying_noise:
            raise ModelError("linear: its process noise Q must be constant to start a GP from it")
        f = cls.from_linear(
            linear.A, linear.B, inducing=inducing, states=states, inputs=inputs,
            lengthscale=lengthscale, outputscale=outputscale,
        )  # fmt: skip
        # a copy: fitting the GP model must not move the linear model's R (or H) in place
        h = copy.deepcopy(linear.measurement)
        return StateSpaceModel(f, h, Q=CholeskyCovariance(Q.detach().clone()))

    def lengthscale(self) -> Tensor:
        """The lengthscales ``(n + nu,)`` as the model uses them (``exp`` of the log-lengthscales
        clamped to :data:`LOG_LENGTHSCALE_BOUNDS`)."""
        return self.log_lengthscale.clamp(*LOG_LENGTHSCALE_BOUNDS).exp()

    def outputscale(self) -> Tensor:
        """The output variances ``s_j``, shape ``(n,)``, as the model uses them (clamped to
        :data:`LOG_OUTPUTSCALE_BOUNDS` in the log)."""
        return self.log_outputscale.clamp(*LOG_OUTPUTSCALE_BOUNDS).exp()

    @property
    def num_inducing(self) -> int:
        """``M``."""
        return int(self.inducing_inputs.shape[0])

    @torch.no_grad()
    def init_inducing(self, states: Tensor, inputs: Tensor | None = None) -> None:
        """Place the inducing inputs on ``M`` points of a state cloud (evenly spaced rows of it
        after sorting by the first principal direction) and set the residual outputs to 0.

        Args:
            states: ``(N, n)`` states (smoothed estimates, a nominal simulation, ...).
            inputs: ``(N, nu)`` inputs aligned with them, or ``None``.

        Raises:
            InputError: fewer points than inducing inputs.
        """
        M = self.num_inducing
        if M == 0:
            return
        z = states if inputs is None or self.input_dim == 0 else torch.cat([states, inputs], -1)
        z = z.reshape(-1, z.shape[-1]).to(self.linear.dtype)
        if z.shape[0] < M:
            raise InputError(f"states: {z.shape[0]} points for {M} inducing inputs")
        c = z - z.mean(0)
        v = torch.linalg.svd(c, full_matrices=False).Vh[0]
        order = torch.argsort(c @ v)
        idx = order[torch.linspace(0, z.shape[0] - 1, M).round().long()]
        self.inducing_inputs.copy_(z[idx])
        self.inducing_outputs.zero_()

    @torch.no_grad()
    def fit_residual(
        self,
        states: Tensor,
        next_states: Tensor,
        inputs: Tensor | None = None,
        *,
        noise: float | Tensor = 1e-2,
    ) -> None:
        """Set the inducing outputs from logged transitions ``x -> x'``: the GP posterior mean at
        the inducing inputs of the residual ``r = x' - (nominal + W z + b)`` (the deterministic
        training conditional, DTC), with the prior ``U_j ~ N(0, s_j C_ZZ)`` and noise ``noise_j``:

            U_j = s_j C_ZZ (noise_j C_ZZ + s_j C_ZX C_XZ)^{-1} C_ZX r_j

        Use it to start a measurement-only fit from whatever states a log does have (place the
        inducing inputs first, e.g. with :meth:`init_inducing` on the same states).

        Args:
            states: ``(N, n)`` logged states ``x_t``.
            next_states: ``(N, n)`` the logged states ``x_{t+1}`` that followed them.
            inputs: ``(N, nu)`` the input rows that drove each step from ``states`` to
                ``next_states`` (the input convention of :mod:`torchfilt.filters`), or ``None``.
            noise: the residual noise variance, a float or ``(n,)`` (e.g. the process noise).

        Raises:
            ShapeError: ``states``, ``next_states`` or ``inputs`` of the wrong shape.
            InputError: non-finite states, or a non-positive ``noise``.
        """
        n, M = self.out_dim, self.num_inducing
        x = torch.as_tensor(states).to(self.linear.dtype)
        xn = torch.as_tensor(next_states).to(self.linear.dtype)
        if x.dim() != 2 or x.shape[-1] != n or xn.shape != x.shape:
            raise ShapeError(
                f"states, next_states: expected two (N, {n}) tensors, got {tuple(x.shape)} and "
                f"{tuple(xn.shape)}"
            )
        if self.input_dim and (inputs is None or inputs.shape != (x.shape[0], self.input_dim)):
            raise ShapeError(f"inputs: expected ({x.shape[0]}, {self.input_dim}) for the states")
        u = None if not self.input_dim else torch.as_tensor(inputs).to(x.dtype)
        if not bool(torch.isfinite(x).all() & torch.isfinite(xn).all()):
            raise InputError("states, next_states: must be finite (drop the missing pairs)")
        if M == 0:
            return
        nz = torch.as_tensor(noise, dtype=x.dtype).expand(n)
        if not bool((nz > 0).all()):
            raise InputError("noise: must be positive")
        self.inducing_outputs.zero_()
        r = xn - self.predict(x, u).mean  # (N, n): the residual with U = 0
        z = self._inputs(x, u)
        ls = self.lengthscale()
        Zs, zs = self.inducing_inputs / ls, z / ls
        Czx = torch.exp(-0.5 * (Zs.unsqueeze(-2) - zs).pow(2).sum(-1))  # (M, N)
        Czz = torch.exp(-0.5 * (Zs.unsqueeze(-2) - Zs).pow(2).sum(-1))
        Czz = Czz + self.jitter * torch.eye(M, dtype=x.dtype)
        sc = self.outputscale()
        for j in range(n):
            S = nz[j] * Czz + sc[j] * Czx @ Czx.mT
            w = torch.linalg.solve(S, Czx @ r[:, j])
            self.inducing_outputs[j] = sc[j] * Czz @ w

    def _inputs(self, x: Tensor, u: Tensor | None) -> Tensor:
        if self.input_dim == 0:
            return x
        if u is None:
            raise InputError("this transition takes inputs (input_dim > 0); pass u")
        if u.shape[-1] != self.input_dim:
            raise ShapeError(f"u: expected (..., {self.input_dim}), got {tuple(u.shape)}")
        return torch.cat([x, u.to(x.dtype).expand(*x.shape[:-1], -1)], -1)

    def predict(self, x: Tensor, u: Tensor | None = None) -> Prediction:
        """Mean and variance at points ``x``.

        Args:
            x: states, shape ``(..., P, n)``.
            u: inputs, shape ``(..., P, nu)``, or ``None``.

        Returns:
            The :class:`~torchfilt.models.Prediction`: mean and variance, each ``(..., P, n)``.
        """
        z = self._inputs(x, u)
        mean = z @ self.linear.to(z.dtype).mT + self.bias.to(z.dtype)
        if self.nominal is not None:
            mean = mean + self.nominal(x, u)
        if self.num_inducing == 0:
            return Prediction(mean)
        ls = self.lengthscale()
        Zs = self.inducing_inputs / ls
        zs = z / ls
        d2 = (zs.unsqueeze(-2) - Zs).pow(2).sum(-1)  # (..., P, M)
        Kxz = torch.exp(-0.5 * d2)
        dzz = (Zs.unsqueeze(-2) - Zs).pow(2).sum(-1)
        M = self.num_inducing
        Kzz = torch.exp(-0.5 * dzz) + self.jitter * torch.eye(M, dtype=z.dtype, device=z.device)
        # jitter where K_ZZ is numerically singular (close inducing inputs); NaN where even that
        # fails, which a fit scores as a non-finite step (GuardedStep steps back), never a raw
        # torch LinAlgError in the middle of an optimiser's line search
        L = safe_cholesky(Kzz, name="InducingTransition K_ZZ (inducing-point kernel)")
        A = torch.cholesky_solve(Kxz.reshape(-1, M).mT, L).mT.reshape(Kxz.shape)  # K_xZ K_ZZ^-1
        mean = mean + A @ self.inducing_outputs.mT.to(z.dtype)
        q = (A * Kxz).sum(-1, keepdim=True).clamp(0.0, 1.0)  # (..., P, 1)
        var = self.outputscale() * (1.0 - q) + self.floor
        return Prediction(mean, var)
