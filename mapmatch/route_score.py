"""Scoring a route against the true one: the route mismatch fraction, geometrically.

Truth and matched route are cut into pieces of ``piece_m`` metres; d− is the length of truth
pieces farther than ``tolerance_m`` from the matched route, d+ the length of matched pieces
farther than that from the truth; the route mismatch fraction (Newson & Krumm 2009) is
RMF = (d− + d+) / truth length. Being geometric, it does not see direction.

:func:`route_mismatch` scores two polylines in metres, :func:`score_route` two lon/lat routes
(``mapmatch eval --route``), :func:`read_route_geojson` reads one from a GeoJSON file, and
:func:`path_geometry` draws an edge path of a map.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.ops import substring

from graph.projection import to_xy
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError


def path_geometry(
    graph: RoadGraph, path: Sequence[int], *, start_offset: float = 0.0, end_offset: float | None = None
) -> NDArray[np.float64]:
    """Polyline (K, 2) of an edge path, cut at offsets on its first and last edge.

    Where consecutive edges do not join (a jump) a row of NaN separates the parts.
    """
    if not path:
        return np.empty((0, 2))
    parts = [np.asarray(graph.edge_xy(e)) for e in path]
    end = float(graph.edge_len[path[-1]]) if end_offset is None else float(end_offset)
    if len(path) == 1:
        lo, hi = sorted((start_offset, end))
        return np.asarray(shapely.get_coordinates(substring(shapely.linestrings(parts[0]), lo, hi)))
    parts[0] = shapely.get_coordinates(
        substring(shapely.linestrings(parts[0]), start_offset, graph.edge_len[path[0]])
    )
    parts[-1] = shapely.get_coordinates(substring(shapely.linestrings(parts[-1]), 0.0, end))
    out = [parts[0]]
    for a, b, xy in zip(path[:-1], path[1:], parts[1:], strict=True):
        if int(graph.edge_v[a]) != int(graph.edge_u[b]):
            out.append(np.full((1, 2), np.nan))
        out.append(xy)
    return np.vstack(out)


def split_parts(xy: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Parts of a polyline separated by NaN rows, each with at least one vertex."""
    if len(xy) == 0:
        return []
    gap = np.isnan(xy[:, 0])
    cuts = np.flatnonzero(gap)
    return [p[~np.isnan(p[:, 0])] for p in np.split(xy, cuts) if (~np.isnan(p[:, 0])).any()]


def _pieces(xy: NDArray[np.float64], piece_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mid-points and lengths of the pieces a polyline (NaN rows separate parts) is cut into."""
    mids_all: list[NDArray[np.float64]] = []
    lens_all: list[NDArray[np.float64]] = []
    for part in split_parts(xy):
        if len(part) < 2:
            continue
        line = shapely.linestrings(part)
        L = float(shapely.length(line))
        if L <= 0:
            continue
        n = max(1, int(np.ceil(L / piece_m)))
        edges = np.linspace(0.0, L, n + 1)
        mids = 0.5 * (edges[1:] + edges[:-1])
        mids_all.append(shapely.get_coordinates(shapely.line_interpolate_point(line, mids)))
        lens_all.append(np.diff(edges))
    if not mids_all:
        return np.empty((0, 2)), np.empty(0)
    return np.vstack(mids_all), np.concatenate(lens_all)


def _geometry(xy: NDArray[np.float64]) -> shapely.Geometry:
    """Lines through the parts of ``xy`` (a point for a single distinct vertex)."""
    geoms = []
    for part in split_parts(xy):
        if len(np.unique(part, axis=0)) < 2:
            geoms.append(shapely.points(part[0]))
        else:
            geoms.append(shapely.linestrings(part))
    if not geoms:
        return shapely.from_wkt("GEOMETRYCOLLECTION EMPTY")
    return geoms[0] if len(geoms) == 1 else shapely.geometrycollections(geoms)


@dataclass(frozen=True)
class RouteMismatch:
    """Route mismatch fraction and its parts (metres)."""

    truth_m: float
    missing_m: float
    extra_m: float

    @property
    def fraction(self) -> float:
        return (self.missing_m + self.extra_m) / self.truth_m if self.truth_m > 0 else float("nan")


def route_mismatch(
    truth_xy: ArrayLike, match_xy: ArrayLike, *, tolerance_m: float = 2.0, piece_m: float = 1.0
) -> RouteMismatch:
    """Geometric route mismatch fraction of a matched route against the true one.

    Parameters
    ----------
    truth_xy, match_xy
        Polylines (K, 2) in metres; an empty matched route misses everything.
    tolerance_m
        A piece closer than this to the other line counts as shared.
    piece_m
        Length of the pieces.
    """
    t = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
    m = np.asarray(match_xy, dtype=np.float64).reshape(-1, 2)
    tm, tl = _pieces(t, piece_m)
    mm, ml = _pieces(m, piece_m)
    if len(mm) == 0:
        return RouteMismatch(truth_m=float(tl.sum()), missing_m=float(tl.sum()), extra_m=0.0)
    tline = _geometry(t)
    mline = _geometry(m)
    dt = shapely.distance(shapely.points(tm), mline)
    dm = shapely.distance(shapely.points(mm), tline)
    return RouteMismatch(
        truth_m=float(tl.sum()),
        missing_m=float(tl[dt > tolerance_m].sum()),
        extra_m=float(ml[dm > tolerance_m].sum()),
    )


@dataclass(frozen=True)
class RouteScore:
    """Route mismatch of one matched route against a true route (``mapmatch eval --route``)."""

    track_id: str
    crs: str
    truth_m: float
    matched_m: float
    rmf: RouteMismatch
    tolerance_m: float
    unmatched_points: int = 0
    points: int = 0

    def table(self) -> str:
        """The score as aligned text rows."""
        r = self.rmf
        rows = [
            ("track", self.track_id),
            ("true route length", f"{r.truth_m:,.0f} m"),
            ("matched route length", f"{self.matched_m:,.0f} m"),
            (
                f"route mismatch fraction (tol {self.tolerance_m:g} m)",
                f"{100 * r.fraction:.2f} % (missing {r.missing_m:,.0f} m, extra {r.extra_m:,.0f} m)",
            ),
        ]
        if self.points:
            rows.append(("unmatched points", f"{self.unmatched_points} of {self.points}"))
        rows.append(("scored in", self.crs))
        w = max(len(k) for k, _ in rows)
        return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def _lonlat_parts(geometry: dict[str, Any] | None) -> list[NDArray[np.float64]]:
    """lon/lat polylines of a GeoJSON (Multi)LineString geometry (other types: none)."""
    if not geometry:
        return []
    kind, coords = geometry.get("type"), geometry.get("coordinates") or []
    lines = [coords] if kind == "LineString" else coords if kind == "MultiLineString" else []
    return [np.asarray(c, dtype=np.float64)[:, :2] for c in lines if len(c) >= 2]


def read_route_geojson(
    path: str | os.PathLike[str], *, track_id: str | None = None
) -> tuple[str, list[NDArray[np.float64]], dict[str, Any]]:
    """One route from a GeoJSON file: ``(track id, lon/lat parts, properties)``.

    The file is a Feature (a true route such as Kubicka's ``truth.geojson``) or a
    FeatureCollection (``mapmatch match`` output: one feature per track, chosen by ``track_id``
    (property ``track_id`` or ``track``) when there are several).

    Raises
    ------
    ValidationError
        Not GeoJSON, no such track, several tracks and none named, or no line geometry.
    """
    import json

    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValidationError("route", f"{path} is not GeoJSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValidationError("route", f"{path} is not a GeoJSON object")
    if doc.get("type") == "FeatureCollection":
        feats = [f for f in doc.get("features") or [] if isinstance(f, dict)]
    elif doc.get("type") == "Feature":
        feats = [doc]
    else:
        feats = [{"type": "Feature", "geometry": doc, "properties": {}}]

    def fid(f: dict[str, Any]) -> str:
        p = f.get("properties") or {}
        return str(p.get("track_id", p.get("track", "")))

    if track_id is not None:
        feats = [f for f in feats if fid(f) == track_id]
        if not feats:
            raise ValidationError("track_id", f"{path} has no track {track_id!r}")
    elif len(feats) > 1:
        ids = ", ".join(fid(f) for f in feats[:5])
        raise ValidationError("track_id", f"{path} holds {len(feats)} tracks ({ids}, ...); name one")
    if not feats:
        raise ValidationError("route", f"{path} holds no feature")
    feat = feats[0]
    parts = _lonlat_parts(feat.get("geometry"))
    props = dict(feat.get("properties") or {})
    return fid(feat), parts, props


def score_route(
    truth_lonlat: Sequence[ArrayLike],
    matched_lonlat: Sequence[ArrayLike],
    *,
    tolerance_m: float = 2.0,
    crs: str | None = None,
    track_id: str = "",
    points: int = 0,
    unmatched_points: int = 0,
) -> RouteScore:
    """Route mismatch fraction of a matched route (lon/lat parts) against the true one.

    Both are projected to ``crs`` (default: the UTM zone of the true route's first vertex) and
    compared by :func:`route_mismatch`; separate parts stay separate.
    """
    from graph.projection import utm_crs

    truth = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in truth_lonlat]
    truth = [p for p in truth if len(p)]
    if not truth:
        raise ValidationError("route", "the true route has no line geometry")
    crs = crs or utm_crs(float(truth[0][0, 0]), float(truth[0][0, 1]))

    def xy(parts: Sequence[ArrayLike]) -> NDArray[np.float64]:
        out: list[NDArray[np.float64]] = []
        for p in parts:
            a = np.asarray(p, dtype=np.float64).reshape(-1, 2)
            if len(a):
                out += [to_xy(crs, a[:, 0], a[:, 1]), np.full((1, 2), np.nan)]
        return np.vstack(out[:-1]) if out else np.empty((0, 2))

    t, m = xy(truth), xy(matched_lonlat)
    _, ml = _pieces(m, 1.0)
    rmf = route_mismatch(t, m, tolerance_m=tolerance_m)
    return RouteScore(
        track_id=track_id, crs=crs, truth_m=rmf.truth_m, matched_m=float(ml.sum()), rmf=rmf,
        tolerance_m=tolerance_m, points=points, unmatched_points=unmatched_points,
    )  # fmt: skip


@dataclass(frozen=True)
class Stretch:
    """A stretch of one route that another route does not cover: its length and its polyline."""

    length_m: float
    xy: NDArray[np.float64]


def trim_route_ends(
    parts: Sequence[ArrayLike], *, first_xy: ArrayLike, last_xy: ArrayLike
) -> list[NDArray[np.float64]]:
    """A route's pieces with the first piece cut before the projection of ``first_xy`` and the
    last piece cut after the projection of ``last_xy`` (as the peers' scorer trims the truth).

    Pieces with fewer than two vertices are left out; a single piece whose projections come in
    reverse order is left whole.
    """
    lines = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in parts]
    lines = [p for p in lines if len(p) >= 2]
    if not lines:
        return []
    first = shapely.linestrings(lines[0])
    s0 = float(shapely.line_locate_point(first, shapely.points(np.asarray(first_xy, dtype=np.float64))))
    last = shapely.linestrings(lines[-1])
    s1 = float(shapely.line_locate_point(last, shapely.points(np.asarray(last_xy, dtype=np.float64))))
    if len(lines) == 1:
        if s0 <= s1:
            lines[0] = np.asarray(shapely.get_coordinates(substring(first, s0, s1)))
        return [p for p in lines if len(p) >= 2]
    lines[0] = np.asarray(shapely.get_coordinates(substring(first, s0, float(shapely.length(first)))))
    lines[-1] = np.asarray(shapely.get_coordinates(substring(last, 0.0, s1)))
    return [p for p in lines if len(p) >= 2]


def uncovered_stretches(
    covering: Sequence[ArrayLike], covered: Sequence[ArrayLike], *, buffer_m: float, min_length_m: float
) -> list[Stretch]:
    """The stretches of the route ``covered`` farther than ``buffer_m`` from the route
    ``covering``, longer than ``min_length_m`` (both routes as pieces of (k, 2) polylines in
    metres). Geometric, so direction is not seen; an empty ``covering`` covers nothing.
    """
    lines = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in covering]
    geoms = [shapely.linestrings(p) for p in lines if len(np.unique(p, axis=0)) >= 2]
    buf = shapely.buffer(shapely.multilinestrings(geoms), buffer_m) if geoms else None
    out: list[Stretch] = []
    for part in covered:
        xy = np.asarray(part, dtype=np.float64).reshape(-1, 2)
        if len(np.unique(xy, axis=0)) < 2:
            continue
        line = shapely.linestrings(xy)
        rest = line if buf is None else shapely.line_merge(shapely.difference(line, buf))
        for g in shapely.get_parts(rest):
            length = float(shapely.length(g))
            if length > min_length_m:
                out.append(Stretch(length_m=length, xy=np.asarray(shapely.get_coordinates(g))))
    return out


def farthest_from(route: Sequence[ArrayLike], xy: ArrayLike, *, step_m: float = 5.0) -> float:
    """The greatest distance from the polyline ``xy`` (sampled every ``step_m`` metres) to the
    route's pieces; infinite for an empty route."""
    lines = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in route]
    geoms = [shapely.linestrings(p) for p in lines if len(np.unique(p, axis=0)) >= 2]
    if not geoms:
        return float("inf")
    line = shapely.linestrings(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    n = max(2, int(np.ceil(float(shapely.length(line)) / step_m)) + 1)
    pts = shapely.line_interpolate_point(line, np.linspace(0.0, 1.0, n), normalized=True)
    return float(shapely.distance(pts, shapely.multilinestrings(geoms)).max())
