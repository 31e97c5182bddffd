"""Spatial index over edge segments: candidate edges near points, vectorised.

One shapely STRtree over the straight segments of every undirected road; a query for many
points at once returns flat parallel arrays of (point, directed edge, distance, offset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from graph.angles import bearing_compiled
from graph.jit import jitable, njit, read_only
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
    lo, hi = int(graph.edge_seg_ptr[edge]), int(graph.edge_seg_ptr[edge + 1])
    off, dist, px, py, _ = project_point(graph.seg_xy[lo:hi].tolist(), 0, hi - lo, x, y, math.inf, 0.0)
    return off, dist, px, py


@jitable
def onto_piece(
    ax: float, ay: float, bx: float, by: float, x: float, y: float
) -> tuple[float, float, float, float]:
    """The point of the piece from ``(ax, ay)`` to ``(bx, by)`` nearest ``(x, y)``: ``(t, qx, qy,
    d2)``, its fraction along the piece, its position and its squared distance (plain Python,
    and compiled into the kernels that call it)."""
    dx, dy = bx - ax, by - ay
    l2 = dx * dx + dy * dy
    t = ((x - ax) * dx + (y - ay) * dy) / l2 if l2 > 1e-12 else 0.0
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    qx, qy = ax + t * dx, ay + t * dy
    return t, qx, qy, (x - qx) ** 2 + (y - qy) ** 2


def project_point(
    seg_xy: Any, lo: int, hi: int, x: float, y: float, length: float, bearing0: float
) -> tuple[float, float, float, float, float]:
    """Project a point onto the polyline ``seg_xy[lo:hi]`` (one edge): the scalar entry.

    ``seg_xy`` is an (n, 2) array or a list of ``[x, y]`` rows (faster from Python);
    :func:`project_point_compiled` is this function compiled, :func:`project_points` the
    vectorised entry. Returns ``(offset, dist, px, py, bearing)``: metres along the polyline
    (at most ``length``), distance, projected position and the bearing of the piece it lies
    on (``bearing0`` on a polyline of zero length). The nearest piece wins; the first of
    equally near ones.
    """
    best = math.inf
    acc = 0.0
    ax, ay = seg_xy[lo][0], seg_xy[lo][1]
    r_off, r_x, r_y, r_dx, r_dy = 0.0, ax, ay, 0.0, 1.0
    for q in range(lo + 1, hi):
        bx, by = seg_xy[q][0], seg_xy[q][1]
        t, qx, qy, d2 = onto_piece(ax, ay, bx, by, x, y)
        dx, dy = bx - ax, by - ay
        seg = math.sqrt(dx * dx + dy * dy)
        if d2 < best:
            best = d2
            r_off, r_x, r_y, r_dx, r_dy = acc + t * seg, qx, qy, dx, dy
        acc += seg
        ax, ay = bx, by
    off = min(r_off, length)
    brg = bearing_compiled(r_dx, r_dy) if (r_dx != 0.0 or r_dy != 0.0) else bearing0
    return off, math.sqrt(best), r_x, r_y, brg


project_point_compiled = njit(cache=True)(project_point)


SKIP_MARGIN = 1e-3
"""Metres by which a piece must lie beyond the nearest piece so far for :func:`project_point_near`
to skip it: far above rounding (about 1e-9 m in projected coordinates), so a skip never changes
an answer."""


@njit(cache=True, nogil=True)
def project_point_near(seg_xy, seg_len, lo, hi, x, y, hint, hint_acc):  # type: ignore[no-untyped-def]
    """:func:`project_point`'s offset, distance and position (length unbounded), the same floats,
    looking closely only at the pieces that can be as near as the nearest piece so far.

    A piece is skipped when its bounding box lies beyond that, and so are the pieces after it
    that the walk along the polyline keeps beyond (``seg_len``: each piece's length, by its first
    vertex, as :func:`mapmatch.batch.lattice.segment_lengths`). ``hint`` (``lo < hint < hi``;
    else none) is the end vertex of a piece to try first, and ``hint_acc`` the offset of its
    start as returned with it: an earlier answer on this edge, such as the last fix's of a stop.
    Returns ``(offset, dist, px, py, piece, piece_acc)``: ``piece`` the end vertex of the piece the
    answer lies on (-1: none) and ``piece_acc`` the offset of its start, a hint for the next call.
    """
    if hi - lo < 2:
        return 0.0, math.inf, seg_xy[lo, 0], seg_xy[lo, 1], -1, 0.0
    q = hint if lo < hint < hi else lo + 1
    d2 = onto_piece(seg_xy[q - 1, 0], seg_xy[q - 1, 1], seg_xy[q, 0], seg_xy[q, 1], x, y)[3]
    lim = (math.sqrt(d2) + SKIP_MARGIN) ** 2
    # project_point's loop over the pieces that can be within ``lim`` (the others would neither
    # win nor tie), in its order: the first of equally near pieces wins
    best = math.inf
    qb = -1
    r_t, r_x, r_y = 0.0, seg_xy[lo, 0], seg_xy[lo, 1]
    q = lo + 1
    while q < hi:
        ax, ay = seg_xy[q - 1, 0], seg_xy[q - 1, 1]
        bx, by = seg_xy[q, 0], seg_xy[q, 1]
        gx = max(min(ax, bx) - x, x - max(ax, bx), 0.0)
        gy = max(min(ay, by) - y, y - max(ay, by), 0.0)
        if gx * gx + gy * gy <= lim:
            t, qx, qy, d2 = onto_piece(ax, ay, bx, by, x, y)
            if d2 < best:
                best = d2
                qb, r_t, r_x, r_y = q, t, qx, qy
                lim = min(lim, (math.sqrt(d2) + SKIP_MARGIN) ** 2)
            q += 1
            continue
        # a far piece: the pieces after it stay at least this far less the way walked
        reach = math.sqrt((x - ax) ** 2 + (y - ay) ** 2) - math.sqrt(lim) - SKIP_MARGIN
        walked = seg_len[q - 1]
        q += 1
        while q < hi and walked + seg_len[q - 1] < reach:
            walked += seg_len[q - 1]
            q += 1
    if qb < 0:
        return 0.0, math.sqrt(best), r_x, r_y, -1, 0.0
    # the offset summed piece by piece in project_point's order (from the hint's, where it is
    # on the way: the same sums)
    q, acc = lo + 1, 0.0
    if lo < hint <= qb:
        q, acc = hint, hint_acc
    while True:
        ax, ay = seg_xy[q - 1, 0], seg_xy[q - 1, 1]
        dx, dy = seg_xy[q, 0] - ax, seg_xy[q, 1] - ay
        seg = math.sqrt(dx * dx + dy * dy)
        if q == qb:
            return acc + r_t * seg, math.sqrt(best), r_x, r_y, qb, acc
        acc += seg
        q += 1


@njit(cache=True)
def _project_many(seg_xy, seg_ptr, edge_len, bearing0, edges, xy):  # type: ignore[no-untyped-def]
    n = len(edges)
    out = np.empty((n, 5))
    for i in range(n):
        e = edges[i]
        r = project_point_compiled(
            seg_xy, seg_ptr[e], seg_ptr[e + 1], xy[i, 0], xy[i, 1], edge_len[e], bearing0[e]
        )
        for k in range(5):
            out[i, k] = r[k]
    return out


def project_points(graph: RoadGraph, edges: ArrayLike, xy: ArrayLike) -> NDArray[np.float64]:
    """The vectorised entry: point ``xy[i]`` projected onto edge ``edges[i]``, as rows
    ``(offset, dist, px, py, bearing)`` of an (n, 5) array."""
    e = np.asarray(edges, dtype=np.int64)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(e) != len(p):
        raise ValueError("one edge per point")
    f8 = np.float64
    return _project_many(  # type: ignore[no-any-return]
        read_only(graph.seg_xy, f8), read_only(graph.edge_seg_ptr, np.int64), read_only(graph.edge_len, f8),
        read_only(graph.edge_bearing_start, f8), e, p,
    )  # fmt: skip
