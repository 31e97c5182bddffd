"""A simulated drive: route → true motion → raw sensors → Kalman filter → fused fixes + truth.

The fused fixes use the columns ``mapmatch replay`` and ``mapmatch send`` read
(:data:`FIX_COLUMNS`). The truth is one row per fix (true position, edge, offset, heading)
plus the route: its edges and the sequence of intersections passed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from graph.files import atomic_path
from graph.projection import to_lonlat, to_xy
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.sim.kalman import DEFAULT_KALMAN, FusedStream, KalmanConfig, fused_stream, run_filter
from mapmatch.sim.profile import DEFAULT_PROFILE, ProfileConfig, Trajectory, drive_profile
from mapmatch.sim.routes import Route, route_from_edges, route_from_geometry
from mapmatch.sim.sensors import DEFAULT_SENSORS, SensorConfig, SensorData, parse_outages, simulate_sensors
from mapmatch.types import Fix

FIX_COLUMNS: tuple[str, ...] = (
    "vehicle_id",
    "time",
    "lat",
    "lon",
    "heading",
    "pos_sigma",
    "heading_sigma",
    "speed",
    "distance",
    "gps_valid",
)
TRUTH_COLUMNS: tuple[str, ...] = (
    "vehicle_id",
    "time",
    "lat",
    "lon",
    "x",
    "y",
    "edge",
    "offset",
    "u",
    "v",
    "way_id",
    "heading",
    "speed",
    "route_s",
    "gps_outage",
)


@dataclass
class Drive:
    """Everything one simulated drive produced.

    ``fixes`` (columns :data:`FIX_COLUMNS`) and ``truth`` (:data:`TRUTH_COLUMNS`) have one
    row per fused fix; ``gps`` holds the raw 1 Hz receiver fixes (NaN in outages).
    """

    route: Route
    trajectory: Trajectory
    sensors: SensorData
    fused: FusedStream
    fixes: pd.DataFrame
    truth: pd.DataFrame
    gps: pd.DataFrame
    node_index: np.ndarray
    node_time: np.ndarray
    outages: list[tuple[float, float]] = field(default_factory=list)

    def fix_objects(self) -> list[Fix]:
        """The fused fixes as :class:`Fix` objects, in time order."""
        f = self.fixes
        cols = [f[c].to_numpy(dtype=np.float64).tolist() for c in FIX_COLUMNS[1:]]
        return [
            Fix(time=t, lat=la, lon=lo, heading=h, pos_sigma=ps, heading_sigma=hs, speed=sp, distance=d,
                gps_valid=bool(v))
            for t, la, lo, h, ps, hs, sp, d, v in zip(*cols, strict=True)
        ]  # fmt: skip


def fixes_frame(graph: RoadGraph, fused: FusedStream, *, vehicle_id: str, time0: float) -> pd.DataFrame:
    """The fused-fix rows (:data:`FIX_COLUMNS`) of a fusion filter's output stream."""
    ll = to_lonlat(graph.crs, fused.x, fused.y)
    return pd.DataFrame(
        {
            "vehicle_id": [vehicle_id] * len(fused.time),
            "time": fused.time + time0,
            "lat": ll[:, 1],
            "lon": ll[:, 0],
            "heading": fused.heading,
            "pos_sigma": fused.pos_sigma,
            "heading_sigma": fused.heading_sigma,
            "speed": fused.speed,
            "distance": fused.distance,
            "gps_valid": fused.gps_valid.astype(int),
        },
        columns=list(FIX_COLUMNS),
    )


class TruthSamples(NamedTuple):
    """The true motion at the fix times: time (written as is), position in metres, route
    distance, heading (degrees), speed (m/s) and whether GPS was out."""

    time: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    route_s: NDArray[np.float64]
    heading: NDArray[np.float64]
    speed: NDArray[np.float64]
    gps_outage: NDArray[np.bool_]


def truth_frame(graph: RoadGraph, route: Route, truth: TruthSamples, *, vehicle_id: str) -> pd.DataFrame:
    """The truth rows (:data:`TRUTH_COLUMNS`) of true positions ``truth.x``, ``truth.y`` at
    ``truth.route_s`` metres along ``route``: their place on the map, the way piece under them,
    heading and speed."""
    edge, off = route.locate(truth.route_s)
    ll = to_lonlat(graph.crs, truth.x, truth.y)
    piece = graph.piece_at(edge, off)
    return pd.DataFrame(
        {
            "vehicle_id": [vehicle_id] * len(truth.time),
            "time": truth.time,
            "lat": ll[:, 1],
            "lon": ll[:, 0],
            "x": truth.x,
            "y": truth.y,
            "edge": edge,
            "offset": off,
            "u": graph.node_id[graph.edge_u[edge]],
            "v": graph.node_id[graph.edge_v[edge]],
            "way_id": np.where(piece >= 0, graph.piece_way_id[np.maximum(piece, 0)], -1),
            "heading": truth.heading,
            "speed": truth.speed,
            "route_s": truth.route_s,
            "gps_outage": np.asarray(truth.gps_outage).astype(int),
        },
        columns=list(TRUTH_COLUMNS),
    )


@dataclass(frozen=True)
class DriveConfig:
    """The simulator's models: the driver (:class:`ProfileConfig`), the raw sensors' errors
    (:class:`SensorConfig`) and the fusion filter (:class:`KalmanConfig`)."""

    profile: ProfileConfig = DEFAULT_PROFILE
    sensors: SensorConfig = DEFAULT_SENSORS
    kalman: KalmanConfig = DEFAULT_KALMAN


DEFAULT_DRIVE = DriveConfig()


def simulate_drive(
    graph: RoadGraph,
    route: Route,
    *,
    rate: float = 1.0,
    outages: str | Sequence[tuple[float, float]] | None = "paper",
    seed: int = 0,
    vehicle_id: str = "sim-1",
    time0: float = 0.0,
    config: DriveConfig = DEFAULT_DRIVE,
) -> Drive:
    """Drive ``route`` and return fused fixes at ``rate`` Hz (1 or 10) with the truth.

    Parameters
    ----------
    graph
        The map the route lies on.
    route
        What to drive (see :mod:`mapmatch.sim.routes`).
    rate
        Fused output rate in Hz: 1 or 10.
    outages
        GPS outages: ``"paper"``, ``"none"``, ``"START:DUR,..."`` or (start, duration) pairs,
        seconds from the start of the drive. Outages past the end of the drive do nothing.
    seed
        Seed of every random choice (driver, sensors).
    vehicle_id, time0
        The vehicle id and the time of the first fix written to the output.
    config
        The driver, sensor and filter models.
    """
    if rate not in (1, 1.0, 10, 10.0):
        raise ValidationError("rate", "must be 1 or 10 Hz")
    rng = np.random.default_rng(seed)
    outs = parse_outages(outages)
    traj = drive_profile(graph, route, rng=rng, rate_hz=config.sensors.gyro_rate, config=config.profile)
    raw = simulate_sensors(traj, rng=rng, outages=outs, config=config.sensors)
    fused = fused_stream(run_filter(raw, config=config.kalman), rate=float(rate))
    # truth at the fix times
    ft = fused.time
    in_out = np.zeros(len(ft), dtype=bool)
    for a, d in outs:
        in_out |= (ft >= a) & (ft < a + d)
    truth = TruthSamples(
        time=ft + time0,
        x=np.interp(ft, traj.t, traj.x),
        y=np.interp(ft, traj.t, traj.y),
        route_s=np.interp(ft, traj.t, traj.s),
        heading=np.degrees(np.interp(ft, traj.t, traj.psi)) % 360.0,
        speed=np.interp(ft, traj.t, traj.speed),
        gps_outage=in_out,
    )
    return Drive(
        route=route,
        trajectory=traj,
        sensors=raw,
        fused=fused,
        fixes=fixes_frame(graph, fused, vehicle_id=vehicle_id, time0=time0),
        truth=truth_frame(graph, route, truth, vehicle_id=vehicle_id),
        gps=gps_frame(graph, raw, time0=time0),
        node_index=route.nodes(graph),
        # time each intersection is passed (the trajectory's route distance is monotonic)
        node_time=np.interp(route.node_distance(), traj.s, traj.t) + time0,
        outages=outs,
    )


def gps_frame(graph: RoadGraph, sensors: SensorData, *, time0: float) -> pd.DataFrame:
    """The raw receiver fixes: time, lon/lat and metres (NaN in outages), multipath flag."""
    gll = to_lonlat(graph.crs, np.nan_to_num(sensors.gps_x), np.nan_to_num(sensors.gps_y))
    have = ~np.isnan(sensors.gps_x)
    return pd.DataFrame(
        {
            "time": sensors.gps_t + time0,
            "lat": np.where(have, gll[:, 1], np.nan),
            "lon": np.where(have, gll[:, 0], np.nan),
            "x": sensors.gps_x,
            "y": sensors.gps_y,
            "outlier": sensors.gps_outlier.astype(int),
        }
    )


# --------------------------------------------------------------------------- files
def write_fixes_csv(drive: Drive, path: str | os.PathLike[str]) -> None:
    """Write the fused fixes (atomic) with the columns :data:`FIX_COLUMNS`."""
    with atomic_path(path) as tmp:
        drive.fixes.to_csv(tmp, index=False, float_format="%.7f")


def truth_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The per-fix truth CSV and the route GeoJSON that belong together (same stem)."""
    p = Path(path)
    if p.suffix.lower() in (".geojson", ".json"):
        return p.with_suffix(".csv"), p
    return p, p.with_suffix(".geojson")


def route_geojson(graph: RoadGraph, drive: Drive) -> dict[str, Any]:
    """The true route as a GeoJSON Feature: geometry, dense edges, external ids, intersections."""
    r = drive.route
    ll = to_lonlat(graph.crs, r.xy[:, 0], r.xy[:, 1])
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": np.round(ll, 7).tolist()},
        "properties": {
            "kind": "mapmatch-sim-truth",
            "edges": r.edges.tolist(),
            "start_offset": r.start_offset,
            "end_offset": r.end_offset,
            "way_ids": graph.edge_way_id[r.edges].tolist(),
            "node_ids": graph.node_id[drive.node_index].tolist(),
            "node_index": drive.node_index.tolist(),
            "node_time": np.round(drive.node_time, 3).tolist(),
            "outages": [list(o) for o in drive.outages],
            "length_m": r.length,
            "duration_s": drive.trajectory.duration,
        },
    }


def write_truth(graph: RoadGraph, drive: Drive, path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write the per-fix truth CSV and the route GeoJSON (both atomic); return their paths."""
    csv_path, gj_path = truth_paths(path)
    with atomic_path(csv_path) as tmp:
        drive.truth.to_csv(tmp, index=False, float_format="%.7f")
    text = json.dumps(route_geojson(graph, drive))
    with atomic_path(gj_path) as tmp:
        tmp.write_text(text)
    return csv_path, gj_path


def read_route(graph: RoadGraph, path: str | os.PathLike[str]) -> Route:
    """A route from a GeoJSON file: the simulator's own truth (edges), else any LineString.

    A simulator truth whose edges do not fit ``graph`` (another map build) falls back to its
    geometry.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValidationError("route", f"{path} is not GeoJSON ({exc})") from None
    feats = data.get("features", [data]) if isinstance(data, dict) else []
    for f in feats:
        props = f.get("properties") or {}
        geom = f.get("geometry") or {}
        edges = props.get("edges")
        if edges and all(isinstance(e, int) and 0 <= e < graph.n_edges for e in edges):
            try:
                return route_from_edges(
                    graph,
                    edges,
                    start_offset=float(props.get("start_offset", 0.0)),
                    end_offset=props.get("end_offset"),
                )
            except Exception:
                pass
        coords: list[Any] = []
        if geom.get("type") == "LineString":
            coords = geom["coordinates"]
        elif geom.get("type") == "MultiLineString":
            coords = [c for part in geom["coordinates"] for c in part]
        if len(coords) >= 2:
            lonlat = np.asarray(coords, dtype=np.float64)[:, :2]
            xy = to_xy(graph.crs, lonlat[:, 0], lonlat[:, 1])
            return route_from_geometry(graph, xy)
    raise ValidationError("route", f"{path}: no LineString feature found")


def position_error(drive: Drive) -> np.ndarray:
    """Distance in metres between each fused fix and the true position."""
    return np.asarray(
        np.hypot(drive.fused.x - drive.truth["x"].to_numpy(), drive.fused.y - drive.truth["y"].to_numpy())
    )
