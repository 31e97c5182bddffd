"""Loosely coupled DR/GPS Kalman filter, as in a fusion node.

State ``[x, y, ψ, b, k, ex, ey, c]``: position (m), heading (rad, clockwise from north), gyro
bias (rad/s), odometer scale correction (true distance = measured · (1 + k)), the GPS receiver's
time-correlated position error (m; first-order Gauss-Markov) and the compass error (rad;
Gauss-Markov: offset plus slowly passing magnetic disturbances).

* Prediction every ``1/rate`` s: ψ += Δθ_gyro − b·dt; position += d·(sin ψ, cos ψ) at the
  mid-step heading, with d the odometer increment times (1 + k).
* The heading and the gyro bias are corrected by the compass (which measures ψ + c) and, when
  moving, by the GPS course; position by the GPS fix (which measures position + e) when there
  is one. The fix's noise comes from the receiver's reported 1-σ: a share ``gps_corr_share`` of
  its variance is the correlated error e, the rest white. Modelling the correlation keeps the
  covariance honest: averaging many fixes does not average away the slowly varying error.
* Every update is gated on its innovation with its covariance (χ², 2 dof for the fix), so
  multipath outliers and magnetic disturbances are rejected. When fixes (or GPS courses) have
  been rejected for ``reject_reset_s`` seconds in a row the filter, not the GPS, is wrong: the
  position (heading) is reset to the fix (course).

The loop runs at the filter rate in compiled code (numba).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.sim.sensors import SensorData

N_STATE = 8


@dataclass(frozen=True)
class KalmanConfig:
    """Noise the filter assumes (1-σ), gates and initial uncertainty.

    ``gyro_noise`` deg/s/√Hz, ``gyro_bias_walk`` deg/s/√s, ``odo_noise`` fraction of distance,
    ``pos_noise`` m/√s, ``scale_walk`` 1/√s, ``compass_sigma`` deg white compass noise,
    ``compass_bias_sigma`` deg and ``compass_bias_time`` s the compass error process,
    ``course_sigma`` deg floor and ``course_speed_noise`` m/s Doppler velocity noise of the
    GPS course (σ = hypot(noise / speed, floor)), ``course_min_speed`` m/s;
    ``gps_corr_share`` share of the reported GPS variance that is correlated over
    ``gps_corr_time`` s (the rest over ``gps_white_time`` s: faster fixes get a larger R), and
    which follows the reported σ smoothed over ``gps_sigma_smooth`` s;
    ``gate_pos`` χ² (2 dof) on the fix's innovation, whose covariance counts at least
    ``gate_gps_share`` of the reported variance; ``gate_angle`` σ; ``reject_reset_s`` seconds
    of rejected fixes before the position is reset to the fix
    (``max_rejects``, if set, also resets after that many rejected fixes in a row).
    """

    rate: float = 10.0
    gyro_noise: float = 0.06
    gyro_bias_walk: float = 0.003
    odo_noise: float = 0.01
    pos_noise: float = 0.05
    scale_walk: float = 1e-5
    compass_sigma: float = 4.0
    compass_bias_sigma: float = 6.0
    compass_bias_time: float = 20.0
    course_sigma: float = 0.3
    course_speed_noise: float = 0.2
    course_min_speed: float = 3.0
    gps_corr_share: float = 0.8
    gps_corr_time: float = 60.0
    gps_white_time: float = 1.0
    gps_sigma_smooth: float = 10.0
    gate_pos: float = 16.0
    gate_gps_share: float = 0.5
    gate_angle: float = 3.0
    reject_reset_s: float = 12.0
    max_rejects: int = 0
    init_pos_sigma: float = 5.0
    init_heading_sigma: float = 10.0
    init_bias_sigma: float = 0.5
    init_scale_sigma: float = 0.03


DEFAULT_KALMAN = KalmanConfig()


@dataclass(frozen=True)
class FilterResult:
    """Filter states at every step ``t`` (the filter rate).

    ``state`` (K, 8) and ``var`` (K, 8) (diagonal of P), ``cov_xy`` the x-y covariance;
    ``gps_used`` / ``gps_rejected`` where a GPS fix was accepted / rejected at that step;
    ``dodo`` the raw odometer increment of each step.
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
def _matvec(P, h):  # type: ignore[no-untyped-def]
    n = len(h)
    out = np.zeros(n)
    for a in range(n):
        acc = 0.0
        for b in range(n):
            acc += P[a, b] * h[b]
        out[a] = acc
    return out


@njit(cache=True)
def _quad(g, P, h):  # type: ignore[no-untyped-def]
    """g' P h."""
    ph = _matvec(P, h)
    acc = 0.0
    for a in range(len(g)):
        acc += g[a] * ph[a]
    return acc


@njit(cache=True)
def _fpft(F, P, FP):  # type: ignore[no-untyped-def]
    """P ← F P Fᵀ (FP is scratch)."""
    n = P.shape[0]
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for c in range(n):
                acc += F[a, c] * P[c, b]
            FP[a, b] = acc
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for c in range(n):
                acc += FP[a, c] * F[b, c]
            P[a, b] = acc


@njit(cache=True)
def _update(X, P, h, nu, r):  # type: ignore[no-untyped-def]
    """Scalar measurement update with row ``h``."""
    n = len(X)
    ph = _matvec(P, h)
    s = _quad(h, P, h) + r
    kg = ph / s
    for a in range(n):
        X[a] += kg[a] * nu
        for b in range(n):
            P[a, b] -= kg[a] * ph[b]


@njit(cache=True)
def _ekf(
    dtheta, dodo, comp, gx, gy, gsig, gcourse, gcsig, dt, x0, p0, q, r_comp, a_comp, q_comp,
    share, a_gps, white_steps, smooth_steps, gate_share, gate_pos, gate_ang, reset_steps, max_rej
):  # type: ignore[no-untyped-def]  # fmt: skip
    n = len(dtheta)
    ns = len(x0)
    X = x0.copy()
    P = p0.copy()
    out = np.empty((n, ns))
    var = np.empty((n, ns))
    cxy = np.empty(n)
    used = np.zeros(n, dtype=np.bool_)
    rejected = np.zeros(n, dtype=np.bool_)
    F = np.eye(ns)
    FP = np.zeros((ns, ns))
    h_pos = np.zeros((2, ns))
    h_pos[0, 0] = 1.0
    h_pos[0, 5] = 1.0
    h_pos[1, 1] = 1.0
    h_pos[1, 6] = 1.0
    h_comp = np.zeros(ns)
    h_comp[2] = 1.0
    h_comp[7] = 1.0
    h_head = np.zeros(ns)
    h_head[2] = 1.0
    rej_start = -1
    crej_start = -1
    rejects = 0
    k_fix = -1
    var_corr = -1.0
    sig_s = 1.0
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
            X[5] *= a_gps
            X[6] *= a_gps
            X[7] *= a_comp
            F[:, :] = 0.0
            for a in range(ns):
                F[a, a] = 1.0
            F[0, 2] = d * cs
            F[0, 3] = -0.5 * dt * d * cs
            F[0, 4] = d0 * sn
            F[1, 2] = -d * sn
            F[1, 3] = 0.5 * dt * d * sn
            F[1, 4] = d0 * cs
            F[2, 3] = -dt
            F[5, 5] = a_gps
            F[6, 6] = a_gps
            F[7, 7] = a_comp
            _fpft(F, P, FP)
            qpos = (q[0] * d0) ** 2 + q[1] ** 2 * dt
            P[0, 0] += qpos
            P[1, 1] += qpos
            P[2, 2] += q[2] ** 2 * dt
            P[3, 3] += q[3] ** 2 * dt
            P[4, 4] += q[4] ** 2 * dt
            if var_corr > 0.0:
                qg = var_corr * (1.0 - a_gps * a_gps)
                P[5, 5] += qg
                P[6, 6] += qg
            P[7, 7] += q_comp
        if not math.isnan(comp[k]):
            nu = _wrap(comp[k] - X[2] - X[7])
            s = _quad(h_comp, P, h_comp) + r_comp
            if nu * nu <= gate_ang * gate_ang * s:
                _update(X, P, h_comp, nu, r_comp)
        if not math.isnan(gcourse[k]):
            r = gcsig[k] ** 2
            nu = _wrap(gcourse[k] - X[2])
            if nu * nu <= gate_ang * gate_ang * (P[2, 2] + r):
                _update(X, P, h_head, nu, r)
                crej_start = -1
            elif crej_start < 0:
                crej_start = k
            elif k - crej_start >= reset_steps:  # the heading has lost it: restart at the course
                for a in range(ns):
                    P[2, a] = 0.0
                    P[a, 2] = 0.0
                P[2, 2] = r
                X[2] += nu
                crej_start = -1
        if not math.isnan(gx[k]):
            sig2 = gsig[k] ** 2
            # fixes closer than the white error's correlation time are not independent
            gap = white_steps if k_fix < 0 else min(k - k_fix, white_steps)
            r = (1.0 - share) * sig2 * white_steps / max(gap, 1)
            if var_corr < 0.0:  # first fix: the correlated error's prior
                sig_s = gsig[k]
                P[5, 5] = share * sig2
                P[6, 6] = share * sig2
            else:
                # the dilution of precision scales the correlated error too: follow the
                # (smoothed) reported σ by scaling the error states and their covariance
                w = min(1.0, (k - k_fix) / smooth_steps)
                ratio = (sig_s + w * (gsig[k] - sig_s)) / sig_s
                sig_s *= ratio
                for a in (5, 6):
                    X[a] *= ratio
                    for b in range(ns):
                        P[a, b] *= ratio
                        P[b, a] *= ratio
            k_fix = k
            var_corr = share * sig_s * sig_s
            hx = h_pos[0]
            hy = h_pos[1]
            # gate with at least a share of the receiver's whole variance: robust when its
            # error is whiter than assumed
            rg = max(1.0 - share, gate_share) * sig2
            s00 = _quad(hx, P, hx) + rg
            s11 = _quad(hy, P, hy) + rg
            s01 = _quad(hx, P, hy)
            nx = gx[k] - X[0] - X[5]
            ny = gy[k] - X[1] - X[6]
            det = s00 * s11 - s01 * s01
            d2 = (s11 * nx * nx - 2.0 * s01 * nx * ny + s00 * ny * ny) / det
            too_long = (rej_start >= 0 and k - rej_start >= reset_steps) or (
                max_rej > 0 and rejects >= max_rej
            )
            if d2 <= gate_pos or too_long:
                if d2 > gate_pos:  # the filter has lost it: restart the position at the fix
                    for a in range(ns):
                        P[0, a] = 0.0
                        P[1, a] = 0.0
                        P[a, 0] = 0.0
                        P[a, 1] = 0.0
                    P[0, 0] = sig2
                    P[1, 1] = sig2
                    X[0] = gx[k] - X[5]
                    X[1] = gy[k] - X[6]
                else:
                    _update(X, P, hx, gx[k] - X[0] - X[5], r)
                    _update(X, P, hy, gy[k] - X[1] - X[6], r)
                used[k] = True
                rej_start = -1
                rejects = 0
            else:
                rejected[k] = True
                rejects += 1
                if rej_start < 0:
                    rej_start = k
        for a in range(ns):
            for b in range(a + 1, ns):
                m = 0.5 * (P[a, b] + P[b, a])
                P[a, b] = m
                P[b, a] = m
        for a in range(ns):  # element-wise: a slice assignment compiles numba's shape-error formatter
            out[k, a] = X[a]
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
        gcsig = np.hypot(config.course_speed_noise / np.maximum(gspeed, 0.1), np.radians(config.course_sigma))
    # initial state: first GPS fix, first compass heading
    first = np.flatnonzero(~np.isnan(gx))
    x0 = np.zeros(N_STATE)
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
            0.0,
            0.0,
            np.radians(config.compass_bias_sigma) ** 2,
        ]
    )
    if len(first):
        p0[0, 0] = p0[1, 1] = max(config.init_pos_sigma, float(gsig[first[0]])) ** 2
    a_comp = float(np.exp(-dt / config.compass_bias_time))
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
        a_comp,
        np.radians(config.compass_bias_sigma) ** 2 * (1.0 - a_comp**2),
        config.gps_corr_share,
        float(np.exp(-dt / config.gps_corr_time)),
        max(1, round(config.gps_white_time * config.rate)),
        max(1.0, config.gps_sigma_smooth * config.rate),
        config.gate_gps_share,
        config.gate_pos,
        config.gate_angle,
        max(1, round(config.reject_reset_s * config.rate)),
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
