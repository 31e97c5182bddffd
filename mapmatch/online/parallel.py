"""Roads running alongside: whether another road lies near the answer's stretch of its edge at
a similar bearing (the commonest place for a sure answer on the wrong road).

An edge is cut into stretches of about ``confidence.parallel_spacing`` metres; for the
middle of each, the spatial index gives the roads within ``confidence.parallel_radius``.
One runs alongside when it is not the edge or its reverse, its bearing there is within
``model.straight_max_deg`` of the edge's (straight on from it), and, when it shares a node
with the edge, the point projects inside it, further than ``measurement.map_sigma`` (the
map's own error) from the shared node: a road leaving at a junction is not alongside.
Computed for an edge the first time an answer lies on it, then kept: a map
property, shared by every vehicle.
"""

from __future__ import annotations

import math

import numpy as np

from graph.angles import angle_diff
from graph.index import EdgeIndex
from mapmatch.config import MatchConfig
from mapmatch.online.road import RoadModel


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
    conf = cfg.confidence
    angle, gap = cfg.model.straight_max_deg, cfg.measurement.map_sigma
    length = road.elen[edge]
    n = max(1, math.ceil(length / conf.parallel_spacing))
    mids = [(k + 0.5) * length / n for k in range(n)]
    pts = [road.locate(edge, s) for s in mids]
    c = index.query(np.array([[p[0], p[1]] for p in pts]), conf.parallel_radius)
    found: list[set[int]] = [set() for _ in range(n)]
    nodes = {road.eu[edge], road.ev[edge]}
    rev = road.rev[edge]
    for k, e2, off in zip(c.point.tolist(), c.edge.tolist(), c.offset.tolist(), strict=True):
        if e2 in (edge, rev) or e2 in found[k]:
            continue
        if (road.eu[e2] in nodes or road.ev[e2] in nodes) and (off < gap or off > road.elen[e2] - gap):
            continue
        if abs(angle_diff(road.bearing_at(e2, off), pts[k][2])) <= angle:
            found[k].add(e2)
    return [tuple(sorted(f)) for f in found]


class ParallelRoads:
    """The roads alongside each stretch of a map's edges, computed on first use and kept
    (thread-safe: a race computes an edge's stretches twice, with the same result)."""

    def __init__(self, road: RoadModel, index: EdgeIndex) -> None:
        self.road = road
        self.index = index
        self._roads: dict[tuple[int, float, float, float, float], list[tuple[int, ...]]] = {}

    def alongside(self, edge: int, offset: float, cfg: MatchConfig) -> tuple[int, ...]:
        """The edges alongside ``edge`` at ``offset`` metres from its start (empty: none)."""
        c = cfg.confidence
        key = (
            edge,
            c.parallel_radius,
            c.parallel_spacing,
            cfg.model.straight_max_deg,
            cfg.measurement.map_sigma,
        )
        roads = self._roads.get(key)
        if roads is None:
            roads = self._roads[key] = stretch_roads(self.road, self.index, edge, cfg)
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
