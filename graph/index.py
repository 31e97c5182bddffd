"""Spatial index over edge segments: candidate edges near points, vectorised.

One shapely STRtree over the straight segments of every undirected road; a query for many
points at once returns flat parallel arrays of (point, directed edge, distance, offset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from graph.road_graph import RoadGraph


@dataclass(frozen=True)
class Candidates:
    """Flat candidate table, sorted by point then distance.

    ``point[i]`` is the query point, ``edge[i]`` the directed edge, ``dist[i]`` the distance in
    metres from the point to the edge, ``offset[i]`` the distance along the edge from its start
    to the projection, and ``xy[i]`` the projected position.
    """

    point: NDArray[np.int64]
    edge: NDArray[np.int32]
    dist: NDArray[np.float64]
    offset: NDArray[np.float64]
    xy: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.point)


class EdgeIndex:
    """Spatial index over a graph's edge segments.

    Parameters
    ----------
    graph
        The road graph. Each undirected road is indexed once; results list both directions.
    """

    def __init__(self, graph: RoadGraph) -> None:
        self.graph = graph
        e = graph.n_edges
        rev = graph.edge_reverse
        keep = (rev < 0) | (np.arange(e) < rev)
        ptr = graph.edge_seg_ptr
        nseg = np.diff(ptr) - 1
        edges = np.repeat(np.arange(e, dtype=np.int32), nseg)
        starts = np.repeat(ptr[:-1], nseg)
        local = np.arange(len(edges)) - np.repeat(np.cumsum(nseg) - nseg, nseg)
        a_idx = starts + local
        sel = keep[edges]
        self.seg_edge = edges[sel]
        self.seg_a = graph.seg_xy[a_idx[sel]]
        self.seg_b = graph.seg_xy[a_idx[sel] + 1]
        d = self.seg_b - self.seg_a
        self.seg_len = np.hypot(d[:, 0], d[:, 1])
        # offset along the edge at each segment's start
        seglen_all = np.hypot(*(graph.seg_xy[a_idx + 1] - graph.seg_xy[a_idx]).T)
        cum = np.cumsum(seglen_all) - seglen_all
        edge_first = np.repeat(np.cumsum(nseg) - nseg, nseg)
        self.seg_off = (cum - cum[edge_first])[sel] if len(cum) else cum
        lines = shapely.linestrings(np.stack([self.seg_a, self.seg_b], axis=1)) if len(self.seg_a) else []
        self.tree = shapely.STRtree(lines)

    def query(self, xy: ArrayLike, radius: float | ArrayLike, *, k: int | None = None) -> Candidates:
        """Directed edges within ``radius`` metres of each point.

        Parameters
        ----------
        xy
            (P, 2) points in the graph's CRS.
        radius
            Search radius in metres, scalar or one per point.
        k
            Keep at most the ``k`` nearest undirected roads per point (both directions of a
            two-way road are kept together). ``None`` keeps all.
        """
        pts_xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(pts_xy),))
        if len(pts_xy) == 0 or len(self.seg_a) == 0:
            return _empty()
        pts = shapely.points(pts_xy)
        pi, si = self.tree.query(pts, predicate="dwithin", distance=r)
        if len(pi) == 0:
            return _empty()
        p = pts_xy[pi]
        a = self.seg_a[si]
        ab = self.seg_b[si] - a
        L = self.seg_len[si]
        t = np.where(L > 0, np.einsum("ij,ij->i", p - a, ab) / np.maximum(L * L, 1e-12), 0.0)
        t = np.clip(t, 0.0, 1.0)
        proj = a + ab * t[:, None]
        dist = np.hypot(*(p - proj).T)
        off = self.seg_off[si] + t * L
        edge = self.seg_edge[si]
        # best segment per (point, edge)
        order = np.lexsort((dist, edge, pi))
        pi, edge, dist, off, proj = pi[order], edge[order], dist[order], off[order], proj[order]
        first = np.ones(len(pi), dtype=bool)
        first[1:] = (pi[1:] != pi[:-1]) | (edge[1:] != edge[:-1])
        pi, edge, dist, off, proj = pi[first], edge[first], dist[first], off[first], proj[first]
        # nearest first within each point, then keep k
        order = np.lexsort((edge, dist, pi))
        pi, edge, dist, off, proj = pi[order], edge[order], dist[order], off[order], proj[order]
        if k is not None:
            starts = np.searchsorted(pi, pi, side="left")
            rank = np.arange(len(pi)) - starts
            keep = rank < k
            pi, edge, dist, off, proj = pi[keep], edge[keep], dist[keep], off[keep], proj[keep]
        # add the reverse direction of two-way roads
        rev = self.graph.edge_reverse[edge]
        has = rev >= 0
        elen = self.graph.edge_len
        pi2 = np.concatenate([pi, pi[has]])
        edge2 = np.concatenate([edge, rev[has]]).astype(np.int32)
        dist2 = np.concatenate([dist, dist[has]])
        off2 = np.concatenate([off, elen[rev[has]] - off[has]])
        proj2 = np.concatenate([proj, proj[has]])
        order = np.lexsort((edge2, dist2, pi2))
        return Candidates(
            point=pi2[order].astype(np.int64),
            edge=edge2[order],
            dist=dist2[order],
            offset=np.clip(off2[order], 0.0, elen[edge2[order]]),
            xy=proj2[order],
        )

    def nearest(self, xy: ArrayLike, max_radius: float) -> Candidates:
        """Candidates for each point at the distance of its nearest road (within ``max_radius``)."""
        pts_xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(pts_xy) == 0 or len(self.seg_a) == 0:
            return _empty()
        _, d = self.tree.query_nearest(shapely.points(pts_xy), max_distance=max_radius, return_distance=True)
        if len(d) == 0:
            return _empty()
        return self.query(pts_xy, float(np.max(d)) + 1e-6, k=1)


def _empty() -> Candidates:
    return Candidates(
        point=np.empty(0, np.int64),
        edge=np.empty(0, np.int32),
        dist=np.empty(0),
        offset=np.empty(0),
        xy=np.empty((0, 2)),
    )


def project_to_edge(graph: RoadGraph, edge: int, x: float, y: float) -> tuple[float, float, float, float]:
    """Project a point onto one edge: ``(offset, dist, px, py)``. Searches nothing else."""
    g = graph.edge_xy(edge)
    a = g[:-1]
    ab = g[1:] - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", np.array([x, y]) - a, ab) / np.maximum(L2, 1e-12), 0.0, 1.0)
    proj = a + ab * t[:, None]
    d = np.hypot(proj[:, 0] - x, proj[:, 1] - y)
    i = int(np.argmin(d))
    seg = np.sqrt(L2)
    off = float(seg[:i].sum() + t[i] * seg[i])
    return off, float(d[i]), float(proj[i, 0]), float(proj[i, 1])


def project_point(
    seg_xy: NDArray[np.float64], lo: int, hi: int, x: float, y: float, length: float, bearing0: float
) -> tuple[float, float, float, float, float]:
    """Project a point onto the polyline ``seg_xy[lo:hi]`` (one edge), scalar entry.

    Returns ``(offset, dist, px, py, bearing)``: metres along the polyline (at most ``length``),
    distance, projected position and the bearing of the piece it lies on (``bearing0`` for a
    polyline of zero length). The nearest piece wins; the first of equally near ones.
    """
    pts = seg_xy[lo:hi].tolist()
    best = math.inf
    acc = 0.0
    res = (0.0, pts[0][0], pts[0][1], 0.0, 1.0)
    ax, ay = pts[0]
    for bx, by in pts[1:]:
        dx, dy = bx - ax, by - ay
        l2 = dx * dx + dy * dy
        t = ((x - ax) * dx + (y - ay) * dy) / l2 if l2 > 1e-12 else 0.0
        t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
        qx, qy = ax + t * dx, ay + t * dy
        d2 = (x - qx) ** 2 + (y - qy) ** 2
        seg = math.sqrt(l2)
        if d2 < best:
            best = d2
            res = (acc + t * seg, qx, qy, dx, dy)
        acc += seg
        ax, ay = bx, by
    off = min(res[0], length)
    brg = math.degrees(math.atan2(res[3], res[4])) % 360.0 if (res[3] or res[4]) else bearing0
    return off, math.sqrt(best), res[1], res[2], brg
