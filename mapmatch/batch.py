"""Batch map matching of historic tracks: exact Viterbi over the whole track (Newson & Krumm 2009).

Candidates for all points come from one vectorised index query; emissions and transitions
from the shared :mod:`mapmatch.model`; route distances from bounded edge-based Dijkstra
(:mod:`mapmatch.routing`); the lattice recursion and the path assembly are compiled with numba.
The matched route is always connected through the network; it is split only where the track
has a time/distance gap or no route exists between consecutive points (both reported).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch import model
from mapmatch.config import BATCH_CONFIG, MatchConfig
from mapmatch.graph.index import Candidates, EdgeIndex, project_point_compiled
from mapmatch.graph.projection import to_lonlat, to_xy
from mapmatch.graph.road_graph import RoadGraph, merge_repeats
from mapmatch.gridindex import GridIndex, grow_array
from mapmatch.model import emission_logp_one, transition_logp_one
from mapmatch.routing import (
    Ubodt,
    Workspace,
    _reset,
    _search,
    path_edges,
    route_graph,
    search_args,
    ubodt_lookup,
    ubodt_path,
)
from mapmatch.types import MatchedPoint, PointStatus, Track, TrackMatch

NEG_INF = -np.inf


@njit(cache=True, inline="always")
def _project_one(seg_xy, seg_ptr, e, x, y):  # type: ignore[no-untyped-def]
    """Offset, distance and position of point ``(x, y)`` projected onto edge ``e``."""
    off, dist, px, py, _ = project_point_compiled(seg_xy, seg_ptr[e], seg_ptr[e + 1], x, y, np.inf, 0.0)
    return off, dist, px, py


STEP_SAME, STEP_UTURN, STEP_ROUTE, STEP_SPLIT = 0, 1, 2, 3


class BatchMatcher:
    """Matches whole tracks against one road graph (read-only, reusable, thread-safe).

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
        self._rg = route_graph(graph, uturns="dead_end")
        self._seg_xy = np.ascontiguousarray(graph.seg_xy, dtype=np.float64)
        self._seg_ptr = np.ascontiguousarray(graph.edge_seg_ptr, dtype=np.int64)
        self._local = threading.local()

    @property
    def _kargs(self) -> tuple[Any, ...]:
        """The compiled kernels' trailing arguments, with this thread's routing workspace
        (built once per thread, so one matcher serves many threads)."""
        args: tuple[Any, ...] | None = getattr(self._local, "kargs", None)
        if args is None:
            ws = Workspace(self.graph.n_edges)
            args = self._local.kargs = (*search_args(self._rg, ws), *self._ubodt_args)
        return args

    def match(self, track: Track, config: MatchConfig | None = None, *, lonlat: bool = True) -> TrackMatch:
        """Match one track; bad points become unmatched, never an exception for the track.

        With ``lonlat=False`` the route geometry is left in the map's CRS (``route_xy``) and the
        per-point results in arrays (``point_arrays``); :func:`fill_route_lonlat` later fills
        ``route_lonlat`` and ``points`` from them.
        """
        cfg = config or self.config
        g = self.graph
        n = len(track)
        lat = np.asarray(track.lat, dtype=np.float64)
        lon = np.asarray(track.lon, dtype=np.float64)
        tim = _opt(track.time, n)
        valid = np.isfinite(lat) & np.isfinite(lon) & (np.abs(lat) <= 90) & (np.abs(lon) <= 180)
        if valid.all():
            xy = to_xy(g.crs, lon, lat)
        else:
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
        sigma: float | NDArray[np.float64] = float(model.position_sigma(np.nan, cfg))
        if track.pos_sigma is not None:
            sigma = model.position_sigma(np.asarray(track.pos_sigma, dtype=np.float64)[kidx], cfg)[
                cands.point
            ]
        heading = None if track.heading is None else np.asarray(track.heading, dtype=np.float64)[kidx]
        if heading is not None and np.isfinite(heading).any():
            kappa = model.heading_kappa(heading, np.nan, _opt(track.speed, n)[kidx], cfg)[cands.point]
            bearing = _bearing_at(cands.edge, cands.offset, self._seg_xy, self._seg_ptr)
            emis = model.emission_logp(cands.dist, sigma, heading[cands.point], bearing, kappa)
        elif np.ndim(sigma):
            emis = model.emission_logp(cands.dist, sigma, np.nan, 0.0, 0.0)
        else:
            emis = np.zeros(0)  # one σ, no heading: computed in the compiled kernel
        odo_cum = np.zeros(0)
        if track.distance is not None:
            odo = np.asarray(track.distance, dtype=np.float64)
            odo_cum = np.where(np.isfinite(odo), np.cumsum(np.where(np.isfinite(odo), odo, 0.0)), np.nan)
        # one compiled call: pruning, Viterbi, route pieces and per-point results
        out = _run(  # type: ignore[call-arg]
            n, valid, kept, xy, tim, odo_cum, kidx, cands.point, cands.edge, cands.offset, cands.xy,
            cands.dist, emis, sigma if isinstance(sigma, float) else 0.0, float(cfg.emission_prune),
            float(cfg.outlier_distance), model.transition_params(cfg),
            np.array([cfg.stop_uturn_speed, cfg.stop_uturn_time, cfg.stop_uturn_penalty], dtype=np.float64),
            float(cfg.max_route_factor), float(cfg.route_slack), float(cfg.beta * cfg.route_lp_cut),
            float(cfg.gap_distance), int(cfg.max_skip), float(cfg.reverse_tolerance), self._seg_xy,
            self._seg_ptr, *self._kargs,
        )  # fmt: skip
        res = _result(str(track.track_id), *out)
        if lonlat:
            fill_route_lonlat(res, g.crs)
        return res


def _result(
    track_id: str,
    p_edge: NDArray[np.int64],
    p_off: NDArray[np.float64],
    p_xy: NDArray[np.float64],
    p_dist: NDArray[np.float64],
    status: NDArray[np.int8],
    splits: NDArray[np.int64],
    route_e: NDArray[np.int64],
    route_ptr: NDArray[np.int64],
    xy_all: NDArray[np.float64],
    rxy_ptr: NDArray[np.int64],
    length: float,
    conf: float,
) -> TrackMatch:
    """A :class:`TrackMatch` from the compiled kernel's arrays (points still as arrays)."""
    res = TrackMatch(
        track_id=track_id, splits=splits.tolist(), length_m=float(length), confidence=float(conf)
    )
    for s in range(len(route_ptr) - 1):
        res.routes.append(route_e[route_ptr[s] : route_ptr[s + 1]].tolist())
        seg = xy_all[rxy_ptr[s] : rxy_ptr[s + 1]]
        res.route_xy.append(np.vstack([seg, seg]) if len(seg) == 1 else seg)
    res.point_arrays = (status, p_edge, p_off, p_xy, p_dist)
    return res


def fill_route_lonlat(result: TrackMatch, crs: str) -> TrackMatch:
    """Fill ``route_lonlat`` from ``route_xy`` and ``points`` from ``point_arrays`` (one projection)."""
    pa = result.point_arrays
    ok = np.zeros(0, dtype=bool)
    parts = list(result.route_xy)
    if pa is not None:
        ok = pa[0] > 0
        parts.append(pa[3][ok])
    ll = to_lonlat(crs, *np.concatenate(parts).T) if parts else np.zeros((0, 2))
    out: list[list[tuple[float, float]]] = []
    i = 0
    for piece in result.route_xy:
        out.append(list(map(tuple, ll[i : i + len(piece)].tolist())))
        i += len(piece)
    result.route_lonlat = out
    if pa is not None:
        status, p_edge, p_off, _, p_dist = pa
        p_ll = np.full((len(status), 2), np.nan)
        p_ll[ok] = ll[i:]
        stat = (PointStatus.UNMATCHED, PointStatus.MATCHED, PointStatus.INTERPOLATED)
        lat, lon = p_ll[:, 1].tolist(), p_ll[:, 0].tolist()
        result.points = [
            MatchedPoint(i, stat[s], e, o, la, lo, d)
            for i, (s, e, o, la, lo, d) in enumerate(
                zip(
                    status.tolist(), p_edge.tolist(), p_off.tolist(), lat, lon,
                    p_dist.tolist(), strict=True,
                )
            )
        ]  # fmt: skip
        result.point_arrays = None
    return result


def route_ways(result: TrackMatch, graph: RoadGraph) -> tuple[list[int], list[str]]:
    """The way ids and names the matched route runs along, in order, consecutive repeats merged.

    Each connected part of the route starts at the way piece under its first placed point
    and ends at the piece under its last one (an edge can be made of several ways).
    """
    bounds = [0, *result.splits, len(result.points)]
    ways: list[int] = []
    names: list[str] = []
    for s, edges in enumerate(result.routes):
        if not edges:
            continue
        pts = (
            [p for p in result.points[bounds[s] : bounds[s + 1]] if p.edge >= 0]
            if s + 1 < len(bounds)
            else []
        )
        start = pts[0].offset if pts and pts[0].edge == edges[0] else 0.0
        end = pts[-1].offset if pts and pts[-1].edge == edges[-1] else math.inf
        w, n = graph.route_ways(edges, start=start, end=end)
        ways += w
        names += n
    return merge_repeats(ways), merge_repeats(names)


def point_ways(result: TrackMatch, graph: RoadGraph) -> tuple[list[int], list[str]]:
    """Per point, the way id and name of the way piece under it (-1 and "" when unplaced)."""
    e = np.array([p.edge for p in result.points], dtype=np.int64)
    off = np.array([p.offset for p in result.points], dtype=np.float64)
    piece = graph.piece_at(e, np.nan_to_num(off))
    ok = piece >= 0
    way = np.where(ok, graph.piece_way_id[np.maximum(piece, 0)] if graph.n_pieces else -1, -1)
    name_idx = np.where(ok, graph.piece_name_idx[np.maximum(piece, 0)] if graph.n_pieces else -1, -1)
    return way.tolist(), [graph.names[i] if i >= 0 else "" for i in name_idx.tolist()]


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
    return np.full(n, np.nan) if a is None else np.ascontiguousarray(a, dtype=np.float64)


# ---------------------------------------------------------------------- compiled kernels
@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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
    node_uturn,
    trav,
    dt,
    bound,
    reverse_tol,
    g,
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
    edge_len = g.edge_len
    edge_rev = g.edge_rev
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
                    if node_uturn < params[3] and edge_len[e] - o <= reverse_tol and coff[j] <= reverse_tol:
                        # turning round at the junction (within reverse_tol) after a stop
                        lp += params[3] - node_uturn
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
            e, edge_len[e] - o, lim, nuniq, g, dist, pred, done, tgt, touched, heap_k, heap_v,
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


@njit(cache=True, nogil=True)
def _solve(  # type: ignore[no-untyped-def]
    cand_ptr,
    cedge,
    coff,
    emis,
    pxy,
    ptime,
    podo,
    params,
    stop_params,
    route_factor,
    route_slack,
    lp_cut_m,
    gap_distance,
    max_skip,
    reverse_tol,
    g,
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
            reached, bound = _try_step(
                prev, t, d, cand_ptr, cedge, coff, emis, pxy, ptime, podo, score, bp, bpu, order, best,
                params, stop_params, route_factor, route_slack, lp_cut_m, reverse_tol, g, dist, pred, done,
                tgt, touched, heap_k, heap_v, u_delta, u_ptr, u_tgt, u_dist, u_pred,
            )  # fmt: skip
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
            # before splitting: maybe the last accepted points were the outliers (a drift onto a
            # road that does not lead on); reach s0 from up to max_skip points before them
            q = prev_pt[prev]
            back = 0
            while q >= 0 and back < max_skip:
                dq = math.hypot(pxy[s0, 0] - pxy[q, 0], pxy[s0, 1] - pxy[q, 1])
                if dq > gap_distance:
                    break
                reached, bound = _try_step(
                    q, s0, dq, cand_ptr, cedge, coff, emis, pxy, ptime, podo, score, bp, bpu, order, best,
                    params, stop_params, route_factor, route_slack, lp_cut_m, reverse_tol, g, dist, pred,
                    done, tgt, touched, heap_k, heap_v, u_delta, u_ptr, u_tgt, u_dist, u_pred,
                )  # fmt: skip
                if reached:
                    for r in range(q + 1, s0):
                        accepted[r] = False
                    accepted[s0] = True
                    prev_pt[s0] = q
                    used_bound[s0] = bound
                    restart = -1
                    break
                q = prev_pt[q]
                back += 1
            if restart < 0:
                prev = s0
                nskip = 0
                t = s0 + 1
                continue
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


@njit(cache=True, nogil=True)
def _pieces(  # type: ignore[no-untyped-def]
    ch_edge,
    ch_off,
    kind,
    bound,
    g,
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
    edge_len = g.edge_len
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
            pe = grow_array(pe, cap)
            ps = grow_array(ps, cap)
            pend = grow_array(pend, cap)
            pseg = grow_array(pseg, cap)
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
                    ch_edge[t - 1], ch_off[t - 1], e, bound[t] + 1.0, g, dist, pred, done, tgt, touched,
                    heap_k, heap_v,
                )  # fmt: skip
            if mid is None:
                bad[t] = True
                k = 3
            else:
                pend[n - 1] = edge_len[ch_edge[t - 1]]
                if n + len(mid) + 4 >= cap:
                    cap = 2 * (n + len(mid) + 4)
                    pe = grow_array(pe, cap)
                    ps = grow_array(ps, cap)
                    pend = grow_array(pend, cap)
                    pseg = grow_array(pseg, cap)
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _prune(nk, cpoint, cedge, coff, cxy, cdist, emis, prune, outlier):  # type: ignore[no-untyped-def]
    """Drop candidates far below their point's best emission or beyond ``outlier`` metres.

    Candidates come sorted by point. Returns the kept ones with their per-point pointer (over
    the points that keep any) and which of the ``nk`` points keep any.
    """
    nc = len(cpoint)
    best = np.full(nk, -np.inf)
    for c in range(nc):
        if emis[c] > best[cpoint[c]]:
            best[cpoint[c]] = emis[c]
    keep = np.zeros(nc, dtype=np.bool_)
    counts = np.zeros(nk, dtype=np.int64)
    nkeep = 0
    for c in range(nc):
        if emis[c] >= best[cpoint[c]] - prune and cdist[c] <= outlier:
            keep[c] = True
            counts[cpoint[c]] += 1
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
    oe = np.empty(nkeep, dtype=cedge.dtype)
    oo = np.empty(nkeep)
    ox = np.empty((nkeep, 2))
    od = np.empty(nkeep)
    om = np.empty(nkeep)
    k = 0
    for c in range(nc):
        if keep[c]:
            oe[k] = cedge[c]
            oo[k] = coff[c]
            ox[k, 0] = cxy[c, 0]
            ox[k, 1] = cxy[c, 1]
            od[k] = cdist[c]
            om[k] = emis[c]
            k += 1
    return ptr, oe, oo, ox, od, om, has


@njit(cache=True, nogil=True)
def _finish(  # type: ignore[no-untyped-def]
    n,
    valid,
    kept,
    xy,
    pts_all,
    choice_all,
    seg_start,
    via_u,
    used_bound,
    cand_ptr,
    cedge,
    coff,
    cxy,
    cdist,
    emis,
    seg_xy,
    seg_ptr,
    reverse_tol,
    g,
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
    """Per-point results, route pieces (edges and geometry), splits, length and confidence."""
    edge_rev = g.edge_rev
    p_edge = np.full(n, -1, dtype=np.int64)
    p_off = np.full(n, np.nan)
    p_xy = np.full((n, 2), np.nan)
    p_dist = np.full(n, np.nan)
    status = np.zeros(n, dtype=np.int8)  # 0 unmatched, 1 matched, 2 interpolated
    # lattice points left out as unreachable outliers are unmatched
    m = 0
    for t in range(len(choice_all)):
        if choice_all[t] >= 0:
            m += 1
    acc = np.empty(m, dtype=np.int64)
    q = 0
    for t in range(len(choice_all)):
        if choice_all[t] >= 0:
            acc[q] = t
            q += 1
    nvalid = 0
    for i in range(n):
        if valid[i]:
            nvalid += 1
    if m == 0:
        return (
            p_edge, p_off, p_xy, p_dist, status, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
            np.zeros(1, dtype=np.int64), np.zeros((0, 2)), np.zeros(1, dtype=np.int64), 0.0, 0.0,
        )  # fmt: skip
    ch_edge = np.empty(m, dtype=np.int64)
    ch_off = np.empty(m)
    kind = np.empty(m, dtype=np.int64)
    bound = np.empty(m)
    pts = np.empty(m, dtype=np.int64)
    post = 0.0
    for i in range(m):
        t = acc[i]
        j = choice_all[t]
        e = cedge[j]
        ch_edge[i] = e
        ch_off[i] = coff[j]
        pts[i] = pts_all[t]
        bound[i] = used_bound[t]
        same = i > 0 and e == ch_edge[i - 1] and coff[j] >= ch_off[i - 1] - reverse_tol
        if i == 0 or seg_start[t]:
            kind[i] = STEP_SPLIT
        elif same:
            kind[i] = STEP_SAME
        elif via_u[t]:
            kind[i] = STEP_UTURN
        else:
            kind[i] = STEP_ROUTE
        p = pts[i]
        p_edge[p] = e
        p_off[p] = coff[j]
        p_xy[p, 0] = cxy[j, 0]
        p_xy[p, 1] = cxy[j, 1]
        p_dist[p] = cdist[j]
        status[p] = 1
        # confidence: normalised emission of the chosen road (both directions of a two-way
        # road count as one) among the point's candidates
        c0 = cand_ptr[t]
        c1 = cand_ptr[t + 1]
        mx = -np.inf
        for c in range(c0, c1):
            mx = max(mx, emis[c])
        road = min(e, edge_rev[e]) if edge_rev[e] >= 0 else e
        tot = 0.0
        mine = 0.0
        for c in range(c0, c1):
            w = math.exp(emis[c] - mx)
            tot += w
            f = cedge[c]
            rf = min(f, edge_rev[f]) if edge_rev[f] >= 0 else f
            if rf == road:
                mine += w
        post += mine / tot
    pe, ps, pend, pseg, bad = _pieces(
        ch_edge, ch_off, kind, bound, g, dist, pred, done, tgt, touched, heap_k, heap_v, u_delta, u_ptr,
        u_tgt, u_dist, u_pred,
    )  # fmt: skip
    # a failed path (should not happen: Viterbi chose a reachable pair) becomes a split
    nsplit = 0
    for i in range(1, m):
        if kind[i] == STEP_SPLIT or bad[i]:
            nsplit += 1
    splits = np.empty(nsplit, dtype=np.int64)
    q = 0
    for i in range(1, m):
        if kind[i] == STEP_SPLIT or bad[i]:
            splits[q] = pts[i]
            q += 1
    xy_all, xptr = _pieces_xy(pe, ps, pend, seg_xy, seg_ptr)
    npc = len(pe)
    nseg = pseg[npc - 1] + 1 if npc else 0
    route_e = np.empty(npc, dtype=np.int64)
    route_ptr = np.zeros(nseg + 1, dtype=np.int64)
    rxy_ptr = np.zeros(nseg + 1, dtype=np.int64)
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
    # interpolated points: projected onto the chosen edge of the nearer kept neighbour
    q = 0
    for i in range(n):
        if not valid[i] or kept[i]:
            continue
        while q < m and pts[q] < i:
            q += 1
        prv = max(q - 1, 0)
        nxt = min(q, m - 1)
        o1, d1, x1, y1 = _project_one(seg_xy, seg_ptr, ch_edge[prv], xy[i, 0], xy[i, 1])
        o2, d2, x2, y2 = _project_one(seg_xy, seg_ptr, ch_edge[nxt], xy[i, 0], xy[i, 1])
        if d2 < d1:
            p_edge[i], p_off[i], p_xy[i, 0], p_xy[i, 1], p_dist[i] = ch_edge[nxt], o2, x2, y2, d2
        else:
            p_edge[i], p_off[i], p_xy[i, 0], p_xy[i, 1], p_dist[i] = ch_edge[prv], o1, x1, y1, d1
        status[i] = 2
    conf = post / max(nvalid, 1)
    return p_edge, p_off, p_xy, p_dist, status, splits, route_e[:k], route_ptr, xy_all, rxy_ptr, length, conf


@njit(cache=True, nogil=True)
def _run(  # type: ignore[no-untyped-def]
    n,
    valid,
    kept,
    xy,
    tim,
    odo_cum,
    kidx,
    cpoint,
    cedge,
    coff,
    cxy,
    cdist,
    emis,
    sigma,
    prune,
    outlier,
    params,
    stop_params,
    route_factor,
    route_slack,
    lp_cut_m,
    gap_distance,
    max_skip,
    reverse_tol,
    seg_xy,
    seg_ptr,
    g,
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
    """Pruning (:func:`_prune`), Viterbi (:func:`_solve`) and results (:func:`_finish`) in one call.

    An empty ``emis`` means distance-only emissions with one ``sigma``, computed here.
    """
    if len(emis) != len(cdist):
        emis = np.empty(len(cdist))
        for c in range(len(cdist)):
            emis[c] = emission_logp_one(cdist[c], sigma, 0.0, 0.0, 0.0)
    cand_ptr, ce, co, cx, cd, em, has = _prune(
        len(kidx), cpoint, cedge, coff, cxy, cdist, emis, prune, outlier
    )
    pts = kidx[has]  # track indices of the lattice's points (those with candidates)
    m = len(pts)
    pxy = np.empty((m, 2))
    ptime = np.empty(m)
    podo = np.full(m, np.nan)
    for i in range(m):
        pxy[i, 0] = xy[pts[i], 0]
        pxy[i, 1] = xy[pts[i], 1]
        ptime[i] = tim[pts[i]]
        if len(odo_cum):
            podo[i] = odo_cum[pts[i]]
    choice, seg_start, via_u, used_bound = _solve(
        cand_ptr, ce, co, em, pxy, ptime, podo, params, stop_params, route_factor, route_slack, lp_cut_m,
        gap_distance, max_skip, reverse_tol, g, dist, pred, done, tgt, touched, heap_k, heap_v, u_delta,
        u_ptr, u_tgt, u_dist, u_pred,
    )  # fmt: skip
    return _finish(
        n, valid, kept, xy, pts, choice, seg_start, via_u, used_bound, cand_ptr, ce, co, cx, cd, em, seg_xy,
        seg_ptr, reverse_tol, g, dist, pred, done, tgt, touched, heap_k, heap_v, u_delta, u_ptr, u_tgt,
        u_dist, u_pred,
    )  # fmt: skip


@njit(cache=True, nogil=True)
def _try_step(  # type: ignore[no-untyped-def]
    prev,
    t,
    d,
    cand_ptr,
    cedge,
    coff,
    emis,
    pxy,
    ptime,
    podo,
    score,
    bp,
    bpu,
    order,
    best,
    params,
    stop_params,
    route_factor,
    route_slack,
    lp_cut_m,
    reverse_tol,
    g,
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
    """The Viterbi step from lattice point ``prev`` to ``t`` (``d`` metres apart): a tight search
    bound first, the full bound only if nothing is reached. Returns (reached, full bound)."""
    trav = d
    od = podo[t] - podo[prev]
    if np.isfinite(od) and od > 0:
        trav = od
    dt = ptime[t] - ptime[prev]
    bound = route_factor * trav + route_slack
    tight = min(bound, trav + lp_cut_m)
    # ``stop_params`` = (stop speed, stop time, U-turn penalty across a stop)
    node_uturn = params[3]
    if dt >= stop_params[1] and d < stop_params[0] * dt:
        node_uturn = min(node_uturn, stop_params[2])
    reached = False
    for npass in range(2):
        lim = tight if npass == 0 else bound
        if npass == 1 and lim <= tight:
            break
        reached = _step(
            cand_ptr[prev], cand_ptr[prev + 1], cand_ptr[t], cand_ptr[t + 1], cedge, coff, emis, score, bp,
            bpu, order, best, params, node_uturn, trav, dt, lim, reverse_tol, g, dist, pred, done, tgt,
            touched, heap_k, heap_v, u_delta, u_ptr, u_tgt, u_dist, u_pred,
        )  # fmt: skip
        if reached:
            break
    return reached, bound
