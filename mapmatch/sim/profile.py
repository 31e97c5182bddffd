"""The vehicle's true motion along a route: rounded corners and a speed profile.

The centre line is resampled every metre and smoothed (vehicles cut corners a little); the
speed is the lowest of the road's free-flow speed (times a driver factor), the curve limit
sqrt(a_lat / |curvature|) and occasional stops at intersections, then limited by the
acceleration and braking rates in a forward and a backward pass. The result is sampled on a
regular time grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graph.jit import for_size, njit
from graph.road_graph import RoadGraph
from mapmatch.sim.routes import Route, edge_speed_mps


@dataclass(frozen=True)
class ProfileConfig:
    """Driving behaviour.

    Attributes
    ----------
    lateral_accel : m/s² allowed in curves and turns.
    accel, brake : m/s² for speeding up and slowing down.
    driver_factor : fraction of the free-flow speed driven (min, max), drawn per drive.
    stop_probability : chance of stopping at an intersection (traffic light, give way).
    stop_seconds : (min, max) duration of a stop.
    smooth_m : window in metres of the corner-rounding moving average.
    start_wait : seconds standing still before driving off.
    """

    lateral_accel: float = 2.0
    accel: float = 1.5
    brake: float = 2.0
    driver_factor: tuple[float, float] = (0.85, 1.0)
    stop_probability: float = 0.15
    stop_seconds: tuple[float, float] = (5.0, 25.0)
    smooth_m: float = 9.0
    start_wait: float = 5.0


DEFAULT_PROFILE = ProfileConfig()


@dataclass(frozen=True)
class Trajectory:
    """True motion sampled every ``dt`` seconds.

    ``x, y`` metres; ``heading`` degrees clockwise from north (unwrapped radians in
    ``psi``); ``yaw_rate`` rad/s (clockwise positive); ``speed`` m/s; ``dist`` metres driven;
    ``s`` route distance of the matching centre-line point (for edge lookups).
    """

    dt: float
    t: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    psi: NDArray[np.float64]
    yaw_rate: NDArray[np.float64]
    speed: NDArray[np.float64]
    dist: NDArray[np.float64]
    s: NDArray[np.float64]

    @property
    def heading(self) -> NDArray[np.float64]:
        return np.degrees(self.psi) % 360.0

    @property
    def duration(self) -> float:
        return float(self.t[-1]) if len(self.t) else 0.0


@njit(cache=True)
def _limit_accel(vlim, ds, accel, brake):  # type: ignore[no-untyped-def]
    n = len(vlim)
    v = vlim.copy()
    for i in range(1, n):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2.0 * accel * ds[i - 1]))
    for i in range(n - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2.0 * brake * ds[i]))
    return v


def _moving_average(a: NDArray[np.float64], w: int) -> NDArray[np.float64]:
    if w <= 1 or len(a) < 3:
        return a.copy()
    w = min(w, len(a) - (1 - len(a) % 2))
    pad = w // 2
    ap = np.concatenate([np.full(pad, a[0]), a, np.full(pad, a[-1])])
    k = np.ones(w) / w
    return np.convolve(ap, k, mode="valid")[: len(a)]


def drive_profile(
    graph: RoadGraph,
    route: Route,
    *,
    rng: np.random.Generator,
    rate_hz: float = 100.0,
    config: ProfileConfig = DEFAULT_PROFILE,
) -> Trajectory:
    """Sample the true motion along ``route`` at ``rate_hz``.

    Parameters
    ----------
    graph
        The map (for free-flow speeds).
    route
        The route to drive, from standstill to standstill.
    rng
        Random source (driver factor, stops).
    rate_hz
        Sampling rate of the result (the gyro rate).
    config
        Driving behaviour.
    """
    L = route.length
    s = np.append(np.arange(0.0, L, 1.0), L)
    c = route.position(s)
    w = max(1, round(config.smooth_m))
    x = _moving_average(c[:, 0], w)
    y = _moving_average(c[:, 1], w)
    dx, dy = np.diff(x), np.diff(y)
    ds = np.maximum(np.hypot(dx, dy), 1e-6)
    seg_psi = np.unwrap(np.arctan2(dx, dy))  # bearing, radians clockwise from north
    psi = np.concatenate([[seg_psi[0]], 0.5 * (seg_psi[1:] + seg_psi[:-1]), [seg_psi[-1]]])
    curv = np.abs(np.gradient(psi)) / np.concatenate([[ds[0]], 0.5 * (ds[1:] + ds[:-1]), [ds[-1]]])
    curv = _moving_average(curv, 5)
    factor = rng.uniform(*config.driver_factor)
    edge, _ = route.locate(s)
    vlim = edge_speed_mps(graph)[edge] * factor
    vlim = np.minimum(vlim, np.sqrt(config.lateral_accel / np.maximum(curv, 1e-6)))
    # stops at some intersections
    node_s = route.node_distance()
    stop_at = node_s[rng.random(len(node_s)) < config.stop_probability]
    stop_i = np.unique(np.clip(np.round(stop_at).astype(np.int64) - 3, 1, len(s) - 2))
    vlim[stop_i] = 0.0
    vlim[0] = vlim[-1] = 0.0
    v = for_size(_limit_accel, len(vlim))(vlim, ds, config.accel, config.brake)
    # time at each metre: trapezoid, with dwell times at stops
    vm = 0.5 * (v[1:] + v[:-1])
    dt = ds / np.maximum(vm, 0.05)
    dwell = np.zeros(len(s))
    dwell[0] = config.start_wait
    dwell[stop_i] = rng.uniform(*config.stop_seconds, size=len(stop_i))
    # knots: each sample arrives at t_arr and leaves at t_arr + dwell
    t_arr = np.concatenate([[0.0], np.cumsum(dt)]) + np.concatenate([[0.0], np.cumsum(dwell[:-1])])
    t_dep = t_arr + dwell
    kt = np.empty(2 * len(s))
    kt[0::2], kt[1::2] = t_arr, t_dep
    ki = np.repeat(np.arange(len(s), dtype=np.float64), 2)
    keep = np.ones(len(kt), dtype=bool)
    keep[1::2] = dwell > 0  # departure knots only where there is a dwell
    kt, ki = kt[keep], ki[keep]
    step = 1.0 / rate_hz
    t = np.arange(0.0, kt[-1] + 1e-9, step)
    fi = np.interp(t, kt, ki)  # fractional sample index along the smoothed path
    arc = np.concatenate([[0.0], np.cumsum(ds)])
    dist = np.interp(fi, np.arange(len(s)), arc)
    tx = np.interp(fi, np.arange(len(s)), x)
    ty = np.interp(fi, np.arange(len(s)), y)
    tpsi = np.interp(fi, np.arange(len(s)), psi)
    ts = np.interp(fi, np.arange(len(s)), s)
    speed = np.gradient(dist, step)
    yaw = np.gradient(tpsi, step)
    return Trajectory(dt=step, t=t, x=tx, y=ty, psi=tpsi, yaw_rate=yaw, speed=speed, dist=dist, s=ts)
