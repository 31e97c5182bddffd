"""Loosely coupled DR/GPS Kalman filter, as in a fusion node.

State ``[x, y, ψ, b, k]``: position (m), heading (rad, clockwise from north), gyro bias
(rad/s) and odometer scale correction (true distance = measured · (1 + k)).

* Prediction every ``1/rate`` s: ψ += Δθ_gyro − b·dt; position += d·(sin ψ, cos ψ) at the
  mid-step heading, with d the odometer increment times (1 + k).
* The heading and the gyro bias are corrected by the compass and, when moving, by the GPS
  course; position (and through the cross-covariances heading, bias and scale) by the GPS fix
  when there is one. Each update is gated on its innovation (χ²), so multipath outliers and
  magnetic disturbances are mostly rejected; after ``max_rejects`` rejected fixes in a row the
  GPS is trusted again (the filter, not the GPS, is then the one that is wrong).

The loop runs at the filter rate in compiled code (numba).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.sim.sensors import SensorData


@dataclass(frozen=True)
class KalmanConfig:
    """Noise the filter assumes (1-σ), gates and initial uncertainty.

    ``gyro_noise`` deg/s/√Hz, ``gyro_bias_walk`` deg/s/√s, ``odo_noise`` fraction of distance,
    ``pos_noise`` m/√s, ``scale_walk`` 1/√s, ``compass_sigma`` deg, ``course_sigma`` deg floor,
    ``course_min_speed`` m/s, ``gate_pos`` χ² (2 dof), ``gate_angle`` σ.
    """

    rate: float = 10.0
    gyro_noise: float = 0.07
    gyro_bias_walk: float = 0.005
    odo_noise: float = 0.01
    pos_noise: float = 0.05
    scale_walk: float = 1e-5
    compass_sigma: float = 5.0
    course_sigma: float = 1.5
    course_min_speed: float = 3.0
    gate_pos: float = 16.0
    gate_angle: float = 3.0
    max_rejects: int = 5
    init_pos_sigma: float = 5.0
    init_heading_sigma: float = 10.0
    init_bias_sigma: float = 0.5
    init_scale_sigma: float = 0.03


DEFAULT_KALMAN = KalmanConfig()


@dataclass(frozen=True)
class FilterResult:
    """Filter states at every step ``t`` (the filter rate).

    ``state`` (K, 5) and ``var`` (K, 5) (diagonal of P); ``gps_used`` where a GPS fix was
    accepted at that step; ``dodo`` the raw odometer increment of each step.
    """

    t: NDArray[np.float64]
    state: NDArray[np.float64]
    var: NDArray[np.float64]
    cov_xy: NDArray[np.float64]
    gps_used: NDArray[np.bool_]
    gps_rejected: NDArray[np.bool_]
    dodo: NDArray[np.float64]


@njit(cache=True)
def _wrap(a):  # type: ignore[no-untyped-def]
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@njit(cache=True)
def _update1(X, P, i, nu, r):  # type: ignore[no-untyped-def]
    s = P[i, i] + r
    kg = P[:, i] / s
    row = P[i, :].copy()
    for a in range(5):
        X[a] += kg[a] * nu
        for b in range(5):
            P[a, b] -= kg[a] * row[b]


@njit(cache=True)
def _ekf(
    dtheta, dodo, comp, gx, gy, gsig, gcourse, gcsig, dt, x0, p0, q, r_comp, gate_pos, gate_ang, max_rej
):  # type: ignore[no-untyped-def]
    n = len(dtheta)
    X = x0.copy()
    P = p0.copy()
    out = np.empty((n, 5))
    var = np.empty((n, 5))
    cxy = np.empty(n)
    used = np.zeros(n, dtype=np.bool_)
    rejected = np.zeros(n, dtype=np.bool_)
    F = np.eye(5)
    FP = np.zeros((5, 5))
    rejects = 0
    for k in range(n):
        if k > 0:
            d0 = dodo[k]
            dpsi = dtheta[k] - X[3] * dt
            pm = X[2] + 0.5 * dpsi
            d = d0 * (1.0 + X[4])
            sn, cs = math.sin(pm), math.cos(pm)
            X[0] += d * sn
            X[1] += d * cs
            X[2] += dpsi
            F[:, :] = 0.0
            for a in range(5):
                F[a, a] = 1.0
            F[0, 2] = d * cs
            F[0, 3] = -0.5 * dt * d * cs
            F[0, 4] = d0 * sn
            F[1, 2] = -d * sn
            F[1, 3] = 0.5 * dt * d * sn
            F[1, 4] = d0 * cs
            F[2, 3] = -dt
            for a in range(5):
                for b in range(5):
                    acc = 0.0
                    for c in range(5):
                        acc += F[a, c] * P[c, b]
                    FP[a, b] = acc
            for a in range(5):
                for b in range(5):
                    acc = 0.0
                    for c in range(5):
                        acc += FP[a, c] * F[b, c]
                    P[a, b] = acc
            qpos = (q[0] * d0) ** 2 + q[1] ** 2 * dt
            P[0, 0] += qpos
            P[1, 1] += qpos
            P[2, 2] += q[2] ** 2 * dt
            P[3, 3] += q[3] ** 2 * dt
            P[4, 4] += q[4] ** 2 * dt
        if not math.isnan(comp[k]):
            nu = _wrap(comp[k] - X[2])
            if nu * nu <= gate_ang * gate_ang * (P[2, 2] + r_comp):
                _update1(X, P, 2, nu, r_comp)
        if not math.isnan(gcourse[k]):
            r = gcsig[k] ** 2
            nu = _wrap(gcourse[k] - X[2])
            if nu * nu <= gate_ang * gate_ang * (P[2, 2] + r):
                _update1(X, P, 2, nu, r)
        if not math.isnan(gx[k]):
            r = gsig[k] ** 2
            s00 = P[0, 0] + r
            s11 = P[1, 1] + r
            s01 = P[0, 1]
            det = s00 * s11 - s01 * s01
            nx = gx[k] - X[0]
            ny = gy[k] - X[1]
            d2 = (s11 * nx * nx - 2.0 * s01 * nx * ny + s00 * ny * ny) / det
            if d2 <= gate_pos or rejects >= max_rej:
                _update1(X, P, 0, gx[k] - X[0], r)
                _update1(X, P, 1, gy[k] - X[1], r)
                used[k] = True
                rejects = 0
            else:
                rejected[k] = True
                rejects += 1
        for a in range(5):
            for b in range(a + 1, 5):
                m = 0.5 * (P[a, b] + P[b, a])
                P[a, b] = m
                P[b, a] = m
        out[k, :] = X
        for a in range(5):
            var[k, a] = P[a, a]
        cxy[k] = P[0, 1]
    return out, var, cxy, used, rejected


def _at_grid(
    t: NDArray[np.float64], ts: NDArray[np.float64], vals: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Values of a sensor stream at the filter grid: the reading at the same instant, else NaN."""
    out = np.full(len(t), np.nan)
    if len(ts) == 0:
        return out
    i = np.clip(np.searchsorted(ts, t - 1e-6), 0, len(ts) - 1)
    hit = np.abs(ts[i] - t) < 1e-6
    out[hit] = vals[i[hit]]
    return out


def run_filter(sensors: SensorData, *, config: KalmanConfig = DEFAULT_KALMAN) -> FilterResult:
    """Fuse raw sensor streams; one state per filter step (``config.rate`` Hz)."""
    dt = 1.0 / config.rate
    T = float(max(sensors.odo_t[-1], sensors.gps_t[-1])) if len(sensors.odo_t) else 0.0
    t = np.arange(0.0, T + 1e-9, dt)
    # gyro: integral of the rate up to each grid time
    g_int = np.concatenate(
        [[0.0], np.cumsum(0.5 * (sensors.gyro[1:] + sensors.gyro[:-1]) * np.diff(sensors.gyro_t))]
    )
    theta = np.interp(t, sensors.gyro_t, g_int)
    dtheta = np.diff(theta, prepend=theta[0])
    odo = np.interp(t, sensors.odo_t, sensors.odo)
    dodo = np.diff(odo, prepend=odo[0])
    comp = np.radians(_at_grid(t, sensors.compass_t, sensors.compass))
    gx = _at_grid(t, sensors.gps_t, sensors.gps_x)
    gy = _at_grid(t, sensors.gps_t, sensors.gps_y)
    gsig = _at_grid(t, sensors.gps_t, sensors.gps_sigma)
    gspeed = _at_grid(t, sensors.gps_t, sensors.gps_speed)
    gcourse = np.radians(_at_grid(t, sensors.gps_t, sensors.gps_course))
    gcourse[~(gspeed >= config.course_min_speed)] = np.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        gcsig = np.hypot(0.3 / np.maximum(gspeed, 0.1), np.radians(config.course_sigma))
    # initial state: first GPS fix, first compass heading
    first = np.flatnonzero(~np.isnan(gx))
    x0 = np.zeros(5)
    if len(first):
        x0[0], x0[1] = gx[first[0]], gy[first[0]]
    fc = np.flatnonzero(~np.isnan(comp))
    x0[2] = comp[fc[0]] if len(fc) else 0.0
    p0 = np.diag(
        [
            config.init_pos_sigma**2,
            config.init_pos_sigma**2,
            np.radians(config.init_heading_sigma) ** 2,
            np.radians(config.init_bias_sigma) ** 2,
            config.init_scale_sigma**2,
        ]
    )
    q = np.array(
        [
            config.odo_noise,
            config.pos_noise,
            np.radians(config.gyro_noise),
            np.radians(config.gyro_bias_walk),
            config.scale_walk,
        ]
    )
    state, var, cxy, used, rejected = _ekf(
        dtheta,
        dodo,
        comp,
        gx,
        gy,
        gsig,
        gcourse,
        gcsig,
        dt,
        x0,
        p0,
        q,
        np.radians(config.compass_sigma) ** 2,
        config.gate_pos,
        config.gate_angle,
        config.max_rejects,
    )
    return FilterResult(
        t=t, state=state, var=var, cov_xy=cxy, gps_used=used, gps_rejected=rejected, dodo=dodo
    )


@dataclass(frozen=True)
class FusedStream:
    """The fusion node's output at the fused rate (what a vehicle sends to the matcher)."""

    time: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    heading: NDArray[np.float64]
    pos_sigma: NDArray[np.float64]
    heading_sigma: NDArray[np.float64]
    speed: NDArray[np.float64]
    distance: NDArray[np.float64]
    gps_valid: NDArray[np.bool_]


def fused_stream(result: FilterResult, *, rate: float = 1.0, gps_window: float = 0.95) -> FusedStream:
    """Subsample the filter to ``rate`` Hz (1 or 10).

    ``distance`` is the scale-corrected odometer distance since the previous output (0 for the
    first), ``speed`` that distance over the output interval, ``gps_valid`` whether a GPS fix
    was accepted within the last ``gps_window`` seconds, ``pos_sigma`` √((σx² + σy²)/2).
    """
    step = max(1, round((1.0 / rate) / (result.t[1] - result.t[0]))) if len(result.t) > 1 else 1
    idx = np.arange(0, len(result.t), step)
    st = result.state
    corr = np.cumsum(result.dodo * (1.0 + st[:, 4]))
    cd = corr[idx]
    distance = np.diff(cd, prepend=cd[0])
    dt_out = step * (result.t[1] - result.t[0]) if len(result.t) > 1 else 1.0
    used_t = result.t[result.gps_used]
    last = np.searchsorted(used_t, result.t[idx] + 1e-9) - 1
    valid = (
        (last >= 0) & (result.t[idx] - used_t[np.maximum(last, 0)] <= gps_window)
        if len(used_t)
        else (np.zeros(len(idx), dtype=bool))
    )
    return FusedStream(
        time=result.t[idx],
        x=st[idx, 0],
        y=st[idx, 1],
        heading=np.degrees(st[idx, 2]) % 360.0,
        pos_sigma=np.sqrt(0.5 * (result.var[idx, 0] + result.var[idx, 1])),
        heading_sigma=np.degrees(np.sqrt(result.var[idx, 2])),
        speed=distance / dt_out,
        distance=distance,
        gps_valid=np.asarray(valid, dtype=bool),
    )
