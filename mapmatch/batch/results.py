"""Turning the compiled assembly into a :class:`~mapmatch.types.TrackMatch`, and the way ids
and names under the matched route and points."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from graph.projection import rows_to_lonlat
from graph.road_graph import RoadGraph, merge_repeats
from mapmatch.batch.packed import TrackResult
from mapmatch.types import MatchedPoint, PointStatus, TrackMatch


def track_match(track_id: str, result: TrackResult) -> TrackMatch:
    """A :class:`TrackMatch` of the compiled kernel's answer (:func:`mapmatch.batch.packed.decode`):
    its list fields are built on first access (:class:`PackedMatch`)."""
    return PackedMatch(track_id, result)


_LAZY = ("routes", "splits", "length_m", "confidence", "route_xy", "point_arrays")
"""The fields a :class:`PackedMatch` builds from its :class:`TrackResult`, in
:meth:`TrackResult.unpacked`'s order."""
_SLOT = {name: TrackMatch.__dict__[name] for name in _LAZY}
""":class:`TrackMatch`'s own storage of those fields."""


class PackedMatch(TrackMatch):
    """A :class:`TrackMatch` that keeps the kernel's :class:`TrackResult` and fills ``routes``,
    ``splits``, ``length_m``, ``confidence``, ``route_xy`` and ``point_arrays`` from it the first
    time any of them is read or set (a call whose answer is not read does not pay for them).
    Compares equal to a :class:`TrackMatch` with the same fields."""

    __slots__ = ("_result",)

    def __init__(self, track_id: str, result: TrackResult) -> None:
        self._result: TrackResult | None = result
        self.track_id = track_id
        self.points = []
        self.route_lonlat = []

    def _fill(self) -> None:
        result = getattr(self, "_result", None)
        self._result = None
        values = result.unpacked() if result is not None else ([], [], 0.0, 0.0, [], None)
        for name, value in zip(_LAZY, values, strict=True):
            _SLOT[name].__set__(self, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TrackMatch):
            return NotImplemented
        names = [f.name for f in dataclasses.fields(TrackMatch)]  # as the dataclass compares
        return tuple(getattr(self, n) for n in names) == tuple(getattr(other, n) for n in names)

    def __reduce__(self) -> tuple[Any, ...]:
        return (TrackMatch, tuple(getattr(self, f.name) for f in dataclasses.fields(TrackMatch)))


def _lazy_field(name: str) -> property:
    slot = _SLOT[name]

    def get(self: PackedMatch) -> Any:
        try:
            return slot.__get__(self)
        except AttributeError:  # not filled yet
            self._fill()
            return slot.__get__(self)

    def put(self: PackedMatch, value: Any) -> None:
        if getattr(self, "_result", None) is not None:
            self._fill()
        slot.__set__(self, value)

    return property(get, put)


for _name in _LAZY:
    setattr(PackedMatch, _name, _lazy_field(_name))


def fill_route_lonlat(result: TrackMatch, crs: str) -> TrackMatch:
    """Fill ``route_lonlat`` from ``route_xy`` and ``points`` from ``point_arrays`` (one projection
    of the route and every point; unmatched points get NaN)."""
    pa = result.point_arrays
    pieces = list(result.route_xy)
    if pa is not None:
        pieces.append(pa[3])
    lon: list[float] = []
    lat: list[float] = []
    if pieces:
        buf = np.ascontiguousarray(np.concatenate(pieces).T)  # rows x, y: projected in place
        rows_to_lonlat(crs, buf)
        lon, lat = buf.tolist()
    out: list[list[tuple[float, float]]] = []
    i = 0
    for piece in result.route_xy:
        out.append(list(zip(lon[i : i + len(piece)], lat[i : i + len(piece)], strict=True)))
        i += len(piece)
    result.route_lonlat = out
    if pa is not None:
        status, p_edge, p_off, _, p_dist = pa
        stat = (PointStatus.UNMATCHED, PointStatus.MATCHED, PointStatus.INTERPOLATED)
        nan = math.nan
        result.points = [
            MatchedPoint(k, stat[s], e, o, la if s else nan, lo if s else nan, d)
            for k, (s, e, o, la, lo, d) in enumerate(
                zip(
                    status.tolist(), p_edge.tolist(), p_off.tolist(), lat[i:], lon[i:],
                    p_dist.tolist(), strict=True,
                )
            )
        ]  # fmt: skip
        result.point_arrays = None
    return result


def route_ways(result: TrackMatch, graph: RoadGraph) -> tuple[list[int], list[str]]:
    """The way ids and names the matched route runs along, in order, consecutive repeats merged.

    Each connected part of the route starts at the way piece under its first placed point
    and ends at the piece under its last one (an edge can be made of several ways).
    """
    bounds = [0, *result.splits, len(result.points)]
    ways: list[int] = []
    names: list[str] = []
    for s, edges in enumerate(result.routes):
        if not edges:
            continue
        pts = (
            [p for p in result.points[bounds[s] : bounds[s + 1]] if p.edge >= 0]
            if s + 1 < len(bounds)
            else []
        )
        start = pts[0].offset if pts and pts[0].edge == edges[0] else 0.0
        end = pts[-1].offset if pts and pts[-1].edge == edges[-1] else math.inf
        w, n = graph.route_ways(edges, start=start, end=end)
        ways += w
        names += n
    return merge_repeats(ways), merge_repeats(names)


def point_ways(result: TrackMatch, graph: RoadGraph) -> tuple[list[int], list[str]]:
    """Per point, the way id and name of the way piece under it (-1 and "" when unplaced)."""
    e = np.array([p.edge for p in result.points], dtype=np.int64)
    off = np.array([p.offset for p in result.points], dtype=np.float64)
    piece = graph.piece_at(e, np.nan_to_num(off))
    ok = piece >= 0
    way = np.where(ok, graph.piece_way_id[np.maximum(piece, 0)] if graph.n_pieces else -1, -1)
    name_idx = np.where(ok, graph.piece_name_idx[np.maximum(piece, 0)] if graph.n_pieces else -1, -1)
    return way.tolist(), [graph.names[i] if i >= 0 else "" for i in name_idx.tolist()]
