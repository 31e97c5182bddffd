"""Truth routes for the simulator: a legal edge path and its centre-line geometry.

A route is a sequence of directed edges, entered at ``start_offset`` metres along the first
and left at ``end_offset`` metres along the last. Random routes chain shortest paths
(by travel time) between random waypoints with an edge-based Dijkstra, so they respect
one-ways and turn restrictions and never U-turn, neither at a node nor at a waypoint.
A given geometry (e.g. a truth GeoJSON) is turned into an edge path by a small Viterbi.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.index import Candidates, EdgeIndex
from graph.road_graph import RoadGraph
from graph.rules import LegalMoves, moves_for
from mapmatch.errors import MatchError
from mapmatch.routing import shortest_path

# default speeds in km/h by OSM highway class, when an edge has none
DEFAULT_SPEED_KPH: dict[str, float] = {
    "motorway": 100.0,
    "motorway_link": 60.0,
    "trunk": 80.0,
    "trunk_link": 50.0,
    "primary": 60.0,
    "primary_link": 40.0,
    "secondary": 50.0,
    "secondary_link": 40.0,
    "tertiary": 40.0,
    "tertiary_link": 30.0,
    "unclassified": 40.0,
    "residential": 30.0,
    "living_street": 15.0,
    "service": 20.0,
}
FALLBACK_SPEED_KPH = 40.0


class RouteError(MatchError):
    """A route cannot be built or is not legal on the map."""


@dataclass(frozen=True)
class Route:
    """A legal path on the map and its geometry.

    Attributes
    ----------
    edges : (M,) int32
        Directed edges in driving order.
    start_offset, end_offset : float
        Metres along the first edge where the drive starts and along the last where it ends.
    edge_start : (M+1,) float64
        Route distance at the start of each edge (the first is ``-start_offset``) and, last,
        the route distance at the end of the last edge.
    xy : (K, 2) float64
        Centre-line polyline of the driven part, metres in the map's CRS.
    s : (K,) float64
        Route distance of each vertex of ``xy``, from 0 to ``length``.
    """

    edges: NDArray[np.int32]
    start_offset: float
    end_offset: float
    edge_start: NDArray[np.float64]
    xy: NDArray[np.float64]
    s: NDArray[np.float64]

    @property
    def length(self) -> float:
        return float(self.s[-1]) if len(self.s) else 0.0

    def nodes(self, graph: RoadGraph) -> NDArray[np.int32]:
        """Intersections passed in order (node indices): the joins between consecutive edges."""
        return graph.edge_v[self.edges[:-1]].astype(np.int32)

    def node_distance(self) -> NDArray[np.float64]:
        """Route distance at which each of :meth:`nodes` is passed."""
        return self.edge_start[1:-1].copy()

    def locate(self, s: ArrayLike) -> tuple[NDArray[np.int32], NDArray[np.float64]]:
        """Edge and offset along it of route distances ``s`` (clipped to the route)."""
        d = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        i = np.clip(np.searchsorted(self.edge_start, d, side="right") - 1, 0, len(self.edges) - 1)
        return self.edges[i].astype(np.int32), d - self.edge_start[i]

    def position(self, s: ArrayLike) -> NDArray[np.float64]:
        """Centre-line positions (P, 2) at route distances ``s``."""
        d = np.asarray(s, dtype=np.float64)
        return np.column_stack([np.interp(d, self.s, self.xy[:, 0]), np.interp(d, self.s, self.xy[:, 1])])


# --------------------------------------------------------------------------- legality
def check_route(graph: RoadGraph, edges: Sequence[int]) -> None:
    """Raise :class:`RouteError` unless consecutive edges join legally without a U-turn."""
    moves = moves_for(graph, uturns="never")
    for a, b in itertools.pairwise(edges):
        if int(graph.edge_v[a]) != int(graph.edge_u[b]):
            raise RouteError(f"edges {a} and {b} do not join")
        if b not in moves.after(int(a)):
            raise RouteError(f"turn {a} -> {b} is a U-turn or restricted")


def edge_speed_mps(graph: RoadGraph) -> NDArray[np.float64]:
    """Free-flow speed per edge in m/s: the map's speed, else a default by highway class."""
    hw = np.array(
        [DEFAULT_SPEED_KPH.get(h, FALLBACK_SPEED_KPH) for h in graph.highways] + [FALLBACK_SPEED_KPH]
    )
    default = hw[graph.edge_highway_idx]  # index -1 picks the fallback
    kph = np.where(np.isfinite(graph.edge_speed_kph), graph.edge_speed_kph, default)
    return np.clip(kph, 5.0, 130.0) / 3.6


# --------------------------------------------------------------------------- construction
def route_from_edges(
    graph: RoadGraph,
    edges: Sequence[int],
    *,
    start_offset: float = 0.0,
    end_offset: float | None = None,
    allow_uturns: bool = False,
) -> Route:
    """A :class:`Route` along ``edges`` (checked for legality; with ``allow_uturns`` only that
    the edges join, as a real drive may turn round)."""
    ed = np.asarray(edges, dtype=np.int32)
    if len(ed) == 0:
        raise RouteError("a route needs at least one edge")
    if allow_uturns:
        if (graph.edge_v[ed[:-1]] != graph.edge_u[ed[1:]]).any():
            raise RouteError("consecutive route edges do not join")
    else:
        check_route(graph, ed.tolist())
    lens = graph.edge_len[ed]
    end = float(lens[-1]) if end_offset is None else float(end_offset)
    start = float(np.clip(start_offset, 0.0, lens[0]))
    end = float(np.clip(end, 0.0, lens[-1]))
    edge_start = np.concatenate([[0.0], np.cumsum(lens)]) - start
    total = float(edge_start[-2] + end)
    if total <= 0.0:
        raise RouteError("the route has zero length")
    parts = []
    svals = []
    for i, e in enumerate(ed.tolist()):
        g = graph.edge_xy(e)
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g, axis=0).T))])
        d = d * (lens[i] / d[-1]) if d[-1] > 0 else d
        if i > 0:  # drop the shared node
            g, d = g[1:], d[1:]
        parts.append(g)
        svals.append(d + edge_start[i])
    xy = np.vstack(parts)
    s = np.concatenate(svals)
    # cut to [0, total], keeping interpolated end points
    inner = (s > 0.0) & (s < total)
    xs = np.concatenate([[np.interp(0.0, s, xy[:, 0])], xy[inner, 0], [np.interp(total, s, xy[:, 0])]])
    ys = np.concatenate([[np.interp(0.0, s, xy[:, 1])], xy[inner, 1], [np.interp(total, s, xy[:, 1])]])
    ss = np.concatenate([[0.0], s[inner], [total]])
    return Route(
        edges=ed,
        start_offset=start,
        end_offset=end,
        edge_start=edge_start,
        xy=np.column_stack([xs, ys]),
        s=ss,
    )


def _strong_edges(graph: RoadGraph, rng: np.random.Generator, tries: int = 8) -> NDArray[np.int64]:
    """Edges of a large strongly connected part of the turn graph (legal turns, no U-turns).

    From any of these edges every other one is reachable, so a random walk between them
    never gets stuck in a dead end or a one-way trap.
    """
    moves = moves_for(graph, uturns="never")
    succ = [moves.after(e) for e in range(graph.n_edges)]
    pred: list[list[int]] = [[] for _ in range(graph.n_edges)]
    for e, fs in enumerate(succ):
        for f in fs:
            pred[f].append(e)

    def reach(seed: int, nbr: list[list[int]]) -> set[int]:
        seen = {seed}
        stack = [seed]
        while stack:
            for f in nbr[stack.pop()]:
                if f not in seen:
                    seen.add(f)
                    stack.append(f)
        return seen

    best: set[int] = set()
    p = graph.edge_len / graph.edge_len.sum()
    for _ in range(tries):
        seed = int(rng.choice(graph.n_edges, p=p))
        if seed in best:
            continue
        comp = reach(seed, succ) & reach(seed, pred)
        if len(comp) > len(best):
            best = comp
        if len(best) > graph.n_edges // 2:
            break
    return np.array(sorted(best), dtype=np.int64)


def random_route(
    graph: RoadGraph,
    *,
    length_m: float,
    rng: np.random.Generator,
    leg_min_m: float = 300.0,
    leg_max_m: float = 1500.0,
    max_tries: int = 200,
) -> Route:
    """A random legal route of at least ``length_m`` metres through random waypoints.

    Each leg is the fastest legal path from the current edge to a random edge whose end is
    ``leg_min_m``..``leg_max_m`` away in a straight line; the next leg continues from there,
    so there is no U-turn at waypoints. Waypoints lie in the largest strongly connected part
    of the turn graph, so the route never runs into a dead end.
    """
    if graph.n_edges == 0:
        raise RouteError("the map has no roads")
    speed = edge_speed_mps(graph)
    cost = graph.edge_len / speed
    strong = _strong_edges(graph, rng)
    if len(strong) < 2:
        raise RouteError("the map has no connected road network to drive on")
    p = graph.edge_len[strong] / graph.edge_len[strong].sum()
    edges = [int(rng.choice(strong, p=p))]
    total = float(graph.edge_len[edges[0]])
    end_xy = graph.node_xy[graph.edge_v[strong]]
    tries = 0
    while total < length_m and tries < max_tries:
        tries += 1
        here = graph.node_xy[graph.edge_v[edges[-1]]]
        d = np.hypot(*(end_xy - here).T)
        pool = strong[(d >= leg_min_m) & (d <= leg_max_m)]
        if len(pool) == 0:
            pool = strong[d > 0] if (d > 0).any() else strong
        target = int(rng.choice(pool))
        leg = shortest_path(graph, edges[-1], int(graph.edge_u[target]), weight=cost, to_edge=target)
        if not leg:
            continue
        edges.extend(leg)
        total += float(graph.edge_len[leg].sum())
    if total < length_m:
        raise RouteError(f"could not build a legal route of {length_m:.0f} m (got {total:.0f} m)")
    return route_from_edges(graph, edges)


def route_from_geometry(
    graph: RoadGraph,
    xy: ArrayLike,
    *,
    index: EdgeIndex | None = None,
    step_m: float = 5.0,
    radius_m: float = 25.0,
    sigma_m: float = 5.0,
) -> Route:
    """The legal edge path that follows a geometry (P, 2) in metres, by a small Viterbi.

    The line is resampled every ``step_m``; states are candidate edges within ``radius_m``;
    a transition stays on the edge, moves to a legal successor, or (heavily penalised) jumps.
    Gaps between non-adjacent chosen edges are closed with shortest paths.
    """
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        raise RouteError("a route geometry needs at least two points")
    seg = np.hypot(*np.diff(pts, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        raise RouteError("the route geometry has zero length")
    ds = np.append(np.arange(0.0, cum[-1], step_m), cum[-1])
    p = np.column_stack([np.interp(ds, cum, pts[:, 0]), np.interp(ds, cum, pts[:, 1])])
    idx = index if index is not None else EdgeIndex(graph)
    c = idx.query(p, radius_m, k=6)
    if len(c) == 0:
        raise RouteError("the route geometry is not near any road")
    moves = moves_for(graph, uturns="never")
    chosen = _best_places(c, len(p), moves, step_m=step_m, sigma_m=sigma_m)
    path = _joined(graph, moves, [e for e, _ in chosen])
    return route_from_edges(graph, path, start_offset=chosen[0][1], end_offset=chosen[-1][1])


def _best_places(
    c: Candidates, n: int, moves: LegalMoves, *, step_m: float, sigma_m: float
) -> list[tuple[int, float]]:
    """The Viterbi path through the candidates ``c`` of ``n`` resampled points: per point with
    candidates its (edge, offset)."""
    starts = np.searchsorted(c.point, np.arange(n + 1))
    prev: tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.float64]] | None = None
    back: list[NDArray[np.int64]] = []
    layers: list[tuple[NDArray[np.int32], NDArray[np.float64]]] = []
    for i in range(n):
        a, b = starts[i], starts[i + 1]
        if a == b:
            continue
        e, off, dist = c.edge[a:b], c.offset[a:b], c.dist[a:b]
        emis = -0.5 * (dist / sigma_m) ** 2
        if prev is None:
            score = emis
            bp = np.full(len(e), -1, dtype=np.int64)
        else:
            tot = prev[2][:, None] + _transitions(prev[0], prev[1], e, off, moves, step_m)
            bp = np.argmax(tot, axis=0)
            score = tot[bp, np.arange(len(e))] + emis
        back.append(bp)
        layers.append((e, off))
        prev = (e, off, score)
    assert prev is not None
    k = int(np.argmax(prev[2]))
    chosen: list[tuple[int, float]] = []
    for layer in range(len(layers) - 1, -1, -1):
        le, loff = layers[layer]
        chosen.append((int(le[k]), float(loff[k])))
        k = int(back[layer][k])
    chosen.reverse()
    return chosen


def _transitions(
    prev_e: NDArray[np.int32],
    prev_off: NDArray[np.float64],
    e: NDArray[np.int32],
    off: NDArray[np.float64],
    moves: LegalMoves,
    step_m: float,
) -> NDArray[np.float64]:
    """Log-score of each move from the previous point's candidates to this one's: staying on
    the edge (not backwards by ``step_m`` or more), a legal successor, or a jump."""
    trans = np.full((len(prev_e), len(e)), -50.0)
    for j, pe in enumerate(prev_e.tolist()):
        succ = moves.after(pe)
        for k, ce in enumerate(e.tolist()):
            if ce == pe:
                back_m = prev_off[j] - off[k]
                trans[j, k] = 0.0 if back_m < step_m else -50.0
            elif ce in succ:
                trans[j, k] = -0.5
    return trans


def _joined(graph: RoadGraph, moves: LegalMoves, edges: list[int]) -> list[int]:
    """The chosen edges as one legal path: repeats merged, gaps closed with shortest paths."""
    path = [edges[0]]
    for ce in edges[1:]:
        if ce == path[-1]:
            continue
        if int(graph.edge_v[path[-1]]) == int(graph.edge_u[ce]) and ce in moves.after(path[-1]):
            path.append(ce)
            continue
        gap = shortest_path(graph, path[-1], int(graph.edge_u[ce]), max_cost=5000.0)
        if gap is None or (gap and ce not in moves.after(gap[-1])):
            raise RouteError("the route geometry does not follow legal roads")
        if not gap and ce not in moves.after(path[-1]):
            raise RouteError("the route geometry does not follow legal roads")
        path.extend(gap)
        path.append(ce)
    return path
