"""Bounded shortest paths on the CSR road graph, compiled with numba.

The search is edge-based (a state is a directed edge, its key the distance to the edge's
start), so turn restrictions and U-turn rules apply exactly. Two ways to get the distances
the batch matcher needs between the candidates of consecutive fixes:

* :func:`_search`: a bounded Dijkstra from one source candidate, stopped as soon as every
  target edge is settled or the bound is passed (no precomputation; the matcher shrinks the
  bound per source, see ``mapmatch.batch``);
* :class:`mapmatch.route_table.Ubodt`: an FMM-style upper-bounded origin-destination table,
  precomputed once per map for a bound in metres, then looked up (``bench/bench_batch.py
  --routing`` compares the two).

The moves come from the map's table of legal moves (:mod:`graph.rules`, policy
``"dead_end"``: turning back at a node only at a dead end); a U-turn along the road is a
separate, penalised move the matcher scores itself.
"""

from __future__ import annotations

import heapq
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit, py_func, read_only
from graph.road_graph import RoadGraph
from graph.rules import UTurnPolicy, moves_for
from mapmatch.arena import int64

INF = np.inf


class RouteGraph(NamedTuple):
    """The graph arrays the compiled searches read: the legal-moves table
    (``move_to[move_ptr[e]:move_ptr[e + 1]]`` are the edges a route may take after ``e``), the
    edge lengths, the edges' reverse twins (-1 for none) and the positions of the edges' start
    and end nodes, ``edge_xy[e] = (x0, y0, x1, y1)`` (for the straight-line lower bound of
    :func:`_search_toward`). ``move_cost`` is each move's turn cost in metres, added to the
    route's length (:func:`turn_costs`).

    Keep it at six arrays (the start and end positions in one): the compiled batch calls are
    sensitive to the number of arrays in the tuples they are handed, and each array added
    slows every call, as one added to :class:`~mapmatch.batch.arrays.Lattice` does.
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
    """The compiled searches' arrays of ``graph``, moves by :func:`graph.rules.moves_for`
    under the U-turn policy ``uturns`` (the batch matcher's: turning back only at a dead end),
    each costing :func:`turn_costs` of ``turn_cost`` metres (finite, not negative)."""
    if not math.isfinite(turn_cost) or turn_cost < 0:
        raise ValueError(f"turn_cost must be a finite non-negative number of metres, got {turn_cost!r}")
    moves = moves_for(graph, uturns=uturns)
    return RouteGraph(
        move_ptr=read_only(moves.ptr, np.int64),
        move_to=read_only(moves.to, np.int32),
        move_cost=read_only(turn_costs(graph, moves.ptr, moves.to, turn_cost), np.float64),
        edge_len=read_only(graph.edge_len, np.float64),
        edge_rev=read_only(graph.edge_reverse, np.int32),
        edge_xy=read_only(np.hstack([graph.node_xy[graph.edge_u], graph.node_xy[graph.edge_v]]), np.float64),
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
    """A :class:`~mapmatch.route_table.Ubodt`'s arrays as the compiled kernels read them
    (``delta < 0``: no table).

    Only what they read: the kernels' tuples cost time per array they carry (see
    :class:`RouteGraph`), so the table's ``pred`` stays out."""

    delta: float
    ptr: NDArray[np.int64]
    tgt: NDArray[np.int32]
    head: NDArray[np.int32]
    """Every :data:`TABLE_BLOCK`-th entry of ``tgt`` (``tgt[::TABLE_BLOCK]``): a row's look-up
    searches these first, then one block, so it reads two or three cache lines of a cold row
    rather than one per halving."""
    dist: NDArray[np.float64]
    pred_pos: NDArray[np.int32]


TABLE_BLOCK = 16
"""Entries of a route table's ``tgt`` per entry of its ``head`` (16 int32: one cache line)."""

NO_TABLE = RouteTable(
    -1.0,
    np.zeros(1, np.int64),
    np.zeros(0, np.int32),
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


search_toward_inlined = njit(nogil=True, inline="always")(py_func(_search_toward))
""":func:`_search_toward` compiled into its caller (the Viterbi step,
:func:`mapmatch.batch.step._step`: one call less per search)."""


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
    nt = _search(src, g.edge_len[src] - src_off, bound, int64(1), g, ws)
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
    a reverse twin, turn restrictions kept: :func:`graph.rules.legal_moves` ``"never"``).

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
