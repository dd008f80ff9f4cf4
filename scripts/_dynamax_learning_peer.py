"""dynamax (and pykalman) as timed peers of learning, run by another Python (a JAX venv).

Called by ``bench_learning.py`` in the same run as the torch rows:

    <jax-python> scripts/_dynamax_learning_peer.py IN.npz OUT.npz TASK REPEATS

TASK (every JAX function jitted; the peer's fastest form, one compiled call per timed unit):

* ``lgssm_grad``: ``jax.jit(jax.value_and_grad(loss))`` of the summed marginal log-likelihood of
  ``vmap(lgssm_filter)`` over the recordings ``y (B, T, m)`` w.r.t. ``(A, Lq, Lr)``
  (``Q = Lq Lq^T``, ``R = Lr Lr^T``); the first predicted moments ``A m0, A P0 A^T + Q`` are
  computed inside, so the gradient is the one of torchfilt's model that starts from ``N(m0, P0)``.
* ``lgssm_em``: one EM iteration as dynamax's ``fit_em`` does it (``vmap(e_step)`` and
  ``m_step`` of ``LinearGaussianSSM`` without biases), jitted as one call and timed per
  iteration over ``REPEATS`` iterations (a ``fit_em`` call re-traces, so a Python loop over the
  jitted step is its fastest form for timing per iteration). The initial state is held (dynamax's
  batched M-step of its covariance is not positive definite, and its fit diverges to NaN); ``A``,
  ``Q``, ``H`` and ``R`` are learned. Writes the log-likelihood before
  every iteration and the cumulative seconds after it.
* ``pykalman_em``: pykalman's ``KalmanFilter.em(n_iter=1)`` on the first recording (pykalman
  fits one sequence), learning ``A, Q, R`` as torchfilt's EM does; the log-likelihood (not
  timed) after every iteration.
* ``ukf_grad``: ``jax.jit(jax.value_and_grad)`` of the summed ``vmap(unscented_kalman_filter)``
  log-likelihood of the re-entry model (RK4 sub-steps in ``jax.lax.fori_loop``) w.r.t.
  ``(gamma, log q)`` (``Q = diag(exp(log q))``), with ``alpha = 1, beta = 0, kappa = 0``: the
  spherical-radial cubature rule, so the value equals torchfilt's CKF; the first prediction of
  ``N(m0, P0)`` is the same cubature transform, inside.

Prints one JSON line (median seconds of REPEATS calls after a compiling call, the compile
seconds, the versions); writes the values and gradients to ``OUT.npz``. Imports no torch and no
torchfilt.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from importlib import metadata
from typing import Any

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402


def _versions() -> dict[str, str]:
    out = {}
    for pkg in ("jax", "jaxlib", "dynamax", "pykalman", "numpy"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "missing"
    return out


def _timed(fn: Any, args: tuple, repeats: int) -> tuple[Any, float, float]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times), compile_s


def _lgssm_params(A: Any, H: Any, Q: Any, R: Any, m1: Any, P1: Any) -> Any:
    from dynamax.linear_gaussian_ssm import (
        ParamsLGSSM,
        ParamsLGSSMDynamics,
        ParamsLGSSMEmissions,
        ParamsLGSSMInitial,
    )

    n, m = A.shape[0], H.shape[0]
    return ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=m1, cov=P1),
        dynamics=ParamsLGSSMDynamics(weights=A, bias=None, input_weights=jnp.zeros((n, 0)), cov=Q),
        emissions=ParamsLGSSMEmissions(
            weights=H, bias=None, input_weights=jnp.zeros((m, 0)), cov=R
        ),
    )


def lgssm_grad(d: Any, repeats: int) -> tuple[dict[str, np.ndarray], float, float]:
    from dynamax.linear_gaussian_ssm import lgssm_filter

    H, m0, P0, y = (jnp.asarray(d[k]) for k in ("H", "m0", "P0", "y"))

    def loss(A: Any, Lq: Any, Lr: Any) -> Any:
        Q, R = Lq @ Lq.T, Lr @ Lr.T
        params = _lgssm_params(A, H, Q, R, A @ m0, A @ P0 @ A.T + Q)
        lls = jax.vmap(lambda yy: lgssm_filter(params, yy).marginal_loglik)(y)
        return lls.sum()

    fn = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))
    args = tuple(jnp.asarray(d[k]) for k in ("A", "Lq", "Lr"))
    (val, grads), secs, comp = _timed(fn, args, repeats)
    out = {"value": np.asarray(val)}
    out.update({f"grad_{k}": np.asarray(g) for k, g in zip(("A", "Lq", "Lr"), grads, strict=True)})
    return out, secs, comp


def lgssm_em(d: Any, iterations: int) -> tuple[dict[str, np.ndarray], float, float]:
    from dynamax.linear_gaussian_ssm import LinearGaussianSSM

    y = jnp.asarray(d["y"])
    n, m = d["A"].shape[0], d["H"].shape[0]
    model = LinearGaussianSSM(n, m, has_dynamics_bias=False, has_emissions_bias=False)
    params, props = model.initialize(
        jax.random.PRNGKey(0),
        initial_mean=jnp.asarray(d["m1"]),
        initial_covariance=jnp.asarray(d["P1"]),
        dynamics_weights=jnp.asarray(d["A"]),
        dynamics_covariance=jnp.asarray(d["Q"]),
        emission_weights=jnp.asarray(d["H"]),
        emission_covariance=jnp.asarray(d["R"]),
    )
    inputs = jnp.zeros((*y.shape[:2], 0))

    @jax.jit
    def step(params: Any) -> tuple[Any, Any]:
        stats, lls = jax.vmap(lambda yy, uu: model.e_step(params, yy, uu))(y, inputs)
        new, _ = model.m_step(params, props, stats, None)
        # dynamax 1.0.3's batched M-step of the initial covariance is not positive definite
        # ((sum x x^T - sum x sum x^T) / N): hold the initial state at its value
        return new._replace(initial=params.initial), lls.sum()

    t0 = time.perf_counter()
    jax.block_until_ready(step(params))
    comp = time.perf_counter() - t0
    lls, cum, per = [], [], []
    total = 0.0
    for _ in range(iterations):
        t0 = time.perf_counter()
        params, ll = jax.block_until_ready(step(params))
        dt = time.perf_counter() - t0
        total += dt
        per.append(dt)
        lls.append(float(ll))
        cum.append(total)
    out = {"log_likelihood": np.array(lls), "elapsed": np.array(cum)}
    return out, statistics.median(per), comp


def pykalman_em(d: Any, iterations: int) -> tuple[dict[str, np.ndarray], float, float]:
    from pykalman import KalmanFilter

    y = np.asarray(d["y"])[0]
    kf = KalmanFilter(
        transition_matrices=np.asarray(d["A"]),
        observation_matrices=np.asarray(d["H"]),
        transition_covariance=np.asarray(d["Q"]),
        observation_covariance=np.asarray(d["R"]),
        initial_state_mean=np.asarray(d["m1"]),
        initial_state_covariance=np.asarray(d["P1"]),
        transition_offsets=np.zeros(d["A"].shape[0]),
        observation_offsets=np.zeros(d["H"].shape[0]),
    )
    em_vars = ["transition_matrices", "transition_covariance", "observation_covariance"]
    lls, cum, per = [float(kf.loglikelihood(y))], [0.0], []
    total = 0.0
    for _ in range(iterations):
        t0 = time.perf_counter()
        kf = kf.em(y, n_iter=1, em_vars=em_vars)
        dt = time.perf_counter() - t0
        total += dt
        per.append(dt)
        lls.append(float(kf.loglikelihood(y)))
        cum.append(total)
    out = {"log_likelihood": np.array(lls), "elapsed": np.array(cum)}
    return out, statistics.median(per), 0.0


def ukf_grad(d: Any, repeats: int) -> tuple[dict[str, np.ndarray], float, float]:
    from dynamax.nonlinear_gaussian_ssm import (
        ParamsNLGSSM,
        UKFHyperParams,
        unscented_kalman_filter,
    )

    m0, P0, R, y = (jnp.asarray(d[k]) for k in ("m0", "P0", "R", "y"))
    dt, substeps = float(d["dt"]), int(d["substeps"])
    M, Hr = float(d["radar_m"]), float(d["radar_h"])
    h_sub = dt / substeps

    def make_f(gamma: Any) -> Any:
        def f(x: Any) -> Any:
            x3 = x[2]

            def acc(a: Any, v: Any) -> Any:
                return -jnp.exp(-gamma * a) * v * v * x3

            def body(_: int, s: Any) -> Any:
                a1, v1 = s
                k1a, k1v = -v1, acc(a1, v1)
                a2, v2 = a1 + 0.5 * h_sub * k1a, v1 + 0.5 * h_sub * k1v
                k2a, k2v = -v2, acc(a2, v2)
                a3, v3 = a1 + 0.5 * h_sub * k2a, v1 + 0.5 * h_sub * k2v
                k3a, k3v = -v3, acc(a3, v3)
                a4, v4 = a1 + h_sub * k3a, v1 + h_sub * k3v
                k4a, k4v = -v4, acc(a4, v4)
                return (
                    a1 + (h_sub / 6.0) * (k1a + 2.0 * k2a + 2.0 * k3a + k4a),
                    v1 + (h_sub / 6.0) * (k1v + 2.0 * k2v + 2.0 * k3v + k4v),
                )

            a, v = jax.lax.fori_loop(0, substeps, body, (x[0], x[1]))
            return jnp.stack([a, v, x3])

        return f

    def h(x: Any) -> Any:
        return jnp.sqrt(M * M + (x[:1] - Hr) ** 2)

    n = m0.shape[0]
    unit = jnp.concatenate([jnp.eye(n), -jnp.eye(n)], 0) * jnp.sqrt(n)
    hyper = UKFHyperParams(alpha=1.0, beta=0.0, kappa=0.0)

    def loss(gamma: Any, logq: Any) -> Any:
        f = make_f(gamma)
        Q = jnp.diag(jnp.exp(logq))
        pts = m0 + unit @ jnp.linalg.cholesky(P0).T  # cubature prediction of N(m0, P0)
        fx = jax.vmap(f)(pts)
        m1 = fx.mean(0)
        dx = fx - m1
        P1 = dx.T @ dx / (2 * n) + Q
        params = ParamsNLGSSM(
            initial_mean=m1, initial_covariance=P1, dynamics_function=f,
            dynamics_covariance=Q, emission_function=h, emission_covariance=R,
        )  # fmt: skip

        def one(yy: Any) -> Any:
            return unscented_kalman_filter(
                params, yy, hyper, output_fields=["filtered_means"]
            ).marginal_loglik

        return jax.vmap(one)(y).sum()

    fn = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    args = (jnp.asarray(d["gamma"]), jnp.asarray(d["logq"]))
    (val, grads), secs, comp = _timed(fn, args, repeats)
    out = {"value": np.asarray(val), "grad_gamma": np.asarray(grads[0])}
    out["grad_logq"] = np.asarray(grads[1])
    return out, secs, comp


def main() -> None:
    src, dst, task, repeats = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    d = dict(np.load(src))
    fn = {
        "lgssm_grad": lgssm_grad,
        "lgssm_em": lgssm_em,
        "pykalman_em": pykalman_em,
        "ukf_grad": ukf_grad,
    }[task]
    out, secs, comp = fn(d, repeats)
    np.savez(dst, **out)
    print(json.dumps({"seconds": secs, "compile_seconds": comp, "versions": _versions()}))


if __name__ == "__main__":
    main()
