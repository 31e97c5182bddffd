"""Fixes placed on tiny ASCII maps and matched edges named by their intersections, for the
batch tests drawn on them (``test_batch_ascii``, ``test_batch_peer_cases``)."""

from __future__ import annotations

import numpy as np

from graph.ascii import AsciiMap
from mapmatch.types import Track


def track_from_xy(amap: AsciiMap, xy: list[tuple[float, float]], *, dt: float = 5.0, tid: str = "t") -> Track:
    """A track through points given in metres relative to the map's origin node positions."""
    ll = np.array([amap.lonlat(x, y) for x, y in xy])
    return Track(tid, np.arange(len(xy), dtype=np.float64) * dt, ll[:, 1], ll[:, 0])


def at(amap: AsciiMap, node: str, dx: float = 0.0, dy: float = 0.0) -> tuple[float, float]:
    """The point ``dx`` metres east and ``dy`` north of intersection ``node``."""
    x, y = amap.xy(node)
    return float(x + dx), float(y + dy)


def names(amap: AsciiMap, edges: list[int]) -> list[str]:
    """Each edge as its two intersections' letters (``"ab"``: from a to b)."""
    inv = {v: k for k, v in amap.nodes.items()}
    g = amap.graph
    return [inv[int(g.edge_u[e])] + inv[int(g.edge_v[e])] for e in edges]
