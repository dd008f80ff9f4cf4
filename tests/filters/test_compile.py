"""CKF(compile=True) gives the same result as the eager filter (slow: compiles with inductor)."""

import pytest
import torch

import torchfilt
from torchfilt.systems import reentry

pytestmark = pytest.mark.slow

#: compiled kernels reorder floating-point operations; results agree to this relative tolerance
COMPILE_RTOL = 1e-9


@pytest.mark.parametrize("batch", [1, 16])
def test_compiled_filter_equals_eager(batch):
    sim = reentry.simulate_truth(batch, seed=4, steps=12)
    kw = dict(x0=torch.tensor(reentry.PRIOR_MEAN), P0=reentry.prior_cov())
    y = sim.measurements.clone()
    y[:, 5] = float("nan")
    eager = torchfilt.CKF(reentry.model()).filter(y, **kw)
    compiled = torchfilt.CKF(reentry.model(), compile=True)
    res = compiled.filter(y, **kw)
    res2 = compiled.filter(y, **kw)  # cached compiled step, guard checks skipped after warm-up
    for got in (res, res2):
        assert torch.allclose(got.mean, eager.mean, rtol=COMPILE_RTOL, atol=0)
        assert torch.allclose(got.cov, eager.cov, rtol=1e-7, atol=1e-12)
        assert torch.allclose(got.log_likelihood, eager.log_likelihood, rtol=COMPILE_RTOL)
