"""The optional Plaza loader (needs gtsam, installed by the dev extra; skipped without it)."""

import numpy as np
import pytest

pytest.importorskip("gtsam")
pytest.importorskip("scipy.io")

from torchfilt.io.plaza import load_plaza, plaza_path

#: Plaza2 has 1816 range readings to 4 beacons (ids 0, 1, 5, 6)
READINGS = 1816


@pytest.fixture(scope="module")
def plaza():
    return load_plaza(2, dt=0.1)


def test_loads_all_readings_on_a_regular_grid(plaza):
    rec = plaza.recording
    assert plaza.readings == READINGS
    assert sorted(plaza.beacons) == [0, 1, 5, 6]
    assert rec.names("measurement") == [f"range_b{b}" for b in plaza.beacons]
    kept = int(np.isfinite(rec.role("measurement")).sum())
    assert kept + plaza.collisions == READINGS
    np.testing.assert_allclose(np.diff(rec.time), 0.1, rtol=1e-9)
    # partial measurements: at most one beacon per step here
    assert (np.isfinite(rec.role("measurement")).sum(1) <= 1).all()


def test_ground_truth_and_odometry_are_consistent(plaza):
    rec = plaza.recording
    x, y = rec.column("x"), rec.column("y")
    path = np.hypot(np.diff(x), np.diff(y)).sum()
    assert rec.column("odo_distance").sum() == pytest.approx(path, rel=0.01)
    # ranges agree with the surveyed beacon positions up to the known few-metre bias
    for b, (bx, by) in plaza.beacons.items():
        r = rec.column(f"range_b{b}")
        ok = np.isfinite(r)
        resid = r[ok] - np.hypot(x[ok] - bx, y[ok] - by)
        assert abs(np.median(resid)) < 5.0 and np.std(resid) < 3.0


def test_argument_errors():
    with pytest.raises(ValueError, match="which must be 1 or 2"):
        plaza_path(3)
    with pytest.raises(ValueError, match="dt must be positive"):
        load_plaza(2, dt=0.0)
