"""Batch map matching of historic tracks: exact Viterbi over the whole track (Newson & Krumm 2009).

Candidates for all points come from one vectorised index query; emissions and transitions
from the shared :mod:`mapmatch.model`; route distances from bounded edge-based Dijkstra
(:mod:`mapmatch.routing`); the lattice recursion and the path assembly are compiled with numba.
The matched route is always connected through the network; it is split only where the track
has a time/distance gap or no route exists between consecutive points (both reported).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from graph.index import Candidates, EdgeIndex
from graph.projection import to_lonlat, to_xy
from graph.road_graph import RoadGraph
from mapmatch import model
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.gridindex import GridIndex
from mapmatch.model import transition_logp_one
from mapmatch.routing import (
    RoutingArrays,
    Ubodt,
    Workspace,
    _reset,
    _search,
    path_edges,
    search_args,
    ubodt_lookup,
    ubodt_path,
)
from mapmatch.types import MatchedPoint, PointStatus, Track, TrackMatch

NEG_INF = -np.inf
BATCH_CONFIG = DEFAULT_CONFIG.replace(gps_sigma=8.0, uturn_penalty=20.0, interpolate_distance=8.0)
"""Batch defaults: the shared model with σ and the U-turn penalty set for raw GPS tracks, and
points closer than σ to the previous kept point interpolated."""
EMISSION_PRUNE = 12.5
"""Candidates whose emission log-probability is this far below the point's best are dropped."""
REVERSE_TOLERANCE = 10.0
"""Metres a candidate may fall behind the previous one on the same edge and count as standing."""

ROUTE_LP_CUT = 30.0
"""Transition log-probability below which routes are searched only as a fallback."""

MAX_SKIP = 8
"""Points in a row that may be left out as unreachable outliers before the track is split."""

STEP_SAME, STEP_UTURN, STEP_ROUTE, STEP_SPLIT = 0, 1, 2, 3


class BatchMatcher:
    """Matches whole tracks against one road graph (read-only, reusable, one per thread).

    Parameters
    ----------
    graph
        The road graph.
    index
        Its spatial index; built when omitted.
    config
        Default parameters (:data:`BATCH_CONFIG` when omitted); :meth:`match` takes a per-call
        override.
    ubodt
        Optional precomputed route table (:class:`mapmatch.routing.Ubodt`); routes within its
        bound are looked up instead of searched. Without it every route is a bounded search.
    """

    def __init__(
        self,
        graph: RoadGraph,
        index: EdgeIndex | None = None,
        config: MatchConfig | None = None,
        *,
        ubodt: Ubodt | None = None,
    ) -> None:
        self.graph = graph
        self.ubodt = ubodt
        self._ubodt_args = (
            (ubodt.delta, ubodt.ptr, ubodt.tgt, ubodt.dist, ubodt.pred)
            if ubodt is not None
            else (-1.0, np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0), np.zeros(0, np.int32))
        )
        self.index = index or EdgeIndex(graph)
        self.config = config or BATCH_CONFIG
        self._grid = GridIndex(self.index, cell=self.config.search_radius)
        self._ra = RoutingArrays.from_graph(graph)
        self._ws = Workspace(graph.n_edges)
        self._seg_xy = np.ascontiguousarray(graph.seg_xy, dtype=np.float64)
        self._seg_ptr = np.ascontiguousarray(graph.edge_seg_ptr, dtype=np.int64)

    def match(self, track: Track, config: MatchConfig | None = None, *, lonlat: bool = True) -> TrackMatch:
        """Match one track; bad points become unmatched, never an exception for the track.

        With ``lonlat=False`` the route geometry is left in the map's CRS (``route_xy``) and
        ``route_lonlat`` is filled later by :func:`fill_route_lonlat`.
        """
        cfg = config or self.config
        g = self.graph
        n = len(track)
        lat = np.asarray(track.lat, dtype=np.float64)
        lon = np.asarray(track.lon, dtype=np.float64)
        tim = _opt(track.time, n)
        valid = np.isfinite(lat) & np.isfinite(lon) & (np.abs(lat) <= 90) & (np.abs(lon) <= 180)
        xy = np.full((n, 2), np.nan)
        if valid.any():
            xy[valid] = to_xy(g.crs, lon[valid], lat[valid])
        # points closer than the noise to the previous kept point are interpolated afterwards
        kept = _thin(xy, valid, float(cfg.interpolate_distance))
        kidx = np.flatnonzero(kept)
        cands = self._grid.query(xy[kidx], cfg.search_radius, k=cfg.max_candidates)
        # points with no road within the search radius look again up to the outlier distance
        lonely = np.flatnonzero(np.bincount(cands.point, minlength=len(kidx)) == 0)
        if len(lonely) and cfg.outlier_distance > cfg.search_radius:
            more = self._grid.query(xy[kidx[lonely]], cfg.outlier_distance, k=cfg.max_candidates)
            cands = _merge_candidates(cands, more, lonely)
        # emissions (shared model), then pruning of hopeless candidates
        sigma = model.position_sigma(_opt(track.pos_sigma, n)[kidx], cfg)[cands.point]
        heading = _opt(track.heading, n)[kidx]
        if np.isfinite(heading).any():
            kappa = model.heading_kappa(heading, np.nan, _opt(track.speed, n)[kidx], cfg)[cands.point]
            bearing = _bearing_at(cands.edge, cands.offset, self._seg_xy, self._seg_ptr)
            emis = model.emission_logp(cands.dist, sigma, heading[cands.point], bearing, kappa)
        else:
            emis = model.emission_logp(cands.dist, sigma, np.nan, 0.0, 0.0)
        best = np.full(len(kidx), NEG_INF)
        np.maximum.at(best, cands.point, emis)
        keep = (emis >= best[cands.point] - EMISSION_PRUNE) & (cands.dist <= cfg.outlier_distance)
        cpoint, cedge, coff, cxy, cdist, emis = (
            cands.point[keep],
            cands.edge[keep],
            cands.offset[keep],
            cands.xy[keep],
            cands.dist[keep],
            emis[keep],
        )
        # points without candidates are unmatched (off the map or outliers)
        counts = np.bincount(cpoint, minlength=len(kidx))
        has = counts > 0
        pts = kidx[has]  # track indices of the lattice's points
        counts = counts[has]
        m = len(pts)
        cand_ptr = np.zeros(m + 1, dtype=np.int64)
        np.cumsum(counts, out=cand_ptr[1:])
        pxy = np.ascontiguousarray(xy[pts])
        ptime = np.ascontiguousarray(tim[pts])
        podo = np.full(m, np.nan)
        if track.distance is not None:
            odo = np.asarray(track.distance, dtype=np.float64)
            csum = np.cumsum(np.where(np.isfinite(odo), odo, 0.0))
            podo = np.where(np.isfinite(odo[pts]), csum[pts], np.nan)
        choice, seg_start, via_u, used_bound = _solve(  # type: ignore[call-arg]
            cand_ptr, cedge, coff, emis, pxy, ptime, podo, model.transition_params(cfg),
            float(cfg.max_route_factor), float(cfg.route_slack), float(cfg.beta * ROUTE_LP_CUT),
            float(cfg.gap_distance), MAX_SKIP, REVERSE_TOLERANCE, *search_args(self._ra, self._ws),
            *self._ubodt_args,
        )  # fmt: skip
        res = self._assemble(
            track, n, valid, kept, xy, pts, cand_ptr, cedge, coff, cxy, cdist, emis, choice, seg_start,
            via_u, used_bound,
        )  # fmt: skip
        if lonlat:
            fill_route_lonlat(res, g.crs)
        return res

    # ------------------------------------------------------------------ output
    def _assemble(
        self,
        track: Track,
        n: int,
        valid: NDArray[np.bool_],
        kept: NDArray[np.bool_],
        xy: NDArray[np.float64],
        pts: NDArray[np.int64],
        cand_ptr: NDArray[np.int64],
        cedge: NDArray[np.int32],
        coff: NDArray[np.float64],
        cxy: NDArray[np.float64],
        cdist: NDArray[np.float64],
        emis: NDArray[np.float64],
        choice_all: NDArray[np.int64],
        seg_start: NDArray[np.bool_],
        via_u: NDArray[np.bool_],
        used_bound: NDArray[np.float64],
    ) -> TrackMatch:
        g = self.graph
        res = TrackMatch(track_id=str(track.track_id))
        p_edge = np.full(n, -1, dtype=np.int64)
        p_off = np.full(n, np.nan)
        p_xy = np.full((n, 2), np.nan)
        p_dist = np.full(n, np.nan)
        status = np.zeros(n, dtype=np.int8)  # 0 unmatched, 1 matched, 2 interpolated
        # lattice points left out as unreachable outliers are unmatched
        acc = np.flatnonzero(choice_all >= 0)
        choice = choice_all[acc]
        pts = pts[acc]
        m = len(pts)
        if m:
            ch_edge = cedge[choice]
            ch_off = coff[choice]
            kind = np.full(m, STEP_ROUTE, dtype=np.int64)
            prev_e = np.r_[-1, ch_edge[:-1]]
            prev_o = np.r_[np.nan, ch_off[:-1]]
            same = (ch_edge == prev_e) & (ch_off >= prev_o - REVERSE_TOLERANCE)
            kind[same] = STEP_SAME
            kind[via_u[acc] & ~same] = STEP_UTURN
            kind[seg_start[acc]] = STEP_SPLIT
            kind[0] = STEP_SPLIT
            bound = used_bound[acc]
            pe, ps, pend, pseg, bad = _pieces(  # type: ignore[call-arg]
                ch_edge, ch_off, kind, bound, *search_args(self._ra, self._ws), *self._ubodt_args
            )
            # a failed path (should not happen: Viterbi chose a reachable pair) becomes a split
            starts = np.flatnonzero((kind == STEP_SPLIT) | bad)
            res.splits = [int(pts[i]) for i in starts[1:]]
            xy_all, xptr = _pieces_xy(pe, ps, pend, self._seg_xy, self._seg_ptr)
            nseg = int(pseg.max()) + 1 if len(pseg) else 0
            piece_bounds = np.searchsorted(pseg, np.arange(nseg + 1))
            for s in range(nseg):
                a, b = piece_bounds[s], piece_bounds[s + 1]
                edges = pe[a:b]
                keep_e = np.ones(len(edges), dtype=bool)
                keep_e[1:] = edges[1:] != edges[:-1]
                res.routes.append(edges[keep_e].tolist())
            res.length_m = float(np.sum(pend - ps))
            p_edge[pts] = ch_edge
            p_off[pts] = ch_off
            p_xy[pts] = cxy[choice]
            p_dist[pts] = cdist[choice]
            status[pts] = 1
            # confidence: matched fraction x mean normalised emission of the chosen road (both
            # directions of a two-way road count as one) among the point's candidates
            w = np.exp(emis - np.repeat(np.maximum.reduceat(emis, cand_ptr[:-1]), np.diff(cand_ptr)))
            tot = np.add.reduceat(w, cand_ptr[:-1])
            rev = g.edge_reverse[cedge]
            road = np.where(rev >= 0, np.minimum(cedge, rev), cedge).astype(np.int64)
            lp = np.repeat(np.arange(len(cand_ptr) - 1), np.diff(cand_ptr))
            key = lp * (g.n_edges + 1) + road
            uk, inv = np.unique(key, return_inverse=True)
            road_w = np.bincount(inv, weights=w, minlength=len(uk))[inv]
            post = road_w[choice] / tot[acc]
            res.confidence = float(np.mean(post) * m / max(int(valid.sum()), 1))
            # interpolated points: projected onto the chosen edge of the nearer kept neighbour
            interp = valid & ~kept
            if interp.any():
                ii = np.flatnonzero(interp)
                k = np.searchsorted(pts, ii) - 1
                nxt = np.minimum(k + 1, m - 1)
                prv = np.maximum(k, 0)
                e1 = ch_edge[prv]
                e2 = ch_edge[nxt]
                o1, d1, x1 = _project_on_edges(xy[ii], e1, self._seg_xy, self._seg_ptr)
                o2, d2, x2 = _project_on_edges(xy[ii], e2, self._seg_xy, self._seg_ptr)
                use2 = d2 < d1
                p_edge[ii] = np.where(use2, e2, e1)
                p_off[ii] = np.where(use2, o2, o1)
                p_xy[ii] = np.where(use2[:, None], x2, x1)
                p_dist[ii] = np.where(use2, d2, d1)
                status[ii] = 2
        ok = status > 0
        p_ll = np.full((n, 2), np.nan)
        if ok.any():
            p_ll[ok] = to_lonlat(g.crs, p_xy[ok, 0], p_xy[ok, 1])
        if m:
            for s in range(len(res.routes)):
                seg = xy_all[xptr[piece_bounds[s]] : xptr[piece_bounds[s + 1]]]
                res.route_xy.append(np.vstack([seg, seg]) if len(seg) == 1 else seg)
        stat = (PointStatus.UNMATCHED, PointStatus.MATCHED, PointStatus.INTERPOLATED)
        res.points = [
            MatchedPoint(i, stat[s], int(e), float(o), float(la), float(lo), float(d))
            for i, s, e, o, la, lo, d in zip(
                range(n),
                status.tolist(),
                p_edge.tolist(),
                p_off.tolist(),
                p_ll[:, 1].tolist(),
                p_ll[:, 0].tolist(),
                p_dist.tolist(),
                strict=True,
            )
        ]
        return res


def fill_route_lonlat(result: TrackMatch, crs: str) -> TrackMatch:
    """Fill ``route_lonlat`` from ``route_xy`` (one projection call for all pieces)."""
    if not result.route_xy:
        result.route_lonlat = []
        return result
    allxy = np.concatenate(result.route_xy)
    ll = to_lonlat(crs, allxy[:, 0], allxy[:, 1]).tolist()
    out: list[list[tuple[float, float]]] = []
    i = 0
    for piece in result.route_xy:
        out.append(list(map(tuple, ll[i : i + len(piece)])))
        i += len(piece)
    result.route_lonlat = out
    return result


def match_track(
    graph: RoadGraph, track: Track, *, index: EdgeIndex | None = None, config: MatchConfig | None = None
) -> TrackMatch:
    """Match one track (builds a :class:`BatchMatcher`; reuse one for many tracks)."""
    return BatchMatcher(graph, index, config).match(track)


def _merge_candidates(a: Candidates, b: Candidates, b_points: NDArray[np.int64]) -> Candidates:
    """Candidates of ``a`` plus those of ``b`` (queried for the points ``b_points``), by point."""
    point = np.concatenate([a.point, b_points[b.point]])
    order = np.argsort(point, kind="stable")
    return Candidates(
        point=point[order],
        edge=np.concatenate([a.edge, b.edge])[order],
        dist=np.concatenate([a.dist, b.dist])[order],
        offset=np.concatenate([a.offset, b.offset])[order],
        xy=np.concatenate([a.xy, b.xy])[order],
    )


def _opt(a: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    return np.full(n, np.nan) if a is None else np.asarray(a, dtype=np.float64)


# ---------------------------------------------------------------------- compiled kernels
@njit(cache=True)
def _thin(xy, valid, min_dist):  # type: ignore[no-untyped-def]
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


@njit(cache=True)
def _step(  # type: ignore[no-untyped-def]
    a0,
    a1,
    b0,
    b1,
    cedge,
    coff,
    emis,
    score,
    bp,
    bpu,
    order,
    best,
    params,
    trav,
    dt,
    bound,
    reverse_tol,
    out_ptr,
    out_edges,
    edge_v,
    edge_len,
    edge_rev,
    r_ptr,
    r_to,
    r_kind,
    dist,
    pred,
    done,
    tgt,
    touched,
    heap_k,
    heap_v,
    u_delta,
    u_ptr,
    u_tgt,
    u_dist,
    u_pred,
):
    """One Viterbi step from candidates ``a0:a1`` to ``b0:b1``, routing as needed.

    Sources are taken best score first. As every transition log-probability is <= 0, a source
    can only improve target ``j`` when its score beats ``best[j]``, and only through a route
    shorter than ``trav + beta * (score - best[j])``: the search bound shrinks accordingly and
    the result stays exact. Returns whether any target was reached.
    """
    ka = a1 - a0
    kb = b1 - b0
    beta = params[0]
    for i in range(ka):
        order[i] = a0 + i
    # insertion sort by descending score (k is small)
    for i in range(1, ka):
        x = order[i]
        q = i - 1
        while q >= 0 and score[order[q]] < score[x]:
            order[q + 1] = order[q]
            q -= 1
        order[q + 1] = x
    for j in range(kb):
        best[j] = -np.inf
        bp[b0 + j] = -1
        bpu[b0 + j] = False
    nuniq = 0
    for j in range(b0, b1):
        if tgt[cedge[j]] == 0:
            tgt[cedge[j]] = 1
            nuniq += 1
    for oi in range(ka):
        i = order[oi]
        si = score[i]
        if si == -np.inf:
            break
        worst = np.inf
        for j in range(kb):
            worst = min(worst, best[j])
        if worst >= si:
            break  # no remaining source can improve any target
        lim = bound
        if worst > -np.inf:
            lim = min(bound, trav + beta * (si - worst))
        e = cedge[i]
        o = coff[i]
        need = False
        for j in range(b0, b1):
            f = cedge[j]
            if f == e and coff[j] >= o - reverse_tol:
                lp = transition_logp_one(max(coff[j] - o, 0.0), trav, dt, params, False)
                if si + lp > best[j - b0]:
                    best[j - b0] = si + lp
                    bp[j] = i
                    bpu[j] = False
            else:
                need = True
                if f == edge_rev[e]:
                    lp = transition_logp_one(abs(edge_len[e] - coff[j] - o), trav, dt, params, True)
                    if si + lp > best[j - b0]:
                        best[j - b0] = si + lp
                        bp[j] = i
                        bpu[j] = True
        if not need or edge_len[e] - o > lim:
            continue
        if lim <= u_delta:  # the table holds every route within the bound
            for j in range(b0, b1):
                f = cedge[j]
                if f == e and coff[j] >= o - reverse_tol:
                    continue
                r = edge_len[e] - o + ubodt_lookup(u_ptr, u_tgt, u_dist, e, f) + coff[j]
                if r <= lim:
                    lp = transition_logp_one(r, trav, dt, params, False)
                    if si + lp > best[j - b0]:
                        best[j - b0] = si + lp
                        bp[j] = i
                        bpu[j] = False
            continue
        nt = _search(
            e, edge_len[e] - o, lim, nuniq, out_ptr, out_edges, edge_v, edge_len, edge_rev,
            r_ptr, r_to, r_kind, dist, pred, done, tgt, touched, heap_k, heap_v,
        )  # fmt: skip
        for j in range(b0, b1):
            f = cedge[j]
            if f == e and coff[j] >= o - reverse_tol:
                continue
            r = dist[f] + coff[j]
            if r <= lim:
                lp = transition_logp_one(r, trav, dt, params, False)
                if si + lp > best[j - b0]:
                    best[j - b0] = si + lp
                    bp[j] = i
                    bpu[j] = False
        _reset(nt, touched, dist, pred, done)
    for j in range(b0, b1):
        tgt[cedge[j]] = 0
    reached = False
    for j in range(kb):
        if best[j] > -np.inf:
            reached = True
            score[b0 + j] = best[j] + emis[b0 + j]
        else:
            score[b0 + j] = -np.inf
    return reached


@njit(cache=True)
def _solve(  # type: ignore[no-untyped-def]
    cand_ptr,
    cedge,
    coff,
    emis,
    pxy,
    ptime,
    podo,
    params,
    route_factor,
    route_slack,
    lp_cut_m,
    gap_distance,
    max_skip,
    reverse_tol,
    out_ptr,
    out_edges,
    edge_v,
    edge_len,
    edge_rev,
    r_ptr,
    r_to,
    r_kind,
    dist,
    pred,
    done,
    tgt,
    touched,
    heap_k,
    heap_v,
    u_delta,
    u_ptr,
    u_tgt,
    u_dist,
    u_pred,
):
    """Exact Viterbi over the lattice, routing each step as it goes.

    A point no candidate of the previous accepted point can reach is left out (an outlier);
    after ``max_skip`` such points in a row, or across a distance gap, a new piece starts at
    the first of them. Returns per lattice point the chosen candidate (-1 = left out), whether a
    piece starts there, whether the step into it is an along-road U-turn, and its route bound.
    """
    m = len(cand_ptr) - 1
    nc = len(emis)
    score = np.full(nc, -np.inf)
    bp = np.full(nc, -1, dtype=np.int64)
    bpu = np.zeros(nc, dtype=np.bool_)
    prev_pt = np.full(m, -1, dtype=np.int64)
    accepted = np.zeros(m, dtype=np.bool_)
    seg_start = np.zeros(m, dtype=np.bool_)
    used_bound = np.zeros(m)
    choice = np.full(m, -1, dtype=np.int64)
    via_u = np.zeros(m, dtype=np.bool_)
    if m == 0:
        return choice, seg_start, via_u, used_bound
    kmax = 1
    for t in range(m):
        kmax = max(kmax, cand_ptr[t + 1] - cand_ptr[t])
    order = np.empty(kmax, dtype=np.int64)
    best = np.empty(kmax)
    prev = 0
    accepted[0] = True
    seg_start[0] = True
    for j in range(cand_ptr[0], cand_ptr[1]):
        score[j] = emis[j]
    nskip = 0
    s0 = -1
    t = 1
    d = 0.0
    while t < m or nskip > 1:
        restart = -1
        if t >= m:
            restart = s0  # several trailing points unreachable: they form their own piece
        else:
            d = math.hypot(pxy[t, 0] - pxy[prev, 0], pxy[t, 1] - pxy[prev, 1])
            if d > gap_distance:
                restart = s0 if nskip > 0 else t
        if restart < 0:
            trav = d
            od = podo[t] - podo[prev]
            if np.isfinite(od) and od > 0:
                trav = od
            dt = ptime[t] - ptime[prev]
            bound = route_factor * trav + route_slack
            tight = min(bound, trav + lp_cut_m)
            reached = False
            for npass in range(2):
                lim = tight if npass == 0 else bound
                if npass == 1 and lim <= tight:
                    break
                reached = _step(
                    cand_ptr[prev], cand_ptr[prev + 1], cand_ptr[t], cand_ptr[t + 1], cedge, coff, emis,
                    score, bp, bpu, order, best, params, trav, dt, lim, reverse_tol, out_ptr, out_edges,
                    edge_v, edge_len, edge_rev, r_ptr, r_to, r_kind, dist, pred, done, tgt, touched,
                    heap_k, heap_v, u_delta, u_ptr, u_tgt, u_dist, u_pred,
                )  # fmt: skip
                if reached:
                    break
            if reached:
                accepted[t] = True
                prev_pt[t] = prev
                used_bound[t] = bound
                prev = t
                nskip = 0
                t += 1
                continue
            if nskip == 0:
                s0 = t
            nskip += 1
            if nskip <= max_skip:
                t += 1
                continue
            restart = s0
        # a new piece starts at ``restart``
        accepted[restart] = True
        seg_start[restart] = True
        for j in range(cand_ptr[restart], cand_ptr[restart + 1]):
            score[j] = emis[j]
        prev = restart
        nskip = 0
        t = restart + 1
    # backtrack
    t = m - 1
    while not accepted[t]:
        t -= 1
    j = cand_ptr[t] + np.argmax(score[cand_ptr[t] : cand_ptr[t + 1]])
    while True:
        choice[t] = j
        if seg_start[t]:
            q = t - 1
            while q >= 0 and not accepted[q]:
                q -= 1
            if q < 0:
                break
            t = q
            j = cand_ptr[t] + np.argmax(score[cand_ptr[t] : cand_ptr[t + 1]])
        else:
            via_u[t] = bpu[j]
            j = bp[j]
            t = prev_pt[t]
    return choice, seg_start, via_u, used_bound


@njit(cache=True)
def _pieces(  # type: ignore[no-untyped-def]
    ch_edge,
    ch_off,
    kind,
    bound,
    out_ptr,
    out_edges,
    edge_v,
    edge_len,
    edge_rev,
    r_ptr,
    r_to,
    r_kind,
    dist,
    pred,
    done,
    tgt,
    touched,
    heap_k,
    heap_v,
    u_delta,
    u_ptr,
    u_tgt,
    u_dist,
    u_pred,
):
    """The route as pieces ``(edge, start offset, end offset, segment)`` along the chosen candidates."""
    m = len(ch_edge)
    cap = 2 * m + 16
    pe = np.empty(cap, dtype=np.int64)
    ps = np.empty(cap)
    pend = np.empty(cap)
    pseg = np.empty(cap, dtype=np.int64)
    bad = np.zeros(m, dtype=np.bool_)
    n = 0
    seg = -1
    for t in range(m):
        e = ch_edge[t]
        o = ch_off[t]
        k = kind[t]
        if n + 4 >= cap:
            cap *= 2
            pe = _grow_i(pe, cap)
            ps = _grow_f(ps, cap)
            pend = _grow_f(pend, cap)
            pseg = _grow_i(pseg, cap)
        if k == 0:
            if o > pend[n - 1]:
                pend[n - 1] = o
            continue
        if k == 1:
            L = edge_len[e]
            turn = max(pend[n - 1], L - o)
            pend[n - 1] = turn
            pe[n] = e
            ps[n] = L - turn
            pend[n] = max(o, L - turn)
            pseg[n] = seg
            n += 1
            continue
        if k == 2:
            mid = None
            if u_delta > 0:
                mid = ubodt_path(u_ptr, u_tgt, u_dist, u_pred, ch_edge[t - 1], e)
            if mid is None:
                mid = path_edges(
                    ch_edge[t - 1], ch_off[t - 1], e, bound[t] + 1.0, out_ptr, out_edges, edge_v, edge_len,
                    edge_rev, r_ptr, r_to, r_kind, dist, pred, done, tgt, touched, heap_k, heap_v,
                )  # fmt: skip
            if mid is None:
                bad[t] = True
                k = 3
            else:
                pend[n - 1] = edge_len[ch_edge[t - 1]]
                if n + len(mid) + 4 >= cap:
                    cap = 2 * (n + len(mid) + 4)
                    pe = _grow_i(pe, cap)
                    ps = _grow_f(ps, cap)
                    pend = _grow_f(pend, cap)
                    pseg = _grow_i(pseg, cap)
                for x in mid:
                    pe[n] = x
                    ps[n] = 0.0
                    pend[n] = edge_len[x]
                    pseg[n] = seg
                    n += 1
                pe[n] = e
                ps[n] = 0.0
                pend[n] = o
                pseg[n] = seg
                n += 1
                continue
        # k == 3: a new piece of route
        seg += 1
        pe[n] = e
        ps[n] = o
        pend[n] = o
        pseg[n] = seg
        n += 1
    return pe[:n], ps[:n], pend[:n], pseg[:n], bad


@njit(cache=True)
def _grow_i(a, cap):  # type: ignore[no-untyped-def]
    b = np.empty(cap, dtype=a.dtype)
    b[: len(a)] = a
    return b


@njit(cache=True)
def _grow_f(a, cap):  # type: ignore[no-untyped-def]
    b = np.empty(cap, dtype=a.dtype)
    b[: len(a)] = a
    return b


@njit(cache=True)
def _pieces_xy(pe, ps, pend, seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Polyline coordinates of each piece (consecutive duplicates dropped); ``ptr`` per piece."""
    n = len(pe)
    total = 0
    for i in range(n):
        total += seg_ptr[pe[i] + 1] - seg_ptr[pe[i]] + 2
    out = np.empty((total, 2))
    ptr = np.zeros(n + 1, dtype=np.int64)
    c = 0
    for i in range(n):
        a0 = seg_ptr[pe[i]]
        a1 = seg_ptr[pe[i] + 1]
        s = ps[i]
        e = pend[i]
        acc = 0.0
        for q in range(a0, a1 - 1):
            x0, y0 = seg_xy[q, 0], seg_xy[q, 1]
            x1, y1 = seg_xy[q + 1, 0], seg_xy[q + 1, 1]
            L = math.hypot(x1 - x0, y1 - y0)
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


@njit(cache=True)
def _bearing_at(edges, offs, seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
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


@njit(cache=True)
def _project_on_edges(xy, edges, seg_xy, seg_ptr):  # type: ignore[no-untyped-def]
    """Project each point onto its given edge: offsets, distances and positions."""
    n = len(edges)
    off = np.empty(n)
    dist = np.empty(n)
    pos = np.empty((n, 2))
    for i in range(n):
        a0 = seg_ptr[edges[i]]
        a1 = seg_ptr[edges[i] + 1]
        best = np.inf
        acc = 0.0
        for q in range(a0, a1 - 1):
            x0, y0 = seg_xy[q, 0], seg_xy[q, 1]
            dx = seg_xy[q + 1, 0] - x0
            dy = seg_xy[q + 1, 1] - y0
            L2 = dx * dx + dy * dy
            f = 0.0
            if L2 > 0:
                f = min(max(((xy[i, 0] - x0) * dx + (xy[i, 1] - y0) * dy) / L2, 0.0), 1.0)
            px = x0 + f * dx
            py = y0 + f * dy
            d = math.hypot(xy[i, 0] - px, xy[i, 1] - py)
            if d < best:
                best = d
                off[i] = acc + f * math.sqrt(L2)
                pos[i, 0] = px
                pos[i, 1] = py
            acc += math.sqrt(L2)
        dist[i] = best
    return off, dist, pos
