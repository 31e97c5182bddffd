"""Pure graph -> graph steps on osmnx-style MultiDiGraphs, and the conversion to RoadGraph.

The input graph ("raw graph") is a ``networkx.MultiDiGraph`` in a projected CRS whose nodes
carry ``x``, ``y`` (metres), ``lon``, ``lat`` and ``osmid`` (the source's node id), with one
edge per straight piece between consecutive vertices. Edges carry ``osmid`` (way or feature
id), and optionally ``name``, ``highway`` and ``speed_kph``. Every vertex is a node, as osmnx
expects before :func:`osmnx.simplify_graph`.

This is the reference path (``BuildOptions(engine="osmnx")``) and the osmnx conversions
(:func:`to_osmnx`, :func:`from_osmnx`); the default build does the same on arrays, in
:mod:`graph.raw_network`, and shares this module's loop splitting and restriction
mapping.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.road_graph import Edges, Nodes, Pieces, RoadGraph

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)


def _is_endpoint(G: nx.MultiDiGraph, node: Any) -> bool:
    """osmnx's endpoint rules 1-3 (self-loop; no in or no out edge; not 2 neighbours with degree 2/4)."""
    preds = set(G.predecessors(node))
    succs = set(G.successors(node))
    nbrs = preds | succs
    if node in nbrs or not preds or not succs:
        return True
    return not (len(nbrs) == 2 and G.degree(node) in (2, 4))


def mark_rings(G: nx.MultiDiGraph) -> int:
    """Mark two opposite nodes of every isolated ring with ``keep=True``.

    osmnx removes isolated rings (components without any endpoint) or leaves them
    unsimplified; keeping two nodes turns each ring into two edges (no self-loop).
    Returns the number of rings found.
    """
    import networkx as nx

    rings = 0
    for comp in nx.weakly_connected_components(G):
        if len(comp) < 3 or any(_is_endpoint(G, n) for n in comp):
            continue
        # walk the ring in order from its smallest node
        start = min(comp)
        order = [start]
        prev, cur = None, start
        while True:
            nxt = [n for n in set(G.predecessors(cur)) | set(G.successors(cur)) if n != prev]
            if not nxt or nxt[0] == start:
                break
            prev, cur = cur, min(nxt)
            order.append(cur)
        G.nodes[order[0]]["keep"] = True
        G.nodes[order[len(order) // 2]]["keep"] = True
        rings += 1
    return rings


def simplify(G: nx.MultiDiGraph) -> nx.MultiDiGraph:
    """Simplify to intersections and dead ends with :func:`osmnx.simplify_graph`.

    The osmnx rule keeps a node where a one-way changes direction (no in or no out edge);
    isolated rings are kept as two edges (see :func:`mark_rings`) instead of being dropped.
    Simplified edges get ``geometry`` and ``merged_edges`` (the original vertex pairs).
    """
    import osmnx as ox

    G = G.copy()
    n_rings = mark_rings(G)
    if n_rings:
        log.info("kept %d isolated rings as two edges each", n_rings)
    Gs = ox.simplify_graph(G, node_attrs_include=["keep"], remove_rings=False, track_merged=True)
    return Gs


def consolidate(G: nx.MultiDiGraph, tolerance: float) -> nx.MultiDiGraph:
    """Merge the nodes of complex intersections within ``tolerance`` metres (osmnx).

    Node ``osmid`` becomes the smallest of the merged nodes' ids (raw node keys are source
    ids); the merged ids are kept in ``osmid_original``.
    """
    import osmnx as ox

    G = G.copy()
    for _, d in G.nodes(data=True):
        d.pop("osmid", None)  # osmnx uses the node key as "osmid" itself
    Gc = ox.consolidate_intersections(G, tolerance=tolerance, rebuild_graph=True, dead_ends=True)
    for _, d in Gc.nodes(data=True):
        if isinstance(d.get("lon"), list) or isinstance(d.get("lat"), list):
            d.pop("lon")  # merged node: lon/lat are recomputed from its new x, y
            d.pop("lat")
        orig = d.get("osmid_original", d.get("osmid"))
        if isinstance(orig, list | tuple | set):
            d["osmid"] = int(min(orig))
        elif orig is not None:
            d["osmid"] = int(orig)
    return Gc


def _first(v: Any) -> Any:
    """First value of an attribute osmnx may have merged into a list."""
    if isinstance(v, list | tuple | set):
        vals = [x for x in v if x is not None and x == x]
        return sorted(vals, key=str)[0] if vals else None
    return v


def _path_nodes(u: Any, data: dict[str, Any]) -> list[Any] | None:
    merged = data.get("merged_edges")
    if not merged:
        return None
    return [u] + [b for _, b in merged]


def _split_loop(
    coords: NDArray[np.float64], path: Sequence[Any] | None, node_order: dict[Any, int]
) -> int | None:
    """Vertex index at which to split a self-loop: nearest half length, ties by node id."""
    if len(coords) < 3:
        return None
    seg = np.hypot(*np.diff(coords, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    inner = np.arange(1, len(coords) - 1)
    dist = np.round(np.abs(cum[inner] - cum[-1] / 2.0), 6)
    if path is not None and len(path) == len(coords):
        key = [(dist[i], node_order.get(path[int(j)], 0)) for i, j in enumerate(inner)]
        return int(inner[min(range(len(inner)), key=lambda i: key[i])])
    return int(inner[int(np.argmin(dist))])


def _speed(v: Any) -> float:
    if isinstance(v, list | tuple | set):
        vals = [float(x) for x in v if x is not None and x == x]
        v = min(vals) if vals else None
    return float(v) if v is not None else np.nan


def _text(v: Any) -> str | None:
    """A name or class as text; None for missing values (None, NaN, empty)."""
    if v is None or (isinstance(v, float) and v != v):
        return None
    return str(v) or None


SegAttrs = tuple[int, str | None, str | None, float]
"""Attributes of one straight piece: way id, name, road class, speed (km/h)."""


def _seg_attrs(
    d: dict[str, Any],
    path: list[Any] | None,
    n_seg: int,
    raw: nx.MultiDiGraph | None,
    coords: NDArray[np.float64] | None = None,
) -> tuple[list[SegAttrs], bool]:
    """Per straight piece of a simplified edge, the attributes of the raw edge it came from.

    Returns the list and whether it is exact (read from the raw graph, or from the
    ``piece_*`` lists :func:`to_osmnx` writes); otherwise every piece gets the simplified
    edge's merged attributes (their first value).
    """
    if "piece_start" in d and coords is not None and len(coords) == n_seg + 1:
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(coords, axis=0).T))])
        at = (
            np.searchsorted(np.asarray(d["piece_start"], dtype=np.float64), cum[:-1] + 1e-6, side="right") - 1
        )
        at = np.clip(at, 0, len(d["piece_start"]) - 1).tolist()
        rows = list(
            zip(d["piece_osmid"], d["piece_name"], d["piece_highway"], d["piece_speed_kph"], strict=True)
        )
        return [(int(rows[i][0]), _text(rows[i][1]), _text(rows[i][2]), _speed(rows[i][3])) for i in at], True
    w = d.get("osmid")
    mine = {x for x in (w if isinstance(w, list | tuple | set) else [w]) if x is not None}
    if raw is not None and path is not None and len(path) == n_seg + 1:
        out: list[SegAttrs] = []
        for a, b in itertools.pairwise(path):
            kd = raw.get_edge_data(a, b)
            if not kd:
                break
            # parallel raw edges: the one of this edge's ways
            r = next((x for _, x in sorted(kd.items()) if x.get("osmid") in mine), kd[min(kd)])
            rw = r.get("osmid")
            out.append(
                (
                    int(rw) if rw is not None else -1,
                    _text(r.get("name")),
                    _text(r.get("highway")),
                    _speed(r.get("speed_kph")),
                )
            )
        else:
            return out, True
    way = _first(w)
    one = (
        int(way) if way is not None else -1,
        _text(_first(d.get("name"))),
        _text(_first(d.get("highway"))),
        _speed(d.get("speed_kph")),
    )
    return [one] * n_seg, False


def to_road_graph(
    G: nx.MultiDiGraph,
    *,
    crs: str,
    restrictions: Iterable[tuple[int, int, int, int]] = (),
    meta: dict[str, Any] | None = None,
    raw: nx.MultiDiGraph | None = None,
) -> tuple[RoadGraph, dict[str, Any]]:
    """Convert a simplified graph into a :class:`RoadGraph`.

    Self-loops are split at the vertex nearest their half length (so no edge has
    ``u == v``); zero-length self-loops are dropped.

    Parameters
    ----------
    G
        Simplified MultiDiGraph (nodes with ``x``, ``y``, ``lon``, ``lat``, ``osmid``).
    crs
        The projected CRS of ``x``/``y``.
    restrictions
        Rows ``(from_way, via_osm_node, to_way, kind)`` in source ids; mapped onto edges.
    meta
        Build metadata stored with the graph.
    raw
        The graph before simplification; with it (and ``merged_edges`` on the simplified
        edges) every edge keeps the ways it is made of as way pieces.

    Returns
    -------
    graph, info
        The graph, and counts of what was dropped or split (for the summary).
    """
    node_keys = list(G.nodes)
    node_order = {n: i for i, n in enumerate(node_keys)}
    nodes = _NodeLists(
        xy=[[G.nodes[n]["x"], G.nodes[n]["y"]] for n in node_keys],
        lonlat=[[G.nodes[n].get("lon", np.nan), G.nodes[n].get("lat", np.nan)] for n in node_keys],
        ids=[int(G.nodes[n].get("osmid", n)) for n in node_keys],
        extra={},
    )
    info = {"self_loops_split": 0, "self_loops_dropped": 0}
    out = _EdgeLists()
    for u, v, d in G.edges(data=True):
        _add_edge(out, nodes, (u, v, d), node_order, raw, info)
    node_xy = np.asarray(nodes.xy, dtype=np.float64).reshape(-1, 2)
    node_ll = np.asarray(nodes.lonlat, dtype=np.float64).reshape(-1, 2)
    if np.isnan(node_ll).any():
        from graph.projection import to_lonlat

        bad = np.isnan(node_ll).any(axis=1)
        node_ll[bad] = to_lonlat(crs, node_xy[bad, 0], node_xy[bad, 1])
    rrows, info["restrictions_unmapped"] = map_restrictions(
        restrictions,
        us=out.us,
        vs=out.vs,
        end_ways=out.end_ways,
        node_keys=node_keys,
        node_ids=nodes.ids,
        G=G,
    )
    rg = RoadGraph.from_edges(
        crs,
        Nodes(node_xy, node_ll, np.asarray(nodes.ids, dtype=np.int64)),
        Edges(
            u=np.asarray(out.us, dtype=np.int32),
            v=np.asarray(out.vs, dtype=np.int32),
            geometry=out.geoms,
            way_id=np.asarray(out.ways, dtype=np.int64),
            name=out.names,
            highway=out.hws,
            speed_kph=np.asarray(out.speeds, dtype=np.float32),
        ),
        restrictions=rrows,
        pieces=out.pieces(),
        meta=meta,
    )
    return rg, info


class _NodeLists(NamedTuple):
    """The converted graph's nodes as they are collected: positions, lon/lat and ids, and the
    node added at each split loop's middle vertex (by its key)."""

    xy: list[list[float]]
    lonlat: list[list[float]]
    ids: list[int]
    extra: dict[Any, int]


@dataclass
class _EdgeLists:
    """The converted graph's edges as they are collected, with their way pieces and, per
    edge, the ways touching its start and its end (for the restrictions)."""

    us: list[int] = field(default_factory=list)
    vs: list[int] = field(default_factory=list)
    geoms: list[NDArray[np.float64]] = field(default_factory=list)
    ways: list[int] = field(default_factory=list)
    names: list[str | None] = field(default_factory=list)
    hws: list[str | None] = field(default_factory=list)
    speeds: list[float] = field(default_factory=list)
    end_ways: list[tuple[set[int], set[int]]] = field(default_factory=list)
    p_edge: list[int] = field(default_factory=list)
    p_start: list[float] = field(default_factory=list)
    p_attrs: list[SegAttrs] = field(default_factory=list)

    def add(
        self, u: int, v: int, g: NDArray[np.float64], segs: list[SegAttrs], exact: bool, d: dict[str, Any]
    ) -> None:
        """One edge ``u -> v`` along ``g`` whose straight pieces have attributes ``segs``
        (``exact``: each piece's own; else the simplified edge ``d``'s merged ones)."""
        e = len(self.us)
        self.us.append(u)
        self.vs.append(v)
        self.geoms.append(g)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g, axis=0).T))])
        keys = [(w, n, h, sp if sp == sp else -1.0) for w, n, h, sp in segs]  # NaN == NaN here
        starts = [i for i in range(len(segs)) if i == 0 or keys[i] != keys[i - 1]]
        bounds = [*starts, len(segs)]
        best, best_len = 0, -1.0
        for k, i in enumerate(starts):
            self.p_edge.append(e)
            self.p_start.append(float(cum[i]))
            self.p_attrs.append(segs[i])
            length = float(cum[bounds[k + 1]] - cum[i])
            if length > best_len:
                best, best_len = k, length
        way, name, hw, sp = segs[starts[best]]
        self.ways.append(way)
        self.names.append(name)
        self.hws.append(hw)
        self.speeds.append(sp)
        if exact:
            self.end_ways.append(({segs[0][0]}, {segs[-1][0]}))
        else:
            w = d.get("osmid")
            allw = {int(x) for x in (w if isinstance(w, list | tuple | set) else [w]) if x is not None}
            self.end_ways.append((allw, allw))

    def pieces(self) -> Pieces:
        return Pieces(
            edge=np.asarray(self.p_edge, dtype=np.int64),
            start=np.asarray(self.p_start, dtype=np.float64),
            way_id=np.asarray([a[0] for a in self.p_attrs], dtype=np.int64),
            name=[a[1] for a in self.p_attrs],
            highway=[a[2] for a in self.p_attrs],
            speed_kph=np.asarray([a[3] for a in self.p_attrs], dtype=np.float32),
        )


def _add_edge(
    out: _EdgeLists,
    nodes: _NodeLists,
    edge: tuple[Any, Any, dict[str, Any]],
    node_order: dict[Any, int],
    raw: nx.MultiDiGraph | None,
    info: dict[str, int],
) -> None:
    """Add one simplified edge ``(u, v, data)`` to ``out``: a self-loop as two edges through a
    new node at its middle vertex (added to ``nodes``), or dropped when it has no length."""
    u, v, d = edge
    geom = d.get("geometry")
    if geom is not None:
        coords = np.asarray(geom.coords, dtype=np.float64)[:, :2]
    else:
        coords = np.array([nodes.xy[node_order[u]], nodes.xy[node_order[v]]], dtype=np.float64)
    path = _path_nodes(u, d)
    if path is None and geom is None:
        path = [u, v]
    if path is not None and "u_original" in d:  # consolidated: ends renamed, raw keys kept
        path = [d["u_original"], *path[1:-1], d.get("v_original", path[-1])]
    segs, exact = _seg_attrs(d, path, len(coords) - 1, raw, coords)
    iu, iv = node_order[u], node_order[v]
    if u != v:
        out.add(iu, iv, coords, segs, exact, d)
        return
    k = _split_loop(coords, path, node_order)
    if k is None:
        info["self_loops_dropped"] += 1
        return
    mid_key = path[k] if path is not None and len(path) == len(coords) else ("loop", u, k)
    if mid_key not in nodes.extra:
        nodes.extra[mid_key] = len(nodes.xy)
        nodes.xy.append(coords[k].tolist())
        # the split vertex was removed by simplification; raw node keys are source ids
        nodes.lonlat.append([np.nan, np.nan])
        nodes.ids.append(int(mid_key) if isinstance(mid_key, int | np.integer) else -len(nodes.extra))
    extra = nodes.extra[mid_key]
    out.add(iu, extra, coords[: k + 1], segs[:k], exact, d)
    out.add(extra, iv, coords[k:], segs[k:], exact, d)
    info["self_loops_split"] += 1


def map_restrictions(
    restrictions: Iterable[tuple[int, int, int, int]],
    *,
    us: Sequence[int],
    vs: Sequence[int],
    end_ways: Sequence[tuple[set[int], set[int]]],
    node_keys: Sequence[Any],
    node_ids: Sequence[int],
    G: nx.MultiDiGraph,
) -> tuple[list[tuple[int, int, int, int]], int]:
    """Map ``(from_way, via_node_id, to_way, kind)`` onto ``(from_edge, via_node, to_edge, kind)``
    for a graph converted from osmnx (node ids merged by consolidation included); see
    :func:`_map_restrictions`."""
    restr = list(restrictions)
    if not restr:
        return [], 0
    by_id: dict[int, int] = {}
    for i, key in enumerate(node_keys):
        orig = G.nodes[key].get("osmid_original", G.nodes[key].get("osmid", key))
        for o in orig if isinstance(orig, list | tuple | set) else [orig]:
            by_id[int(o)] = i
    for i, nid in enumerate(node_ids[len(node_keys) :]):
        by_id.setdefault(int(nid), len(node_keys) + i)
    return _map_restrictions(restr, us=us, vs=vs, end_ways=end_ways, by_id=by_id)


def _map_restrictions(
    restr: list[tuple[int, int, int, int]],
    *,
    us: Sequence[int],
    vs: Sequence[int],
    end_ways: Sequence[tuple[set[int], set[int]]],
    by_id: dict[int, int],
) -> tuple[list[tuple[int, int, int, int]], int]:
    """Map ``(from_way, via_node_id, to_way, kind)`` onto ``(from_edge, via_node, to_edge, kind)``.

    The via node must be a node of the simplified graph (an intersection). ``from_edge`` is
    an edge entering it whose last way piece (the one touching the via node) is
    ``from_way``; ``to_edge`` one leaving it whose first piece is ``to_way``. ``end_ways``
    holds per edge the ways at its start and at its end. Returns the rows and how many
    could not be mapped.
    """
    rows: list[tuple[int, int, int, int]] = []
    unmapped = 0
    if not restr:
        return rows, 0
    into: dict[int, list[int]] = {}
    outof: dict[int, list[int]] = {}
    for e, (u, v) in enumerate(zip(us, vs, strict=True)):
        outof.setdefault(u, []).append(e)
        into.setdefault(v, []).append(e)
    for from_way, via_id, to_way, kind in restr:
        via = by_id.get(int(via_id))
        if via is None:
            unmapped += 1
            continue
        froms = [e for e in into.get(via, []) if from_way in end_ways[e][1]]
        tos = [e for e in outof.get(via, []) if to_way in end_ways[e][0]]
        if not froms or not tos:
            unmapped += 1
            continue
        pairs = [(fe, te) for fe in froms for te in tos]
        if from_way == to_way:  # e.g. no_u_turn: only the turn back onto the same way
            pairs = [(fe, te) for fe, te in pairs if vs[te] == us[fe]]
        rows.extend((fe, via, te, kind) for fe, te in pairs)
    return rows, unmapped


def to_osmnx(graph: RoadGraph) -> nx.MultiDiGraph:
    """The graph as an osmnx-style simplified MultiDiGraph in its projected CRS.

    Nodes are keyed by ``node_id`` with ``x``, ``y`` (metres), ``lon``, ``lat`` and
    ``street_count``; edges carry osmnx's names: ``osmid`` (the way id, or the list of way ids
    of its pieces), ``name``, ``highway``, ``speed_kph``, ``oneway``, ``reversed``,
    ``length`` and ``geometry`` (a shapely LineString), plus ``edge`` (the edge index) and
    ``piece_start``, ``piece_osmid``, ``piece_name``, ``piece_highway``, ``piece_speed_kph``
    (the way pieces, so :func:`from_osmnx` gives the same graph back).
    """
    import networkx as nx
    import shapely

    G = nx.MultiDiGraph(crs=graph.crs, simplified=True)
    keys = graph.node_id.tolist()
    deg = np.diff(graph.out_ptr) + np.diff(graph.in_ptr)
    G.add_nodes_from(
        (k, {"x": p[0], "y": p[1], "lon": q[0], "lat": q[1], "street_count": int(c)})
        for k, p, q, c in zip(
            keys, graph.node_xy.tolist(), graph.node_lonlat.tolist(), deg.tolist(), strict=True
        )
    )
    names = [*graph.names, None]
    hws = [*graph.highways, None]
    for e in range(graph.n_edges):
        p = range(int(graph.piece_ptr[e]), int(graph.piece_ptr[e + 1]))
        ways = [int(graph.piece_way_id[i]) for i in p]
        uniq = list(dict.fromkeys(ways))
        pname = [names[graph.piece_name_idx[i]] for i in p]
        phw = [hws[graph.piece_highway_idx[i]] for i in p]
        G.add_edge(
            keys[int(graph.edge_u[e])],
            keys[int(graph.edge_v[e])],
            edge=e,
            osmid=uniq[0] if len(uniq) == 1 else uniq,
            name=graph.edge_name(e) or None,
            highway=graph.edge_highway(e) or None,
            speed_kph=float(graph.edge_speed_kph[e]),
            oneway=bool(graph.edge_reverse[e] < 0),
            reversed=False,
            length=float(graph.edge_len[e]),
            geometry=shapely.LineString(graph.edge_xy(e)),
            piece_start=[float(graph.piece_start[i]) for i in p],
            piece_osmid=ways,
            piece_name=pname,
            piece_highway=phw,
            piece_speed_kph=[float(graph.piece_speed_kph[i]) for i in p],
        )
    return G


def from_osmnx(G: nx.MultiDiGraph, *, meta: dict[str, Any] | None = None) -> RoadGraph:
    """A :class:`RoadGraph` from an osmnx MultiDiGraph (simplified or not; unprojected graphs
    are projected to their UTM zone). Way pieces come from the ``piece_*`` lists
    :func:`to_osmnx` writes, else one piece per edge."""
    crs = str(G.graph.get("crs", "EPSG:4326"))
    from pyproj import CRS

    if CRS.from_user_input(crs).is_geographic:
        import osmnx as ox

        G = ox.project_graph(G)
        crs = str(G.graph["crs"])
    rg, _ = to_road_graph(G, crs=crs, meta=meta)
    return rg
