"""dynamax's Kalman filter and smoother as a timed peer, run by another Python (a JAX venv).

Called by ``bench_linear.py`` and ``bench_parallel.py`` in the same run as the torch rows:

    <jax-python> scripts/_dynamax_peer.py IN.npz OUT.npz TASK REPEATS

``IN.npz`` holds ``A, H, Q, R, m1, P1`` and ``y`` (``(T, m)`` or ``(B, T, m)``, then vmapped).
dynamax starts with an update of ``N(m1, P1)``; the caller passes torchfilt's first predicted
moments so both compute the same posterior. TASK is ``filter``, ``smoother``, ``parallel_filter``
or ``parallel_smoother``. Prints one JSON line: the median seconds of REPEATS jitted calls (after a
compiling warm-up) and the JAX version; writes the means (and the log-likelihood) to ``OUT.npz``.
Imports no torch and no torchfilt.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
from dynamax.linear_gaussian_ssm import (  # noqa: E402
    ParamsLGSSM,
    ParamsLGSSMDynamics,
    ParamsLGSSMEmissions,
    ParamsLGSSMInitial,
    lgssm_filter,
    lgssm_smoother,
    parallel_lgssm_filter,
    parallel_lgssm_smoother,
)


def main() -> None:
    src, dst, task, repeats = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    d = np.load(src)
    n, m = d["A"].shape[0], d["H"].shape[0]
    params = ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=jnp.asarray(d["m1"]), cov=jnp.asarray(d["P1"])),
        dynamics=ParamsLGSSMDynamics(
            weights=jnp.asarray(d["A"]),
            bias=jnp.zeros(n),
            input_weights=jnp.zeros((n, 0)),
            cov=jnp.asarray(d["Q"]),
        ),
        emissions=ParamsLGSSMEmissions(
            weights=jnp.asarray(d["H"]),
            bias=jnp.zeros(m),
            input_weights=jnp.zeros((m, 0)),
            cov=jnp.asarray(d["R"]),
        ),
    )
    fn = {
        "filter": lgssm_filter,
        "smoother": lgssm_smoother,
        "parallel_filter": parallel_lgssm_filter,
        "parallel_smoother": parallel_lgssm_smoother,
    }[task]
    smoothing = task.endswith("smoother")

    def one(y: jax.Array) -> tuple[jax.Array, jax.Array]:
        post = fn(params, y)
        mean = post.smoothed_means if smoothing else post.filtered_means
        return mean, post.marginal_loglik

    y = jnp.asarray(d["y"])
    run = jax.jit(one if y.ndim == 2 else jax.vmap(one))
    jax.block_until_ready(run(y))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(run(y))
        times.append(time.perf_counter() - t0)
    np.savez(dst, mean=np.asarray(out[0]), loglik=np.asarray(out[1]))
    print(json.dumps({"seconds": statistics.median(times), "jax": jax.__version__}))


if __name__ == "__main__":
    main()
