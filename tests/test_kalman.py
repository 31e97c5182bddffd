"""The DR/GPS Kalman filter on known cases: a static vehicle, a straight drive, gyro bias."""

from __future__ import annotations

import numpy as np
import pytest

from mapmatch.sim.kalman import fused_stream, run_filter
from mapmatch.sim.profile import Trajectory
from mapmatch.sim.sensors import SensorConfig, simulate_sensors

# no multipath, no magnetic disturbance, no correlated GPS error: the cases stay exact
CLEAN = SensorConfig(gps_corr=0.0001, multipath_rate=0.0, disturbance_per_km=0.0, compass_offset=0.0)


def _line(duration: float, speed: float, heading_deg: float, rate: float = 100.0) -> Trajectory:
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    psi = np.full(len(t), np.radians(heading_deg))
    dist = speed * t
    return Trajectory(
        dt=1.0 / rate,
        t=t,
        x=1000.0 + dist * np.sin(psi),
        y=2000.0 + dist * np.cos(psi),
        psi=psi,
        yaw_rate=np.zeros(len(t)),
        speed=np.full(len(t), speed),
        dist=dist,
        s=dist,
    )


def _err(traj: Trajectory, stream) -> np.ndarray:  # type: ignore[no-untyped-def]
    x = np.interp(stream.time, traj.t, traj.x)
    y = np.interp(stream.time, traj.t, traj.y)
    return np.hypot(stream.x - x, stream.y - y)


def test_static_vehicle_stays_put_and_learns_the_bias() -> None:
    traj = _line(600.0, 0.0, 45.0)
    cfg = SensorConfig(**{**CLEAN.__dict__, "gyro_bias": 0.0, "gyro_bias_walk": 0.0})
    raw = simulate_sensors(traj, rng=np.random.default_rng(1), config=cfg)
    # a known turn-on bias of 0.5 deg/s
    raw = raw.__class__(**{**raw.__dict__, "gyro": raw.gyro + np.radians(0.5)})
    res = run_filter(raw)
    out = fused_stream(res, rate=1.0)
    err = _err(traj, out)
    assert err[60:].mean() < 1.0  # averaging 1 m white GPS noise
    assert np.all(out.distance == 0.0) and np.all(out.speed == 0.0)
    bias = np.degrees(res.state[-1, 3])
    assert bias == pytest.approx(0.5, abs=0.05)
    head = (out.heading[-100:] - 45.0 + 180.0) % 360.0 - 180.0
    assert np.abs(head).max() < 3.0


def test_straight_drive_tracks_and_learns_odometer_scale() -> None:
    traj = _line(600.0, 15.0, 80.0)
    raw = simulate_sensors(traj, rng=np.random.default_rng(2), config=CLEAN)
    res = run_filter(raw)
    out = fused_stream(res, rate=10.0)
    assert len(out.time) == pytest.approx(6001, abs=1)
    err = _err(traj, out)
    assert err[100:].mean() < 1.5
    assert np.median(out.speed[100:]) == pytest.approx(15.0, abs=0.3)
    assert np.all(out.gps_valid)
    # the filter estimates the odometer's scale error: true = measured * (1 + k)
    k = res.state[-1, 4]
    assert (1 + raw.true_odo_scale) * (1 + k) == pytest.approx(1.0, abs=0.003)


def test_outage_error_grows_like_dead_reckoning_then_recovers() -> None:
    traj = _line(400.0, 15.0, 10.0)
    raw = simulate_sensors(traj, rng=np.random.default_rng(3), outages=[(200.0, 90.0)], config=CLEAN)
    out = fused_stream(run_filter(raw), rate=1.0)
    err = _err(traj, out)
    assert not out.gps_valid[[200, 250, 289]].any() and out.gps_valid[[199, 292, 399]].all()
    inside = err[201:290]
    # dead reckoning: error (mostly) grows through the outage, stays within a few % of distance
    assert inside[-10:].mean() > inside[:10].mean()
    assert inside.max() < 0.03 * 90 * 15.0
    # the sigma the filter reports grows too
    assert out.pos_sigma[289] > 3 * out.pos_sigma[199]
    assert err[300:].mean() < 1.5


def test_gyro_bias_converges_while_turning() -> None:
    # a circle at 10 m/s, 3 deg/s: heading changes all the time
    rate = 100.0
    t = np.arange(0.0, 900.0 + 1e-9, 1.0 / rate)
    w = np.radians(3.0)
    psi = w * t
    r = 10.0 / w
    traj = Trajectory(
        dt=1.0 / rate,
        t=t,
        x=r * (1 - np.cos(psi)),
        y=r * np.sin(psi),
        psi=psi,
        yaw_rate=np.full(len(t), w),
        speed=np.full(len(t), 10.0),
        dist=10.0 * t,
        s=10.0 * t,
    )
    cfg = SensorConfig(**{**CLEAN.__dict__, "gyro_bias": 0.0, "gyro_bias_walk": 0.0})
    raw = simulate_sensors(traj, rng=np.random.default_rng(4), config=cfg)
    raw = raw.__class__(**{**raw.__dict__, "gyro": raw.gyro - np.radians(0.8)})
    res = run_filter(raw)
    est = np.degrees(res.state[:, 3])
    assert abs(est[0]) < 1e-9
    assert est[-1] == pytest.approx(-0.8, abs=0.05)
    sd = np.degrees(np.sqrt(res.var[:, 3]))
    assert sd[-1] < sd[0] / 5
    assert _err(traj, fused_stream(res, rate=1.0))[100:].mean() < 1.5
