"""Step-response models: exact sampling of FOPDT/IPDT entries (fractional dead times included), array
and simulation constructors, the settling rules, and clear errors for bad input."""

import math

import numpy as np
import pytest
import scipy.integrate
import scipy.signal
import torch

from torchfilt import LinearGaussianModel
from torchfilt.dmc import FOPDT, IPDT, StepResponseModel
from torchfilt.exceptions import ShapeError

D = torch.float64
#: Agreement of two exact evaluations of the same sampled response (different formulas / op order).
EXACT_TOL = 1e-12
#: Agreement with an adaptive ODE integration run at rtol 1e-12.
ODE_TOL = 1e-9

# dead times on, between and below the sampling instants (T = 2)
DEAD_TIMES = [0.0, 0.7, 2.0, 3.3, 5.99]


def modified_z_fopdt(K, tau, theta, T, n):
    """FOPDT step response from its ZOH pulse transfer function (modified z-transform):

    G(z) = K z^{-(d+1)} [(1 - a^m) + (a^m - a) z^{-1}] / (1 - a z^{-1}),
    theta = d T + phi (0 <= phi < T), a = exp(-T/tau), m = 1 - phi/T.
    """
    d = math.floor(theta / T)
    phi = theta - d * T
    a = math.exp(-T / tau)
    am = a ** (1 - phi / T)
    b = np.zeros(d + 3)
    b[d + 1], b[d + 2] = K * (1 - am), K * (am - a)
    y = scipy.signal.lfilter(b, [1.0, -a], np.ones(n + 1))
    return y[1:]  # S_1..S_n


def ode_ipdt(K, tau, theta, T, n):
    """IPDT step response by integrating tau z' = -z + K, y' = z from t = theta."""
    t_eval = T * np.arange(1, n + 1)
    out = np.zeros(n)
    after = t_eval > theta
    if tau == 0:
        return K * np.clip(t_eval - theta, 0, None)
    sol = scipy.integrate.solve_ivp(
        lambda t, x: [x[1], (K - x[1]) / tau],
        (theta, t_eval[-1]),
        [0.0, 0.0],
        t_eval=t_eval[after],
        rtol=1e-12,
        atol=1e-14,
        method="DOP853",
    )
    out[after] = sol.y[0]
    return out


@pytest.mark.parametrize("theta", DEAD_TIMES)
@pytest.mark.parametrize("tau", [0.5, 7.0])
def test_fopdt_matches_modified_z_transform(tau, theta):
    T, n, K = 2.0, 40, -1.7
    got = FOPDT(K, tau, theta).step(T * torch.arange(1, n + 1, dtype=D)).numpy()
    np.testing.assert_allclose(got, modified_z_fopdt(K, tau, theta, T, n), rtol=0, atol=EXACT_TOL)


@pytest.mark.parametrize("theta", DEAD_TIMES)
@pytest.mark.parametrize("tau", [0.0, 0.5, 7.0])
def test_ipdt_matches_ode_integration(tau, theta):
    T, n, K = 2.0, 40, 0.3
    got = IPDT(K, tau, theta).step(T * torch.arange(1, n + 1, dtype=D)).numpy()
    np.testing.assert_allclose(got, ode_ipdt(K, tau, theta, T, n), rtol=0, atol=ODE_TOL)


@pytest.mark.parametrize("d", [0, 1, 3])
def test_ipdt_integer_delay_matches_scipy_zoh(d):
    T, n, K, tau = 1.5, 30, 0.4, 3.0
    # K / (s (tau s + 1)) in state space: y' = z, tau z' = -z + K u
    A = np.array([[0.0, 1.0], [0.0, -1.0 / tau]])
    B = np.array([[0.0], [K / tau]])
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete((A, B, np.eye(1, 2), np.zeros((1, 1))), T, "zoh")
    _, (ys,) = scipy.signal.dstep((Ad, Bd, Cd, Dd, T), n=n + 1)
    ref = np.concatenate([np.zeros(d), ys.ravel()])[1 : n + 1]
    got = IPDT(K, tau, d * T).step(T * torch.arange(1, n + 1, dtype=D)).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=EXACT_TOL)


def test_pure_gain_with_fractional_delay():
    s = FOPDT(3.0, 0.0, 2.5).step(torch.arange(1, 6, dtype=D))
    assert s.tolist() == [0.0, 0.0, 3.0, 3.0, 3.0]


def test_from_transfer_functions_layout_and_values():
    Gu = [[FOPDT(2.0, 5.0, 1.3), None], [IPDT(0.1, 2.0, 0.4), FOPDT(1.0, 3.0)]]
    Gv = [[0], [FOPDT(0.5, 1.0, 2.2)]]
    m = StepResponseModel.from_transfer_functions(Gu, Gv, dt=0.5, horizon=30)
    assert (m.ny, m.nu, m.nv, m.horizon) == (2, 2, 1, 30)
    assert m.Su.shape == (31, 2, 2) and m.Sv.shape == (31, 2, 1)
    assert m.integrating.tolist() == [False, True]  # a row with an IPDT entry is integrating
    t = 0.5 * torch.arange(1, 32, dtype=D)
    torch.testing.assert_close(m.Su[:, 0, 0], FOPDT(2.0, 5.0, 1.3).step(t), rtol=0, atol=0)
    torch.testing.assert_close(m.Sv[:, 1, 0], FOPDT(0.5, 1.0, 2.2).step(t), rtol=0, atol=0)
    assert not m.Su[:, 0, 1].any() and not m.Sv[:, 0, 0].any()
    # a stable CV may be put in the integrating layout, not the reverse
    assert m.with_layout([True, True]).integrating.tolist() == [True, True]
    with pytest.raises(ValueError, match=r"CV\(s\) \[1\] have integrating"):
        StepResponseModel.from_transfer_functions(Gu, Gv, dt=0.5, horizon=30, integrating=[1, 0])


def test_settling_rules_extend_the_horizon_model():
    Su = torch.tensor([[[1.0]], [[3.0]], [[4.0]], [[4.5]]], dtype=D)  # S_1..S_4
    stable = StepResponseModel.from_arrays(Su, horizon=3)
    # the horizon-3 stable model holds S_3 = 4 (the stored S_4 is beyond the horizon)
    assert stable.coefficients(6)[:, 0, 0].tolist() == [1.0, 3.0, 4.0, 4.0, 4.0, 4.0]
    integ = StepResponseModel.from_arrays(Su, integrating=[True], horizon=2)
    # integrating: S_1..S_{N+1} = 1, 3, 4, then slope S_3 - S_2 = 1
    assert integ.coefficients(6)[:, 0, 0].tolist() == [1.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert float(integ.steady_gain()) == 1.0 and float(stable.steady_gain()) == 4.0
    # default horizon: L for stable models, L - 1 with an integrating CV
    assert StepResponseModel.from_arrays(Su).horizon == 4
    assert StepResponseModel.from_arrays(Su, integrating=[True]).horizon == 3


def first_order_delay_lgm(K, tau, T, d):
    """ZOH-exact first order with a d-sample input delay as a LinearGaussianModel (shift register)."""
    a = math.exp(-T / tau)
    n = d + 1
    A = torch.zeros(n, n, dtype=D)
    B = torch.zeros(n, 1, dtype=D)
    A[0, 0] = a
    if d == 0:
        B[0, 0] = K * (1 - a)
    else:
        A[0, d] = K * (1 - a)  # the oldest delayed input drives the lag
        for i in range(1, d):
            A[i + 1, i] = 1.0
        B[1, 0] = 1.0
    H = torch.zeros(1, n, dtype=D)
    H[0, 0] = 1.0
    return LinearGaussianModel(A, H, torch.eye(n, dtype=D), torch.eye(1, dtype=D), B=B)


@pytest.mark.parametrize("d", [0, 2])
def test_from_simulation_of_linear_model_equals_closed_form(d):
    K, tau, T = 1.8, 4.0, 1.0
    lgm = first_order_delay_lgm(K, tau, T, d)
    n = lgm.state_dim
    # a non-equilibrium start: the baseline run removes the free response exactly
    x0 = torch.linspace(0.5, -0.3, n, dtype=D)
    m = StepResponseModel.from_simulation(lgm, x0, torch.zeros(1, dtype=D), nu=1, horizon=25)
    ref = FOPDT(K, tau, d * T).step(T * torch.arange(1, 27, dtype=D))
    torch.testing.assert_close(m.Su[:, 0, 0], ref, rtol=0, atol=EXACT_TOL)


def test_from_simulation_mv_and_dv_channels_and_interfaces():
    # two-state model, input w = [u, v]: x+ = diag(a) x + B w, y = x
    a = torch.tensor([0.8, 0.5], dtype=D)
    B = torch.tensor([[1.0, 0.2], [0.0, -0.4]], dtype=D)

    def f(x, w):
        return a * x + w @ B.mT

    def h(x):
        return x

    class Model:
        def step(self, x, w):
            return f(x, w)

        def output(self, x):
            return h(x)

    x0, w0 = torch.zeros(2, dtype=D), torch.tensor([0.3, -0.1], dtype=D)
    m1 = StepResponseModel.from_simulation((f, h), x0, w0, nu=1, horizon=10, amplitude=0.5)
    m2 = StepResponseModel.from_simulation(Model(), x0, w0, nu=1, horizon=10)
    i = torch.arange(1, 12, dtype=D)[:, None]
    # closed form: S_i = (1 - a^i) / (1 - a) * B
    ref = ((1 - a**i) / (1 - a))[:, :, None] * B  # (L, 2, 2)
    for m in (m1, m2):
        assert (m.nu, m.nv) == (1, 1)
        torch.testing.assert_close(m.Su, ref[:, :, :1], rtol=0, atol=EXACT_TOL)
        torch.testing.assert_close(m.Sv, ref[:, :, 1:], rtol=0, atol=EXACT_TOL)


def test_from_simulation_rejects_feedthrough():
    lgm = first_order_delay_lgm(1.0, 2.0, 1.0, 0)
    direct = LinearGaussianModel(
        lgm.A,
        lgm.H,
        torch.eye(1, dtype=D),
        torch.eye(1, dtype=D),
        B=lgm.B,
        D=torch.ones(1, 1, dtype=D),
    )
    with pytest.raises(ValueError, match="feed-through matrix D"):
        StepResponseModel.from_simulation(
            direct, torch.zeros(1, dtype=D), torch.zeros(1, dtype=D), nu=1, horizon=5
        )


@pytest.mark.parametrize(
    ("make", "err", "match"),
    [
        (lambda: FOPDT(1.0, -2.0, 1.0), ValueError, r"tau \(time constant\) must be non-negative"),
        (lambda: FOPDT(1.0, 2.0, -1.0), ValueError, r"theta \(dead time\) must be non-negative"),
        (lambda: IPDT(float("nan"), 2.0), ValueError, "K must be finite"),
        (lambda: FOPDT(1.0, 0.0, 0.0), ValueError, "direct feed-through"),
        (lambda: FOPDT("a", 1.0), TypeError, "K must be a real number"),
    ],
)
def test_bad_entries(make, err, match):
    with pytest.raises(err, match=match):
        make()


def test_bad_transfer_matrices_and_arrays():
    e = FOPDT(1.0, 2.0)
    with pytest.raises(ShapeError, match=r"Gu is ragged: row 0 has 2 entries but row 1 has 1"):
        StepResponseModel.from_transfer_functions([[e, e], [e]], dt=1.0, horizon=5)
    with pytest.raises(ShapeError, match="Gv has 1 rows but Gu has 2"):
        StepResponseModel.from_transfer_functions([[e], [e]], [[e]], dt=1.0, horizon=5)
    with pytest.raises(TypeError, match=r"Gu\[0\]\[1\] must be an FOPDT, an IPDT"):
        StepResponseModel.from_transfer_functions([[e, "x"]], dt=1.0, horizon=5)
    with pytest.raises(ValueError, match=r"dt .* must be positive"):
        StepResponseModel.from_transfer_functions([[e]], dt=0.0, horizon=5)
    with pytest.raises(ValueError, match="horizon must be a positive integer"):
        StepResponseModel.from_transfer_functions([[e]], dt=1.0, horizon=0)
    with pytest.raises(ShapeError, match=r"Su: expected shape \(L, ny, nu\)"):
        StepResponseModel.from_arrays(torch.zeros(5, 2))
    with pytest.raises(ShapeError, match=r"Sv: expected shape \(5, 2, nv\) to match Su"):
        StepResponseModel.from_arrays(torch.zeros(5, 2, 1), torch.zeros(4, 2, 1))
    with pytest.raises(ShapeError, match=r"Sv: expected shape \(5, 2, nv\) to match Su"):
        StepResponseModel.from_arrays(torch.zeros(5, 2, 1), torch.zeros(5, 3, 1))
    with pytest.raises(ShapeError, match="integrating: expected 2 flags"):
        StepResponseModel.from_arrays(torch.zeros(5, 2, 1), integrating=[True])
    with pytest.raises(ValueError, match="Su contains non-finite"):
        StepResponseModel.from_arrays(torch.full((5, 1, 1), float("inf")))
    with pytest.raises(ShapeError, match=r"x0: expected shape \(n,\)"):
        StepResponseModel.from_simulation(
            (lambda x, w: x, lambda x: x), torch.zeros(2, 2), torch.zeros(1), nu=1, horizon=3
        )
    with pytest.raises(ShapeError, match=r"nu = 3 must lie in 1\.\.1"):
        StepResponseModel.from_simulation(
            (lambda x, w: x, lambda x: x), torch.zeros(2), torch.zeros(1), nu=3, horizon=3
        )
    with pytest.raises(TypeError, match="model must be a torchfilt StateSpaceModel"):
        StepResponseModel.from_simulation(object(), torch.zeros(2), torch.zeros(1), nu=1, horizon=3)
