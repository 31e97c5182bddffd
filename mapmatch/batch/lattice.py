"""The lattice: which points enter it, and the pruned road candidates of each (compiled).

Points closer than the noise to the previous kept point are thinned out (interpolated after
the match); candidates far below their point's best emission, or beyond the outlier
distance, are pruned; a point left with none is not in the lattice.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from graph.angles import bearing_compiled
from graph.jit import njit
from mapmatch.arena import full_b1, full_f8, full_i8, take_b1, take_f8, take_i8, take_xy
from mapmatch.batch.arrays import CandidateArrays, KernelParams, Lattice, TrackPoints
from mapmatch.model import emission_logp_one


@njit(cache=True, nogil=True)
def thin_into(xy, valid, min_dist, kept):  # type: ignore[no-untyped-def]
    """Keep valid points at least ``min_dist`` from the previously kept one (always the last):
    flags into ``kept`` (all False on entry)."""
    n = len(valid)
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
def along_lengths(seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Per polyline segment (indexed by its first vertex), the distance along its edge to the
    segment's end, summed in order from the edge's start (the last vertex of an edge gets 0)."""
    out = np.zeros(len(seg_xy))
    for e in range(len(seg_ptr) - 1):
        acc = 0.0
        for q in range(seg_ptr[e], seg_ptr[e + 1] - 1):
            acc += math.hypot(seg_xy[q + 1, 0] - seg_xy[q, 0], seg_xy[q + 1, 1] - seg_xy[q, 1])
            out[q] = acc
    return out


@njit(cache=True, nogil=True)
def segment_lengths(seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Per polyline segment (indexed by its first vertex), its length in the float steps of
    :func:`mapmatch.batch.route.pieces_xy` (the last vertex of an edge gets 0)."""
    out = np.zeros(len(seg_xy))
    for e in range(len(seg_ptr) - 1):
        for q in range(seg_ptr[e], seg_ptr[e + 1] - 1):
            out[q] = math.hypot(seg_xy[q + 1, 0] - seg_xy[q, 0], seg_xy[q + 1, 1] - seg_xy[q, 1])
    return out


@njit(cache=True, nogil=True, inline="always")
def segment_at(seg_ptr, seg_end, e, off):  # type: ignore[no-untyped-def]
    """The segment (index of its first vertex) of edge ``e`` at offset ``off``: the first one
    ending at or beyond it, the last one when beyond the edge; -1 for an edge of one vertex.
    A binary search on ``seg_end`` (:func:`along_lengths`)."""
    lo = seg_ptr[e]
    hi = seg_ptr[e + 1] - 2
    if hi < lo:
        return -1
    while lo < hi:
        mid = (lo + hi) >> 1
        if seg_end[mid] >= off:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def segment_bearings(seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Per polyline segment (indexed by its first vertex), its compass bearing in degrees: its
    own, else that of the nearest non-degenerate segment before it on its edge (0 if none);
    computed once per map."""
    out = np.zeros(len(seg_xy))
    for e in range(len(seg_ptr) - 1):
        b = 0.0
        for q in range(seg_ptr[e], seg_ptr[e + 1] - 1):
            dx = seg_xy[q + 1, 0] - seg_xy[q, 0]
            dy = seg_xy[q + 1, 1] - seg_xy[q, 1]
            if math.hypot(dx, dy) > 0:
                b = bearing_compiled(dx, dy)
            out[q] = b
    return out


@njit(cache=True, nogil=True)
def bearing_on(edges, offs, seg_ptr, seg_end, seg_bearing, out):  # type: ignore[no-untyped-def]
    """Compass bearing (degrees) of the edge polyline segment at each offset, into ``out``: the
    first segment ending at or beyond it (the last one when beyond the edge), found by a binary
    search over ``seg_end`` (:func:`along_lengths`), with the bearings of
    :func:`segment_bearings` (a look-up instead of an arctangent per candidate); 0 where the
    edge has no segment."""
    for i in range(len(edges)):
        lo = segment_at(seg_ptr, seg_end, edges[i], offs[i])
        out[i] = 0.0 if lo < 0 else seg_bearing[lo]
    return out


class PruneRule(NamedTuple):
    """How :func:`prune` drops candidates (from :class:`~mapmatch.batch.arrays.KernelParams`)."""

    prune_lp: float
    """Log-probability below the point's best emission beyond which a candidate goes."""
    outlier: float
    """Metres beyond which a candidate goes."""
    sigma: float
    """The σ of candidates without one of their own."""
    off_map_sigmas: float
    """Candidates beyond this many times their σ go (0: no σ limit)."""


@njit(cache=True, nogil=True)
def prune(nk, c: CandidateArrays, emis, rule: PruneRule, ar):  # type: ignore[no-untyped-def]
    """Drop candidates far below their point's best emission, beyond ``outlier`` metres or
    beyond ``off_map_sigmas`` times their σ (``c.sigma``, else ``sigma``), by the ``rule``
    (:class:`PruneRule`).

    Candidates come sorted by point. Returns the kept ones with their per-point pointer (over
    the points that keep any) and which of the ``nk`` points keep any.
    """
    cpoint = c.point
    nc = len(cpoint)
    keep, counts = _within_reach(nk, c, emis, rule, ar)
    nkeep = 0
    for i in range(nc):
        if keep[i]:
            nkeep += 1
    has = take_b1(ar, nk)
    m = 0
    for p in range(nk):
        has[p] = counts[p] > 0
        if has[p]:
            m += 1
    ptr = full_i8(ar, m + 1, 0)
    q = 0
    for p in range(nk):
        if has[p]:
            ptr[q + 1] = ptr[q] + counts[p]
            q += 1
    oe = take_i8(ar, nkeep)
    oo = take_f8(ar, nkeep)
    ox = take_xy(ar, nkeep)
    od = take_f8(ar, nkeep)
    om = take_f8(ar, nkeep)
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
def _within_reach(nk, c, emis, rule, ar):  # type: ignore[no-untyped-def]
    """Which candidates are within ``rule.prune_lp`` of their point's best emission and within
    the outlier distance and σ limit: the flags and the count per point."""
    cpoint = c.point
    nc = len(cpoint)
    best = full_f8(ar, nk, -np.inf)
    for i in range(nc):
        if emis[i] > best[cpoint[i]]:
            best[cpoint[i]] = emis[i]
    keep = full_b1(ar, nc, False)
    counts = full_i8(ar, nk, 0)
    for i in range(nc):
        lim = rule.outlier
        if rule.off_map_sigmas > 0:
            s = c.sigma[i] if len(c.sigma) == len(cpoint) else rule.sigma
            lim = min(lim, rule.off_map_sigmas * s)
        if emis[i] >= best[cpoint[i]] - rule.prune_lp and c.dist[i] <= lim:
            keep[i] = True
            counts[cpoint[i]] += 1
    return keep, counts


@njit(cache=True, nogil=True)
def build_lattice(pt: TrackPoints, c: CandidateArrays, p: KernelParams, ar) -> Lattice:  # type: ignore[no-untyped-def]
    """Emissions (distance-only with one σ when ``c.emis`` is empty), pruning, and the lattice
    points' positions, times and odometer readings."""
    emis = c.emis
    if len(emis) != len(c.dist):
        emis = take_f8(ar, len(c.dist))
        for i in range(len(c.dist)):
            emis[i] = emission_logp_one(c.dist[i], p.sigma, 0.0, 0.0, 0.0)
    rule = PruneRule(p.prune, p.outlier, p.sigma, p.off_map_sigmas)
    ptr, ce, co, cx, cd, em, has = prune(len(pt.kidx), c, emis, rule, ar)
    m = len(ptr) - 1
    pts = take_i8(ar, m)
    q = 0
    for i in range(len(has)):
        if has[i]:
            pts[q] = pt.kidx[i]
            q += 1
    pxy = take_xy(ar, m)
    ptime = take_f8(ar, m)
    podo = full_f8(ar, m, np.nan)
    for i in range(m):
        pxy[i, 0] = pt.xy[pts[i], 0]
        pxy[i, 1] = pt.xy[pts[i], 1]
        ptime[i] = pt.time[pts[i]]
        if len(pt.odo):
            podo[i] = pt.odo[pts[i]]
    run = left_out_runs(pt, has, ar)
    return Lattice(ptr, ce, co, cx, cd, em, pts, pxy, ptime, podo, run)


@njit(cache=True, nogil=True)
def lattice_sigma(pt: TrackPoints, c: CandidateArrays, sigma, lat: Lattice, ar):  # type: ignore[no-untyped-def]
    """Each lattice point's σ: its candidates' (``c.sigma``), else ``sigma``."""
    m = len(lat.pts)
    out = full_f8(ar, m, sigma)
    if len(c.sigma) != len(c.point):
        return out
    q = 0
    for i in range(len(c.point)):
        k = pt.kidx[c.point[i]]
        while q < m and lat.pts[q] < k:
            q += 1
        if q == m:
            break
        if lat.pts[q] == k:
            out[q] = c.sigma[i]
    return out


@njit(cache=True, nogil=True)
def left_out_runs(pt: TrackPoints, has, ar):  # type: ignore[no-untyped-def]
    """Per lattice point, about the kept points just before it (columns 0, 2, 4, 6-7) and just
    after it (1, 3, 5, 8-9): their path length from the track's first kept point (0, 1), their
    position among the kept points (2, 3), their time (4, 5) and position (6-7, 8-9). A step
    from lattice point ``a`` to ``b`` leaves out the kept points between them: ``run[b, 2] -
    run[a, 3] + 1`` points that travel ``run[b, 0] - run[a, 1]`` among themselves in
    ``run[b, 4] - run[a, 5]`` seconds, from ``run[a, 8:10]`` to ``run[b, 6:8]``."""
    nk = len(has)
    m = 0
    for q in range(nk):
        if has[q]:
            m += 1
    run = take_f8(ar, 10 * m).reshape((m, 10))
    cum = 0.0
    prev_cum = 0.0
    t = 0
    for q in range(nk):
        if q > 0:
            a = pt.kidx[q - 1]
            b = pt.kidx[q]
            prev_cum = cum
            cum += math.hypot(pt.xy[b, 0] - pt.xy[a, 0], pt.xy[b, 1] - pt.xy[a, 1])
            if t > 0 and has[q - 1]:
                run[t - 1, 1] = cum
                run[t - 1, 3] = q
                run[t - 1, 5] = pt.time[b]
                run[t - 1, 8] = pt.xy[b, 0]
                run[t - 1, 9] = pt.xy[b, 1]
        if has[q]:
            k = pt.kidx[q]
            j = pt.kidx[q - 1] if q > 0 else k
            run[t, 0] = prev_cum if q > 0 else 0.0
            run[t, 2] = q - 1
            run[t, 4] = pt.time[j]
            run[t, 6] = pt.xy[j, 0]
            run[t, 7] = pt.xy[j, 1]
            run[t, 1] = cum  # the last kept point: no point after it
            run[t, 3] = q + 1
            run[t, 5] = pt.time[k]
            run[t, 8] = pt.xy[k, 0]
            run[t, 9] = pt.xy[k, 1]
            t += 1
    return run


@njit(cache=True, nogil=True)
def motion_heading_into(xy, kidx, min_leg, max_turn, end_leg_max, out):  # type: ignore[no-untyped-def]
    """Direction of travel (compass degrees) at each kept point from its two legs (to the
    previous and the next kept point; at the ends the first or last two legs), where both
    are at least ``min_leg`` metres and turn by at most ``max_turn`` degrees; NaN elsewhere
    (``out`` is all NaN on entry).

    The first and last point take the direction only where their own leg is at most
    ``end_leg_max`` metres (0: any length): a turn at a junction soon after the first fix (or
    soon before the last) leaves both legs straight, so over a long leg it goes unseen."""
    k = len(kidx)
    if k < 3:
        return out
    cos_max = math.cos(math.radians(max_turn))
    end_max = end_leg_max if end_leg_max > 0 else np.inf
    last = -1  # the previous centre point: its second leg is this one's first
    vx = vy = lv = 0.0
    h = np.nan  # the direction at the previous centre point
    for i in range(k):
        c = min(max(i, 1), k - 2)
        if c == last:  # the ends: the same two legs as the neighbour
            if i < k - 1 or lv <= end_max:
                out[i] = h
            continue
        b = kidx[c]
        if c == last + 1:
            ux, uy, lu = vx, vy, lv
        else:
            a = kidx[c - 1]
            ux = xy[b, 0] - xy[a, 0]
            uy = xy[b, 1] - xy[a, 1]
            lu = math.hypot(ux, uy)
        last = c
        d = kidx[c + 1]
        vx = xy[d, 0] - xy[b, 0]
        vy = xy[d, 1] - xy[b, 1]
        lv = math.hypot(vx, vy)
        h = np.nan
        if lu < min_leg or lv < min_leg or ux * vx + uy * vy < cos_max * lu * lv:
            continue
        h = _wrap360(math.degrees(math.atan2(ux / lu + vx / lv, uy / lu + vy / lv)))
        if i > 0 or lu <= end_max:
            out[i] = h
    return out


@njit(cache=True, nogil=True, inline="always")
def _wrap360(h):  # type: ignore[no-untyped-def]
    """``h % 360.0`` for ``h`` in [-360, 360) (an arctangent in degrees), in Python's float steps
    (-0.0 gives 0.0, NaN stays NaN) without the ``fmod`` call."""
    return h + 360.0 if h < 0.0 else h + 0.0


@njit(cache=True, nogil=True)
def drop_spikes_into(xy, time, kidx, sigma, min_sigmas, max_speed, max_time, out):  # type: ignore[no-untyped-def]
    """Valid flags with jumps cleared: a kept point, or a run of them lasting at most
    ``max_time`` seconds, that the track reaches and leaves in opposite directions (legs longer
    than ``min_sigmas * sigma``; for a run also longer than any leg within it, the way back
    undoing the way out: together they move less than either) where visiting it needs more
    than ``max_speed`` m/s on average between the neighbours (0 disables it): from the last
    valid fix before the run (a thinned fix is near the kept one before it) to the kept one
    after. The shortest such run is dropped. ``kidx``: the kept points' indices; ``out``: a copy
    of the valid flags on entry."""
    if max_speed <= 0:
        return out
    noise = min_sigmas * sigma
    a = -1
    q = 0
    while q < len(kidx) - 1:
        b = kidx[q]
        if a < 0:
            a = b
            q += 1
            continue
        ux = xy[b, 0] - xy[a, 0]
        uy = xy[b, 1] - xy[a, 1]
        lu = math.hypot(ux, uy)
        run = 0
        if lu > noise:
            # the vehicle was near ``a`` until the last valid fix before ``b`` (fixes between
            # are thinned out, as a stopped vehicle's are): its time starts the visit
            tp = b - 1
            while tp > a and not out[tp]:
                tp -= 1
            inside = 0.0  # the path within the run
            longest = 0.0  # its longest leg
            for m in range(1, len(kidx) - q):
                e = kidx[q + m - 1]
                c = kidx[q + m]
                if m > 1:
                    if not time[e] - time[b] <= max_time:
                        break
                    leg = math.hypot(xy[e, 0] - xy[kidx[q + m - 2], 0], xy[e, 1] - xy[kidx[q + m - 2], 1])
                    inside += leg
                    longest = max(longest, leg)
                vx = xy[c, 0] - xy[e, 0]
                vy = xy[c, 1] - xy[e, 1]
                lv = math.hypot(vx, vy)
                dt = time[c] - time[tp]
                reverses = lv > noise and ux * vx + uy * vy < -0.5 * lu * lv
                if m > 1:
                    # a burst moves with the vehicle and the jump is its way in and out: legs
                    # longer than any within the run, the way back undoing the way out
                    back = math.hypot(ux + vx, uy + vy)
                    reverses = reverses and longest < min(lu, lv) and back < min(lu, lv)
                if reverses and dt > 0 and (lu + inside + lv) / dt > max_speed:
                    run = m
                    break
        if run:
            for k in range(q, q + run):
                out[kidx[k]] = False
            q += run  # ``a`` stays the neighbour of the next point
            continue
        a = b
        q += 1
    return out
