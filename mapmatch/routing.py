"""Bounded shortest paths on the CSR road graph, compiled with numba.

The search is edge-based (a state is a directed edge, its key the distance to the edge's
start), so turn restrictions and U-turn rules apply exactly. Two ways to get the distances
the batch matcher needs between the candidates of consecutive fixes:

* :func:`_search`: a bounded Dijkstra from one source candidate, stopped as soon as every
  target edge is settled or the bound is passed (no precomputation; the matcher shrinks the
  bound per source, see ``mapmatch.batch``);
* :class:`Ubodt`: an FMM-style upper-bounded origin-destination table, precomputed once per
  map for a bound in metres, then looked up (``bench/bench_batch.py --routing`` measures both).

The moves come from the map's table of legal moves (:mod:`mapmatch.graph.rules`, policy
``"dead_end"``: turning back at a node only at a dead end); a U-turn along the road is a
separate, penalised move the matcher scores itself.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.config import BATCH_CONFIG
from mapmatch.graph.road_graph import RoadGraph
from mapmatch.graph.rules import UTurnPolicy, moves_for

INF = np.inf


class RouteGraph(NamedTuple):
    """The graph arrays the compiled searches read: the legal-moves table
    (``move_to[move_ptr[e]:move_ptr[e + 1]]`` are the edges a route may take after ``e``), the
    edge lengths, the edges' reverse twins (-1 for none) and the positions of the edges' start
    and end nodes, ``edge_xy[e] = (x0, y0, x1, y1)`` (for the straight-line lower bound of
    :func:`_search_toward`). ``move_cost`` is each move's turn cost in metres, added to the
    route's length (:func:`turn_costs`).

    Keep it at six arrays: with the start and end positions as two arrays (seven in all) every
    batch call took about 20 % longer (interleaved A/B, REAL Kubicka tracks), as a thirteenth
    :class:`~mapmatch.batch.arrays.Lattice` array did.
    """

    move_ptr: NDArray[np.int64]
    move_to: NDArray[np.int32]
    move_cost: NDArray[np.float64]
    edge_len: NDArray[np.float64]
    edge_rev: NDArray[np.int32]
    edge_xy: NDArray[np.float64]


def turn_costs(
    graph: RoadGraph, ptr: NDArray[np.int64], to: NDArray[np.int32], cost: float
) -> NDArray[np.float64]:
    """Each move's turn cost: ``cost`` metres times ``(1 - cos θ) / 2`` for the turn angle θ
    between the end of the edge and the start of the next (0 straight on, ``cost`` turning back)."""
    frm = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr))
    theta = np.radians(graph.edge_bearing_start[to] - graph.edge_bearing_end[frm])
    return np.ascontiguousarray(cost * 0.5 * (1.0 - np.cos(theta)), dtype=np.float64)


def route_graph(graph: RoadGraph, *, uturns: UTurnPolicy = "dead_end", turn_cost: float = 0.0) -> RouteGraph:
    """The compiled searches' arrays of ``graph``, moves by :func:`mapmatch.graph.rules.moves_for`
    under the U-turn policy ``uturns`` (the batch matcher's: turning back only at a dead end),
    each costing :func:`turn_costs` of ``turn_cost`` metres (finite, not negative)."""
    if not math.isfinite(turn_cost) or turn_cost < 0:
        raise ValueError(f"turn_cost must be a finite non-negative number of metres, got {turn_cost!r}")
    moves = moves_for(graph, uturns=uturns)
    return RouteGraph(
        move_ptr=np.ascontiguousarray(moves.ptr, dtype=np.int64),
        move_to=np.ascontiguousarray(moves.to, dtype=np.int32),
        move_cost=turn_costs(graph, moves.ptr, moves.to, turn_cost),
        edge_len=np.ascontiguousarray(graph.edge_len, dtype=np.float64),
        edge_rev=np.ascontiguousarray(graph.edge_reverse, dtype=np.int32),
        edge_xy=np.ascontiguousarray(
            np.hstack([graph.node_xy[graph.edge_u], graph.node_xy[graph.edge_v]]), dtype=np.float64
        ),
    )


class Workspace(NamedTuple):
    """Per-thread scratch arrays sized to the graph (reset after each search, never reallocated)."""

    dist: NDArray[np.float64]
    pred: NDArray[np.int32]
    done: NDArray[np.uint8]
    tgt: NDArray[np.uint8]
    touched: NDArray[np.int32]
    heap_k: NDArray[np.float64]
    heap_v: NDArray[np.int32]

    @classmethod
    def new(cls, n_edges: int) -> Workspace:
        """A clean workspace for a graph of ``n_edges`` edges."""
        return cls(
            dist=np.full(n_edges, INF),
            pred=np.full(n_edges, -1, dtype=np.int32),
            done=np.zeros(n_edges, dtype=np.uint8),
            tgt=np.zeros(n_edges, dtype=np.uint8),
            touched=np.empty(n_edges + 1, dtype=np.int32),
            heap_k=np.empty(n_edges + 16, dtype=np.float64),
            heap_v=np.empty(n_edges + 16, dtype=np.int32),
        )


class RouteTable(NamedTuple):
    """A :class:`Ubodt`'s arrays as the compiled kernels read them (``delta < 0``: no table).

    Only what they read: the kernels' tuples cost time per array they carry (see
    :class:`RouteGraph`), so the table's ``pred`` stays out."""

    delta: float
    ptr: NDArray[np.int64]
    tgt: NDArray[np.int32]
    dist: NDArray[np.float64]
    pred_pos: NDArray[np.int32]


NO_TABLE = RouteTable(
    -1.0,
    np.zeros(1, np.int64),
    np.zeros(0, np.int32),
    np.zeros(0),
    np.zeros(0, np.int32),
)
"""The empty table: every route is searched."""


class Router(NamedTuple):
    """Everything a compiled route query reads: the moves, one thread's workspace and the table."""

    g: RouteGraph
    ws: Workspace
    table: RouteTable


@njit(cache=True, nogil=True, inline="always")
def _push(heap_k, heap_v, n: int, k: float, v: int) -> int:  # type: ignore[no-untyped-def]
    i = n
    heap_k[i] = k
    heap_v[i] = v
    while i > 0:
        p = (i - 1) >> 1
        if heap_k[p] <= heap_k[i]:
            break
        heap_k[p], heap_k[i] = heap_k[i], heap_k[p]
        heap_v[p], heap_v[i] = heap_v[i], heap_v[p]
        i = p
    return n + 1


@njit(cache=True, nogil=True, inline="always")
def _pop(heap_k, heap_v, n: int) -> int:  # type: ignore[no-untyped-def]
    n -= 1
    heap_k[0] = heap_k[n]
    heap_v[0] = heap_v[n]
    i = 0
    while True:
        left = 2 * i + 1
        if left >= n:
            break
        c = left
        if left + 1 < n and heap_k[left + 1] < heap_k[left]:
            c = left + 1
        if heap_k[i] <= heap_k[c]:
            break
        heap_k[c], heap_k[i] = heap_k[i], heap_k[c]
        heap_v[c], heap_v[i] = heap_v[i], heap_v[c]
        i = c
    return n


NO_TARGETS = np.zeros(0, dtype=np.int64)
"""No target positions: :func:`_search_toward` is then a plain bounded Dijkstra."""


@njit(cache=True, nogil=True)
def _search(  # type: ignore[no-untyped-def]
    src: int,
    base: float,
    bound: float,
    n_targets: int,
    g,
    ws,
) -> int:
    """Dijkstra from the end of edge ``src`` (``base`` metres ahead of the start point).

    ``dist[f]`` becomes the distance to the start of edge ``f`` (metres of road plus the turn
    costs of the moves, :func:`turn_costs`); stops when ``n_targets``
    edges flagged in ``tgt`` are settled or keys pass ``bound``. Returns the number of
    touched edges (listed in ``touched``; the caller resets them with :func:`_reset`).
    """
    return _search_toward(src, base, bound, n_targets, NO_TARGETS, g, ws)


LOWER_BOUND_SCALE = 1.0 - 1e-6
"""The straight-line lower bound of :func:`_search_toward` is scaled by this, so that rounding
(edge lengths agree with their chords to about 1e-10 m) can never make it exceed a route."""


@njit(cache=True, nogil=True)
def _search_toward(  # type: ignore[no-untyped-def]
    src: int,
    base: float,
    bound: float,
    n_targets: int,
    targets,
    g,
    ws,
) -> int:
    """:func:`_search` with the same answer for the flagged ``targets`` (an A* search).

    The key of an edge is its distance plus a lower bound of the rest of the way to any target:
    the straight line to the first target's start node less the farthest other target's start
    from it (scaled by :data:`LOWER_BOUND_SCALE`). The bound is consistent, so each target is
    settled at its shortest distance, and edges whose key passes ``bound`` cannot lie on a
    route within it: the search covers an ellipse around source and targets, not a disc.
    With no ``targets`` given the lower bound is 0 (plain Dijkstra, :func:`_search`).
    """
    dist, pred, done, tgt, touched, heap_k, heap_v = ws
    move_ptr = g.move_ptr
    move_to = g.move_to
    move_cost = g.move_cost
    edge_len = g.edge_len
    exy = g.edge_xy
    goal = len(targets) > 0
    gx = gy = reach = 0.0
    if goal:
        gx = exy[targets[0], 0]
        gy = exy[targets[0], 1]
    for i in range(1, len(targets)):
        f = targets[i]
        reach = max(reach, math.hypot(exy[f, 0] - gx, exy[f, 1] - gy))
    nt = 0
    nh = 0
    h = 0.0
    if goal:
        h = max(math.hypot(exy[src, 2] - gx, exy[src, 3] - gy) - reach, 0.0) * LOWER_BOUND_SCALE
    if base + h <= bound:
        for i in range(move_ptr[src], move_ptr[src + 1]):
            f = move_to[i]
            c = base + move_cost[i]
            if c < dist[f]:
                if dist[f] == INF:
                    touched[nt] = f
                    nt += 1
                dist[f] = c
                pred[f] = src
                nh = _push(heap_k, heap_v, nh, c + h, f)
    left = n_targets
    while nh > 0 and left != 0:
        e = heap_v[0]
        nh = _pop(heap_k, heap_v, nh)
        if done[e]:
            continue  # a stale entry: the first pop of an edge has its least key
        done[e] = 1
        if tgt[e]:
            left -= 1
        nd = dist[e] + edge_len[e]
        if goal:
            h = max(math.hypot(exy[e, 2] - gx, exy[e, 3] - gy) - reach, 0.0) * LOWER_BOUND_SCALE
        if nd + h > bound:
            continue
        for i in range(move_ptr[e], move_ptr[e + 1]):
            f = move_to[i]
            c = nd + move_cost[i]
            if c < dist[f] and not done[f]:
                if dist[f] == INF:
                    touched[nt] = f
                    nt += 1
                dist[f] = c
                pred[f] = e
                if nh < len(heap_k):
                    nh = _push(heap_k, heap_v, nh, c + h, f)
    return nt


search_toward_inlined = njit(nogil=True, inline="always")(_search_toward.py_func)
""":func:`_search_toward` compiled into its caller (the Viterbi step,
:func:`mapmatch.batch.viterbi._step`: one call less per search)."""


@njit(cache=True, nogil=True, inline="always")
def _reset(nt: int, ws) -> None:  # type: ignore[no-untyped-def]
    for i in range(nt):
        f = ws.touched[i]
        ws.dist[f] = INF
        ws.pred[f] = -1
        ws.done[f] = 0


@njit(cache=True, nogil=True)
def path_edges(  # type: ignore[no-untyped-def]
    src: int,
    src_off: float,
    dst: int,
    bound: float,
    g,
    ws,
):
    """The edges strictly between ``src`` and ``dst`` on the shortest route (None if none)."""
    dist, pred, tgt = ws.dist, ws.pred, ws.tgt
    tgt[dst] = 1
    nt = _search(src, g.edge_len[src] - src_off, bound, 1, g, ws)
    tgt[dst] = 0
    ok = dist[dst] < INF
    out = np.empty(0, dtype=np.int32)
    if ok:
        m = 0
        e = pred[dst]
        while e != src and e >= 0:
            m += 1
            e = pred[e]
        out = np.empty(m, dtype=np.int32)
        e = pred[dst]
        while e != src and e >= 0:
            m -= 1
            out[m] = e
            e = pred[e]
    _reset(nt, ws)
    if not ok:
        return None
    return out


def shortest_route(
    graph: RoadGraph,
    src: int,
    src_off: float,
    dst: int,
    dst_off: float,
    *,
    bound: float = 1e9,
    rg: RouteGraph | None = None,
    ws: Workspace | None = None,
) -> tuple[float, list[int]] | None:
    """Shortest route from a position on ``src`` to one on ``dst``: ``(metres, edges)``.

    ``edges`` runs from ``src`` to ``dst`` inclusive. None when unreachable within ``bound``.
    """
    rg = rg or route_graph(graph)
    ws = ws or Workspace.new(graph.n_edges)
    if src == dst and dst_off >= src_off:
        return dst_off - src_off, [src]
    mid = path_edges(src, src_off, dst, bound, rg, ws)
    if mid is None:
        return None
    edges = [src, *(int(e) for e in mid), dst]
    metres = float(graph.edge_len[src] - src_off + graph.edge_len[edges[1:-1]].sum() + dst_off)
    return metres, edges


def shortest_path(
    graph: RoadGraph,
    from_edge: int,
    to_node: int,
    *,
    weight: NDArray[np.float64] | None = None,
    max_cost: float = np.inf,
    to_edge: int | None = None,
) -> list[int] | None:
    """Cheapest legal edge path from the end of ``from_edge`` to ``to_node`` (no U-turns onto
    a reverse twin, turn restrictions kept: :func:`mapmatch.graph.rules.legal_moves` ``"never"``).

    Returns the edges after ``from_edge`` (empty when ``from_edge`` already ends there), or
    None when unreachable within ``max_cost``. ``weight`` is the cost of each edge (default:
    its length). With ``to_edge`` the path ends with that edge (which must leave ``to_node``).
    """
    if to_edge is None and int(graph.edge_v[from_edge]) == to_node:
        return []
    w = graph.edge_len if weight is None else weight
    moves = moves_for(graph, uturns="never")
    best = {from_edge: 0.0}
    pred: dict[int, int] = {}
    heap = [(0.0, from_edge)]
    while heap:
        c, e = heapq.heappop(heap)
        if c > best.get(e, np.inf) or c > max_cost:
            continue
        if e != from_edge and (e == to_edge if to_edge is not None else int(graph.edge_v[e]) == to_node):
            path = [e]
            while path[-1] in pred and pred[path[-1]] != from_edge:
                path.append(pred[path[-1]])
            return path[::-1]
        for f in moves.after(e):
            cf = c + float(w[f])
            if cf < best.get(f, np.inf):
                best[f] = cf
                pred[f] = e
                heapq.heappush(heap, (cf, f))
    return None


@dataclass(frozen=True)
class Ubodt:
    """Upper-bounded origin-destination table (FMM's UBODT, edge-based).

    For every edge ``e``, the edges ``f`` whose start is within ``delta`` metres (turn costs
    counted, as in the searches) of the end of
    ``e`` (turn rules applied), sorted by ``f``: ``tgt[ptr[e]:ptr[e+1]]`` with the distances in
    ``dist`` and the edge before ``f`` on the route in ``pred`` (``e`` itself for a neighbour),
    whose place in the same row is ``pred_pos`` (-1 for a neighbour), so a route is read back
    hop by hop without searching. A route query within the bound is then a binary search
    instead of a search.
    """

    delta: float
    ptr: NDArray[np.int64]
    tgt: NDArray[np.int32]
    dist: NDArray[np.float64]
    pred: NDArray[np.int32]
    pred_pos: NDArray[np.int32]
    turn_cost: float = 0.0
    """The turn cost its routes were found with (:func:`route_graph`); a matcher uses the
    table only for a config with the same ``turn_cost``."""

    @classmethod
    def build(
        cls,
        graph: RoadGraph,
        delta: float,
        *,
        turn_cost: float | None = None,
        max_bytes: int | None = None,
    ) -> Ubodt:
        """Precompute the table for ``delta`` metres (time and memory grow fast with it), routes
        costing ``turn_cost`` metres per turn back (:func:`turn_costs`; by default the batch
        matcher's, ``BATCH_CONFIG.turn_cost``).

        With ``max_bytes``, the bound is first lowered until the table's estimated size
        (:func:`ubodt_estimate`) fits: a dense map then gets a shorter table, not an
        out-of-memory error. The matches stay the same, as routes beyond a table's bound are
        searched; the table's ``delta`` is the bound it was built for.
        """
        if not (math.isfinite(delta) and delta > 0):
            raise ValueError(f"delta must be a positive number of metres, got {delta!r}")
        if max_bytes is not None and not max_bytes > 0:
            raise ValueError(f"max_bytes must be a positive number of bytes, got {max_bytes!r}")
        if turn_cost is None:
            turn_cost = float(BATCH_CONFIG.turn_cost)
        ws = Workspace.new(graph.n_edges)
        rg = route_graph(graph, turn_cost=turn_cost)
        delta, entries = _fit_delta(float(delta), max_bytes, graph.n_edges, rg, ws)
        cap = int(entries * ESTIMATE_HEADROOM) + 16  # no doubling, no copy: a lower peak
        ptr, tgt, dist, pred, pos = _build_ubodt(delta, graph.n_edges, rg, ws, cap)
        return cls(delta, ptr, tgt, dist, pred, pos, float(turn_cost))

    @property
    def table(self) -> RouteTable:
        """The arrays as the compiled kernels read them."""
        return RouteTable(self.delta, self.ptr, self.tgt, self.dist, self.pred_pos)

    @property
    def nbytes(self) -> int:
        return int(
            self.ptr.nbytes + self.tgt.nbytes + self.dist.nbytes + self.pred.nbytes + self.pred_pos.nbytes
        )


UBODT_ENTRY_BYTES = 4 + 8 + 4 + 4
"""Bytes per entry of a :class:`Ubodt` (``tgt``, ``dist``, ``pred``, ``pred_pos``); each edge
adds 8 (``ptr``)."""

ESTIMATE_SAMPLE = 512
"""Rows searched to estimate a table's size (edges evenly spaced in the map's spatial order)."""

FIT_STEPS = 6
"""Bisection steps of a bound lowered to fit a memory budget (within 1/64 of the last halving)."""

ESTIMATE_HEADROOM = 1.15
"""The build's first allocation over the estimated entries (it grows if the estimate was low)."""


def ubodt_estimate(graph: RoadGraph, delta: float, *, turn_cost: float | None = None) -> int:
    """The estimated size in bytes of ``Ubodt.build(graph, delta, turn_cost=turn_cost)``, from
    the rows of :data:`ESTIMATE_SAMPLE` edges evenly spaced through the map's edges (a map
    prepared by :func:`mapmatch.graph.build.build_map` stores them in spatial order, so the
    sample spreads over the map)."""
    if turn_cost is None:
        turn_cost = float(BATCH_CONFIG.turn_cost)
    rg = route_graph(graph, turn_cost=turn_cost)
    entries = _estimate_entries(float(delta), graph.n_edges, rg, Workspace.new(graph.n_edges))
    return _table_bytes(entries, graph.n_edges)


def _table_bytes(entries: float, n_edges: int) -> int:
    return int(entries * UBODT_ENTRY_BYTES + 8 * (n_edges + 1))


def _estimate_entries(delta: float, n_edges: int, g: RouteGraph, ws: Workspace) -> float:
    if n_edges == 0:
        return 0.0
    sample = np.unique(np.linspace(0, n_edges - 1, min(n_edges, ESTIMATE_SAMPLE)).astype(np.int64))
    rows = _row_lengths(delta, sample, g, ws)
    return float(rows.mean()) * n_edges


def _fit_delta(
    delta: float, max_bytes: int | None, n_edges: int, g: RouteGraph, ws: Workspace
) -> tuple[float, float]:
    """The largest bound up to ``delta`` whose estimated table fits ``max_bytes`` (``None``:
    ``delta``), to within :data:`FIT_STEPS` halvings of the last step, and its estimated
    entries."""
    entries = _estimate_entries(delta, n_edges, g, ws)
    if max_bytes is None or _table_bytes(entries, n_edges) <= max_bytes:
        return delta, entries
    hi = lo = delta
    while lo >= 1.0:  # halve until it fits
        hi, lo = lo, lo / 2
        entries = _estimate_entries(lo, n_edges, g, ws)
        if _table_bytes(entries, n_edges) <= max_bytes:
            break
    for _ in range(FIT_STEPS):  # then bisect between the bounds that fit and that do not
        mid = (lo + hi) / 2
        e = _estimate_entries(mid, n_edges, g, ws)
        if _table_bytes(e, n_edges) <= max_bytes:
            lo, entries = mid, e
        else:
            hi = mid
    return lo, entries


@njit(cache=True, nogil=True)
def _row_lengths(delta, edges, g, ws):  # type: ignore[no-untyped-def]
    """The number of entries of each of ``edges``'s table rows (as :func:`_build_ubodt` fills them)."""
    out = np.zeros(len(edges), dtype=np.int64)
    for k in range(len(edges)):
        nt = _search(edges[k], 0.0, delta, -1, g, ws)
        for i in range(nt):
            f = ws.touched[i]
            if ws.done[f] and ws.dist[f] <= delta:
                out[k] += 1
        _reset(nt, ws)
    return out


@njit(cache=True, nogil=True)
def _build_ubodt(  # type: ignore[no-untyped-def]
    delta,
    n_edges,
    g,
    ws,
    cap,
):
    dist, pred, done, touched = ws.dist, ws.pred, ws.done, ws.touched
    ptr = np.zeros(n_edges + 1, dtype=np.int64)
    out_t = np.empty(cap, dtype=np.int32)
    out_d = np.empty(cap)
    out_p = np.empty(cap, dtype=np.int32)
    m = 0
    for e in range(n_edges):
        nt = _search(e, 0.0, delta, -1, g, ws)
        if m + nt > cap:
            cap = 2 * (m + nt)
            t2 = np.empty(cap, dtype=np.int32)
            t2[:m] = out_t[:m]
            d2 = np.empty(cap)
            d2[:m] = out_d[:m]
            p2 = np.empty(cap, dtype=np.int32)
            p2[:m] = out_p[:m]
            out_t, out_d, out_p = t2, d2, p2
        start = m
        for i in range(nt):
            f = touched[i]
            if done[f] and dist[f] <= delta:
                out_t[m] = f
                out_d[m] = dist[f]
                out_p[m] = pred[f]
                m += 1
        order = np.argsort(out_t[start:m])
        st = out_t[start:m][order].copy()
        sd = out_d[start:m][order].copy()
        sp = out_p[start:m][order].copy()
        out_t[start:m] = st
        out_d[start:m] = sd
        out_p[start:m] = sp
        ptr[e + 1] = m
        _reset(nt, ws)
    # each entry's predecessor as a place in its row (-1: the row's own edge)
    pos = np.full(m, -1, dtype=np.int32)
    for e in range(n_edges):
        a, b = ptr[e], ptr[e + 1]
        for k in range(a, b):
            p = out_p[k]
            if p != e:
                q = np.searchsorted(out_t[a:b], p)
                if q < b - a and out_t[a + q] == p:
                    pos[k] = q
    if 4 * cap <= 5 * m:  # within a quarter of the size: keep the arrays rather than copy them
        return ptr, out_t[:m], out_d[:m], out_p[:m], pos
    return ptr, out_t[:m].copy(), out_d[:m].copy(), out_p[:m].copy(), pos


@njit(cache=True, nogil=True, inline="always")
def _row_place(table, e: int, f: int) -> int:  # type: ignore[no-untyped-def]
    """The place of ``f`` in the table's row of ``e`` (a binary search), -1 when not in it."""
    ptr, tgt = table.ptr, table.tgt
    lo = ptr[e]
    hi = ptr[e + 1]
    while lo < hi:
        mid = (lo + hi) >> 1
        if tgt[mid] < f:
            lo = mid + 1
        else:
            hi = mid
    if lo < ptr[e + 1] and tgt[lo] == f:
        return lo
    return -1


@njit(cache=True, nogil=True, inline="always")
def ubodt_lookup(table, e: int, f: int) -> float:  # type: ignore[no-untyped-def]
    """Distance (with turn costs) from the end of ``e`` to the start of ``f`` if within the table,
    else inf."""
    k = _row_place(table, e, f)
    return table.dist[k] if k >= 0 else INF


@njit(cache=True, nogil=True)
def ubodt_path(table, src: int, dst: int):  # type: ignore[no-untyped-def]
    """The edges strictly between ``src`` and ``dst`` from the table (None if not in it)."""
    pos, tgt = table.pred_pos, table.tgt
    a = table.ptr[src]
    lo = _row_place(table, src, dst)
    if lo < 0:
        return None
    m = 0
    k = pos[lo]
    while k >= 0:
        m += 1
        k = pos[a + k]
    out = np.empty(m, dtype=np.int32)
    k = pos[lo]
    while k >= 0:
        m -= 1
        out[m] = tgt[a + k]
        k = pos[a + k]
    return out
