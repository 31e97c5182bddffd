"""Proto <-> domain conversion: the only module that imports both the stubs and ``mapmatch`` types.

Unset optional proto fields become NaN/None in the domain types and back.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from google.protobuf import struct_pb2
from google.protobuf.json_format import ParseDict

from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.types import (
    Candidate,
    Correction,
    Fix,
    MapAidedMeasurement,
    MatchedPoint,
    PointStatus,
    SnapResult,
    State,
    Track,
    TrackMatch,
    Turn,
    check_field_array,
)
from service.gen import mapmatch_pb2 as pb

_STATE = {
    State.INITIALISING: pb.STATE_INITIALISING,
    State.ON_ROAD: pb.STATE_ON_ROAD,
    State.AMBIGUOUS: pb.STATE_AMBIGUOUS,
    State.OFF_ROAD: pb.STATE_OFF_ROAD,
    State.REINITIALISED: pb.STATE_REINITIALISED,
}
_STATE_BACK = {v: k for k, v in _STATE.items()}
_TURN = {
    Turn.NONE: pb.TURN_NONE,
    Turn.LEFT: pb.TURN_LEFT,
    Turn.RIGHT: pb.TURN_RIGHT,
    Turn.STRAIGHT: pb.TURN_STRAIGHT,
    Turn.U_TURN: pb.TURN_U_TURN,
}
_TURN_BACK = {v: k for k, v in _TURN.items()}
_POINT = {
    PointStatus.MATCHED: pb.POINT_STATUS_MATCHED,
    PointStatus.INTERPOLATED: pb.POINT_STATUS_INTERPOLATED,
    PointStatus.UNMATCHED: pb.POINT_STATUS_UNMATCHED,
}
_NAN = math.nan


# ---------------------------------------------------------------------------------- fixes
def fix_from_proto(msg: pb.Fix) -> Fix:
    """A domain :class:`Fix`; unset optional fields are NaN/None. Not validated here."""
    has = msg.HasField
    if has("pos_cov"):
        c = msg.pos_cov
        cov: tuple[float, float, float] | None = (c.var_e, c.cov_en, c.var_n)
    else:
        cov = None
    return Fix(
        msg.time,
        msg.lat,
        msg.lon,
        msg.heading if has("heading") else _NAN,
        msg.pos_sigma if has("pos_sigma") else _NAN,
        msg.heading_sigma if has("heading_sigma") else _NAN,
        msg.speed if has("speed") else _NAN,
        msg.distance if has("distance") else _NAN,
        msg.gps_valid if has("gps_valid") else None,
        cov,
    )


def fix_to_proto(fix: Fix) -> pb.Fix:
    """The proto of a domain fix; NaN/None fields are left unset."""
    kw: dict[str, Any] = {"time": fix.time, "lat": fix.lat, "lon": fix.lon}
    for name in ("heading", "pos_sigma", "heading_sigma", "speed", "distance"):
        v = getattr(fix, name)
        if not math.isnan(v):
            kw[name] = v
    if fix.gps_valid is not None:
        kw["gps_valid"] = bool(fix.gps_valid)
    if fix.pos_cov is not None:
        ve, cen, vn = fix.pos_cov
        kw["pos_cov"] = pb.PositionCovariance(var_e=ve, cov_en=cen, var_n=vn)
    return pb.Fix(**kw)


# ---------------------------------------------------------------------------------- results
# Answers are built from plain dicts in one constructor call: upb fills nested messages from
# dicts faster than from message objects, which it would copy.
def _candidate_fields(c: Candidate) -> dict[str, Any]:
    return {
        "edge": c.edge, "u": c.u, "v": c.v, "way_id": c.way_id,
        "probability": c.probability, "offset": c.offset, "dist": c.dist,
    }  # fmt: skip


def _snap_result_fields(r: SnapResult) -> dict[str, Any]:
    d: dict[str, Any] = {
        "time": r.time, "state": _STATE[r.state], "edge": r.edge, "u": r.u, "v": r.v,
        "way_id": r.way_id, "offset": r.offset, "lat": r.lat, "lon": r.lon, "bearing": r.bearing,
        "dist": r.dist, "turn": _TURN[r.turn], "candidates": [_candidate_fields(c) for c in r.candidates],
        "raw_lat": r.raw_lat, "raw_lon": r.raw_lon, "name": r.name, "road_class": r.road_class,
        "speed_kph": r.speed_kph,
    }  # fmt: skip
    m = r.map_aided
    if m != _NO_AID:  # unset: no road (the receiver gets the same default back)
        d["map_aided"] = {
            "lat": m.lat, "lon": m.lon, "cov": [m.var_e, m.cov_en, m.var_n], "along_sigma": m.along_sigma,
            "cross_sigma": m.cross_sigma, "heading": m.heading, "heading_sigma": m.heading_sigma,
            "probability": m.probability, "usable": m.usable, "reason": m.reason,
        }  # fmt: skip
    c = r.correction
    if c is not None:
        d["correction"] = {
            "time_from": c.time_from, "time_to": c.time_to, "edges": c.edges,
            "replaced_edges": c.replaced_edges, "edge_times": c.edge_times,
        }  # fmt: skip
    return d


def snap_result_to_proto(r: SnapResult) -> pb.SnapResult:
    """The proto of an online :class:`SnapResult`."""
    return pb.SnapResult(**_snap_result_fields(r))


def snap_response(map_id: str, vehicle_id: str, seq: int, r: SnapResult) -> pb.SnapResponse:
    """The stream answer carrying ``r`` (built in one call: it is made once per fix)."""
    return pb.SnapResponse(map_id=map_id, vehicle_id=vehicle_id, seq=seq, result=_snap_result_fields(r))


def snap_result_from_proto(msg: pb.SnapResult) -> SnapResult:
    """The domain :class:`SnapResult` of a response (used by the client)."""
    corr = None
    if msg.HasField("correction"):
        c = msg.correction
        corr = Correction(
            time_from=c.time_from,
            time_to=c.time_to,
            edges=tuple(c.edges),
            replaced_edges=tuple(c.replaced_edges),
            edge_times=tuple(c.edge_times),
        )
    return SnapResult(
        time=msg.time,
        state=_STATE_BACK.get(msg.state, State.INITIALISING),
        edge=msg.edge,
        u=msg.u,
        v=msg.v,
        way_id=msg.way_id,
        offset=msg.offset,
        lat=msg.lat,
        lon=msg.lon,
        bearing=msg.bearing,
        dist=msg.dist,
        turn=_TURN_BACK.get(msg.turn, Turn.NONE),
        candidates=tuple(
            Candidate(
                edge=c.edge,
                u=c.u,
                v=c.v,
                way_id=c.way_id,
                probability=c.probability,
                offset=c.offset,
                dist=c.dist,
            )
            for c in msg.candidates
        ),
        correction=corr,
        raw_lat=msg.raw_lat,
        raw_lon=msg.raw_lon,
        name=msg.name,
        road_class=msg.road_class,
        speed_kph=msg.speed_kph,
        map_aided=_aided_from_proto(msg.map_aided) if msg.HasField("map_aided") else MapAidedMeasurement(),
    )


_NO_AID = MapAidedMeasurement()


def _aided_from_proto(msg: pb.MapAidedMeasurement) -> MapAidedMeasurement:
    cov = list(msg.cov) if len(msg.cov) == 3 else [math.nan] * 3
    return MapAidedMeasurement(
        lat=msg.lat, lon=msg.lon, var_e=cov[0], cov_en=cov[1], var_n=cov[2], along_sigma=msg.along_sigma,
        cross_sigma=msg.cross_sigma, heading=msg.heading, heading_sigma=msg.heading_sigma,
        probability=msg.probability, usable=msg.usable, reason=msg.reason,
    )  # fmt: skip


def error_to_proto(code: int, field: str, message: str) -> pb.Error:
    return pb.Error(code=code, field=field, message=message)


# ---------------------------------------------------------------------------------- tracks
_TRACK_OPTIONAL = ("heading", "speed", "pos_sigma", "distance")


def track_from_proto(msg: pb.Track, *, prefix: str = "track") -> Track:
    """A domain :class:`Track`; raises :class:`ValidationError` naming a bad array, or the
    first bad value (``track.pos_sigma[3]``) by the rules of a fix's fields
    (:data:`mapmatch.types.FIELD_RULES`)."""
    lat = np.asarray(msg.lat, dtype=np.float64)
    lon = np.asarray(msg.lon, dtype=np.float64)
    n = len(lat)
    if n == 0:
        raise ValidationError(f"{prefix}.lat", "a track needs at least one point")
    if len(lon) != n:
        raise ValidationError(f"{prefix}.lon", f"has {len(lon)} values for {n} latitudes")
    check_field_array("lat", lat, prefix=prefix)
    check_field_array("lon", lon, prefix=prefix)
    time = np.asarray(msg.time, dtype=np.float64) if len(msg.time) else np.full(n, np.nan)
    if len(time) != n:
        raise ValidationError(
            f"{prefix}.time", f"has {len(time)} values for {n} points (give none or one each)"
        )
    check_field_array("time", time, prefix=prefix, unset=True)  # a track's times may be unknown
    opt: dict[str, Any] = {}
    for name in _TRACK_OPTIONAL:
        vals = getattr(msg, name)
        if not len(vals):
            opt[name] = None
            continue
        a = np.asarray(vals, dtype=np.float64)
        if len(a) != n:
            raise ValidationError(
                f"{prefix}.{name}", f"has {len(a)} values for {n} points (give none or one each)"
            )
        check_field_array(name, a, prefix=prefix)  # the rules a fix's field obeys (SnapFix)
        opt[name] = a
    return Track(track_id=msg.track_id, time=time, lat=lat, lon=lon, **opt)


def track_to_proto(track: Track) -> pb.Track:
    kw: dict[str, Any] = {
        "track_id": track.track_id,
        "lat": track.lat.tolist(),
        "lon": track.lon.tolist(),
        "time": track.time.tolist(),
    }
    for name in _TRACK_OPTIONAL:
        a = getattr(track, name)
        if a is not None:
            kw[name] = np.asarray(a, dtype=np.float64).tolist()
    return pb.Track(**kw)


def _part_points(m: TrackMatch, part: int) -> list[MatchedPoint]:
    bounds = [0, *m.splits, len(m.points)]
    return m.points[bounds[part] : bounds[part + 1]] if part + 1 < len(bounds) else []


def track_match_to_proto(m: TrackMatch, graph: RoadGraph) -> pb.TrackResult:
    """The proto of a batch :class:`TrackMatch` (way ids of the way pieces each route part
    runs along, consecutive repeats merged)."""
    from mapmatch.batch import route_ways

    routes = []
    for i, edges in enumerate(m.routes):
        e = np.asarray(edges, dtype=np.int64)
        part = TrackMatch(m.track_id, points=_part_points(m, i), routes=[list(edges)])
        ways = route_ways(part, graph)[0] if len(e) else []
        ll = m.route_lonlat[i] if i < len(m.route_lonlat) else []
        routes.append(
            pb.Route(edges=e.tolist(), way_ids=ways, lon=[p[0] for p in ll], lat=[p[1] for p in ll])
        )
    out = pb.TrackResult(
        track_id=m.track_id,
        routes=routes,
        splits=list(m.splits),
        length_m=m.length_m,
        confidence=m.confidence,
    )
    # points added in place: about 3 times faster than building a MatchedPoint message per
    # point and copying it into the list
    add, st = out.points.add, _POINT
    for p in m.points:
        add(
            index=p.index,
            status=st[p.status],
            edge=p.edge,
            offset=p.offset,
            lat=p.lat,
            lon=p.lon,
            dist=p.dist,
        )
    return out


# ---------------------------------------------------------------------------------- maps
def map_info_to_proto(entry: Any, *, session_count: int = 0) -> pb.MapInfo:
    """The proto of a :class:`service.maps.MapEntry`."""
    g: RoadGraph = entry.graph
    bbox = g.bbox
    stats = g.stats()
    build = struct_pb2.Struct()
    ParseDict(_plain(entry.build_parameters), build)
    return pb.MapInfo(
        map_id=entry.map_id,
        min_lon=bbox[0],
        min_lat=bbox[1],
        max_lon=bbox[2],
        max_lat=bbox[3],
        node_count=g.n_nodes,
        edge_count=g.n_edges,
        restriction_count=len(g.restrictions),
        road_km=float(stats["road_km"]),
        version=entry.version,
        checksum=entry.checksum,
        crs=g.crs,
        source=entry.source,
        build_parameters=build,
        session_count=session_count,
    )


def _plain(obj: Any) -> Any:
    """JSON-like values for a protobuf Struct (numbers as floats, unknown objects as strings)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, int | float):
        f = float(obj)
        return f if math.isfinite(f) else None
    return str(obj)
