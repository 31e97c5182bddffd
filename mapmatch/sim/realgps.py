"""A fused drive from a real GPS track and its true route (Kubicka tracks), for benchmarks.

The simulator (:func:`mapmatch.sim.drive.simulate_drive`) moves *simulated* GPS along a true
route. Here the GPS-aided positions are a real receiver's fixes instead, with the errors of
real receivers (biases that last minutes, multipath, lag at turns); only the dead-reckoning
sensors are modelled. The result is the same :class:`~mapmatch.sim.drive.Drive`, so the same
scoring, ``write_fixes_csv`` and ``mapmatch replay`` apply.

Steps (:func:`real_drive`):

1. The true route: ``truth.geojson`` is turned into an edge path on the prepared map
   geometrically: the map's edges come from the same ``roads.geojson``, so the truth's vertices
   at map nodes give the node sequence and the edges between them the path (U-turns allowed,
   as real drives turn round; :func:`route_from_truth`), else the geometry is followed by
   :func:`~mapmatch.sim.routes.route_from_geometry`. The path is cut to where the first and
   last fixes lie.
2. The true motion: each real fix is projected onto the route within a window ahead of the
   previous one (at most ``max_speed_mps`` times the time step, plus a little), the route
   distances are smoothed over ``timing_smooth_s`` and made non-decreasing by an isotonic
   (least-squares) fit: a running maximum would carry the largest forward excursion of the
   GPS through every stop. This gives the true route distance at every fix time; between
   fixes it is interpolated linearly. The true heading is the route's tangent over
   ±``heading_base_m``.
   Where no fix lies within ``truth_radius_m`` of the route for longer than
   ``truth_max_gap_s`` (a long gap in the track, or the vehicle off the mapped roads: parked
   in a yard, before the true route begins or after it ends), the truth only holds a place on
   the route: its ``truth_known`` column is false there and the benchmarks do not score the
   road of those fixes.
3. The fused output, on a base grid of 10 Hz, subsampled to 1 Hz:

   * **position with GPS**: the real fix; between two real fixes at most ``max_interp_gap_s``
     apart (at 10 Hz, and at 1 Hz where a track has a 2 s step) interpolated linearly, but
     never towards or from a fix an outage hides (there the position is dead-reckoned). After
     a stretch without GPS, the dead-reckoned offset is blended out: a share ``blend_keep``
     of it remains at the first fix, and it decays by that factor per second (a Kalman
     filter whose position covariance has grown in the outage takes most of the first fix);
   * **position without GPS** (the injected outages, and real gaps in the track longer than
     ``max_interp_gap_s``): dead reckoning from the last output with the reported heading and
     odometer below;
   * **heading**: the true heading passed through a first-order lag of ``heading_lag_s``
     (a fused heading trails the turn), plus a Gauss-Markov bias (σ ``heading_bias_deg``,
     correlation ``heading_bias_time_s``) and white noise ``heading_noise_deg``. Without GPS
     the gyro's residual bias is integrated: a constant per drive (σ ``gyro_bias_dps``) plus
     a random walk (``gyro_bias_walk_dps`` per √s), so the heading drifts through an outage
     and snaps back when GPS returns;
   * **odometer**: the distance along the vehicle's path, the route's centre line with its
     corners rounded by a moving average over ``corner_smooth_m`` (vehicles cut corners, as
     the simulator's vehicles do; the odometer measures that path, not the centre line),
     times ``1 + k`` with a residual scale error k per drive
     (σ ``odo_scale_sigma``: what is left after the fusion node learnt the scale), plus white
     noise ``odo_noise_m`` per output interval; ``speed`` is that distance over the interval;
   * **reported σ**: ``pos_sigma`` is ``gps_sigma_m`` (the receiver's nominal accuracy; the
     tracks carry none) times a slowly varying log-normal factor (σ ``gps_sigma_var``), and
     without GPS it grows as the error model predicts (scale error times distance, heading
     error and gyro drift times distance); ``heading_sigma`` likewise.

The truth (per fix: position on the route centre line, edge, offset, heading, speed, whether
GPS was missing) and the route are built exactly as the simulator builds them.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import pandas as pd
import shapely
from numpy.typing import NDArray

from graph.index import project_to_edge
from graph.projection import to_lonlat, to_xy
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.sim.drive import Drive, TruthSamples, fixes_frame, truth_frame
from mapmatch.sim.kalman import FusedStream
from mapmatch.sim.profile import Trajectory, _moving_average
from mapmatch.sim.routes import Route, RouteError, route_from_edges, route_from_geometry
from mapmatch.sim.sensors import SensorData, spread_outages

BASE_RATE_HZ = 10.0


@dataclass(frozen=True)
class RealGpsConfig:
    """Error model of the dead-reckoning side of a real-GPS fused drive (1-σ unless stated).

    Timing of the true motion: ``max_speed_mps`` the fastest the vehicle moves between fixes,
    ``timing_smooth_s`` the window smoothing the fixes' route distances, ``heading_base_m`` the
    half-length of route over which the true heading is taken; the small Viterbi that places
    each fix on the route (:func:`fix_route_distance`) looks ``timing_radius_m`` around it,
    keeps the best projection per ``timing_bin_m`` of route, scores distance with σ
    ``timing_sigma_m``, lets a step go back at most ``timing_back_m`` and costs
    ``timing_jump_cost`` per metre moved and ``timing_back_cost`` more per metre back.
    GPS: ``max_interp_gap_s`` the longest gap between real fixes still interpolated (longer
    gaps are dead-reckoned), ``gps_sigma_m`` the receiver's nominal 1-σ, ``gps_sigma_var`` σ of
    its slowly varying log factor over ``gps_sigma_time_s``, ``blend_keep`` the share of the
    dead-reckoning offset left at the first fix after an outage (and per second after).
    Heading: ``heading_noise_deg`` white, ``heading_bias_deg`` Gauss-Markov over
    ``heading_bias_time_s``, ``heading_lag_s`` lag behind the true heading, ``gyro_bias_dps``
    the gyro's residual bias in deg/s (constant per drive) and ``gyro_bias_walk_dps`` its
    random walk in deg/s/√s, both integrated only without GPS.
    Odometer: ``odo_scale_sigma`` residual scale error per drive, ``odo_noise_m`` white noise
    per output interval, ``corner_smooth_m`` the window in metres of the moving average that
    rounds the route's corners into the path the vehicle drives and the odometer measures
    (0: the centre line).
    Truth: it is known where a real fix within ``truth_radius_m`` of the true route lies at
    most ``truth_max_gap_s`` away in time on either side (else the vehicle's place on the
    route is a guess).
    """

    max_speed_mps: float = 45.0
    timing_smooth_s: float = 5.0
    timing_radius_m: float = 60.0
    timing_sigma_m: float = 10.0
    timing_back_m: float = 10.0
    timing_jump_cost: float = 0.002
    timing_back_cost: float = 0.2
    timing_bin_m: float = 30.0
    heading_base_m: float = 4.0
    max_interp_gap_s: float = 2.5
    gps_sigma_m: float = 5.0
    gps_sigma_var: float = 0.2
    gps_sigma_time_s: float = 120.0
    blend_keep: float = 0.15
    heading_noise_deg: float = 1.0
    heading_bias_deg: float = 1.5
    heading_bias_time_s: float = 30.0
    heading_lag_s: float = 0.3
    gyro_bias_dps: float = 0.05
    gyro_bias_walk_dps: float = 0.002
    odo_scale_sigma: float = 0.01
    odo_noise_m: float = 0.02
    corner_smooth_m: float = 9.0
    truth_radius_m: float = 50.0
    truth_max_gap_s: float = 10.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValidationError(f.name, f"must be a finite number >= 0, got {v!r}")
        for name in (
            "max_speed_mps",
            "timing_smooth_s",
            "heading_base_m",
            "max_interp_gap_s",
            "gps_sigma_m",
            "truth_radius_m",
        ):
            if getattr(self, name) <= 0:
                raise ValidationError(name, "must be > 0")
        for name in ("gps_sigma_time_s", "heading_bias_time_s"):
            if getattr(self, name) <= 0:
                raise ValidationError(name, "must be > 0")
        if self.blend_keep >= 1.0:
            raise ValidationError("blend_keep", "must be < 1")


DEFAULT_REALGPS = RealGpsConfig()


# --------------------------------------------------------------------------- reading
def read_track(path: str | os.PathLike[str]) -> pd.DataFrame:
    """A Kubicka ``track.csv`` (``t,lat,lon``) sorted by time, duplicate times dropped."""
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ValidationError("track", f"{path}: cannot read ({exc})") from None
    if not {"t", "lat", "lon"} <= set(df.columns):
        raise ValidationError("track", f"{path}: needs columns t, lat, lon")
    df = df[["t", "lat", "lon"]].astype(float).dropna()
    df = df.sort_values("t").drop_duplicates("t").reset_index(drop=True)
    if len(df) < 2:
        raise ValidationError("track", f"{path}: fewer than two fixes")
    return df


def read_truth_xy(graph: RoadGraph, path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """The true route of a ``truth.geojson`` (LineString or MultiLineString) in map metres."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValidationError("truth", f"{path}: not GeoJSON ({exc})") from None
    feats = data.get("features", [data]) if isinstance(data, dict) else []
    coords: list[list[float]] = []
    for f in feats:
        geom = (f or {}).get("geometry") or {}
        if geom.get("type") == "LineString":
            coords += geom["coordinates"]
        elif geom.get("type") == "MultiLineString":
            coords += [c for part in geom["coordinates"] for c in part]
    if len(coords) < 2:
        raise ValidationError("truth", f"{path}: no route line")
    ll = np.asarray(coords, dtype=np.float64)[:, :2]
    keep = np.concatenate([[True], np.any(np.diff(ll, axis=0) != 0.0, axis=1)])
    return to_xy(graph.crs, ll[keep, 0], ll[keep, 1])


# --------------------------------------------------------------------------- true motion
def fix_route_distance(
    route: Route,
    xy: NDArray[np.float64],
    t: NDArray[np.float64],
    *,
    config: RealGpsConfig = DEFAULT_REALGPS,
) -> NDArray[np.float64]:
    """Route distance of each fix: a small Viterbi over its projections onto the route.

    Candidates are the fix's projections within ``timing_radius_m`` (the best per
    ``timing_bin_m`` of route distance, so each pass of a route that comes back is one
    candidate), scored by distance (σ ``timing_sigma_m``); a step may go back at most
    ``timing_back_m`` and forward at most ``max_speed_mps`` times the time step (plus 30 m), and
    costs ``timing_jump_cost`` per metre (and ``timing_back_cost`` per metre back), so a later
    pass of the same place is not taken early and an earlier one is not walked back along.
    Fixes with no candidate are interpolated in time. The result is smoothed over
    ``timing_smooth_s`` and made non-decreasing by an isotonic fit (:func:`isotonic`).
    """
    radius_m, sigma_m, back_m = config.timing_radius_m, config.timing_sigma_m, config.timing_back_m
    jump_cost, back_cost, bin_m = config.timing_jump_cost, config.timing_back_cost, config.timing_bin_m
    segs = shapely.linestrings(np.stack([route.xy[:-1], route.xy[1:]], axis=1))
    pi, si = shapely.STRtree(segs).query(shapely.points(xy), predicate="dwithin", distance=radius_m)
    a0 = route.xy[si]
    dv = route.xy[si + 1] - a0
    f = np.clip(((xy[pi] - a0) * dv).sum(axis=1) / np.maximum((dv**2).sum(axis=1), 1e-12), 0.0, 1.0)
    dist = np.hypot(*(a0 + f[:, None] * dv - xy[pi]).T)
    sc = route.s[si] + f * (route.s[si + 1] - route.s[si])
    # best candidate per (fix, bin of route distance)
    key = np.floor(sc / bin_m).astype(np.int64)
    order = np.lexsort((dist, key, pi))
    pi, sc, dist, key = pi[order], sc[order], dist[order], key[order]
    first = np.ones(len(pi), dtype=bool)
    first[1:] = (pi[1:] != pi[:-1]) | (key[1:] != key[:-1])
    pi, sc, dist = pi[first], sc[first], dist[first]
    starts = np.searchsorted(pi, np.arange(len(xy) + 1))
    layers: list[tuple[int, NDArray[np.float64], NDArray[np.int64]]] = []
    prev_s: NDArray[np.float64] | None = None
    prev_score: NDArray[np.float64] | None = None
    prev_t = 0.0
    for i in range(len(xy)):
        lo, hi = starts[i], starts[i + 1]
        if lo == hi:
            continue
        s_i = sc[lo:hi]
        emis = -0.5 * (dist[lo:hi] / sigma_m) ** 2
        if prev_s is None or prev_score is None:
            score = emis - jump_cost * s_i
            bp = np.full(len(s_i), -1, dtype=np.int64)
        else:
            ds = s_i[None, :] - prev_s[:, None]
            ok = (ds >= -back_m) & (ds <= config.max_speed_mps * float(t[i] - prev_t) + 30.0)
            cost = jump_cost * np.abs(ds) + back_cost * np.maximum(-ds, 0.0)
            trans = np.where(ok, -cost, -50.0 - cost)
            tot = prev_score[:, None] + trans
            bp = np.argmax(tot, axis=0)
            score = tot[bp, np.arange(len(s_i))] + emis
        layers.append((i, s_i, bp))
        prev_s, prev_score, prev_t = s_i, score, float(t[i])
    if prev_score is None:
        raise RouteError("no fix lies near the true route")
    k = int(np.argmax(prev_score))
    idx_known = np.empty(len(layers), dtype=np.int64)
    s_known = np.empty(len(layers))
    for li in range(len(layers) - 1, -1, -1):
        i, s_i, bp = layers[li]
        idx_known[li], s_known[li] = i, s_i[k]
        k = int(bp[k])
    out = np.interp(t, t[idx_known], s_known)
    # smooth by time, then non-decreasing
    w = config.timing_smooth_s
    cs = np.concatenate([[0.0], np.cumsum(out)])
    lo_i = np.searchsorted(t, t - w / 2.0, side="left")
    hi_i = np.searchsorted(t, t + w / 2.0, side="right")
    sm = (cs[hi_i] - cs[lo_i]) / np.maximum(hi_i - lo_i, 1)
    return np.clip(isotonic(sm), 0.0, route.length)


def isotonic(y: NDArray[np.float64]) -> NDArray[np.float64]:
    """The non-decreasing sequence closest to ``y`` in least squares (pool adjacent violators)."""
    means: list[float] = []
    counts: list[int] = []
    for v in np.asarray(y, dtype=np.float64).tolist():
        m, c = v, 1
        while means and means[-1] > m:
            pm, pc = means.pop(), counts.pop()
            m, c = (pm * pc + m * c) / (pc + c), pc + c
        means.append(m)
        counts.append(c)
    return np.repeat(np.asarray(means), np.asarray(counts, dtype=np.int64))


def truth_known(
    route: Route,
    xy: NDArray[np.float64],
    t: NDArray[np.float64],
    at: NDArray[np.float64],
    *,
    config: RealGpsConfig = DEFAULT_REALGPS,
) -> NDArray[np.bool_]:
    """Whether the truth is known at times ``at``: a fix (``xy`` at ``t``) within
    ``truth_radius_m`` of the route lies at most ``truth_max_gap_s`` before and after."""
    segs = shapely.linestrings(np.stack([route.xy[:-1], route.xy[1:]], axis=1))
    tree = shapely.STRtree(segs)
    pi, _ = tree.query(shapely.points(xy), predicate="dwithin", distance=config.truth_radius_m)
    near = np.zeros(len(xy), dtype=bool)
    near[pi] = True
    tk = np.asarray(t, dtype=np.float64)[near]
    if len(tk) == 0:
        return np.zeros(len(at), dtype=bool)
    j = np.searchsorted(tk, at, side="right")
    prev = tk[np.maximum(j - 1, 0)]
    nxt = tk[np.minimum(j, len(tk) - 1)]
    w = config.truth_max_gap_s
    exact = np.abs(prev - at) < 1e-6
    inside = (j > 0) & (j < len(tk)) & (nxt - prev <= w)
    return exact | inside


def route_from_truth(graph: RoadGraph, xy: NDArray[np.float64], *, tol_m: float = 1.0) -> Route:
    """The edge path of a true route drawn through the map's own nodes (U-turns allowed).

    The route's vertices that lie within ``tol_m`` of a map node give the node sequence; each
    consecutive pair is joined by the edge between them (of the length closest to the route's
    between them). Raises :class:`RouteError` when two consecutive nodes share no edge.
    """
    cell: dict[tuple[int, int], int] = {}
    for i, (x, y) in enumerate(graph.node_xy.tolist()):
        cell.setdefault((int(x // tol_m), int(y // tol_m)), i)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    seq: list[tuple[int, float, int]] = []
    for v, ((x, y), s) in enumerate(zip(xy.tolist(), cum.tolist(), strict=True)):
        cx, cy = int(x // tol_m), int(y // tol_m)
        best, bd = -1, tol_m
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                n = cell.get((cx + dx, cy + dy), -1)
                if n >= 0:
                    d = math.hypot(graph.node_xy[n, 0] - x, graph.node_xy[n, 1] - y)
                    if d <= bd:
                        best, bd = n, d
        if best >= 0 and (not seq or seq[-1][0] != best or s - seq[-1][1] > 4.0 * tol_m):
            seq.append((best, s, v))  # the same node again further on: a loop or a turn
    path: list[int] = []
    for (a, sa, va), (b, sb, vb) in itertools.pairwise(seq):
        out = [int(e) for e in graph.out_of(a).tolist() if int(graph.edge_v[e]) == b]
        if not out and a == b:  # turned round on an edge: along it to its end and back
            far = xy[va + int(np.argmax(np.hypot(*(xy[va : vb + 1] - graph.node_xy[a]).T)))]
            cand = [int(e) for e in graph.out_of(a).tolist() if int(graph.edge_reverse[e]) >= 0]
            if cand:
                e = min(cand, key=lambda e: project_to_edge(graph, e, float(far[0]), float(far[1]))[1])
                path += [e, int(graph.edge_reverse[e])]
            continue
        if not out:
            raise RouteError(f"no edge joins map nodes {a} and {b} of the true route")
        path.append(min(out, key=lambda e: abs(float(graph.edge_len[e]) - (sb - sa))))
    if not path:
        raise RouteError("the true route passes fewer than two map nodes")
    return route_from_edges(graph, path, allow_uturns=True)


def _trim(graph: RoadGraph, route: Route, s_from: float, s_to: float) -> Route:
    """The part of ``route`` between route distances ``s_from`` and ``s_to``."""
    e0 = int(np.clip(np.searchsorted(route.edge_start, s_from, side="right") - 1, 0, len(route.edges) - 1))
    e1 = int(np.clip(np.searchsorted(route.edge_start, s_to, side="right") - 1, e0, len(route.edges) - 1))
    return route_from_edges(
        graph,
        route.edges[e0 : e1 + 1].tolist(),
        start_offset=s_from - float(route.edge_start[e0]),
        end_offset=s_to - float(route.edge_start[e1]),
        allow_uturns=True,
    )


def _route_heading(route: Route, s: NDArray[np.float64], half_m: float) -> NDArray[np.float64]:
    """Unwrapped heading (rad, clockwise from north) of the route at distances ``s``: the chord
    over ±``half_m``, or where the route turns back within it (a U-turn, whose chord is about
    nothing and its direction the rounding's) the way in until the turning point is passed,
    then the way out."""
    p0 = route.position(np.clip(s - half_m, 0.0, route.length))
    pm = route.position(np.clip(s, 0.0, route.length))
    p1 = route.position(np.clip(s + half_m, 0.0, route.length))
    d = p1 - p0
    folded = np.hypot(d[:, 0], d[:, 1]) < 0.5 * half_m
    if folded.any():
        back, ahead = pm - p0, p1 - pm
        way_in = np.hypot(back[:, 0], back[:, 1]) > np.hypot(ahead[:, 0], ahead[:, 1])
        d = np.where(folded[:, None], np.where(way_in[:, None], back, ahead), d)
    return np.unwrap(np.arctan2(d[:, 0], d[:, 1]))


def driven_distance(route: Route, s: NDArray[np.float64], smooth_m: float) -> NDArray[np.float64]:
    """Distance along the path a vehicle drives at route distances ``s``: the centre line
    resampled every metre with its corners rounded by a moving average over ``smooth_m`` metres
    (vehicles cut corners: at a 90° turn the path is a metre or two shorter than the line)."""
    grid = np.append(np.arange(0.0, route.length, 1.0), route.length)
    c = route.position(grid)
    w = max(1, round(smooth_m))
    x, y = _moving_average(c[:, 0], w), _moving_average(c[:, 1], w)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return np.interp(s, grid, arc)


def _gauss_markov(
    n: int, dt: float, tau: float, sigma: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    a = math.exp(-dt / tau)
    w = rng.normal(0.0, sigma * math.sqrt(1.0 - a * a), n)
    out = np.empty(n)
    x = rng.normal(0.0, sigma)
    for i in range(n):
        x = a * x + w[i]
        out[i] = x
    return out


# --------------------------------------------------------------------------- the drive
def real_drive(
    graph: RoadGraph,
    track_dir: str | os.PathLike[str],
    *,
    rate_hz: float = 1.0,
    outages: bool | Sequence[tuple[float, float]] = True,
    seed: int = 0,
    vehicle_id: str | None = None,
    time0: float = 0.0,
    config: RealGpsConfig = DEFAULT_REALGPS,
) -> Drive:
    """The fused drive of a real GPS track (``track.csv`` + ``truth.geojson`` in ``track_dir``).

    Parameters
    ----------
    graph
        The map prepared from the track's ``roads.geojson``.
    track_dir
        A Kubicka track folder.
    rate_hz
        Fused output rate: 1 or 10 Hz.
    outages
        True: the seed papers' five outages spread over the drive
        (:func:`~mapmatch.sim.sensors.spread_outages`); False: none; or (start, duration)
        pairs in seconds from the first fix.
    seed
        Seed of the dead-reckoning errors.
    vehicle_id, time0
        Vehicle id (default: the folder's name) and the time of the first fix.
    config
        The error model (:class:`RealGpsConfig`).
    """
    if rate_hz not in (1, 1.0, 10, 10.0):
        raise ValidationError("rate_hz", "must be 1 or 10 Hz")
    folder = Path(track_dir)
    vid = vehicle_id if vehicle_id is not None else folder.name
    real = _real_fixes(graph, folder, config)
    outs = _outage_list(outages, float(real.t[-1]))
    rng = np.random.default_rng(seed)
    motion = _true_motion(real, float(real.t[-1]), config)
    gps = _gps_availability(real, motion.t, outs, config)
    # the errors in this order (one generator): heading, odometer scale, σ, odometer noise
    dr = _dead_reckoning(real.route, motion, gps.have, config, rng)
    fx, fy = _fused_position(motion.t, gps, dr, config.blend_keep)
    sig_gps, pos_sigma, head_sigma = _reported_sigma(motion.t, gps.have, dr, config, rng)
    # ---- subsample to the output rate
    step = max(1, round(BASE_RATE_HZ / float(rate_hz)))
    idx = np.arange(0, len(motion.t), step)
    ot = motion.t[idx]
    od = dr.odo[idx]
    dist = np.diff(od, prepend=od[0]) + np.where(
        np.arange(len(idx)) > 0, rng.normal(0.0, config.odo_noise_m, len(idx)), 0.0
    )
    dist = np.maximum(dist, 0.0)
    fused = FusedStream(
        time=ot,
        x=fx[idx],
        y=fy[idx],
        heading=np.degrees(dr.head[idx]) % 360.0,
        pos_sigma=pos_sigma[idx],
        heading_sigma=head_sigma[idx],
        speed=dist / (step * motion.traj.dt),
        distance=dist,
        gps_valid=gps.have[idx],
    )
    truth = _truth(graph, real, motion, (idx, gps.have[idx]), time0=time0, vehicle_id=vid, config=config)
    return Drive(
        route=real.route,
        trajectory=motion.traj,
        sensors=_sensor_data(real, motion, gps, dr, sig_gps, tuple(outs)),
        fused=fused,
        fixes=fixes_frame(graph, fused, vehicle_id=vid, time0=time0),
        truth=truth,
        gps=_gps_frame(graph, real, gps.fix_in_out, time0),
        node_index=real.route.nodes(graph),
        node_time=np.interp(real.route.node_distance(), motion.s, motion.t) + time0,
        outages=list(outs),
    )


def _outage_list(outages: bool | Sequence[tuple[float, float]], duration: float) -> list[tuple[float, float]]:
    """``(start, duration)`` of each outage: the seed papers' five spread over the drive (True),
    none (False) or as given."""
    if outages is True:
        return spread_outages(duration)
    if outages is False:
        return []
    return [(float(a), float(b)) for a, b in outages]


def _truth(
    graph: RoadGraph,
    real: _RealFixes,
    motion: _Motion,
    out: tuple[NDArray[np.int64], NDArray[np.bool_]],
    *,
    time0: float,
    vehicle_id: str,
    config: RealGpsConfig,
) -> pd.DataFrame:
    """The per-fix truth at the output samples ``out`` (base-grid indices, GPS there), with
    where it is known."""
    idx, have = out
    ot = motion.t[idx]
    truth = truth_frame(
        graph,
        real.route,
        TruthSamples(
            time=ot + time0,
            x=motion.pos[idx, 0],
            y=motion.pos[idx, 1],
            route_s=motion.s[idx],
            heading=np.degrees(motion.psi[idx]) % 360.0,
            speed=motion.speed[idx],
            gps_outage=~have,  # injected outages and long track gaps
        ),
        vehicle_id=vehicle_id,
    )
    truth["truth_known"] = truth_known(real.route, real.xy, real.t, ot, config=config)
    return truth


@dataclass(frozen=True)
class _RealFixes:
    """A real track's fixes: times from the first (s), positions in the map's CRS, the true
    route trimmed to the drive, and each fix's distance along it."""

    t: NDArray[np.float64]
    xy: NDArray[np.float64]
    route: Route
    s: NDArray[np.float64]


def _real_fixes(graph: RoadGraph, folder: Path, cfg: RealGpsConfig) -> _RealFixes:
    track = read_track(folder / "track.csv")
    t_fix = track["t"].to_numpy() - float(track["t"].iloc[0])
    fix_xy = to_xy(graph.crs, track["lon"].to_numpy(), track["lat"].to_numpy())
    truth_xy = read_truth_xy(graph, folder / "truth.geojson")
    try:
        full = route_from_truth(graph, truth_xy)
    except RouteError:  # the truth is not drawn through this map's nodes: follow its geometry
        full = route_from_geometry(graph, truth_xy)
    s_full = fix_route_distance(full, fix_xy, t_fix, config=cfg)
    s_from, s_to = float(s_full[0]), float(s_full[-1])
    if s_to - s_from < 1.0:
        raise ValidationError("truth", f"{folder}: the fixes do not move along the true route")
    route = _trim(graph, full, s_from, s_to)
    return _RealFixes(t_fix, fix_xy, route, np.clip(s_full - s_from, 0.0, route.length))


@dataclass(frozen=True)
class _Motion:
    """The true motion on the base grid: times, route distance, position, heading (rad) and
    speed, and the trajectory record."""

    t: NDArray[np.float64]
    s: NDArray[np.float64]
    pos: NDArray[np.float64]
    psi: NDArray[np.float64]
    speed: NDArray[np.float64]
    yaw: NDArray[np.float64]
    traj: Trajectory


def _true_motion(real: _RealFixes, duration: float, cfg: RealGpsConfig) -> _Motion:
    dt = 1.0 / BASE_RATE_HZ
    tb = np.arange(0.0, duration + 1e-9, dt)
    n = len(tb)
    sb = np.interp(tb, real.t, real.s)
    pos = real.route.position(sb)
    psi = _route_heading(real.route, sb, cfg.heading_base_m)
    speed = np.gradient(sb, dt) if n > 1 else np.zeros(n)
    yaw = np.gradient(psi, dt) if n > 1 else np.zeros(n)
    traj = Trajectory(
        dt=dt, t=tb, x=pos[:, 0], y=pos[:, 1], psi=psi, yaw_rate=yaw, speed=speed, dist=sb, s=sb
    )
    return _Motion(tb, sb, pos, psi, speed, yaw, traj)


@dataclass(frozen=True)
class _Gps:
    """Where the receiver gives a position on the base grid (``have``) and that position; which
    real fixes the outages hide."""

    have: NDArray[np.bool_]
    xy: NDArray[np.float64]
    fix_in_out: NDArray[np.bool_]


def _gps_availability(
    real: _RealFixes, tb: NDArray[np.float64], outs: list[tuple[float, float]], cfg: RealGpsConfig
) -> _Gps:
    """GPS availability and position: the real fixes, interpolated between close ones."""
    t_fix, fix_xy, n = real.t, real.xy, len(tb)
    k = np.clip(np.searchsorted(t_fix, tb, side="right") - 1, 0, len(t_fix) - 1)
    k1 = np.minimum(k + 1, len(t_fix) - 1)
    exact = np.abs(t_fix[k] - tb) < 1e-6
    gap = t_fix[k1] - t_fix[k]
    fix_in_out = np.zeros(len(t_fix), dtype=bool)  # real fixes the outages hide
    in_out = np.zeros(n, dtype=bool)
    for a, d in outs:
        fix_in_out |= (t_fix >= a) & (t_fix < a + d)
        in_out |= (tb >= a) & (tb < a + d)
    # interpolated only between two fixes the receiver gave: next to an outage a position is
    # not built from a fix the outage hides (it is dead-reckoned)
    between = (gap <= cfg.max_interp_gap_s) & (tb > t_fix[k]) & (tb < t_fix[k1]) & ~fix_in_out[k1]
    have = (exact | between) & ~fix_in_out[k] & ~in_out
    frac = np.where(gap > 0, (tb - t_fix[k]) / np.where(gap > 0, gap, 1.0), 0.0)
    frac = np.where(exact, 0.0, frac)
    return _Gps(have, fix_xy[k] + frac[:, None] * (fix_xy[k1] - fix_xy[k]), fix_in_out)


@dataclass(frozen=True)
class _DeadReckoning:
    """The reported heading (rad), the gyro's bias, seconds without GPS, the odometer's scale
    error, its steps and its reading."""

    head: NDArray[np.float64]
    gyro_bias: NDArray[np.float64]
    since: NDArray[np.float64]
    scale: float
    step_d: NDArray[np.float64]
    odo: NDArray[np.float64]


def _dead_reckoning(
    route: Route, motion: _Motion, have: NDArray[np.bool_], cfg: RealGpsConfig, rng: np.random.Generator
) -> _DeadReckoning:
    """Reported heading (lagged truth, bias, noise, gyro drift without GPS) and odometer (the
    length of the path driven, corners rounded, with a scale error)."""
    psi, n, dt = motion.psi, len(motion.t), motion.traj.dt
    lag = psi.copy()
    if cfg.heading_lag_s > 0:
        alpha = 1.0 - math.exp(-dt / cfg.heading_lag_s)
        for i in range(1, n):
            lag[i] = lag[i - 1] + alpha * (psi[i] - lag[i - 1])
    h_err = np.radians(
        _gauss_markov(n, dt, cfg.heading_bias_time_s, cfg.heading_bias_deg, rng)
        + rng.normal(0.0, cfg.heading_noise_deg, n)
    )
    gyro_bias = np.radians(
        rng.normal(0.0, cfg.gyro_bias_dps)
        + np.cumsum(rng.normal(0.0, cfg.gyro_bias_walk_dps * math.sqrt(dt), n))
    )
    # drift integrated over each stretch without GPS, reset when GPS is back
    drift = np.zeros(n)
    since = np.zeros(n)  # seconds without GPS
    for i in range(1, n):
        if not have[i]:
            drift[i] = drift[i - 1] + gyro_bias[i] * dt
            since[i] = since[i - 1] + dt
    scale = float(rng.normal(0.0, cfg.odo_scale_sigma))
    driven = driven_distance(route, motion.s, cfg.corner_smooth_m)
    step_d = np.diff(driven, prepend=driven[0]) * (1.0 + scale)
    return _DeadReckoning(lag + h_err + drift, gyro_bias, since, scale, step_d, np.cumsum(step_d))


def _fused_position(
    tb: NDArray[np.float64], gps: _Gps, dr: _DeadReckoning, blend_keep: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The fused position: GPS, dead reckoning without it, the offset blended out on return."""
    n, have, head, step_d = len(tb), gps.have, dr.head, dr.step_d
    fx = np.empty(n)
    fy = np.empty(n)
    off_x = off_y = 0.0
    back_t = -1.0
    keep_rate = math.log(blend_keep) if blend_keep > 0 else -np.inf
    for i in range(n):
        if have[i]:
            if i > 0 and not have[i - 1]:  # GPS is back: remember the dead-reckoning offset
                px = fx[i - 1] + step_d[i] * math.sin(head[i])
                py = fy[i - 1] + step_d[i] * math.cos(head[i])
                off_x, off_y = px - gps.xy[i, 0], py - gps.xy[i, 1]
                back_t = tb[i]
            w = math.exp(keep_rate * (1.0 + tb[i] - back_t)) if back_t >= 0 else 0.0
            fx[i] = gps.xy[i, 0] + w * off_x
            fy[i] = gps.xy[i, 1] + w * off_y
        elif i == 0:
            fx[i], fy[i] = gps.xy[i, 0], gps.xy[i, 1]
        else:
            hm = head[i]
            fx[i] = fx[i - 1] + step_d[i] * math.sin(hm)
            fy[i] = fy[i - 1] + step_d[i] * math.cos(hm)
    return fx, fy


def _reported_sigma(
    tb: NDArray[np.float64],
    have: NDArray[np.bool_],
    dr: _DeadReckoning,
    cfg: RealGpsConfig,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The receiver's σ on the base grid, and the fused position's and heading's reported σ."""
    n, dt = len(tb), 1.0 / BASE_RATE_HZ
    sig_gps = cfg.gps_sigma_m * np.exp(_gauss_markov(n, dt, cfg.gps_sigma_time_s, cfg.gps_sigma_var, rng))
    dist_out = np.zeros(n)  # metres driven without GPS
    for i in range(1, n):
        if not have[i]:
            dist_out[i] = dist_out[i - 1] + dr.step_d[i]
    h_sig0 = math.radians(math.hypot(cfg.heading_noise_deg, cfg.heading_bias_deg))
    g_sig = math.radians(cfg.gyro_bias_dps)
    pos_sigma = np.sqrt(
        sig_gps**2
        + (cfg.odo_scale_sigma * dist_out) ** 2
        + (h_sig0 * dist_out) ** 2
        + (g_sig * dr.since * dist_out / 2) ** 2
    )
    return sig_gps, pos_sigma, np.degrees(np.hypot(h_sig0, g_sig * dr.since))


def _gps_frame(
    graph: RoadGraph, real: _RealFixes, fix_in_out: NDArray[np.bool_], time0: float
) -> pd.DataFrame:
    """The real fixes the fusion saw (NaN where an outage hides them)."""
    gll = to_lonlat(graph.crs, real.xy[:, 0], real.xy[:, 1])
    return pd.DataFrame(
        {
            "time": real.t + time0,
            "lat": np.where(fix_in_out, np.nan, gll[:, 1]),
            "lon": np.where(fix_in_out, np.nan, gll[:, 0]),
            "x": np.where(fix_in_out, np.nan, real.xy[:, 0]),
            "y": np.where(fix_in_out, np.nan, real.xy[:, 1]),
            "outlier": np.zeros(len(real.t), dtype=int),
        }
    )


def _sensor_data(
    real: _RealFixes,
    motion: _Motion,
    gps: _Gps,
    dr: _DeadReckoning,
    sig_gps: NDArray[np.float64],
    outs: tuple[tuple[float, float], ...],
) -> SensorData:
    """The raw sensors behind the fused drive (for the closed-loop filter)."""
    t_fix, tb = real.t, motion.t
    nan_fix = np.where(gps.fix_in_out, np.nan, 1.0)
    return SensorData(
        gps_t=t_fix,
        gps_x=real.xy[:, 0] * nan_fix,
        gps_y=real.xy[:, 1] * nan_fix,
        gps_sigma=np.interp(t_fix, tb, sig_gps) * nan_fix,
        gps_speed=np.interp(t_fix, tb, motion.speed) * nan_fix,
        gps_course=np.full(len(t_fix), np.nan),
        gps_outlier=np.zeros(len(t_fix), dtype=bool),
        gyro_t=tb,
        gyro=motion.yaw + dr.gyro_bias,
        odo_t=tb,
        odo=dr.odo,
        compass_t=np.empty(0),
        compass=np.empty(0),
        true_gyro_bias=dr.gyro_bias,
        true_odo_scale=dr.scale,
        outages=outs,
    )
