"""Shared fixtures and named tolerances."""

from __future__ import annotations

import numpy as np
import pytest
import torch

#: float64 agreement between two exact computations of the same quantity (different op order).
TIGHT = 1e-9
#: float64 agreement between our filter and an independent reference implementation.
REF_RTOL = 1e-8
REF_ATOL = 1e-10

BATCH_SHAPES = [(), (4,), (3, 2)]


def pytest_configure(config: pytest.Config) -> None:
    # The suite is dominated by tiny tensor ops: one thread is faster and immune to spin-waiting
    # when the machine is shared. Benchmarks (scripts/) choose their own thread count.
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.fixture(scope="module")
def ray_local():
    """A local Ray instance with 2 CPUs (the CI machine's), one per test module that asks."""
    import ray  # the distributed extra; only the modules that use this fixture need it

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def random_spd(
    rng: np.random.Generator, n: int, scale: float = 1.0, cond: float = 10.0
) -> np.ndarray:
    """A random SPD matrix with eigenvalues in [scale/cond, scale]."""
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    ev = scale * np.exp(rng.uniform(np.log(1.0 / cond), 0.0, n))
    return (q * ev) @ q.T
