"""Route assembly: from the chosen candidates to the route's edges, geometry and per-point
results (compiled).

Each lattice point is reached from the previous one by one of four kinds of step: along the
same edge, a U-turn along the road, a routed path, or a split (a new piece of route). Points
thinned out before the match are projected onto the chosen edge of the nearer kept neighbour.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.index import project_point_near
from graph.jit import njit
from mapmatch.arena import UNCOUNTED, full_b1, full_f8, full_i8, int64, take_f8, take_i8, take_xy
from mapmatch.batch.arrays import Assembly, EdgeGeometry, KernelParams, Lattice, TrackPoints
from mapmatch.batch.leave_out import Chosen
from mapmatch.batch.step import standing_tol
from mapmatch.gridindex import grow_array
from mapmatch.route_table import path_into, path_place
from mapmatch.routing import path_edges

STEP_SAME, STEP_UTURN, STEP_ROUTE, STEP_SPLIT = 0, 1, 2, 3
ON_NODE = 1e-6  # metres: an offset this near an edge's end is at its node (float noise)


class RouteSteps(NamedTuple):
    """The accepted lattice points' chosen candidates, in track order."""

    edge: NDArray[np.int64]
    off: NDArray[np.float64]
    kind: NDArray[np.int64]
    """How it is reached from the previous one (``STEP_*``)."""
    bound: NDArray[np.float64]
    """The route bound of the step into it."""
    pts: NDArray[np.int64]
    """Its index among the track's points."""
    bad: NDArray[np.bool_]
    """A routed step whose path was not found (it becomes a split)."""


class RoutePieces(NamedTuple):
    """The route as pieces: an edge from a start to an end offset, and the piece of route
    (segment between splits) it belongs to."""

    edge: NDArray[np.int64]
    start: NDArray[np.float64]
    end: NDArray[np.float64]
    seg: NDArray[np.int64]


class PointMatch(NamedTuple):
    """Per track point: the matched edge, offset, road point and distance, and its status."""

    edge: NDArray[np.int64]
    off: NDArray[np.float64]
    xy: NDArray[np.float64]
    dist: NDArray[np.float64]
    status: NDArray[np.int64]
    """0 unmatched, 1 matched, 2 interpolated."""


@njit(cache=True, nogil=True)
def route_pieces(ch, router, ar):  # type: ignore[no-untyped-def]
    """The route as :class:`RoutePieces` along the chosen candidates ``ch`` (:class:`RouteSteps`; its
    ``bad`` flags set where a path is not found)."""
    m = len(ch.edge)
    cap = 2 * m + 16
    pc = RoutePieces(take_i8(ar, cap), take_f8(ar, cap), take_f8(ar, cap), take_i8(ar, cap))
    n = int64(0)  # not 0: one compile of ``_pieces_into`` (``mapmatch.arena.int64``)
    seg = int64(-1)
    t = int64(0)
    while t < m:
        # the pieces stop at the first step that does not fit; grow, and go on from there
        t, n, seg, need = _pieces_into(ch, router, t, n, seg, pc)
        if t < m:
            cap = 2 * need
            pc = RoutePieces(
                grow_array(pc.edge, cap),
                grow_array(pc.start, cap),
                grow_array(pc.end, cap),
                grow_array(pc.seg, cap),
            )
    return RoutePieces(pc.edge[:n], pc.start[:n], pc.end[:n], pc.seg[:n])


@njit(cache=True, nogil=True)
def _pieces_into(ch, router, t0, n, seg, pc):  # type: ignore[no-untyped-def]
    """:func:`route_pieces` from step ``t0`` on, written into ``pc`` from piece ``n`` (``seg``:
    the current piece of route), until a step does not fit: ``(next step, pieces, seg, room it
    needs)`` (no array is replaced in the loop, so none is reference-counted there)."""
    edge_len = router.g.edge_len
    table = router.table
    pe, ps, pend, pseg = pc
    ch_edge, ch_off, kind, bound, bad = ch.edge, ch.off, ch.kind, ch.bound, ch.bad
    cap = len(pe)
    for t in range(t0, len(ch_edge)):
        e = ch_edge[t]
        o = ch_off[t]
        k = kind[t]
        if n + 4 >= cap:
            return t, n, seg, n + 4
        if k == STEP_SAME:
            if o > pend[n - 1]:
                pend[n - 1] = o
            continue
        if k == STEP_UTURN:
            L = edge_len[e]
            turn = max(pend[n - 1], L - o)
            pend[n - 1] = turn
            pe[n] = e
            ps[n] = L - turn
            pend[n] = max(o, L - turn)
            pseg[n] = seg
            n += 1
            continue
        if k == STEP_ROUTE:
            src = ch_edge[t - 1]
            place, nm = path_place(table, src, e) if table.delta > 0 else (-1, -1)
            got = None
            if place < 0:
                got = path_edges(src, ch_off[t - 1], e, bound[t] + 1.0, router.g, router.ws)
                nm = -1 if got is None else len(got)
            if nm < 0:
                bad[t] = True
                k = STEP_SPLIT
            else:
                if n + nm + 4 >= cap:
                    return t, n, seg, n + nm + 4
                pend[n - 1] = edge_len[src]
                if got is None:
                    path_into(table, src, place, nm, pe, n)
                else:
                    pe[n : n + nm] = got
                for i in range(n, n + nm):
                    ps[i] = 0.0
                    pend[i] = edge_len[pe[i]]
                    pseg[i] = seg
                n += nm
                pe[n] = e
                ps[n] = 0.0
                pend[n] = o
                pseg[n] = seg
                n += 1
                continue
        # STEP_SPLIT: a new piece of route
        seg += 1
        pe[n] = e
        ps[n] = o
        pend[n] = o
        pseg[n] = seg
        n += 1
    return len(ch_edge), n, seg, n


@njit(cache=True, nogil=True)
def trim_ends(pe, ps, pend, pseg, edge_len, ar):  # type: ignore[no-untyped-def]
    """Which pieces to keep: a piece of route that begins at the very end of its edge (or ends
    at the very start of it) is no road driven, only the node where the next (or previous)
    piece begins. Such a piece is dropped at either end of a route with more than one piece."""
    n = len(pe)
    keep = full_b1(ar, n, True)
    for i in range(n):
        first = i == 0 or pseg[i - 1] != pseg[i]
        last = i == n - 1 or pseg[i + 1] != pseg[i]
        if first == last or pend[i] - ps[i] > ON_NODE:
            continue
        if (first and ps[i] >= edge_len[pe[i]] - ON_NODE) or (last and pend[i] <= ON_NODE):
            keep[i] = False
    return keep


@njit(cache=True, nogil=True)
def pieces_xy(pe, ps, pend, geom, edge_len, ar):  # type: ignore[no-untyped-def]
    """Polyline coordinates of each piece (consecutive duplicates dropped); ``ptr`` per piece.

    A piece that covers its whole edge (from 0 to ``edge_len``, as every edge a routed path
    passes through does) takes the edge's vertices as they are; a part of an edge is cut from
    its segments."""
    seg_xy = geom.seg_xy
    seg_ptr = geom.seg_ptr
    seg_len = geom.seg_len
    n = len(pe)
    total = 0
    for i in range(n):
        total += seg_ptr[pe[i] + 1] - seg_ptr[pe[i]] + 2
    out = take_xy(ar, total)
    ptr = full_i8(ar, n + 1, 0)
    c = 0
    for i in range(n):
        a0 = seg_ptr[pe[i]]
        a1 = seg_ptr[pe[i] + 1]
        s = ps[i]
        e = pend[i]
        if s <= 0.0 and e >= edge_len[pe[i]]:
            for q in range(a0, a1):
                x, y = seg_xy[q, 0], seg_xy[q, 1]
                if c == 0 or abs(out[c - 1, 0] - x) > 1e-9 or abs(out[c - 1, 1] - y) > 1e-9:
                    out[c, 0] = x
                    out[c, 1] = y
                    c += 1
            ptr[i + 1] = c
            continue
        acc = 0.0
        for q in range(a0, a1 - 1):
            x0, y0 = seg_xy[q, 0], seg_xy[q, 1]
            x1, y1 = seg_xy[q + 1, 0], seg_xy[q + 1, 1]
            L = seg_len[q]
            lo = max(s, acc)
            hi = min(e, acc + L)
            if hi >= lo and (L > 0 or q == a0):
                f0 = (lo - acc) / L if L > 0 else 0.0
                f1 = (hi - acc) / L if L > 0 else 0.0
                for f in (f0, f1):
                    x = x0 + f * (x1 - x0)
                    y = y0 + f * (y1 - y0)
                    if c == 0 or abs(out[c - 1, 0] - x) > 1e-9 or abs(out[c - 1, 1] - y) > 1e-9:
                        out[c, 0] = x
                        out[c, 1] = y
                        c += 1
            acc += L
            if acc > e:
                break
        ptr[i + 1] = c
    return out[:c], ptr


@njit(cache=True, nogil=True)
def _trimmed(pc, ch, pm, router, ar):  # type: ignore[no-untyped-def]
    """The route pieces ``pc`` (:class:`RoutePieces`) without those :func:`trim_ends` drops; the
    chosen points ``ch`` (:class:`RouteSteps`) on a dropped piece move to the same node on the
    neighbouring piece (their edge and offset, and those of ``pm``, :class:`PointMatch`, in
    place)."""
    pe, ps, pend, pseg = pc
    keep = trim_ends(pe, ps, pend, pseg, router.g.edge_len, ar)
    n = len(pe)
    k = 0
    for i in range(n):
        if keep[i]:
            k += 1
    if k == n:
        return pc
    # each segment's dropped head (tail): the edge and offset its points move to
    nseg = pseg[n - 1] + 1
    head = full_i8(ar, nseg, -1)
    tail = full_i8(ar, nseg, -1)
    for i in range(n):
        if not keep[i]:
            if i + 1 < n and pseg[i + 1] == pseg[i] and keep[i + 1] and (i == 0 or pseg[i - 1] != pseg[i]):
                head[pseg[i]] = i
            else:
                tail[pseg[i]] = i
    ch_edge, ch_off, kind, bad, pts = ch.edge, ch.off, ch.kind, ch.bad, ch.pts
    p_edge, p_off = pm.edge, pm.off
    seg = -1
    for c in range(len(ch_edge)):
        if kind[c] == STEP_SPLIT or bad[c]:
            seg += 1
        h = head[seg]
        t = tail[seg]
        if h >= 0 and ch_edge[c] == pe[h] and ch_off[c] >= ps[h] - ON_NODE:
            ch_edge[c], ch_off[c] = pe[h + 1], ps[h + 1]
        elif t >= 0 and ch_edge[c] == pe[t] and ch_off[c] <= pend[t] + ON_NODE:
            ch_edge[c], ch_off[c] = pe[t - 1], pend[t - 1]
        else:
            continue
        p_edge[pts[c]] = ch_edge[c]
        p_off[pts[c]] = ch_off[c]
    qe = take_i8(ar, k)
    qs = take_f8(ar, k)
    qend = take_f8(ar, k)
    qseg = take_i8(ar, k)
    k = 0
    for i in range(n):
        if keep[i]:
            qe[k], qs[k], qend[k], qseg[k] = pe[i], ps[i], pend[i], pseg[i]
            k += 1
    return RoutePieces(qe, qs, qend, qseg)


@njit(cache=True, nogil=True)
def assemble(
    pt: TrackPoints, lat: Lattice, dec: Chosen, p: KernelParams, geom: EdgeGeometry, router, ar
) -> Assembly:  # type: ignore[no-untyped-def]
    """Per-point results, route pieces (edges and geometry), splits, length and confidence, from
    the search's answer ``dec`` (:class:`~mapmatch.batch.leave_out.Chosen`)."""
    n = len(pt.valid)
    pm = PointMatch(
        full_i8(ar, n, -1), full_f8(ar, n, np.nan), full_f8(ar, 2 * n, np.nan).reshape((n, 2)),
        full_f8(ar, n, np.nan), full_i8(ar, n, 0),
    )  # fmt: skip
    # lattice points left out as unreachable outliers are unmatched
    acc = _accepted(dec.choice, ar)
    m = len(acc)
    valid, status = pt.valid, pm.status
    nvalid = 0
    for i in range(n):
        if valid[i]:
            nvalid += 1
    if m == 0:
        return Assembly(
            pm.edge, pm.off, pm.xy, pm.dist, pm.status, take_i8(ar, 0), take_i8(ar, 0),
            full_i8(ar, 1, 0), take_xy(ar, 0), full_i8(ar, 1, 0), 0.0, 0.0,
        )  # fmt: skip
    ch = RouteSteps(
        take_i8(ar, m), take_f8(ar, m), take_i8(ar, m), take_f8(ar, m), take_i8(ar, m), full_b1(ar, m, False)
    )
    post = _choose(acc, lat, dec, (p.reverse_tol, p.one_way_tol), router.g.edge_rev, ch, pm)
    pc = _trimmed(route_pieces(ch, router, ar), ch, pm, router, ar)
    splits = _splits(ch, ar)
    xy_all, xptr = pieces_xy(pc.edge, pc.start, pc.end, geom, router.g.edge_len, ar)
    route_e, route_ptr, rxy_ptr, length = _route_edges(pc, xptr, len(splits) + 1, ar)
    _interpolate(pt, ch, geom, pm)
    # the matched fraction (interpolated points count) times the lattice points' mean
    nmatched = 0
    for i in range(n):
        if valid[i] and status[i] != 0:
            nmatched += 1
    conf = nmatched / max(nvalid, 1) * post / m
    return Assembly(
        pm.edge, pm.off, pm.xy, pm.dist, pm.status, splits, route_e, route_ptr, xy_all, rxy_ptr, length, conf
    )


@njit(cache=True, nogil=True)
def _accepted(choice, ar):  # type: ignore[no-untyped-def]
    """The lattice points with a chosen candidate (the others were left out), in order."""
    m = 0
    for t in range(len(choice)):
        if choice[t] >= 0:
            m += 1
    acc = take_i8(ar, m)
    q = 0
    for t in range(len(choice)):
        if choice[t] >= 0:
            acc[q] = t
            q += 1
    return acc


@njit(**UNCOUNTED)
def _choose(acc, lat, dec, tols, edge_rev, ch, pm):  # type: ignore[no-untyped-def]
    """The accepted lattice points ``acc``'s chosen candidates into ``ch`` (:class:`RouteSteps`,
    with the kind of step into each; ``bad`` untouched) and their points' matches into ``pm``
    (:class:`PointMatch`); returns the sum of their confidences (:func:`_road_share`).
    Allocates nothing (:data:`~mapmatch.arena.UNCOUNTED`: an inlined call handed a tuple of
    arrays in a reference-counted loop would count every array in it)."""
    post = 0.0
    for i in range(len(acc)):
        t = acc[i]
        j = dec.choice[t]
        e = lat.edge[j]
        ch.edge[i] = e
        ch.off[i] = lat.offset[j]
        ch.pts[i] = lat.pts[t]
        ch.bound[i] = dec.used_bound[t]
        tol = standing_tol(e, edge_rev, tols[0], tols[1])
        same = i > 0 and e == ch.edge[i - 1] and lat.offset[j] >= ch.off[i - 1] - tol
        if i == 0 or dec.seg_start[t]:
            ch.kind[i] = STEP_SPLIT
        elif same:
            ch.kind[i] = STEP_SAME
        elif dec.via_u[t]:
            ch.kind[i] = STEP_UTURN
        else:
            ch.kind[i] = STEP_ROUTE
        pi = ch.pts[i]
        pm.edge[pi] = e
        pm.off[pi] = lat.offset[j]
        pm.xy[pi, 0] = lat.xy[j, 0]
        pm.xy[pi, 1] = lat.xy[j, 1]
        pm.dist[pi] = lat.dist[j]
        pm.status[pi] = 1
        post += _road_share(lat, t, e, edge_rev)
    return post


@njit(cache=True, nogil=True, inline="always")
def _road_share(lat, t, e, edge_rev):  # type: ignore[no-untyped-def]
    """The confidence of edge ``e`` at lattice point ``t``: its road's share of the point's
    normalised emissions (both directions of a two-way road count as one)."""
    c0 = lat.ptr[t]
    c1 = lat.ptr[t + 1]
    mx = -np.inf
    for c in range(c0, c1):
        mx = max(mx, lat.emis[c])
    road = min(e, edge_rev[e]) if edge_rev[e] >= 0 else e
    tot = 0.0
    mine = 0.0
    for c in range(c0, c1):
        w = math.exp(lat.emis[c] - mx)
        tot += w
        f = lat.edge[c]
        rf = min(f, edge_rev[f]) if edge_rev[f] >= 0 else f
        if rf == road:
            mine += w
    return mine / tot


@njit(cache=True, nogil=True)
def _splits(ch, ar):  # type: ignore[no-untyped-def]
    """The points where a new piece of route starts after the first: a split, or a failed path
    (should not happen: Viterbi chose a reachable pair)."""
    kind, bad = ch.kind, ch.bad
    m = len(kind)
    nsplit = 0
    for i in range(1, m):
        if kind[i] == STEP_SPLIT or bad[i]:
            nsplit += 1
    splits = take_i8(ar, nsplit)
    q = 0
    for i in range(1, m):
        if kind[i] == STEP_SPLIT or bad[i]:
            splits[q] = ch.pts[i]
            q += 1
    return splits


@njit(cache=True, nogil=True)
def _route_edges(pc, xptr, nseg, ar):  # type: ignore[no-untyped-def]
    """The route's edges (consecutive pieces on one edge once) with their pointer per piece of
    route, the geometry's pointer per piece of route (from ``xptr``, per piece) and the
    length: ``route_e, route_ptr, rxy_ptr, length`` (``nseg`` pieces of route, a last one
    trimmed to nothing too)."""
    pe, ps, pend, pseg = pc
    npc = len(pe)
    route_e = take_i8(ar, npc)
    route_ptr = full_i8(ar, nseg + 1, 0)
    rxy_ptr = full_i8(ar, nseg + 1, 0)
    length = 0.0
    k = 0
    for i in range(npc):
        length += pend[i] - ps[i]
        s = pseg[i]
        if i == 0 or pseg[i - 1] != s or pe[i] != pe[i - 1]:
            route_e[k] = pe[i]
            k += 1
        route_ptr[s + 1] = k
        rxy_ptr[s + 1] = xptr[i + 1]
    for s in range(nseg):  # a piece trimmed to nothing ends where the one before it ends
        route_ptr[s + 1] = max(route_ptr[s + 1], route_ptr[s])
        rxy_ptr[s + 1] = max(rxy_ptr[s + 1], rxy_ptr[s])
    return route_e[:k], route_ptr, rxy_ptr, length


@njit(cache=True, nogil=True)
def _interpolate(pt, ch, geom, pm):  # type: ignore[no-untyped-def]
    """The points thinned out before the match, into ``pm`` (:class:`PointMatch`): each
    projected onto the chosen edge of the nearer kept neighbour in ``ch`` (:class:`RouteSteps`);
    those thinned after an unmatched kept point (off the map, a jump) stay unmatched with it."""
    seg_xy, seg_len, seg_ptr = geom.seg_xy, geom.seg_len, geom.seg_ptr
    valid, kept, xy = pt.valid, pt.kept, pt.xy
    ch_edge, pts = ch.edge, ch.pts
    p_edge, p_off, p_xy, p_dist, status = pm
    m = len(ch_edge)
    q = 0
    last_matched = True
    # the last projection's edge, piece and the piece's start: a stop's fixes share them
    # (``int64(-1)``, not -1: one compile of project_point_near, ``mapmatch.arena.int64``)
    hint_e, hint, hint_acc = -1, int64(-1), 0.0
    for i in range(len(valid)):
        if kept[i]:
            last_matched = status[i] == 1
        if not valid[i] or kept[i] or not last_matched:
            continue
        while q < m and pts[q] < i:
            q += 1
        prv = max(q - 1, 0)
        nxt = min(q, m - 1)
        x, y = xy[i, 0], xy[i, 1]
        e1, e2 = ch_edge[prv], ch_edge[nxt]
        if e1 != hint_e:
            hint_e, hint = e1, int64(-1)
        o1, d1, x1, y1, hint, hint_acc = project_point_near(
            seg_xy, seg_len, seg_ptr[e1], seg_ptr[e1 + 1], x, y, hint, hint_acc
        )
        o2, d2, x2, y2 = 0.0, np.inf, 0.0, 0.0  # both neighbours on one edge (a stop): one projection
        if e2 != e1:
            lo, hi = seg_ptr[e2], seg_ptr[e2 + 1]
            o2, d2, x2, y2, _, _ = project_point_near(seg_xy, seg_len, lo, hi, x, y, int64(-1), 0.0)
        if d2 < d1:
            p_edge[i], p_off[i], p_xy[i, 0], p_xy[i, 1], p_dist[i] = ch_edge[nxt], o2, x2, y2, d2
        else:
            p_edge[i], p_off[i], p_xy[i, 0], p_xy[i, 1], p_dist[i] = ch_edge[prv], o1, x1, y1, d1
        status[i] = 2
