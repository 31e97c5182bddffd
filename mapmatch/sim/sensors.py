"""Raw sensors of a fusion node, simulated from the true motion (vectorised).

* GPS at 1 Hz: correlated (first-order Gauss-Markov) plus white position noise scaled by a
  slowly varying dilution of precision, multipath outliers lasting a few seconds, Doppler speed
  and course, and outages with no fix at all. Like a real receiver it reports its 1-σ accuracy
  per fix (from the dilution, with some estimation error); it does not know about multipath;
* gyro at 100 Hz: yaw rate with a constant bias, a bias random walk and white noise;
* odometer: cumulative distance with a scale-factor error and pulse quantisation;
* compass: heading with white noise, a constant offset and magnetic disturbance zones along
  the road (bridges, tram lines, parked lorries) where it is pulled off by tens of degrees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.angles import bearings
from mapmatch.errors import ValidationError
from mapmatch.sim.profile import Trajectory

# the seed papers' scenario: five outages (start s, duration s)
PAPER_OUTAGES: tuple[tuple[float, float], ...] = (
    (296.0, 60.0),
    (896.0, 90.0),
    (1510.0, 92.0),
    (2160.0, 83.0),
    (3230.0, 48.0),
)


def spread_outages(duration: float) -> list[tuple[float, float]]:
    """The paper's outages when they fit in ``duration`` s, else the same five durations spread over it.

    When even spread there would be less than 20 s of GPS between them, as many as fit with
    20 s of GPS before each.
    """
    if PAPER_OUTAGES[-1][0] + PAPER_OUTAGES[-1][1] + 30.0 <= duration:
        return list(PAPER_OUTAGES)
    durations = tuple(d for _, d in PAPER_OUTAGES)
    total = sum(durations)
    gap = (duration - total) / (len(durations) + 1)
    if gap < 20.0:  # too short for all five: as many as fit with 20 s of GPS between them
        out, t = [], 20.0
        for d in durations:
            if t + d + 20.0 > duration:
                break
            out.append((t, d))
            t += d + 20.0
        return out
    out, t = [], gap
    for d in durations:
        out.append((t, d))
        t += d + gap
    return out


def parse_outages(spec: str | Sequence[tuple[float, float]] | None) -> list[tuple[float, float]]:
    """Outages from a preset name (``"paper"``, ``"none"``) or ``"START:DUR,START:DUR"``.

    Raises :class:`ValidationError` on a malformed specification.
    """
    out: list[tuple[float, float]]
    if spec is None:
        return []
    if not isinstance(spec, str):
        out = [(float(a), float(b)) for a, b in spec]
    elif spec.strip().lower() in ("", "none"):
        return []
    elif spec.strip().lower() == "paper":
        return list(PAPER_OUTAGES)
    else:
        out = []
        for part in spec.split(","):
            try:
                sa, sb = part.split(":")
                out.append((float(sa), float(sb)))
            except ValueError:
                raise ValidationError(
                    "outages", f"expected 'paper', 'none' or START:DURATION[,...], got {part!r}"
                ) from None
    for a, b in out:
        if not (np.isfinite(a) and np.isfinite(b) and a >= 0 and b > 0):
            raise ValidationError("outages", "start must be >= 0 and duration > 0 seconds")
    return sorted(out)


@dataclass(frozen=True)
class SensorConfig:
    """Error model of the raw sensors (1-σ values unless stated).

    GPS: ``gps_white`` and ``gps_corr`` metres per axis, ``gps_corr_time`` s;
    ``multipath_rate`` outlier events per second, ``multipath_m`` (min, max) jump, lasting
    ``multipath_s`` (min, max) seconds; ``gps_speed_sigma`` m/s Doppler noise. The dilution of
    precision scales both position errors by ``exp(g)``, g Gauss-Markov with σ ``gps_dop_var``
    and correlation time ``gps_dop_time`` s; the reported σ per axis is
    ``hypot(gps_white, gps_corr) · exp(g)`` times a log-normal estimation error of σ
    ``gps_sigma_error``.
    Gyro: ``gyro_bias`` deg/s σ of the turn-on bias, ``gyro_bias_walk`` deg/s/√s,
    ``gyro_noise`` deg/s/√Hz.
    Odometer: ``odo_scale`` σ of the scale-factor error, ``odo_quantum`` metres per pulse.
    Compass: ``compass_noise`` deg, ``compass_offset`` deg σ of the constant offset,
    ``disturbance_per_km`` zones, ``disturbance_deg`` max pull, ``disturbance_m`` (min, max) length.
    """

    gps_rate: float = 1.0
    gps_white: float = 1.0
    gps_corr: float = 2.0
    gps_corr_time: float = 60.0
    multipath_rate: float = 0.01
    multipath_m: tuple[float, float] = (10.0, 40.0)
    multipath_s: tuple[float, float] = (1.0, 5.0)
    gps_speed_sigma: float = 0.2
    gps_dop_var: float = 0.25
    gps_dop_time: float = 120.0
    gps_sigma_error: float = 0.1
    gyro_rate: float = 100.0
    gyro_bias: float = 0.3
    gyro_bias_walk: float = 0.002
    gyro_noise: float = 0.05
    odo_rate: float = 10.0
    odo_scale: float = 0.02
    odo_quantum: float = 0.02
    compass_rate: float = 10.0
    compass_noise: float = 3.0
    compass_offset: float = 2.0
    disturbance_per_km: float = 2.0
    disturbance_deg: float = 30.0
    disturbance_m: tuple[float, float] = (20.0, 120.0)


DEFAULT_SENSORS = SensorConfig()


@dataclass(frozen=True)
class SensorData:
    """Raw sensor streams. Angles in degrees (bearing), gyro in rad/s clockwise positive.

    GPS arrays are NaN where there is no fix (outage); ``gps_outlier`` marks multipath fixes.
    ``odo`` is the cumulative measured distance at ``odo_t``. The ``true_*`` values are the
    realised error parameters, for tests and reports.
    """

    gps_t: NDArray[np.float64]
    gps_x: NDArray[np.float64]
    gps_y: NDArray[np.float64]
    gps_sigma: NDArray[np.float64]
    gps_speed: NDArray[np.float64]
    gps_course: NDArray[np.float64]
    gps_outlier: NDArray[np.bool_]
    gyro_t: NDArray[np.float64]
    gyro: NDArray[np.float64]
    odo_t: NDArray[np.float64]
    odo: NDArray[np.float64]
    compass_t: NDArray[np.float64]
    compass: NDArray[np.float64]
    true_gyro_bias: NDArray[np.float64]
    true_odo_scale: float
    outages: tuple[tuple[float, float], ...]


def _gauss_markov(
    n: int, dt: float, tau: float, sigma: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    """First-order Gauss-Markov sequence (stationary σ, correlation time τ), via an IIR filter."""
    if n == 0:
        return np.empty(0)
    a = np.exp(-dt / tau)
    w = rng.normal(0.0, sigma * np.sqrt(1.0 - a * a), n)
    w[0] = rng.normal(0.0, sigma)
    # x[k] = a x[k-1] + w[k]  ==  cumulative sum with geometric weights, done in blocks for stability
    out = np.empty(n)
    block = max(1, min(256, int(20.0 * tau / dt)))
    prev = 0.0
    p = a ** np.arange(block)
    for i in range(0, n, block):
        ww = w[i : i + block]
        m = len(ww)
        pw = p[:m]
        out[i : i + m] = pw * (prev * a + np.cumsum(ww / pw)) if m else ww
        prev = out[i + m - 1]
    return out


def _sample(traj: Trajectory, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    return (
        np.interp(t, traj.t, traj.x),
        np.interp(t, traj.t, traj.y),
        np.interp(t, traj.t, traj.psi),
        np.interp(t, traj.t, traj.speed),
        np.interp(t, traj.t, traj.dist),
    )


def simulate_sensors(
    traj: Trajectory,
    *,
    rng: np.random.Generator,
    outages: Sequence[tuple[float, float]] = (),
    config: SensorConfig = DEFAULT_SENSORS,
) -> SensorData:
    """Raw sensor readings for the true motion ``traj`` (GPS, gyro, odometer, then compass
    draw from ``rng`` in that order)."""
    gps = _gps(traj, rng, outages, config)
    gyro_t, gyro, bias = _gyro(traj, rng, config)
    odo_t, odo, scale = _odometer(traj, rng, config)
    compass_t, compass = _compass(traj, rng, config)
    return SensorData(
        gps_t=gps.t,
        gps_x=gps.x,
        gps_y=gps.y,
        gps_sigma=gps.sigma,
        gps_speed=gps.speed,
        gps_course=gps.course,
        gps_outlier=gps.outlier,
        gyro_t=gyro_t,
        gyro=gyro,
        odo_t=odo_t,
        odo=odo,
        compass_t=compass_t,
        compass=compass,
        true_gyro_bias=bias,
        true_odo_scale=scale,
        outages=tuple((float(a), float(b)) for a, b in outages),
    )


class _Gps(NamedTuple):
    """Receiver fixes: time, position, reported 1-σ, Doppler speed and course (NaN in
    outages), and which fixes multipath moved."""

    t: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    sigma: NDArray[np.float64]
    speed: NDArray[np.float64]
    course: NDArray[np.float64]
    outlier: NDArray[np.bool_]


def _gps(
    traj: Trajectory, rng: np.random.Generator, outages: Sequence[tuple[float, float]], config: SensorConfig
) -> _Gps:
    """GPS fixes: correlated and white noise scaled by the dilution, multipath, outages."""
    gt = np.arange(0.0, traj.duration + 1e-9, 1.0 / config.gps_rate)
    x, y, psi, v, _ = _sample(traj, gt)
    dtg = 1.0 / config.gps_rate
    ex = _gauss_markov(len(gt), dtg, config.gps_corr_time, config.gps_corr, rng)
    ey = _gauss_markov(len(gt), dtg, config.gps_corr_time, config.gps_corr, rng)
    ex += rng.normal(0.0, config.gps_white, len(gt))
    ey += rng.normal(0.0, config.gps_white, len(gt))
    dop = np.exp(_gauss_markov(len(gt), dtg, config.gps_dop_time, config.gps_dop_var, rng))
    ex *= dop
    ey *= dop
    outlier = np.zeros(len(gt), dtype=bool)
    events = np.flatnonzero(rng.random(len(gt)) < config.multipath_rate * dtg)
    for k in events:
        n = max(1, round(rng.uniform(*config.multipath_s) * config.gps_rate))
        mag = rng.uniform(*config.multipath_m)
        ang = rng.uniform(0.0, 2 * np.pi)
        ex[k : k + n] += mag * np.sin(ang)
        ey[k : k + n] += mag * np.cos(ang)
        outlier[k : k + n] = True
    sigma = np.hypot(config.gps_white, config.gps_corr) * dop
    sigma *= np.exp(rng.normal(0.0, config.gps_sigma_error, len(gt)))
    gspeed = np.maximum(v + rng.normal(0.0, config.gps_speed_sigma, len(gt)), 0.0)
    ve = v * np.sin(psi) + rng.normal(0.0, config.gps_speed_sigma, len(gt))
    vn = v * np.cos(psi) + rng.normal(0.0, config.gps_speed_sigma, len(gt))
    course = bearings(ve, vn)
    course[v < 1.0] = np.nan
    gx, gy = x + ex, y + ey
    off = np.zeros(len(gt), dtype=bool)
    for a, d in outages:
        off |= (gt >= a) & (gt < a + d)
    for arr in (gx, gy, sigma, gspeed, course):
        arr[off] = np.nan
    outlier &= ~off
    return _Gps(gt, gx, gy, sigma, gspeed, course, outlier)


def _gyro(
    traj: Trajectory, rng: np.random.Generator, config: SensorConfig
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gyro readings at the trajectory's times (rad/s), with the true bias at each."""
    n = len(traj.t)
    b0 = np.radians(rng.normal(0.0, config.gyro_bias))
    walk = np.cumsum(rng.normal(0.0, np.radians(config.gyro_bias_walk) * np.sqrt(traj.dt), n))
    bias = b0 + walk
    gyro = (
        traj.yaw_rate + bias + rng.normal(0.0, np.radians(config.gyro_noise) * np.sqrt(config.gyro_rate), n)
    )
    return traj.t, gyro, bias


def _odometer(
    traj: Trajectory, rng: np.random.Generator, config: SensorConfig
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Odometer times and cumulative distances (scale error, pulse quantisation), and the scale error."""
    ot = np.arange(0.0, traj.duration + 1e-9, 1.0 / config.odo_rate)
    od = np.interp(ot, traj.t, traj.dist)
    scale = float(rng.normal(0.0, config.odo_scale))
    odo = np.floor(od * (1.0 + scale) / config.odo_quantum) * config.odo_quantum
    return ot, odo, scale


def _compass(
    traj: Trajectory, rng: np.random.Generator, config: SensorConfig
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Compass times and headings (degrees): noise, a constant offset and disturbance zones."""
    ct = np.arange(0.0, traj.duration + 1e-9, 1.0 / config.compass_rate)
    cpsi = np.interp(ct, traj.t, traj.psi)
    cdist = np.interp(ct, traj.t, traj.dist)
    dist_total = float(traj.dist[-1]) if len(traj.t) else 0.0
    nz = rng.poisson(config.disturbance_per_km * dist_total / 1000.0)
    centre = rng.uniform(0.0, max(dist_total, 1.0), nz)
    width = rng.uniform(*config.disturbance_m, nz)
    amp = rng.uniform(-config.disturbance_deg, config.disturbance_deg, nz)
    dist_err = np.zeros(len(ct))
    for c, w_, a_ in zip(centre, width, amp, strict=True):
        dist_err += a_ * np.exp(-0.5 * ((cdist - c) / (w_ / 4.0)) ** 2)
    comp = (
        np.degrees(cpsi)
        + rng.normal(0.0, config.compass_offset)
        + dist_err
        + rng.normal(0.0, config.compass_noise, len(ct))
    ) % 360.0
    return ct, comp
