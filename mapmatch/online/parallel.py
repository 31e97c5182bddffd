"""Roads running alongside: whether another road lies near the answer's stretch of its edge at
a similar bearing (the commonest place for a sure answer on the wrong road).

An edge is cut into stretches of about ``confidence.parallel_spacing`` metres; for the
middle of each, the spatial index gives the roads within ``confidence.parallel_radius``.
One runs alongside when it is not the edge or its reverse, its bearing there is within
``model.straight_max_deg`` of the edge's (straight on from it), and, when it shares a node
with the edge, the point projects inside it, further than ``measurement.map_sigma`` (the
map's own error) from the shared node: a road leaving at a junction is not alongside. A map
property, shared by every vehicle: computed for every edge of the map at once
(:func:`alongside_table`, one vectorised pass) when the matcher is made, or on the first
answer of a configuration of other settings, so no fix pays a spatial query.
"""

from __future__ import annotations

import itertools
import math
import threading
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.angles import angle_diff
from graph.index import EdgeIndex
from mapmatch.config import MatchConfig
from mapmatch.online.geometry import locate_all
from mapmatch.online.road import RoadModel


class AlongsideSettings(NamedTuple):
    """What counts as a road alongside, from the configuration (the key of a map's table)."""

    radius: float  # confidence.parallel_radius
    angle: float  # model.straight_max_deg
    spacing: float  # confidence.parallel_spacing
    node_gap: float  # measurement.map_sigma

    @classmethod
    def of(cls, cfg: MatchConfig) -> AlongsideSettings:
        """The settings of ``cfg``."""
        c = cfg.confidence
        return cls(
            c.parallel_radius, cfg.model.straight_max_deg, c.parallel_spacing, cfg.measurement.map_sigma
        )


def stretch_roads(road: RoadModel, index: EdgeIndex, edge: int, cfg: MatchConfig) -> list[tuple[int, ...]]:
    """Per stretch of ``edge`` (see the module docstring), the edges that run alongside it.

    Parameters
    ----------
    road : the road model of the map.
    index : its spatial index.
    edge : the edge.
    cfg : the configuration (``confidence.parallel_radius``, ``confidence.parallel_spacing``,
        ``model.straight_max_deg``, ``measurement.map_sigma``).

    Returns
    -------
    list of tuple of int
        Per stretch, from the edge's start, the edges alongside (empty: none).
    """
    st = AlongsideSettings.of(cfg)
    length = road.elen[edge]
    n = max(1, math.ceil(length / st.spacing))
    mids = [(k + 0.5) * length / n for k in range(n)]
    pts = [road.locate(edge, s) for s in mids]
    c = index.query(np.array([[p[0], p[1]] for p in pts]), st.radius)
    found: list[set[int]] = [set() for _ in range(n)]
    nodes = {road.eu[edge], road.ev[edge]}
    rev = road.rev[edge]
    for k, e2, off in zip(c.point.tolist(), c.edge.tolist(), c.offset.tolist(), strict=True):
        if e2 in (edge, rev) or e2 in found[k]:
            continue
        if (road.eu[e2] in nodes or road.ev[e2] in nodes) and (
            off < st.node_gap or off > road.elen[e2] - st.node_gap
        ):
            continue
        if abs(angle_diff(road.bearing_at(e2, off), pts[k][2])) <= st.angle:
            found[k].add(e2)
    return [tuple(sorted(f)) for f in found]


QUERY_POINTS = 50_000
"""Stretch middles per spatial query of :func:`alongside_table` (bounds its working memory,
not its answer)."""


@dataclass(frozen=True)
class AlongsideTable:
    """The roads alongside every stretch of every edge of a map, for one confidence section's
    settings (compressed rows: edge -> its stretches -> their roads).

    ``stretch_ptr[e]:stretch_ptr[e + 1]`` are edge ``e``'s stretches, from its start;
    ``road_ptr[s]:road_ptr[s + 1]`` the rows of ``roads`` (edges, ascending) alongside
    stretch ``s``.
    """

    stretch_ptr: NDArray[np.int64]
    road_ptr: NDArray[np.int64]
    roads: NDArray[np.int32]

    @property
    def nbytes(self) -> int:
        """The table's memory in bytes."""
        return int(self.stretch_ptr.nbytes + self.road_ptr.nbytes + self.roads.nbytes)

    def stretches(self, edge: int) -> list[tuple[int, ...]]:
        """Per stretch of ``edge``, from its start, the edges alongside (as :func:`stretch_roads`)."""
        lo, hi = int(self.stretch_ptr[edge]), int(self.stretch_ptr[edge + 1])
        ptr = self.road_ptr[lo : hi + 1].tolist()
        if ptr[0] == ptr[-1]:
            return [()] * (hi - lo)
        roads = self.roads[ptr[0] : ptr[-1]].tolist()
        base = ptr[0]
        return [tuple(roads[a - base : b - base]) for a, b in itertools.pairwise(ptr)]


def alongside_table(road: RoadModel, index: EdgeIndex, cfg: MatchConfig) -> AlongsideTable:
    """:func:`stretch_roads` of every edge of the map, in one vectorised pass (the same answers).

    Parameters
    ----------
    road : the road model of the map.
    index : its spatial index.
    cfg : the configuration (``confidence.parallel_radius``, ``confidence.parallel_spacing``,
        ``model.straight_max_deg``, ``measurement.map_sigma``).

    Returns
    -------
    AlongsideTable
        Every edge's stretches and the edges alongside each.
    """
    st = AlongsideSettings.of(cfg)
    elen = np.asarray(road.elen, dtype=np.float64)
    n_e = len(elen)
    n = np.maximum(1, np.ceil(elen / st.spacing)).astype(np.int64) if n_e else np.zeros(0, np.int64)
    stretch_ptr = np.zeros(n_e + 1, dtype=np.int64)
    np.cumsum(n, out=stretch_ptr[1:])
    n_s = int(stretch_ptr[-1])
    s_edge = np.repeat(np.arange(n_e, dtype=np.int64), n)
    k = np.arange(n_s, dtype=np.int64) - stretch_ptr[s_edge]
    mids = (k + 0.5) * elen[s_edge] / n[s_edge]
    # each middle's place and bearing (the compiled ``locate``, as :func:`stretch_roads`)
    mid = locate_all(road.arrays, s_edge, mids)
    px, py, s_brg = mid[:, 0], mid[:, 1], mid[:, 2]
    eu = np.asarray(road.eu, dtype=np.int64)
    ev = np.asarray(road.ev, dtype=np.int64)
    rev = np.asarray(road.rev, dtype=np.int64)
    gap = st.node_gap
    kept_s: list[NDArray[np.int64]] = []
    kept_e: list[NDArray[np.int64]] = []
    for lo in range(0, n_s, QUERY_POINTS):
        hi = min(lo + QUERY_POINTS, n_s)
        c = index.query(np.stack([px[lo:hi], py[lo:hi]], axis=1), st.radius)
        s = c.point + lo
        e2 = c.edge.astype(np.int64)
        off = c.offset
        e1 = s_edge[s]
        ok = (e2 != e1) & (e2 != rev[e1])
        shares = (eu[e2] == eu[e1]) | (eu[e2] == ev[e1]) | (ev[e2] == eu[e1]) | (ev[e2] == ev[e1])
        ok &= ~(shares & ((off < gap) | (off > elen[e2] - gap)))
        s, e2, off = s[ok], e2[ok], off[ok]
        b2 = locate_all(road.arrays, e2, off)[:, 2]
        d = (b2 - s_brg[s] + 180.0) % 360.0 - 180.0  # angle_diff (its -180 is 180: the same size)
        ok = np.abs(d) <= st.angle
        kept_s.append(s[ok])
        kept_e.append(e2[ok])
    s = np.concatenate(kept_s) if kept_s else np.zeros(0, np.int64)
    e2 = np.concatenate(kept_e) if kept_e else np.zeros(0, np.int64)
    order = np.lexsort((e2, s))
    s, e2 = s[order], e2[order]
    road_ptr = np.zeros(n_s + 1, dtype=np.int64)
    np.cumsum(np.bincount(s, minlength=n_s), out=road_ptr[1:])
    return AlongsideTable(stretch_ptr, road_ptr, e2.astype(np.int32))


_Kept = dict[int, list[tuple[int, ...]]]
"""Each edge's stretches, as :meth:`AlongsideTable.stretches` gives them."""


class ParallelRoads:
    """The roads alongside each stretch of a map's edges: the map's :class:`AlongsideTable`
    per setting of what counts as alongside, made once (:meth:`prepare`, or on first use), and each
    edge's stretches as Python tuples, kept from its first use (thread-safe: a race builds the
    same thing twice)."""

    def __init__(self, road: RoadModel, index: EdgeIndex) -> None:
        self.road = road
        self.index = index
        self._tables: dict[AlongsideSettings, AlongsideTable] = {}
        # per settings: each edge's stretches
        self._roads: dict[AlongsideSettings, _Kept] = {}
        self._last: tuple[MatchConfig | None, AlongsideTable | None, _Kept] = (None, None, {})
        self._lock = threading.Lock()

    def prepare(self, cfg: MatchConfig) -> AlongsideTable:
        """The table of ``cfg``'s settings, made now when it is not yet."""
        key = AlongsideSettings.of(cfg)
        table = self._tables.get(key)
        if table is None:
            with self._lock:
                table = self._tables.get(key)
                if table is None:
                    table = self._tables[key] = alongside_table(self.road, self.index, cfg)
        return table

    def alongside(self, edge: int, offset: float, cfg: MatchConfig) -> tuple[int, ...]:
        """The edges alongside ``edge`` at ``offset`` metres from its start (empty: none)."""
        last = self._last
        if last[0] is not cfg:  # the stretches of this configuration's settings (a per-fix path)
            table = self.prepare(cfg)
            last = self._last = (cfg, table, self._roads.setdefault(AlongsideSettings.of(cfg), {}))
        kept = last[2]
        roads = kept.get(edge)
        if roads is None:
            roads = kept[edge] = last[1].stretches(edge)  # type: ignore[union-attr]
        length = self.road.elen[edge]
        k = int(offset / length * len(roads)) if length > 0.0 else 0
        return roads[min(max(k, 0), len(roads) - 1)]

    def nearest(self, edge: int, offset: float, x: float, y: float, cfg: MatchConfig) -> float:
        """Metres from the point ``(x, y)`` to the nearest road alongside ``edge`` at
        ``offset`` (inf: none)."""
        best = math.inf
        for e2 in self.alongside(edge, offset, cfg):
            d = self.road.project(e2, x, y)[1]
            if d < best:
                best = d
        return best
