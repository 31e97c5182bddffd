"""Roads running alongside: whether another road lies near the answer's stretch of its edge at
a similar bearing (the commonest place for a sure answer on the wrong road).

An edge is cut into stretches of about ``confidence.parallel_spacing`` metres; for the
middle of each, the spatial index gives the roads within ``confidence.parallel_radius``.
One runs alongside when it is not the edge or its reverse, its bearing there is within
``confidence.parallel_angle`` of the edge's, and, when it shares a node with the edge, the
point projects inside it (not onto the shared node: a road leaving at a junction is not
alongside). Computed for an edge the first time an answer lies on it, then kept: a map
property, shared by every vehicle.
"""

from __future__ import annotations

import math

import numpy as np

from graph.angles import angle_diff
from graph.index import EdgeIndex
from mapmatch.config import ConfidenceConfig
from mapmatch.online.road import RoadModel


def stretch_roads(
    road: RoadModel, index: EdgeIndex, edge: int, stretch: int, cfg: ConfidenceConfig
) -> tuple[int, ...]:
    """The edges that run alongside one stretch of ``edge`` (see the module docstring).

    Parameters
    ----------
    road : the road model of the map.
    index : its spatial index.
    edge : the edge.
    stretch : which stretch, counted from the edge's start (:func:`stretch_of`).
    cfg : the confidence section (``parallel_radius``, ``parallel_angle``,
        ``parallel_spacing``, ``parallel_node_gap``).

    Returns
    -------
    tuple of int
        The edges alongside, sorted (empty: none).
    """
    length = road.elen[edge]
    n = stretch_count(length, cfg)
    x, y, bearing = road.locate(edge, (stretch + 0.5) * length / n)
    c = index.query(np.array([[x, y]]), cfg.parallel_radius)
    found: set[int] = set()
    nodes = {road.eu[edge], road.ev[edge]}
    rev = road.rev[edge]
    gap = cfg.parallel_node_gap
    for e2, off in zip(c.edge.tolist(), c.offset.tolist(), strict=True):
        if e2 in (edge, rev) or e2 in found:
            continue
        if (road.eu[e2] in nodes or road.ev[e2] in nodes) and (off < gap or off > road.elen[e2] - gap):
            continue
        if abs(angle_diff(road.bearing_at(e2, off), bearing)) <= cfg.parallel_angle:
            found.add(e2)
    return tuple(sorted(found))


def stretch_count(length: float, cfg: ConfidenceConfig) -> int:
    """How many stretches an edge of ``length`` metres is cut into."""
    return max(1, math.ceil(length / cfg.parallel_spacing))


def stretch_of(length: float, offset: float, cfg: ConfidenceConfig) -> int:
    """The stretch of an edge of ``length`` metres that holds ``offset``."""
    n = stretch_count(length, cfg)
    k = int(offset / length * n) if length > 0.0 else 0
    return min(max(k, 0), n - 1)


class ParallelRoads:
    """The roads alongside each stretch of a map's edges, computed the first time an answer
    lies on that stretch and kept (thread-safe: a race computes a stretch twice, with the
    same result)."""

    def __init__(self, road: RoadModel, index: EdgeIndex) -> None:
        self.road = road
        self.index = index
        self._roads: dict[tuple[int, int, ConfidenceConfig], tuple[int, ...]] = {}

    def alongside(self, edge: int, offset: float, cfg: ConfidenceConfig) -> tuple[int, ...]:
        """The edges alongside ``edge`` at ``offset`` metres from its start (empty: none)."""
        k = stretch_of(self.road.elen[edge], offset, cfg)
        key = (edge, k, cfg)
        roads = self._roads.get(key)
        if roads is None:
            roads = self._roads[key] = stretch_roads(self.road, self.index, edge, k, cfg)
        return roads

    def nearest(self, edge: int, offset: float, x: float, y: float, cfg: ConfidenceConfig) -> float:
        """Metres from the point ``(x, y)`` to the nearest road alongside ``edge`` at
        ``offset`` (inf: none)."""
        best = math.inf
        for e2 in self.alongside(edge, offset, cfg):
            d = self.road.project(e2, x, y)[1]
            if d < best:
                best = d
        return best
