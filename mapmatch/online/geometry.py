"""Compiled path geometry for the online hot path: one map's polylines as arrays, and the
projection, the point at an offset and the bearing along a path of edges on them."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.angles import angle_diff_compiled, bearing_compiled
from graph.index import project_point_compiled
from graph.jit import njit

angle_diff_c = angle_diff_compiled


class RoadArrays(NamedTuple):
    """One map's edges for the compiled kernels."""

    seg: NDArray[np.float64]  # (n, 2) polyline vertices of every edge, in order
    ptr: NDArray[np.int64]  # edge e's vertices are seg[ptr[e]:ptr[e + 1]]
    elen: NDArray[np.float64]  # edge length (m)
    bstart: NDArray[np.float64]  # bearing at the edge's start (degrees clockwise from north)
    bend: NDArray[np.float64]  # bearing at its end
    vcum: NDArray[np.float64]  # every vertex's distance along its edge


@njit(cache=True)
def project(road: RoadArrays, e: int, x: float, y: float) -> tuple[float, float, float, float, float]:
    """``(offset, dist, px, py, bearing)`` of the point's projection onto edge ``e``."""
    return project_point_compiled(  # type: ignore[no-any-return]
        road.seg, road.ptr[e], road.ptr[e + 1], x, y, road.elen[e], road.bstart[e]
    )


@njit(cache=True)
def project_between(  # type: ignore[no-untyped-def]
    road: RoadArrays, e: int, x: float, y: float, lo: float, hi: float
):
    """``(found, offset, dist, px, py, bearing)``: the point's nearest point on edge ``e``
    between ``lo`` and ``hi`` metres along it, found when it is a foot of its own inside that
    stretch (not the stretch's end)."""
    lo, hi = max(lo, 0.0), min(hi, road.elen[e])
    a, b = road.ptr[e], road.ptr[e + 1]
    if hi <= lo:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    q0 = max(a + np.searchsorted(road.vcum[a:b], lo, side="right") - 1, a)
    q1 = min(a + np.searchsorted(road.vcum[a:b], hi, side="left") + 1, b)
    if q1 - q0 < 2:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    off, dist, px, py, brg = project_point_compiled(road.seg, q0, q1, x, y, math.inf, road.bstart[e])
    off += road.vcum[q0]
    return lo < off < hi, off, dist, px, py, brg


@njit(cache=True)
def locate_on(seg_xy, lo, hi, off, bearing_end):  # type: ignore[no-untyped-def]
    """``(x, y, bearing)`` at ``off`` metres along the polyline ``seg_xy[lo:hi]``."""
    acc = 0.0
    ax, ay = seg_xy[lo, 0], seg_xy[lo, 1]
    for q in range(lo + 1, hi):
        bx, by = seg_xy[q, 0], seg_xy[q, 1]
        dx, dy = bx - ax, by - ay
        seg = math.hypot(dx, dy)
        if acc + seg >= off and seg > 0.0:
            t = (off - acc) / seg
            return ax + t * dx, ay + t * dy, bearing_compiled(dx, dy)
        acc += seg
        ax, ay = bx, by
    return ax, ay, bearing_end


@njit(cache=True)
def locate(road: RoadArrays, e: int, off: float) -> tuple[float, float, float]:
    """``(x, y, bearing)`` at ``off`` metres along edge ``e``."""
    return locate_on(road.seg, road.ptr[e], road.ptr[e + 1], off, road.bend[e])  # type: ignore[no-any-return]


@njit(cache=True)
def locate_all(road: RoadArrays, edges: NDArray[np.int64], offs: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`locate` of every ``(edges[i], offs[i])``: rows of ``(x, y, bearing)``."""
    out = np.empty((len(edges), 3))
    for i in range(len(edges)):
        out[i, 0], out[i, 1], out[i, 2] = locate(road, edges[i], offs[i])
    return out


@njit(cache=True)
def bearing_on_path(road: RoadArrays, edges: NDArray[np.int64], s: float) -> float:
    """The road's bearing ``s`` metres along the path ``edges``."""
    if s <= 0.0:
        return road.bstart[edges[0]]  # type: ignore[no-any-return]
    acc = 0.0
    for e in edges:
        if s <= acc + road.elen[e]:
            return locate(road, e, s - acc)[2]  # type: ignore[no-any-return]
        acc += road.elen[e]
    return road.bend[edges[-1]]  # type: ignore[no-any-return]


@njit(cache=True)
def straight(road: RoadArrays, e: int, e2: int, straight_max_deg: float) -> bool:
    """Whether ``e2`` continues ``e`` straight on at their shared node."""
    return abs(angle_diff_c(road.bstart[e2], road.bend[e])) <= straight_max_deg  # type: ignore[no-any-return]


@njit(cache=True)
def hypot(x: float, y: float) -> float:
    """``math.hypot(x, y)`` as CPython computes it (compensated, to the last bit; the C
    library's ``hypot`` that a compiled ``math.hypot`` calls may differ in it)."""
    ax, ay = abs(x), abs(y)
    if math.isinf(ax) or math.isinf(ay):
        return math.inf
    if math.isnan(ax) or math.isnan(ay):
        return math.nan
    top = max(ax, ay)
    if top == 0.0:
        return top
    _, e = math.frexp(top)
    if e < -1023:  # subnormal: not worth the exact path
        return math.sqrt(ax * ax + ay * ay)
    scale = math.ldexp(1.0, -e)
    csum, frac1, frac2 = 1.0, 0.0, 0.0
    for v in (ax, ay):
        v *= scale
        hi, lo = _mul12(v, v)
        s = csum + hi
        frac2 += (csum - s) + hi
        csum = s
        frac1 += lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2))
    hi, lo = _mul12(-h, h)
    s = csum + hi
    frac2 += (csum - s) + hi
    csum = s
    frac1 += lo
    v = csum - 1.0 + (frac1 + frac2)
    h += v / (2.0 * h)
    return h / scale  # type: ignore[no-any-return]


@njit(cache=True)
def _mul12(x: float, y: float) -> tuple[float, float]:
    """``x · y`` as ``hi + lo`` exactly (Dekker)."""
    c = 134217729.0  # 2^27 + 1
    cx = c * x
    hx = cx - (cx - x)
    tx = x - hx
    cy = c * y
    hy = cy - (cy - y)
    ty = y - hy
    hi = x * y
    lo = (((hx * hy - hi) + hx * ty) + tx * hy) + tx * ty
    return hi, lo
