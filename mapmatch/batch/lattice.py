"""The lattice: which points enter it, and the pruned road candidates of each (compiled).

Points closer than the noise to the previous kept point are thinned out (interpolated after
the match); candidates far below their point's best emission, or beyond the outlier
distance, are pruned; a point left with none is not in the lattice.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mapmatch.batch.arrays import CandidateArrays, KernelParams, Lattice, TrackPoints
from mapmatch.model import emission_logp_one


@njit(cache=True, nogil=True)
def thin(xy, valid, min_dist):  # type: ignore[no-untyped-def]
    """Keep valid points at least ``min_dist`` from the previously kept one (always the last)."""
    n = len(valid)
    kept = np.zeros(n, dtype=np.bool_)
    last = -1
    for i in range(n):
        if not valid[i]:
            continue
        if last < 0 or min_dist <= 0.0:
            kept[i] = True
            last = i
            continue
        dx = xy[i, 0] - xy[last, 0]
        dy = xy[i, 1] - xy[last, 1]
        if dx * dx + dy * dy >= min_dist * min_dist:
            kept[i] = True
            last = i
    if last >= 0:
        for i in range(n - 1, -1, -1):
            if valid[i]:
                kept[i] = True
                break
    return kept


@njit(cache=True, nogil=True)
def bearing_at(edges, offs, seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Compass bearing (degrees) of the edge polyline segment at each offset."""
    out = np.empty(len(edges))
    for i in range(len(edges)):
        a0 = seg_ptr[edges[i]]
        a1 = seg_ptr[edges[i] + 1]
        acc = 0.0
        b = 0.0
        for q in range(a0, a1 - 1):
            dx = seg_xy[q + 1, 0] - seg_xy[q, 0]
            dy = seg_xy[q + 1, 1] - seg_xy[q, 1]
            L = math.hypot(dx, dy)
            if L > 0:
                b = math.degrees(math.atan2(dx, dy)) % 360.0
            acc += L
            if acc >= offs[i]:
                break
        out[i] = b
    return out


@njit(cache=True, nogil=True)
def prune(nk, c: CandidateArrays, emis, prune_lp, outlier):  # type: ignore[no-untyped-def]
    """Drop candidates far below their point's best emission or beyond ``outlier`` metres.

    Candidates come sorted by point. Returns the kept ones with their per-point pointer (over
    the points that keep any) and which of the ``nk`` points keep any.
    """
    cpoint = c.point
    nc = len(cpoint)
    best = np.full(nk, -np.inf)
    for i in range(nc):
        if emis[i] > best[cpoint[i]]:
            best[cpoint[i]] = emis[i]
    keep = np.zeros(nc, dtype=np.bool_)
    counts = np.zeros(nk, dtype=np.int64)
    nkeep = 0
    for i in range(nc):
        if emis[i] >= best[cpoint[i]] - prune_lp and c.dist[i] <= outlier:
            keep[i] = True
            counts[cpoint[i]] += 1
            nkeep += 1
    has = counts > 0
    m = 0
    for p in range(nk):
        if has[p]:
            m += 1
    ptr = np.zeros(m + 1, dtype=np.int64)
    q = 0
    for p in range(nk):
        if has[p]:
            ptr[q + 1] = ptr[q] + counts[p]
            q += 1
    oe = np.empty(nkeep, dtype=np.int64)
    oo = np.empty(nkeep)
    ox = np.empty((nkeep, 2))
    od = np.empty(nkeep)
    om = np.empty(nkeep)
    k = 0
    for i in range(nc):
        if keep[i]:
            oe[k] = c.edge[i]
            oo[k] = c.offset[i]
            ox[k, 0] = c.xy[i, 0]
            ox[k, 1] = c.xy[i, 1]
            od[k] = c.dist[i]
            om[k] = emis[i]
            k += 1
    return ptr, oe, oo, ox, od, om, has


@njit(cache=True, nogil=True)
def build_lattice(pt: TrackPoints, c: CandidateArrays, p: KernelParams) -> Lattice:
    """Emissions (distance-only with one σ when ``c.emis`` is empty), pruning, and the lattice
    points' positions, times and odometer readings."""
    emis = c.emis
    if len(emis) != len(c.dist):
        emis = np.empty(len(c.dist))
        for i in range(len(c.dist)):
            emis[i] = emission_logp_one(c.dist[i], p.sigma, 0.0, 0.0, 0.0)
    ptr, ce, co, cx, cd, em, has = prune(len(pt.kidx), c, emis, p.prune, p.outlier)
    pts = pt.kidx[has]
    m = len(pts)
    pxy = np.empty((m, 2))
    ptime = np.empty(m)
    podo = np.full(m, np.nan)
    for i in range(m):
        pxy[i, 0] = pt.xy[pts[i], 0]
        pxy[i, 1] = pt.xy[pts[i], 1]
        ptime[i] = pt.time[pts[i]]
        if len(pt.odo):
            podo[i] = pt.odo[pts[i]]
    return Lattice(ptr, ce, co, cx, cd, em, pts, pxy, ptime, podo)
