"""The fusion filter with the map matcher in the loop: each answer fed back as a measurement.

A drive's raw sensors (:class:`~mapmatch.sim.drive.Drive`) are fused again, fix by fix. Every
fused fix goes to a matcher (in process, or a server over gRPC); its answer's map-aided
measurement (:mod:`mapmatch.measurement`), when ``usable``, is applied at the next fix, as a
real loop would (the answer to fix k is used at fix k+1, moved on by the dead reckoning since
fix k). The filter applies the consistency rule and its χ² gate (:mod:`mapmatch.sim.kalman`).
The result is a drive like the open-loop one (same truth, same raw sensors, new fused fixes)
and the matcher's answers to those fixes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graph.projection import point_to_xy, to_lonlat
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.online import OnlineMatcher
from mapmatch.sim.drive import Drive
from mapmatch.sim.kalman import (
    DEFAULT_KALMAN,
    FilterSetup,
    KalmanConfig,
    MapAid,
    Outputs,
    filter_result,
    filter_setup,
    fused_stream,
    new_carry,
    new_outputs,
    no_map_aid,
    run_steps,
)
from mapmatch.types import Fix, MapAidedMeasurement, SnapResult

MatchFn = Callable[[Fix], SnapResult | None]
"""One fix in, the matcher's answer out (None: the fix was rejected)."""

GPS_WINDOW_S = 0.95  # as :func:`mapmatch.sim.kalman.fused_stream`: GPS-valid within this of a used fix


@dataclass(frozen=True)
class ClosedLoop:
    """A closed-loop run: the drive with its new fused fixes, and what the matcher answered.

    ``results`` one answer per fused fix (None: rejected); ``fed`` per fix whether its answer's
    measurement was fed back (usable), ``accepted`` whether the filter's χ² gate took it at the
    next fix (``rejected``: gated out).
    """

    drive: Drive
    results: list[SnapResult | None]
    fed: np.ndarray
    accepted: np.ndarray
    rejected: np.ndarray


def in_process(matcher: OnlineMatcher) -> MatchFn:
    """A :data:`MatchFn` over a new session of ``matcher``."""
    state = matcher.new_session()

    def match(fix: Fix) -> SnapResult | None:
        try:
            return matcher.update(state, fix)
        except ValidationError:
            return None

    return match


def fused_rate(drive: Drive) -> float:
    """The drive's fused output rate in Hz."""
    t = drive.fused.time
    return 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 1.0


def closed_loop_drive(
    graph: RoadGraph,
    drive: Drive,
    match: MatchFn,
    *,
    kalman: KalmanConfig = DEFAULT_KALMAN,
    feed: str = "usable",
) -> ClosedLoop:
    """Fuse ``drive``'s raw sensors again with the matcher's answers fed back.

    Parameters
    ----------
    graph
        The map the drive lies on (its CRS is the filter's).
    drive
        An open-loop drive (:func:`~mapmatch.sim.drive.simulate_drive`); its raw sensors,
        rate, vehicle id and time origin are reused, its truth is the closed loop's.
    match
        The matcher: :func:`in_process` or a :class:`ServerMatcher`.
    kalman
        The filter's configuration (the open loop's, for a fair comparison).
    feed
        ``"usable"``: feed back the answers whose measurement is usable; ``"none"``: the open
        loop, fix by fix (the same filter, the matcher only listens); ``"all"``: every answer
        on a road, ignoring ``usable`` (to show what the flag guards against).
    """
    if feed not in ("usable", "none", "all"):
        raise ValidationError("feed", "must be 'usable', 'none' or 'all'")
    rate = fused_rate(drive)
    setup = filter_setup(drive.sensors, config=kalman)
    t = setup.t
    n = len(t)
    step = max(1, round((1.0 / rate) / (t[1] - t[0]))) if n > 1 else 1
    idx = np.arange(0, n, step)
    if len(idx) != len(drive.fixes):
        raise ValidationError("drive", "its fixes do not match its sensors' filter grid")
    time0 = float(drive.fixes["time"].iloc[0] - drive.fused.time[0]) if len(idx) else 0.0
    carry = new_carry(setup.x0, setup.p0)
    out = new_outputs(n)
    aid = no_map_aid(n)
    fixes = _FusedFixes(graph.crs, setup, out, time0=time0, dt_out=step * (t[1] - t[0]) if n > 1 else 1.0)
    results: list[SnapResult | None] = []
    fed = np.zeros(len(idx), dtype=bool)
    k_prev = -1
    for i, k in enumerate(idx.tolist()):
        run_steps(setup, carry, aid, out, k_prev + 1, k + 1)
        fix = fixes.at(k_prev, k)
        res = match(fix)
        results.append(res)
        k_prev = k
        m = res.map_aided if res is not None else None
        if m is None or i + 1 >= len(idx) or feed == "none" or not (m.usable or feed == "all"):
            continue
        if not math.isfinite(m.lat):
            continue
        fed[i] = True
        _feed_back(aid, graph.crs, m, at=int(idx[i + 1]), ref=k, gps_valid=bool(fix.gps_valid))
    fused = fused_stream(filter_result(setup, out), rate=rate)
    ll = to_lonlat(graph.crs, fused.x, fused.y)
    new_fixes = drive.fixes.assign(
        lat=ll[:, 1],
        lon=ll[:, 0],
        heading=fused.heading,
        pos_sigma=fused.pos_sigma,
        heading_sigma=fused.heading_sigma,
        speed=fused.speed,
        distance=fused.distance,
        gps_valid=fused.gps_valid.astype(int),
    )
    nxt = np.r_[idx[1:], 0]
    return ClosedLoop(
        drive=dataclasses.replace(drive, fused=fused, fixes=new_fixes),
        results=results,
        fed=fed,
        accepted=fed & out.map_used[nxt],
        rejected=fed & out.map_rejected[nxt],
    )


class _FusedFixes:
    """The fix a fusion node sends at a filter step, from the filter's outputs so far: its
    state, the odometer distance corrected by the learnt scale since the last fix, and
    whether GPS was used within :data:`GPS_WINDOW_S`."""

    def __init__(self, crs: str, setup: FilterSetup, out: Outputs, *, time0: float, dt_out: float) -> None:
        self.crs, self.setup, self.out, self.time0, self.dt_out = crs, setup, out, time0, dt_out
        self.corr = 0.0
        self.corr_prev = math.nan
        self.last_used = -math.inf

    def at(self, k_prev: int, k: int) -> Fix:
        """The fix at step ``k``, the previous one having been at ``k_prev``."""
        t, out, dodo = self.setup.t, self.out, self.setup.streams.dodo
        for j in range(k_prev + 1, k + 1):
            self.corr += dodo[j] * (1.0 + out.state[j, 4])
            if out.used[j]:
                self.last_used = t[j]
        distance = 0.0 if math.isnan(self.corr_prev) else self.corr - self.corr_prev
        self.corr_prev = self.corr
        x, y = float(out.state[k, 0]), float(out.state[k, 1])
        ll = to_lonlat(self.crs, np.array([x]), np.array([y]))
        return Fix(
            time=float(t[k]) + self.time0,
            lat=float(ll[0, 1]),
            lon=float(ll[0, 0]),
            heading=float(np.degrees(out.state[k, 2]) % 360.0),
            pos_sigma=float(np.sqrt(0.5 * (out.var[k, 0] + out.var[k, 1]))),
            heading_sigma=float(np.degrees(np.sqrt(out.var[k, 2]))),
            speed=distance / self.dt_out,
            distance=distance,
            gps_valid=bool(t[k] - self.last_used <= GPS_WINDOW_S),
        )


def _feed_back(aid: MapAid, crs: str, m: MapAidedMeasurement, *, at: int, ref: int, gps_valid: bool) -> None:
    """Apply measurement ``m`` of the fix at step ``ref`` at step ``at``: the whole position
    while GPS is valid, else the cross-track and heading constraint."""
    mx, my = point_to_xy(crs, m.lon, m.lat)
    aid.mode[at] = 1 if gps_valid else 2
    aid.ref[at] = ref
    aid.x[at], aid.y[at] = mx, my
    aid.vee[at], aid.ven[at], aid.vnn[at] = m.var_e, m.cov_en, m.var_n
    aid.cross_var[at] = m.cross_sigma**2
    aid.bearing[at] = math.radians(m.heading)
    aid.head_var[at] = math.radians(m.heading_sigma) ** 2
