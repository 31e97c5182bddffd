"""Parallel neighbours of every edge: other roads within a band at a similar bearing.

A carriageway of a divided road, a frontage or service road, a ramp beside the main road, or
the other branch of a fork at a small angle: roads the GPS cannot tell from the one believed
until the evidence has built up. The table is computed once per map from the graph's arrays
(one vectorised segment-to-segment query), so an online matcher looks them up per fix instead of
searching the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray

from graph.angles import angle_diffs, bearings
from graph.index import EdgeIndex
from graph.road_graph import RoadGraph


@dataclass(frozen=True)
class Neighbours:
    """CSR table: the neighbours of edge ``e`` are ``edge[ptr[e]:ptr[e + 1]]``, nearest first,
    with ``dist`` the smallest distance in metres between the two."""

    ptr: NDArray[np.int64]
    edge: NDArray[np.int32]
    dist: NDArray[np.float64]

    def of(self, e: int) -> NDArray[np.int32]:
        """The neighbours of edge ``e``."""
        return self.edge[self.ptr[e] : self.ptr[e + 1]]


def _bearing(d: NDArray[np.float64]) -> NDArray[np.float64]:
    return bearings(d[:, 0], d[:, 1])


def edge_neighbours(
    graph: RoadGraph,
    *,
    band_m: float = 40.0,
    max_angle_deg: float = 30.0,
    max_per_edge: int = 8,
    index: EdgeIndex | None = None,
    edges: NDArray[np.int64] | list[int] | None = None,
) -> Neighbours:
    """For every directed edge, the other directed edges with a segment within ``band_m`` of
    one of its own segments at a bearing within ``max_angle_deg``.

    The edge's reverse twin and the edges that continue it (leaving its end node or entering its
    start node) are not neighbours; branches of a fork (leaving the same node) are. At most
    ``max_per_edge`` neighbours are kept, nearest first. One vectorised segment-to-segment
    query of the spatial index; with ``edges``, only the rows of those edges are filled
    (the others are empty), for a table filled as edges are first needed.
    """
    n = graph.n_edges
    if n == 0 or graph.n_edges == 0:
        return Neighbours(np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0))
    idx = index if index is not None else EdgeIndex(graph)
    if len(idx.seg_a) == 0:
        return Neighbours(np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0))
    lines = np.asarray(idx.tree.geometries)
    rev = graph.edge_reverse.astype(np.int64)
    want: NDArray[np.bool_] | None = None
    if edges is None:
        i, j = idx.tree.query(lines, predicate="dwithin", distance=band_m)
    else:
        want = np.zeros(n, dtype=bool)
        want[np.asarray(edges, dtype=np.int64)] = True
        road = want.copy()
        road[rev[want & (rev >= 0)]] = True
        mine = np.flatnonzero(road[idx.seg_edge])
        i, j = idx.tree.query(lines[mine], predicate="dwithin", distance=band_m)
        i = mine[i]
    i, j = i.astype(np.int64), j.astype(np.int64)
    ea, eb = idx.seg_edge[i].astype(np.int64), idx.seg_edge[j].astype(np.int64)
    ok = ea != eb
    i, j, ea, eb = i[ok], j[ok], ea[ok], eb[ok]
    d = idx.seg_b - idx.seg_a
    brg = _bearing(d)
    ang = np.abs(angle_diffs(brg[j], brg[i]))
    same = ang <= max_angle_deg
    opposite = ang >= 180.0 - max_angle_deg
    sel = same | opposite
    i, j, ea, eb, same = i[sel], j[sel], ea[sel], eb[sel], same[sel]
    dist = shapely.distance(lines[i], lines[j])
    # the indexed direction of each road, and its twin: pairs with the same sense of travel
    ra, rb = rev[ea], rev[eb]
    src = np.concatenate([ea, ra, ea, ra])
    dst = np.concatenate([eb, rb, rb, eb])
    dd = np.concatenate([dist, dist, dist, dist])
    valid = np.concatenate([same, same & (ra >= 0) & (rb >= 0), ~same & (rb >= 0), ~same & (ra >= 0)])
    src, dst, dd = src[valid], dst[valid], dd[valid]
    u, v = graph.edge_u.astype(np.int64), graph.edge_v.astype(np.int64)
    keep = (dst != src) & (dst != rev[src]) & (u[dst] != v[src]) & (v[dst] != u[src])
    if want is not None:
        keep &= want[src]
    src, dst, dd = src[keep], dst[keep], dd[keep]
    # nearest distance per (edge, neighbour), then at most max_per_edge per edge
    order = np.lexsort((dd, dst, src))
    src, dst, dd = src[order], dst[order], dd[order]
    first = np.ones(len(src), dtype=bool)
    first[1:] = (src[1:] != src[:-1]) | (dst[1:] != dst[:-1])
    src, dst, dd = src[first], dst[first], dd[first]
    order = np.lexsort((dd, src))
    src, dst, dd = src[order], dst[order], dd[order]
    rank = np.arange(len(src)) - np.searchsorted(src, src, side="left")
    sel = rank < max_per_edge
    src, dst, dd = src[sel], dst[sel], dd[sel]
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(ptr, src + 1, 1)
    return Neighbours(np.cumsum(ptr), dst.astype(np.int32), dd)
