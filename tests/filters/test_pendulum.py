"""Reproduce Särkkä & Svensson's published pendulum RMSEs (data/reference/pendulum)."""

import json
from pathlib import Path

import pytest
import torch

import torchfilt
from torchfilt.cubature import UnscentedRule
from torchfilt.systems import pendulum

DATA = Path(__file__).resolve().parents[2] / "data" / "reference" / "pendulum" / "pendulum.json"
#: the book's printed values are reproduced to this relative accuracy
PUBLISHED_RTOL = 1e-9

PUBLISHED = {
    "ckf": (0.1141966031380275, 0.04064624229594188),
    "ukf": (0.09524392125923083, 0.036617555415464256),
}


@pytest.fixture(scope="module")
def data():
    d = json.loads(DATA.read_text())
    X = torch.tensor(d["X"], dtype=torch.float64).T
    Y = torch.tensor(d["Y"], dtype=torch.float64)[:, None]
    return X, Y


@pytest.mark.parametrize("sqrt", [False, True], ids=["plain", "sqrt"])
@pytest.mark.parametrize("name", ["ckf", "ukf"])
def test_published_rmse(data, name, sqrt):
    X, Y = data
    rule = UnscentedRule(alpha=1.0, beta=0.0, kappa=None) if name == "ukf" else None
    filt = torchfilt.CKF(pendulum.model(), rule=rule, sqrt=sqrt)
    sm = filt.smooth(
        Y, x0=torch.zeros(2, dtype=torch.float64), P0=torch.eye(2, dtype=torch.float64)
    )
    rmse_f = float(torchfilt.rmse(X[:, 0], sm.filtered.mean[:, 0], dim=0))
    rmse_s = float(torchfilt.rmse(X[:, 0], sm.mean[:, 0], dim=0))
    assert rmse_f == pytest.approx(PUBLISHED[name][0], rel=PUBLISHED_RTOL)
    assert rmse_s == pytest.approx(PUBLISHED[name][1], rel=PUBLISHED_RTOL)
