"""Raw sensor simulation: outages, outliers, gyro bias, odometer scale, compass disturbance."""

from __future__ import annotations

import numpy as np
import pytest

from mapmatch.errors import ValidationError
from mapmatch.sim.profile import Trajectory
from mapmatch.sim.sensors import PAPER_OUTAGES, SensorConfig, parse_outages, simulate_sensors


def _straight(duration: float = 1200.0, speed: float = 12.0) -> Trajectory:
    t = np.arange(0.0, duration + 1e-9, 0.01)
    dist = speed * t
    return Trajectory(
        dt=0.01,
        t=t,
        x=dist,
        y=np.zeros(len(t)),
        psi=np.full(len(t), np.pi / 2),
        yaw_rate=np.zeros(len(t)),
        speed=np.full(len(t), speed),
        dist=dist,
        s=dist,
    )


def test_outage_presets_and_parsing() -> None:
    assert parse_outages("paper") == list(PAPER_OUTAGES)
    assert [d for _, d in PAPER_OUTAGES] == [60, 90, 92, 83, 48]
    assert [a for a, _ in PAPER_OUTAGES] == [296, 896, 1510, 2160, 3230]
    assert parse_outages("none") == [] and parse_outages(None) == []
    assert parse_outages("30:10,5:2") == [(5.0, 2.0), (30.0, 10.0)]
    with pytest.raises(ValidationError, match="outages"):
        parse_outages("30-10")
    with pytest.raises(ValidationError, match="outages"):
        parse_outages("30:0")


def test_gps_has_no_fix_in_outages_and_rare_outliers() -> None:
    tr = _straight()
    cfg = SensorConfig(multipath_rate=0.02)
    raw = simulate_sensors(
        tr, rng=np.random.default_rng(0), outages=[(100.0, 60.0), (500.0, 92.0)], config=cfg
    )
    t = raw.gps_t
    off = ((t >= 100) & (t < 160)) | ((t >= 500) & (t < 592))
    assert np.isnan(raw.gps_x[off]).all() and not np.isnan(raw.gps_x[~off]).any()
    err = np.hypot(raw.gps_x - np.interp(t, tr.t, tr.x), raw.gps_y)
    good = ~off & ~raw.gps_outlier
    assert 1.5 < np.sqrt(np.mean(err[good] ** 2)) < 5.0
    assert 0.01 < raw.gps_outlier.mean() < 0.15
    assert np.median(err[raw.gps_outlier]) > 8.0


def test_gyro_odometer_compass_errors() -> None:
    tr = _straight()
    cfg = SensorConfig(gyro_bias=0.5, odo_scale=0.02, disturbance_per_km=0.0, compass_offset=0.0)
    raw = simulate_sensors(tr, rng=np.random.default_rng(5), config=cfg)
    assert len(raw.gyro) == len(tr.t)  # 100 Hz
    assert np.mean(raw.gyro) == pytest.approx(np.mean(raw.true_gyro_bias), abs=np.radians(0.01))
    assert np.std(raw.gyro) == pytest.approx(np.radians(0.05) * 10.0, rel=0.1)
    assert raw.odo[-1] == pytest.approx(tr.dist[-1] * (1 + raw.true_odo_scale), abs=0.05)
    assert np.all(np.diff(raw.odo) >= 0)
    cerr = (raw.compass - 90.0 + 180.0) % 360.0 - 180.0
    assert np.std(cerr) == pytest.approx(3.0, rel=0.1)
    # with magnetic disturbance, some stretches are pulled off by far more than the noise
    dis = simulate_sensors(
        tr, rng=np.random.default_rng(6), config=SensorConfig(disturbance_per_km=3.0, disturbance_deg=30.0)
    )
    derr = np.abs((dis.compass - 90.0 + 180.0) % 360.0 - 180.0)
    assert np.percentile(derr, 99.5) > 15.0
