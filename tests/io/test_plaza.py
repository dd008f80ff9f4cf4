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


#: Share of the moving steps (> MOVING m) that must go along heading + pi.
BACKWARD_SHARE = 0.99
MOVING = 0.003
#: Ranges against the ground truth: scale r / d and per-step odometry heading gain and bias.
RANGE_SCALE = (1.06, 1.08)
HEADING_GAIN = (1.005, 1.025)
HEADING_BIAS = (5e-4, 9e-4)


def _steps(plaza):
    rec = plaza.recording
    x, y, th = rec.column("x"), rec.column("y"), rec.column("heading")
    return np.diff(x), np.diff(y), th[:-1], np.diff(th)


def test_robot_travels_along_heading_plus_pi_with_unsigned_distance(plaza):
    dx, dy, th, _ = _steps(plaza)
    step = np.hypot(dx, dy)
    moving = step > MOVING
    along = (dx * np.cos(th) + dy * np.sin(th)) / np.maximum(step, 1e-12)
    assert (along[moving] < -0.5).mean() > BACKWARD_SHARE
    # it does back up (along +heading) at the end, and the odometry distance stays positive there
    backing = np.flatnonzero(moving & (along > 0.5))
    assert backing.size > 0 and backing.min() > 0.95 * step.size
    assert (plaza.recording.column("odo_distance") >= 0).all()


def test_odometry_and_ranges_are_aligned_with_the_ground_truth(plaza):
    rec = plaza.recording
    dx, dy, _, dth = _steps(plaza)
    step = np.hypot(dx, dy)
    od, oh = rec.column("odo_distance")[:-1], rec.column("odo_heading")[:-1]
    # odometry row k is the increment from row k to k + 1: lag 0 fits better than a lag of one
    for a, b in ((od, step), (oh, dth)):
        c0 = np.corrcoef(a, b)[0, 1]
        assert c0 > np.corrcoef(a[1:], b[:-1])[0, 1] and c0 > np.corrcoef(a[:-1], b[1:])[0, 1]
    gain, bias = np.polyfit(oh, dth, 1)
    assert HEADING_GAIN[0] < gain < HEADING_GAIN[1] and HEADING_BIAS[0] < bias < HEADING_BIAS[1]
    # each range sits at its nearest step: moving it one step either way fits the truth worse
    x, y = rec.column("x"), rec.column("y")
    for b, (bx, by) in plaza.beacons.items():
        r = rec.column(f"range_b{b}")
        spread = {}
        for shift in (-1, 0, 1):
            rs = np.roll(r, shift)
            ok = np.isfinite(rs)
            ok[[0, -1]] = False
            d = np.hypot(x[ok] - bx, y[ok] - by)
            scale = (rs[ok] @ d) / (d @ d)
            spread[shift] = np.std(rs[ok] - scale * d)
            if shift == 0:
                assert RANGE_SCALE[0] < scale < RANGE_SCALE[1]
        assert spread[0] < min(spread[-1], spread[1]), spread
