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
* A map-aided measurement (:mod:`mapmatch.measurement`; the closed loop of
  :mod:`mapmatch.sim.closed_loop`) refers to the state at its fix and is moved on by the dead
  reckoning since. It is not independent of that fix: while GPS is valid only its cross-track
  position and its heading are used, in dead reckoning its whole position (with its 2x2
  covariance) and its heading. It is gated like GPS (χ² on the innovation) and never resets
  the filter.

The loop runs in chunks (:func:`run_steps`, so that a closed loop can run it fix by fix) at the
filter rate in compiled code (numba).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import interpreted, njit
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
    (``max_rejects``, if set, also resets after that many rejected fixes in a row);
    ``gate_map_cross`` χ² (1 dof) on a map-aided cross-track innovation, ``gate_map_pos`` χ²
    (2 dof) on a map-aided position innovation (its heading is gated by ``gate_angle`` σ);
    ``map_corr_distance`` metres over which the map-aided measurement's error is correlated
    (lane offset, map drawing): measurements closer together count as one (their variance is
    scaled up by the ratio; 0: every one independent).
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
    gate_map_cross: float = 9.0
    gate_map_pos: float = 11.8
    map_corr_distance: float = 20.0
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
    ``dodo`` the raw odometer increment of each step; ``map_used`` / ``map_rejected`` where a
    map-aided measurement was accepted / rejected by its χ² gate.
    """

    t: NDArray[np.float64]
    state: NDArray[np.float64]
    var: NDArray[np.float64]
    cov_xy: NDArray[np.float64]
    gps_used: NDArray[np.bool_]
    gps_rejected: NDArray[np.bool_]
    dodo: NDArray[np.float64]
    map_used: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))
    map_rejected: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))


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


def fpft_lists(F, P, FP):  # type: ignore[no-untyped-def]
    """:func:`_fpft` on Python lists, for kernels run interpreted: the same products summed in
    the same order, so the same floats, in a quarter of the time of indexing the arrays (the
    filter's 8×8 products at 10 Hz are most of an interpreted drive)."""
    rows = range(P.shape[0])
    f, p = F.tolist(), P.tolist()
    fp = []
    for a in rows:
        fa, row = f[a], []
        for b in rows:
            acc = 0.0
            for c in rows:
                acc += fa[c] * p[c][b]
            row.append(acc)
        fp.append(row)
    out = []
    for a in rows:
        fpa, row = fp[a], []
        for b in rows:
            fb = f[b]
            acc = 0.0
            for c in rows:
                acc += fpa[c] * fb[c]
            row.append(acc)
        out.append(row)
    FP[:] = fp
    P[:] = out


if interpreted():
    _fpft = fpft_lists


@njit(cache=True)
def _update(X, P, h, nu, r):  # type: ignore[no-untyped-def]
    """Scalar measurement update with row ``h``."""
    n = len(X)
    ph = _matvec(P, h)
    s = _quad(h, P, h) + r
    for a in range(n):  # element-wise: an array expression costs seconds to compile
        kg = ph[a] / s
        X[a] += kg * nu
        for b in range(n):
            P[a, b] -= kg * ph[b]


class Streams(NamedTuple):
    """The sensor streams at the filter grid (NaN: no reading at that step)."""

    dtheta: NDArray[np.float64]
    dodo: NDArray[np.float64]
    comp: NDArray[np.float64]
    gx: NDArray[np.float64]
    gy: NDArray[np.float64]
    gsig: NDArray[np.float64]
    gcourse: NDArray[np.float64]
    gcsig: NDArray[np.float64]


class Params(NamedTuple):
    """The filter's constants in the units of the kernel (per step, radians)."""

    dt: float
    q: NDArray[np.float64]
    r_comp: float
    a_comp: float
    q_comp: float
    share: float
    a_gps: float
    white_steps: int
    smooth_steps: float
    gate_share: float
    gate_pos: float
    gate_ang: float
    reset_steps: int
    max_rej: int
    gate_map_cross: float
    gate_map_pos: float
    map_corr_distance: float


class MapAid(NamedTuple):
    """Map-aided measurements per filter step (``mode`` 0 none, 1 cross-track and heading
    constraint, 2 full position and heading). Each refers to the state at step ``ref`` (its
    fix) and is moved on by the dead reckoning since: ``x``/``y`` m, covariance ``vee``/``ven``/
    ``vnn`` m², ``cross_var`` m², ``bearing`` rad, ``head_var`` rad²."""

    mode: NDArray[np.int64]
    ref: NDArray[np.int64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    vee: NDArray[np.float64]
    ven: NDArray[np.float64]
    vnn: NDArray[np.float64]
    cross_var: NDArray[np.float64]
    bearing: NDArray[np.float64]
    head_var: NDArray[np.float64]


class Outputs(NamedTuple):
    """What the kernel writes per step; ``inc`` the dead-reckoning move (dx, dy, dψ) of it."""

    state: NDArray[np.float64]
    var: NDArray[np.float64]
    cxy: NDArray[np.float64]
    used: NDArray[np.bool_]
    rejected: NDArray[np.bool_]
    map_used: NDArray[np.bool_]
    map_rejected: NDArray[np.bool_]
    inc: NDArray[np.float64]


class Carry(NamedTuple):
    """The filter's state between kernel calls (``scalars``: rej_start, crej_start, rejects,
    k_fix, var_corr, sig_s, distance at the last map-aided update, distance driven)."""

    X: NDArray[np.float64]
    P: NDArray[np.float64]
    scalars: NDArray[np.float64]


def new_carry(x0: NDArray[np.float64], p0: NDArray[np.float64]) -> Carry:
    """The carry before the first step."""
    return Carry(x0.copy(), p0.copy(), np.array([-1.0, -1.0, 0.0, -1.0, -1.0, 1.0, -1e9, 0.0]))


def new_outputs(n: int) -> Outputs:
    """Empty per-step outputs for ``n`` steps."""
    z = np.zeros
    return Outputs(
        np.empty((n, N_STATE)),
        np.empty((n, N_STATE)),
        np.empty(n),
        z(n, dtype=np.bool_),
        z(n, dtype=np.bool_),
        z(n, dtype=np.bool_),
        z(n, dtype=np.bool_),
        z((n, 3)),
    )


def no_map_aid(n: int) -> MapAid:
    """No map-aided measurement at any of ``n`` steps."""
    nan = [np.full(n, np.nan) for _ in range(8)]
    return MapAid(np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64), *nan)


@njit(cache=True)
def _map_update(X, P, k, m, out, p, inflate):  # type: ignore[no-untyped-def]
    """Apply the map-aided measurement of step ``k`` (see :class:`MapAid`), gated by ``p``'s
    (:class:`Params`) map and heading gates, its variances times ``inflate`` (its error is
    correlated along the road); True when accepted."""
    gate_cross, gate_pos, gate_ang = p.gate_map_cross, p.gate_map_pos, p.gate_ang
    ns = len(X)
    # move the measurement on by the dead reckoning since its fix
    dx = dy = dpsi = 0.0
    for j in range(m.ref[k] + 1, k + 1):
        dx += out.inc[j, 0]
        dy += out.inc[j, 1]
        dpsi += out.inc[j, 2]
    zx, zy = m.x[k] + dx, m.y[k] + dy
    b = m.bearing[k] + dpsi
    hx = np.zeros(ns)
    hx[0] = 1.0
    hy = np.zeros(ns)
    hy[1] = 1.0
    hh = np.zeros(ns)
    hh[2] = 1.0
    nh = _wrap(b - X[2])
    sh = P[2, 2] + m.head_var[k]
    head_ok = nh * nh <= gate_ang * gate_ang * sh
    if m.mode[k] == 1:  # with GPS: across the road only (along, it is the fix's own projection)
        hn = np.zeros(ns)
        hn[0] = math.cos(b)
        hn[1] = -math.sin(b)
        nu = hn[0] * (zx - X[0]) + hn[1] * (zy - X[1])
        s = _quad(hn, P, hn) + m.cross_var[k]
        if nu * nu > gate_cross * s:
            return False
        _update(X, P, hn, nu, m.cross_var[k] * inflate)
    else:  # dead reckoning: the whole position
        r00, r01, r11 = m.vee[k], m.ven[k], m.vnn[k]
        s00 = P[0, 0] + r00
        s11 = P[1, 1] + r11
        s01 = P[0, 1] + r01
        nx, ny = zx - X[0], zy - X[1]
        det = s00 * s11 - s01 * s01
        if det <= 0.0 or (s11 * nx * nx - 2.0 * s01 * nx * ny + s00 * ny * ny) / det > gate_pos:
            return False
        r00, r01, r11 = r00 * inflate, r01 * inflate, r11 * inflate
        # decorrelate R: x first, then y given x (sequential scalar updates)
        _update(X, P, hx, nx, r00)
        # y's innovation with its part explained by x's removed
        ry = r11 - r01 * r01 / r00 if r00 > 0.0 else r11
        hyc = hy.copy()
        hyc[0] = -r01 / r00 if r00 > 0.0 else 0.0
        nyc = (zy - X[1]) - (r01 / r00 if r00 > 0.0 else 0.0) * (zx - X[0])
        _update(X, P, hyc, nyc, max(ry, 1e-6))
    if head_ok:
        _update(X, P, hh, _wrap(b - X[2]), m.head_var[k] * inflate)
    return True


class Work(NamedTuple):
    """The filter's scratch: the transition matrix ``F`` (set at every step), ``F P``, and the
    measurement rows of the fix (position plus its correlated error), the compass (heading
    plus its error) and the heading."""

    F: NDArray[np.float64]
    FP: NDArray[np.float64]
    h_pos: NDArray[np.float64]
    h_comp: NDArray[np.float64]
    h_head: NDArray[np.float64]


class GpsTrack(NamedTuple):
    """What the GPS update carries from fix to fix (kept in :class:`Carry`'s ``scalars``)."""

    rej_start: int
    """The step of the first of the fixes rejected in a row (-1: none)."""
    rejects: int
    """How many fixes were rejected in a row."""
    k_fix: int
    """The step of the last fix (-1: none yet)."""
    var_corr: float
    """The correlated error's variance (< 0 before the first fix)."""
    sig_s: float
    """The receiver's reported σ, smoothed."""


@njit(cache=True, inline="always")
def _work(ns):  # type: ignore[no-untyped-def]
    """A :class:`Work` for ``ns`` states."""
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
    return Work(np.zeros((ns, ns)), np.zeros((ns, ns)), h_pos, h_comp, h_head)


@njit(cache=True)
def _ekf(k0, k1, c, st, p, m, o):  # type: ignore[no-untyped-def]
    """Run the filter over steps ``k0 .. k1 - 1`` from carry ``c`` (updated in place), writing
    ``o`` (:class:`Outputs`); ``st`` :class:`Streams`, ``p`` :class:`Params`, ``m`` :class:`MapAid`
    or None (none at any step: numba then leaves the map-aided update out of this compile).
    Each step's parts are compiled into it (one compile instead of one per part)."""
    w = _work(len(c.X))
    crej_start = int(c.scalars[1])
    g = GpsTrack(int(c.scalars[0]), int(c.scalars[2]), int(c.scalars[3]), c.scalars[4], c.scalars[5])
    for k in range(k0, k1):
        if k > 0:
            _predict(k, c, st, p, w, o, g.var_corr)
        _compass_update(k, c, st, p, w.h_comp)
        crej_start = _course_update(k, c, st, p, w.h_head, crej_start)
        if not math.isnan(st.gx[k]):
            g = _gps_update(k, c, st, p, w, o, g)
        if k > 0:
            c.scalars[7] += st.dodo[k] * (1.0 + c.X[4])
        if m is not None and m.mode[k] > 0:
            # measurements closer than the map error's correlation distance are not independent
            gap = c.scalars[7] - c.scalars[6]
            inflate = min(p.map_corr_distance / max(gap, 1e-3), 1e6) if p.map_corr_distance > 0.0 else 1.0
            if _map_update(c.X, c.P, k, m, o, p, max(inflate, 1.0)):
                o.map_used[k] = True
                c.scalars[6] = c.scalars[7]
            else:
                o.map_rejected[k] = True
        _end_step(k, c.X, c.P, o)
    c.scalars[0] = g.rej_start
    c.scalars[1] = crej_start
    c.scalars[2] = g.rejects
    c.scalars[3] = g.k_fix
    c.scalars[4] = g.var_corr
    c.scalars[5] = g.sig_s


@njit(cache=True, inline="always")
def _predict(k, c, st, p, w, o, var_corr):  # type: ignore[no-untyped-def]
    """The prediction into step ``k``: heading by the gyro less its bias, position by the
    odometer times its scale at the mid-step heading (the move into ``o.inc``), the error
    states decayed, and the covariance carried by ``F`` plus the process noise (``var_corr``:
    the GPS correlated error's variance, < 0 before the first fix)."""
    X, P, F = c.X, c.P, w.F
    dt, q, a_gps, a_comp = p.dt, p.q, p.a_gps, p.a_comp
    ns = len(X)
    d0 = st.dodo[k]
    dpsi = st.dtheta[k] - X[3] * dt
    pm = X[2] + 0.5 * dpsi
    d = d0 * (1.0 + X[4])
    sn, cs = math.sin(pm), math.cos(pm)
    X[0] += d * sn
    X[1] += d * cs
    X[2] += dpsi
    o.inc[k, 0] = d * sn
    o.inc[k, 1] = d * cs
    o.inc[k, 2] = dpsi
    X[5] *= a_gps
    X[6] *= a_gps
    X[7] *= a_comp
    for a in range(ns):
        for b in range(ns):
            F[a, b] = 1.0 if a == b else 0.0
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
    _fpft(F, P, w.FP)
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
    P[7, 7] += p.q_comp


@njit(cache=True, inline="always")
def _compass_update(k, c, st, p, h_comp):  # type: ignore[no-untyped-def]
    """The compass reading of step ``k`` (heading plus the compass error), gated by
    ``gate_ang`` σ."""
    comp = st.comp[k]
    if math.isnan(comp):
        return
    nu = _wrap(comp - c.X[2] - c.X[7])
    s = _quad(h_comp, c.P, h_comp) + p.r_comp
    if nu * nu <= p.gate_ang * p.gate_ang * s:
        _update(c.X, c.P, h_comp, nu, p.r_comp)


@njit(cache=True, inline="always")
def _course_update(k, c, st, p, h_head, crej_start):  # type: ignore[no-untyped-def]
    """The GPS course of step ``k``, gated by ``gate_ang`` σ; after ``reset_steps`` of
    rejected courses (since ``crej_start``, -1: none) the heading restarts at the course.
    Returns the new ``crej_start``."""
    gcourse = st.gcourse[k]
    if math.isnan(gcourse):
        return crej_start
    X, P = c.X, c.P
    r = st.gcsig[k] ** 2
    nu = _wrap(gcourse - X[2])
    if nu * nu <= p.gate_ang * p.gate_ang * (P[2, 2] + r):
        _update(X, P, h_head, nu, r)
        crej_start = -1
    elif crej_start < 0:
        crej_start = k
    elif k - crej_start >= p.reset_steps:  # the heading has lost it: restart at the course
        for a in range(len(X)):
            P[2, a] = 0.0
            P[a, 2] = 0.0
        P[2, 2] = r
        X[2] += nu
        crej_start = -1
    return crej_start


@njit(cache=True, inline="always")
def _gps_noise(k, c, st, p, g):  # type: ignore[no-untyped-def]
    """The fix of step ``k``'s white noise variance, and ``g`` (:class:`GpsTrack`) with the
    correlated error following the receiver's (smoothed) reported σ: ``(r, g)``."""
    X, P = c.X, c.P
    share, white_steps = p.share, p.white_steps
    k_fix, sig_s = g.k_fix, g.sig_s
    sig2 = st.gsig[k] ** 2
    # fixes closer than the white error's correlation time are not independent
    gap = white_steps if k_fix < 0 else min(k - k_fix, white_steps)
    r = (1.0 - share) * sig2 * white_steps / max(gap, 1)
    if g.var_corr < 0.0:  # first fix: the correlated error's prior
        sig_s = st.gsig[k]
        P[5, 5] = share * sig2
        P[6, 6] = share * sig2
    else:
        # the dilution of precision scales the correlated error too: follow the
        # (smoothed) reported σ by scaling the error states and their covariance
        w = min(1.0, (k - k_fix) / p.smooth_steps)
        ratio = (sig_s + w * (st.gsig[k] - sig_s)) / sig_s
        sig_s *= ratio
        for a in (5, 6):
            X[a] *= ratio
            for b in range(len(X)):
                P[a, b] *= ratio
                P[b, a] *= ratio
    return r, GpsTrack(g.rej_start, g.rejects, k, share * sig_s * sig_s, sig_s)


@njit(cache=True, inline="always")
def _gps_update(k, c, st, p, w, o, g):  # type: ignore[no-untyped-def]
    """The fix of step ``k``: its noise (:func:`_gps_noise`), then gated by χ² on its
    innovation; when fixes have been rejected for ``reset_steps`` (or ``max_rej`` of them)
    in a row the position restarts at the fix. Returns the new ``g`` (:class:`GpsTrack`)."""
    X, P = c.X, c.P
    r, g = _gps_noise(k, c, st, p, g)
    rej_start, rejects = g.rej_start, g.rejects
    sig2 = st.gsig[k] ** 2
    gx, gy = st.gx[k], st.gy[k]
    hx = w.h_pos[0]
    hy = w.h_pos[1]
    # gate with at least a share of the receiver's whole variance: robust when its
    # error is whiter than assumed
    rg = max(1.0 - p.share, p.gate_share) * sig2
    s00 = _quad(hx, P, hx) + rg
    s11 = _quad(hy, P, hy) + rg
    s01 = _quad(hx, P, hy)
    nx = gx - X[0] - X[5]
    ny = gy - X[1] - X[6]
    det = s00 * s11 - s01 * s01
    d2 = (s11 * nx * nx - 2.0 * s01 * nx * ny + s00 * ny * ny) / det
    too_long = (rej_start >= 0 and k - rej_start >= p.reset_steps) or (p.max_rej > 0 and rejects >= p.max_rej)
    if d2 <= p.gate_pos or too_long:
        if d2 > p.gate_pos:  # the filter has lost it: restart the position at the fix
            for a in range(len(X)):
                P[0, a] = 0.0
                P[1, a] = 0.0
                P[a, 0] = 0.0
                P[a, 1] = 0.0
            P[0, 0] = sig2
            P[1, 1] = sig2
            X[0] = gx - X[5]
            X[1] = gy - X[6]
        else:
            _update(X, P, hx, gx - X[0] - X[5], r)
            _update(X, P, hy, gy - X[1] - X[6], r)
        o.used[k] = True
        rej_start = -1
        rejects = 0
    else:
        o.rejected[k] = True
        rejects += 1
        if rej_start < 0:
            rej_start = k
    return GpsTrack(rej_start, rejects, g.k_fix, g.var_corr, g.sig_s)


@njit(cache=True, inline="always")
def _end_step(k, X, P, o):  # type: ignore[no-untyped-def]
    """The end of step ``k``: ``P`` made symmetric, the state, variances and x-y covariance
    into ``o``."""
    ns = len(X)
    for a in range(ns):
        for b in range(a + 1, ns):
            m_ = 0.5 * (P[a, b] + P[b, a])
            P[a, b] = m_
            P[b, a] = m_
    for a in range(ns):  # element-wise: a slice assignment compiles numba's shape-error formatter
        o.state[k, a] = X[a]
        o.var[k, a] = P[a, a]
    o.cxy[k] = P[0, 1]


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


class FilterSetup(NamedTuple):
    """Everything the kernel needs: the grid ``t``, the streams, the constants, the prior."""

    t: NDArray[np.float64]
    streams: Streams
    params: Params
    x0: NDArray[np.float64]
    p0: NDArray[np.float64]


def filter_setup(sensors: SensorData, *, config: KalmanConfig = DEFAULT_KALMAN) -> FilterSetup:
    """The sensor streams on the filter grid (``config.rate`` Hz), the constants and the prior."""
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
    params = Params(
        dt,
        q,
        float(np.radians(config.compass_sigma) ** 2),
        a_comp,
        float(np.radians(config.compass_bias_sigma) ** 2 * (1.0 - a_comp**2)),
        config.gps_corr_share,
        float(np.exp(-dt / config.gps_corr_time)),
        max(1, round(config.gps_white_time * config.rate)),
        max(1.0, config.gps_sigma_smooth * config.rate),
        config.gate_gps_share,
        config.gate_pos,
        config.gate_angle,
        max(1, round(config.reject_reset_s * config.rate)),
        config.max_rejects,
        config.gate_map_cross,
        config.gate_map_pos,
        config.map_corr_distance,
    )
    streams = Streams(dtheta, dodo, comp, gx, gy, gsig, gcourse, gcsig)
    return FilterSetup(t, streams, params, x0, p0)


def run_steps(setup: FilterSetup, carry: Carry, aid: MapAid | None, out: Outputs, k0: int, k1: int) -> None:
    """Run the filter over steps ``k0 .. k1 - 1`` (carry and outputs updated in place);
    ``aid`` None: no map-aided measurement at any step (the open loop)."""
    _ekf(k0, k1, carry, setup.streams, setup.params, aid, out)


def filter_result(setup: FilterSetup, out: Outputs) -> FilterResult:
    """The :class:`FilterResult` of a finished run."""
    return FilterResult(
        t=setup.t,
        state=out.state,
        var=out.var,
        cov_xy=out.cxy,
        gps_used=out.used,
        gps_rejected=out.rejected,
        dodo=setup.streams.dodo,
        map_used=out.map_used,
        map_rejected=out.map_rejected,
    )


def run_filter(sensors: SensorData, *, config: KalmanConfig = DEFAULT_KALMAN) -> FilterResult:
    """Fuse raw sensor streams; one state per filter step (``config.rate`` Hz)."""
    setup = filter_setup(sensors, config=config)
    n = len(setup.t)
    out = new_outputs(n)
    run_steps(setup, new_carry(setup.x0, setup.p0), None, out, 0, n)
    return filter_result(setup, out)


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
