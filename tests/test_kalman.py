"""The DR/GPS Kalman filter on known cases: a static vehicle, a straight drive, gyro bias."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapmatch.sim.kalman import fused_stream, run_filter
from mapmatch.sim.profile import Trajectory
from mapmatch.sim.sensors import DEFAULT_SENSORS, SensorConfig, simulate_sensors

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
    # the gate assumes mostly correlated GPS error: with all-white error it rejects a few good fixes
    assert out.gps_valid.mean() > 0.97
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


def _sensors(sigma: float, **kw: float) -> SensorConfig:
    white = sigma / 3.0
    return replace(DEFAULT_SENSORS, gps_white=white, gps_corr=float(np.sqrt(sigma**2 - white**2)), **kw)


def _head_err(traj: Trajectory, stream) -> np.ndarray:  # type: ignore[no-untyped-def]
    th = np.degrees(np.interp(stream.time, traj.t, traj.psi))
    return np.abs((stream.heading - th + 180.0) % 360.0 - 180.0)


def test_reported_sigma_is_honest_on_a_straight_drive() -> None:
    # the GPS error is correlated over a minute: pool several drives for a fair share
    pz, hz = [], []
    for seed in range(4):
        traj = _line(900.0, 12.0, 30.0 + 40 * seed)
        raw = simulate_sensors(traj, rng=np.random.default_rng(10 + seed), config=_sensors(5.0))
        out = fused_stream(run_filter(raw), rate=1.0)
        pz.append((_err(traj, out) / out.pos_sigma)[30:])
        hz.append((_head_err(traj, out) / out.heading_sigma)[30:])
    p, h = np.concatenate(pz), np.concatenate(hz)
    # a fair 2-D σ per axis: 39 % of fixes within 1σ, 86 % within 2σ; heading 68 % and 95 %
    assert 0.2 < np.mean(p <= 1.0) < 0.6
    assert 0.65 < np.mean(p <= 2.0) < 0.98
    assert 0.5 < np.mean(h <= 1.0) < 0.92
    assert np.mean(h <= 2.0) > 0.85


def test_reported_sigma_grows_with_the_error_through_an_outage() -> None:
    pz, grow_err, grow_sig = [], [], []
    for seed in range(4):
        traj = _line(500.0, 15.0, 10.0 + 50 * seed)
        raw = simulate_sensors(
            traj, rng=np.random.default_rng(20 + seed), outages=[(200.0, 90.0)], config=_sensors(3.0)
        )
        out = fused_stream(run_filter(raw), rate=1.0)
        err = _err(traj, out)
        pz.append((err / out.pos_sigma)[200:290])
        grow_err.append(err[280:290].mean() - err[200:210].mean())
        grow_sig.append(out.pos_sigma[289] / out.pos_sigma[199])
    p = np.concatenate(pz)
    assert np.mean(p <= 2.0) > 0.6 and np.mean(p <= 1.0) < 0.9
    assert np.mean(grow_err) > 0 and min(grow_sig) > 1.3


@pytest.mark.parametrize(("sigma", "gps_rate"), [(3.0, 1.0), (3.0, 10.0), (10.0, 1.0), (10.0, 10.0)])
def test_a_multipath_outlier_barely_moves_the_fused_position(sigma: float, gps_rate: float) -> None:
    traj = _line(400.0, 12.0, 60.0)
    sens = _sensors(sigma, multipath_rate=0.0, gps_rate=gps_rate)
    raw = simulate_sensors(traj, rng=np.random.default_rng(7), config=sens)
    clean = fused_stream(run_filter(raw), rate=10.0)
    # a 4 s, 40 m jump at 200 s, the receiver still reporting its usual σ
    hit = (raw.gps_t >= 200.0) & (raw.gps_t < 204.0)
    bad = replace(raw, gps_x=raw.gps_x + 40.0 * hit * np.sin(1.0), gps_y=raw.gps_y + 40.0 * hit * np.cos(1.0))
    res = run_filter(bad)
    out = fused_stream(res, rate=10.0)
    moved = np.hypot(out.x - clean.x, out.y - clean.y)
    assert moved.max() < 3.0
    if sigma <= 5.0:  # 40 m is 13σ: the gate rejects every one of those fixes
        k = np.round(raw.gps_t[hit] * 10.0).astype(int)
        assert res.gps_rejected[k].all()


def test_a_filter_that_has_lost_it_resets_to_the_gps() -> None:
    traj = _line(400.0, 12.0, 60.0)
    raw = simulate_sensors(traj, rng=np.random.default_rng(8), config=CLEAN)
    # the compass reads 60 deg off from the start: the first heading is wrong and every GPS
    # course is rejected by the gate until the heading is reset to the course
    bad = replace(raw, compass=(raw.compass + 60.0) % 360.0)
    res = run_filter(bad)
    out = fused_stream(res, rate=1.0)
    assert _head_err(traj, out)[30:].max() < 3.0
    assert _err(traj, out)[60:].mean() < 1.5
    # the receiver is right after a jump of 150 m (a new satellite set, say): after
    # ``reject_reset_s`` seconds of rejected fixes the position restarts at the fixes
    jump = raw.gps_t >= 200.0
    moved = replace(raw, gps_x=raw.gps_x + 150.0 * jump)
    res = run_filter(moved)
    out = fused_stream(res, rate=1.0)
    # (then only the few good fixes an all-white receiver loses to the gate, see above)
    assert res.gps_rejected[2000:2100].any() and res.gps_rejected[2300:].sum() <= 10
    e = np.hypot(
        out.x - np.interp(out.time, traj.t, traj.x) - 150.0, out.y - np.interp(out.time, traj.t, traj.y)
    )
    assert e[230:].max() < 3.0
