"""A compiled uniform-grid twin of :meth:`graph.index.EdgeIndex.query` for batch candidate search.

Same segments, same answer (tests check it against ``EdgeIndex.query``), several times faster
on many points: the segments are bucketed in square cells kept as a sorted cell-id array,
and a point looks only at the cells within its radius. Built once per matcher; the grid is
read-only and each thread has its own scratch arrays.
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.index import Candidates, EdgeIndex
from graph.jit import njit, read_only
from mapmatch.arena import UNCOUNTED, Arena, int64, take_f8, take_i8, take_xy

DENSE_MAX_CELLS = 1 << 23
"""Up to this many cells the grid keeps a dense cell table (8 bytes a cell)."""
CELL_MARGIN = 1e-6
"""Metres by which a cell's box is widened when testing whether a segment crosses it (a wider
box lists a segment in more cells: a little more time, never another answer)."""


class Grid(NamedTuple):
    """The grid's read-only arrays as the compiled query reads them (segments bucketed by cell)."""

    origin: NDArray[np.float64]
    cell: float
    nx: int
    ny: int
    cell_ptr: NDArray[np.int64]
    """Dense cell table (empty: binary search in ``cell_ids``)."""
    cell_ids: NDArray[np.int64]
    cell_seg: NDArray[np.int64]
    seg_a: NDArray[np.float64]
    seg_b: NDArray[np.float64]
    seg_len: NDArray[np.float64]
    seg_off: NDArray[np.float64]
    seg_edge: NDArray[np.int64]
    edge_rev: NDArray[np.int64]
    edge_len: NDArray[np.float64]


class GridScratch(NamedTuple):
    """One thread's marks; per-point marks (``stamp[0]`` counts them) never repeat, so they
    are never cleared."""

    stamp_seg: NDArray[np.int64]
    stamp_edge: NDArray[np.int64]
    best: NDArray[np.int64]
    stamp: NDArray[np.int64]

    @classmethod
    def new(cls, n_segments: int, n_edges: int) -> GridScratch:
        """Clean marks for a grid of ``n_segments`` segments over ``n_edges`` edges."""
        return cls(
            np.full(n_segments, -1, dtype=np.int64),
            np.full(n_edges, -1, dtype=np.int64),
            np.zeros(n_edges, dtype=np.int64),
            np.zeros(1, dtype=np.int64),
        )


class GridQuery(NamedTuple):
    """A query as :func:`_scan_into` reads it: the points, the radius, how many roads (< 0: all)."""

    pts: NDArray[np.float64]
    radius: float
    k: int
    r2: float
    """The squared-distance pre-check: beyond it, the distance exceeds ``radius`` too (its
    margin far above rounding)."""
    cells: int
    """How many cells around a point's own cell the radius reaches."""


class ScanRows(NamedTuple):
    """The answer rows :func:`query_grid` writes (as :class:`~graph.index.Candidates`)."""

    point: NDArray[np.int64]
    edge: NDArray[np.int64]
    dist: NDArray[np.float64]
    offset: NDArray[np.float64]
    xy: NDArray[np.float64]


class NearRoads(NamedTuple):
    """One point's roads while its cells are scanned (room for ``len(edge)``)."""

    edge: NDArray[np.int64]
    feat: NDArray[np.float64]
    """Per road: distance, offset, x, y of its nearest point."""
    order: NDArray[np.int64]
    """The roads nearest first (filled once the scan is done)."""


class RoadHit(NamedTuple):
    """A segment within a point's radius: its edge, the distance and offset of its point
    nearest the fix, and that point."""

    edge: int
    dist: float
    off: float
    x: float
    y: float


class GridIndex:
    """Candidate search over an :class:`EdgeIndex`'s segments with a uniform grid.

    Parameters
    ----------
    index
        The edge index whose segments (and result conventions) to use.
    cell
        Cell size in metres; about the usual search radius.
    """

    def __init__(self, index: EdgeIndex, *, cell: float = 50.0) -> None:
        self.index = index
        self.graph = index.graph
        self.cell = float(cell)
        a, b = index.seg_a, index.seg_b
        if len(a):
            self.origin = np.minimum(a.min(axis=0), b.min(axis=0)) - 1.0
            hi = np.maximum(a.max(axis=0), b.max(axis=0)) + 1.0
        else:
            self.origin = np.zeros(2)
            hi = np.ones(2)
        self.ny = math.ceil((hi[1] - self.origin[1]) / self.cell) + 1
        self.nx = math.ceil((hi[0] - self.origin[0]) / self.cell) + 1
        self.cell_ids, self.cell_seg = _bucket(a, b, self.origin, self.cell, self.ny)
        # a dense cell table when it is small enough, else a binary search in cell_ids
        ncell = self.nx * self.ny
        if ncell <= DENSE_MAX_CELLS:
            self.cell_ptr = np.zeros(ncell + 1, dtype=np.int64)
            np.cumsum(np.bincount(self.cell_ids, minlength=ncell), out=self.cell_ptr[1:])
        else:
            self.cell_ptr = np.zeros(0, dtype=np.int64)
        i8, f8 = np.int64, np.float64
        self.arrays = Grid(
            origin=read_only(self.origin, f8),
            cell=self.cell,
            nx=int(self.nx),
            ny=int(self.ny),
            cell_ptr=read_only(self.cell_ptr, i8),
            cell_ids=read_only(self.cell_ids, i8),
            cell_seg=read_only(self.cell_seg, i8),
            seg_a=read_only(a, f8),
            seg_b=read_only(b, f8),
            seg_len=read_only(index.seg_len, f8),
            seg_off=read_only(index.seg_off, f8),
            seg_edge=read_only(index.seg_edge, i8),
            edge_rev=read_only(self.graph.edge_reverse, i8),
            edge_len=read_only(self.graph.edge_len, f8),
        )
        """The compiled query's arrays (:class:`Grid`)."""
        self._local = threading.local()

    def scratch(self) -> GridScratch:
        """This thread's marks (the grid itself is read-only and shared)."""
        sc: GridScratch | None = getattr(self._local, "scratch", None)
        if sc is None:
            sc = self._local.scratch = GridScratch.new(len(self.index.seg_a), self.graph.n_edges)
        return sc

    def query(self, xy: ArrayLike, radius: float, *, k: int | None = None) -> Candidates:
        """As :meth:`EdgeIndex.query` (scalar radius): directed edges within ``radius`` of each point."""
        pts = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        p, e, d, o, q = query_grid(
            pts, float(radius), -1 if k is None else int(k), self.arrays, self.scratch(), Arena.new()
        )
        return Candidates(point=p, edge=e, dist=d, offset=o, xy=q)


@njit(cache=True, nogil=True)
def _bucket(a, b, origin, cell, ny):  # type: ignore[no-untyped-def]
    """Cell ids (sorted) and the segment in each, for every cell a segment crosses.

    A segment is listed only in the cells its line passes through (not every cell of its box:
    a diagonal segment's box holds about twice as many). That is enough: the point of a segment
    nearest a fix lies in one of them, and that cell is no further from the fix than the
    segment, so the query looks in it. Each cell's box is widened by ``CELL_MARGIN`` for the
    crossing test, so a rounding at a cell's edge can only add an entry, never drop one.
    """
    n = len(a)
    cnt = 0
    for i in range(n):
        x0, x1, y0, y1 = _box_cells(a[i], b[i], origin, cell)
        cnt += (x1 - x0 + 1) * (y1 - y0 + 1)
    ids = np.empty(cnt, dtype=np.int64)
    seg = np.empty(cnt, dtype=np.int64)
    c = 0
    for i in range(n):
        ax, ay, bx, by = a[i, 0], a[i, 1], b[i, 0], b[i, 1]
        x0, x1, y0, y1 = _box_cells(a[i], b[i], origin, cell)
        for cx in range(x0, x1 + 1):
            for cy in range(y0, y1 + 1):
                lx = origin[0] + cx * cell - CELL_MARGIN
                ly = origin[1] + cy * cell - CELL_MARGIN
                side = cell + 2.0 * CELL_MARGIN
                if x0 == x1 or y0 == y1 or _crosses(ax, ay, bx, by, lx, ly, lx + side, ly + side):
                    ids[c] = cx * ny + cy
                    seg[c] = i
                    c += 1
    order = np.argsort(ids[:c], kind="mergesort")
    return ids[:c][order], seg[:c][order]


@njit(cache=True, nogil=True, inline="always")
def _box_cells(a, b, origin, cell):  # type: ignore[no-untyped-def]
    """The first and last cell column and row of the box of segment ``a``-``b``."""
    x0 = int((min(a[0], b[0]) - origin[0]) // cell)
    x1 = int((max(a[0], b[0]) - origin[0]) // cell)
    y0 = int((min(a[1], b[1]) - origin[1]) // cell)
    y1 = int((max(a[1], b[1]) - origin[1]) // cell)
    return x0, x1, y0, y1


@njit(cache=True, nogil=True, inline="always")
def _crosses(ax, ay, bx, by, x0, y0, x1, y1):  # type: ignore[no-untyped-def]
    """Whether segment ``a``-``b`` meets the closed box ``[x0, x1] x [y0, y1]`` (Liang-Barsky clip)."""
    dx, dy = bx - ax, by - ay
    t0, t1 = 0.0, 1.0
    for p, q in ((-dx, ax - x0), (dx, x1 - ax), (-dy, ay - y0), (dy, y1 - ay)):
        if p == 0.0:
            if q < 0.0:
                return False
        else:
            r = q / p
            if p < 0.0:
                if r > t1:
                    return False
                t0 = max(t0, r)
            else:
                if r < t0:
                    return False
                t1 = min(t1, r)
    return True


@njit(cache=True, nogil=True)
def query_grid(pts, radius, k, grid, sc, ar):  # type: ignore[no-untyped-def]
    """Directed edges within ``radius`` of each point of ``pts`` (non-finite points have none),
    nearest ``k`` roads (``k < 0``: all) with their reverse twins, sorted by point then (distance,
    edge): ``(point, edge, dist, offset, xy)`` as :class:`~graph.index.Candidates`.
    Working arrays and the answer come from the arena ``ar`` (:mod:`mapmatch.arena`)."""
    n = len(pts)
    q = GridQuery(pts, radius, k, radius * radius * (1.0 + 1e-9), math.ceil(radius / grid.cell))
    cap = 16 * n + 16
    rows = ScanRows(take_i8(ar, cap), take_i8(ar, cap), take_f8(ar, cap), take_f8(ar, cap), take_xy(ar, cap))
    room = 64  # roads near one point
    near = NearRoads(take_i8(ar, room), take_f8(ar, 4 * room), take_i8(ar, room))
    m = int64(0)  # not 0: one compile of ``_scan_into`` (``mapmatch.arena.int64``)
    p = int64(0)
    while p < n:
        # the scan stops at the first point that does not fit; grow, and go on from there
        m, p, more_loc = _scan_into(q, p, m, grid, sc, near, rows)
        if p >= n:
            break
        if more_loc:
            room *= 2
            near = NearRoads(
                np.empty(room, dtype=np.int64), np.empty(4 * room), np.empty(room, dtype=np.int64)
            )
        else:
            cap *= 2
            oq = np.empty((cap, 2))
            oq[:m] = rows.xy[:m]
            rows = ScanRows(
                grow_array(rows.point, cap), grow_array(rows.edge, cap), grow_array(rows.dist, cap),
                grow_array(rows.offset, cap), oq,
            )  # fmt: skip
    return rows.point[:m], rows.edge[:m], rows.dist[:m], rows.offset[:m], rows.xy[:m]


@njit(**UNCOUNTED)
def _scan_into(q, p0, m, grid, sc, near, rows):  # type: ignore[no-untyped-def]
    """:func:`query_grid`'s answer rows for the points of ``q`` (:class:`GridQuery`) from ``p0``
    on, written into ``rows`` (:class:`ScanRows`) from row ``m``, until a point does not fit:
    ``(rows, next point, whether the per-point scratch near was too small)``. Allocates
    nothing (:data:`~mapmatch.arena.UNCOUNTED`)."""
    n = len(q.pts)
    for p in range(p0, n):
        px, py = q.pts[p, 0], q.pts[p, 1]
        if not (math.isfinite(px) and math.isfinite(py)):
            continue
        nl = _roads_near(px, py, q, grid, sc, near)
        if nl < 0:
            return m, p, True
        if nl == 0:
            continue
        end = _point_rows(p, nl, q.k, grid, near, rows, m)
        if end < 0:
            return m, p, False
        m = end
    return m, n, False


@njit(cache=True, nogil=True, inline="always")
def _roads_near(px, py, q, grid, sc, near):  # type: ignore[no-untyped-def]
    """The roads within the radius of the query ``q`` (:class:`GridQuery`) of ``(px, py)``
    into ``near`` (:class:`NearRoads`), each edge once at its nearest segment
    (:func:`_offer_road`): how many, or -1 when ``near`` has no room for them. Looks only at
    the grid cells within the radius, each segment once (a fresh mark, ``sc.stamp``, per
    call)."""
    origin, cell, ny = grid.origin, grid.cell, grid.ny
    cell_ptr, cell_seg, seg_a, seg_b, seg_len = (
        grid.cell_ptr,
        grid.cell_seg,
        grid.seg_a,
        grid.seg_b,
        grid.seg_len,
    )
    stamp_seg = sc.stamp_seg
    radius, r2, r = q.radius, q.r2, q.cells
    stamp = sc.stamp[0]
    sc.stamp[0] = stamp + 1  # a fresh mark for every attempt at a point
    cx0 = int((px - origin[0]) // cell)
    cy0 = int((py - origin[1]) // cell)
    nl = 0
    for cx in range(cx0 - r, cx0 + r + 1):
        # the point's distance to the cell's column, then to the cell (beyond: skipped)
        gx = max(origin[0] + cx * cell - px, px - (origin[0] + (cx + 1) * cell), 0.0)
        for cy in range(cy0 - r, cy0 + r + 1):
            if cx < 0 or cy < 0 or cx >= grid.nx or cy >= ny:
                continue
            gy = max(origin[1] + cy * cell - py, py - (origin[1] + (cy + 1) * cell), 0.0)
            if gx * gx + gy * gy > r2:
                continue
            cid = cx * ny + cy
            if len(cell_ptr):
                lo = cell_ptr[cid]
                end = cell_ptr[cid + 1]
            else:
                lo = np.searchsorted(grid.cell_ids, cid)
                end = np.searchsorted(grid.cell_ids, cid, side="right")
            while lo < end:
                s = cell_seg[lo]
                lo += 1
                if stamp_seg[s] == stamp:
                    continue
                stamp_seg[s] = stamp
                ax, ay = seg_a[s, 0], seg_a[s, 1]
                dx, dy = seg_b[s, 0] - ax, seg_b[s, 1] - ay
                L = seg_len[s]
                t = 0.0
                if L > 0:
                    t = ((px - ax) * dx + (py - ay) * dy) / max(L * L, 1e-12)
                    t = min(max(t, 0.0), 1.0)
                qx, qy = ax + dx * t, ay + dy * t
                ex, ey = px - qx, py - qy
                if ex * ex + ey * ey > r2:
                    continue
                d = math.sqrt(ex * ex + ey * ey)
                if d > radius:
                    continue
                hit = RoadHit(grid.seg_edge[s], d, grid.seg_off[s] + t * L, qx, qy)
                nl = _offer_road(sc, near, stamp, nl, hit)
                if nl < 0:
                    return nl
    return nl


@njit(cache=True, nogil=True, inline="always")
def _offer_road(sc, near, stamp, nl, hit):  # type: ignore[no-untyped-def]
    """A segment's ``hit`` (:class:`RoadHit`) among the point's ``nl`` roads in ``near``: a new
    road joins them, a road already there moves nearer when the hit is nearer. The new count,
    or -1 when ``near`` has no room."""
    e = hit.edge
    if sc.stamp_edge[e] == stamp:
        j = sc.best[e]
        if hit.dist < near.feat[4 * j]:
            _set_road(near.feat, j, hit)
        return nl
    sc.stamp_edge[e] = stamp
    if nl == len(near.edge):
        return -1
    sc.best[e] = nl
    near.edge[nl] = e
    _set_road(near.feat, nl, hit)
    return nl + 1


@njit(cache=True, nogil=True, inline="always")
def _set_road(feat, j, hit):  # type: ignore[no-untyped-def]
    """Road ``j``'s distance, offset and nearest point in ``feat`` (four values a road)."""
    feat[4 * j] = hit.dist
    feat[4 * j + 1] = hit.off
    feat[4 * j + 2] = hit.x
    feat[4 * j + 3] = hit.y


@njit(cache=True, nogil=True, inline="always")
def _point_rows(p, nl, k, grid, near, rows, m):  # type: ignore[no-untyped-def]
    """Point ``p``'s answer rows from its ``nl`` roads in ``near``: the nearest ``k`` (ties by
    edge; ``k < 0``: all) with their reverse twins, ordered by (distance, edge), written into
    ``rows`` from row ``m``. The row after them, or -1 when they do not fit."""
    edge_len, edge_rev = grid.edge_len, grid.edge_rev
    loc_e, loc_f, sel = near.edge, near.feat, near.order
    for a in range(nl):  # nearest first, ties by edge
        da, ea = loc_f[4 * a], loc_e[a]
        b = a - 1
        while b >= 0 and (loc_f[4 * sel[b]] > da or (loc_f[4 * sel[b]] == da and loc_e[sel[b]] > ea)):
            sel[b + 1] = sel[b]
            b -= 1
        sel[b + 1] = a
    kk = nl if k < 0 else min(k, nl)
    if m + 2 * kk > len(rows.point):
        return -1
    start = m
    for a in range(kk):
        j = sel[a]
        e = loc_e[j]
        dj, oj, xj, yj = loc_f[4 * j], loc_f[4 * j + 1], loc_f[4 * j + 2], loc_f[4 * j + 3]
        _set_row(rows, m, p, e, dj, min(max(oj, 0.0), edge_len[e]), xj, yj)
        m += 1
        rv = edge_rev[e]
        if rv >= 0:
            _set_row(rows, m, p, rv, dj, min(max(edge_len[rv] - oj, 0.0), edge_len[rv]), xj, yj)
            m += 1
    _order_rows(rows, start, m)
    return m


@njit(cache=True, nogil=True, inline="always")
def _set_row(rows, m, p, e, d, off, x, y):  # type: ignore[no-untyped-def]
    """Row ``m`` of ``rows``: point ``p`` on edge ``e``, ``d`` from it at offset ``off``, ``(x, y)``."""
    rows.point[m] = p
    rows.edge[m] = e
    rows.dist[m] = d
    rows.offset[m] = off
    rows.xy[m, 0] = x
    rows.xy[m, 1] = y


@njit(cache=True, nogil=True, inline="always")
def _order_rows(rows, start, m):  # type: ignore[no-untyped-def]
    """Rows ``start .. m - 1`` (one point's) ordered by (distance, edge), an insertion sort."""
    od, oe, oo, oq = rows.dist, rows.edge, rows.offset, rows.xy
    for a in range(start + 1, m):
        d0, e0 = od[a], oe[a]
        o0, x0, y0 = oo[a], oq[a, 0], oq[a, 1]
        b = a - 1
        while b >= start and (od[b] > d0 or (od[b] == d0 and oe[b] > e0)):
            od[b + 1], oe[b + 1], oo[b + 1] = od[b], oe[b], oo[b]
            oq[b + 1, 0], oq[b + 1, 1] = oq[b, 0], oq[b, 1]
            b -= 1
        od[b + 1], oe[b + 1], oo[b + 1] = d0, e0, o0
        oq[b + 1, 0], oq[b + 1, 1] = x0, y0


@njit(cache=True, nogil=True)
def grow_array(a, cap):  # type: ignore[no-untyped-def]
    """A copy of ``a`` with room for ``cap`` items (compiled once per dtype)."""
    b = np.empty(cap, dtype=a.dtype)
    b[: len(a)] = a
    return b
