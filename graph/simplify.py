"""Pure graph -> graph steps on osmnx-style MultiDiGraphs, and the conversion to RoadGraph.

The input graph ("raw graph") is a ``networkx.MultiDiGraph`` in a projected CRS whose nodes
carry ``x``, ``y`` (metres), ``lon``, ``lat`` and ``osmid`` (the source's node id), with one
edge per straight piece between consecutive vertices. Edges carry ``osmid`` (way or feature
id), and optionally ``name``, ``highway`` and ``speed_kph``. Every vertex is a node, as osmnx
expects before :func:`osmnx.simplify_graph`.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mapmatch.graph.keys import unique, unique_inverse
from mapmatch.graph.order import spatial_edge_order, take_edges
from mapmatch.graph.road_graph import Labels, Pieces, RoadGraph

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
    xy = [[G.nodes[n]["x"], G.nodes[n]["y"]] for n in node_keys]
    lonlat = [[G.nodes[n].get("lon", np.nan), G.nodes[n].get("lat", np.nan)] for n in node_keys]
    ids = [int(G.nodes[n].get("osmid", n)) for n in node_keys]
    extra_nodes: dict[Any, int] = {}
    info = {"self_loops_split": 0, "self_loops_dropped": 0}
    us: list[int] = []
    vs: list[int] = []
    geoms: list[NDArray[np.float64]] = []
    ways: list[int] = []
    names: list[str | None] = []
    hws: list[str | None] = []
    speeds: list[float] = []
    end_ways: list[tuple[set[int], set[int]]] = []  # ways touching u, ways touching v
    p_edge: list[int] = []
    p_start: list[float] = []
    p_attrs: list[SegAttrs] = []

    def _add(
        u: int, v: int, g: NDArray[np.float64], segs: list[SegAttrs], exact: bool, d: dict[str, Any]
    ) -> None:
        e = len(us)
        us.append(u)
        vs.append(v)
        geoms.append(g)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g, axis=0).T))])
        keys = [(w, n, h, sp if sp == sp else -1.0) for w, n, h, sp in segs]  # NaN == NaN here
        starts = [i for i in range(len(segs)) if i == 0 or keys[i] != keys[i - 1]]
        bounds = [*starts, len(segs)]
        best, best_len = 0, -1.0
        for k, i in enumerate(starts):
            p_edge.append(e)
            p_start.append(float(cum[i]))
            p_attrs.append(segs[i])
            length = float(cum[bounds[k + 1]] - cum[i])
            if length > best_len:
                best, best_len = k, length
        way, name, hw, sp = segs[starts[best]]
        ways.append(way)
        names.append(name)
        hws.append(hw)
        speeds.append(sp)
        if exact:
            end_ways.append(({segs[0][0]}, {segs[-1][0]}))
        else:
            w = d.get("osmid")
            allw = {int(x) for x in (w if isinstance(w, list | tuple | set) else [w]) if x is not None}
            end_ways.append((allw, allw))

    for u, v, d in G.edges(data=True):
        geom = d.get("geometry")
        if geom is not None:
            coords = np.asarray(geom.coords, dtype=np.float64)[:, :2]
        else:
            coords = np.array([xy[node_order[u]], xy[node_order[v]]], dtype=np.float64)
        path = _path_nodes(u, d)
        if path is None and geom is None:
            path = [u, v]
        if path is not None and "u_original" in d:  # consolidated: ends renamed, raw keys kept
            path = [d["u_original"], *path[1:-1], d.get("v_original", path[-1])]
        segs, exact = _seg_attrs(d, path, len(coords) - 1, raw, coords)
        iu, iv = node_order[u], node_order[v]
        if u != v:
            _add(iu, iv, coords, segs, exact, d)
            continue
        k = _split_loop(coords, path, node_order)
        if k is None:
            info["self_loops_dropped"] += 1
            continue
        mid_key = path[k] if path is not None and len(path) == len(coords) else ("loop", u, k)
        if mid_key not in extra_nodes:
            extra_nodes[mid_key] = len(xy)
            xy.append(coords[k].tolist())
            # the split vertex was removed by simplification; raw node keys are source ids
            lonlat.append([np.nan, np.nan])
            ids.append(int(mid_key) if isinstance(mid_key, int | np.integer) else -len(extra_nodes))
        m = extra_nodes[mid_key]
        _add(iu, m, coords[: k + 1], segs[:k], exact, d)
        _add(m, iv, coords[k:], segs[k:], exact, d)
        info["self_loops_split"] += 1

    node_xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    node_ll = np.asarray(lonlat, dtype=np.float64).reshape(-1, 2)
    if np.isnan(node_ll).any():
        from mapmatch.graph.projection import to_lonlat

        bad = np.isnan(node_ll).any(axis=1)
        node_ll[bad] = to_lonlat(crs, node_xy[bad, 0], node_xy[bad, 1])
    rrows, info["restrictions_unmapped"] = map_restrictions(
        restrictions, us=us, vs=vs, end_ways=end_ways, node_keys=node_keys, node_ids=ids, G=G
    )
    pieces = Pieces(
        edge=np.asarray(p_edge, dtype=np.int64),
        start=np.asarray(p_start, dtype=np.float64),
        way_id=np.asarray([a[0] for a in p_attrs], dtype=np.int64),
        name=[a[1] for a in p_attrs],
        highway=[a[2] for a in p_attrs],
        speed_kph=np.asarray([a[3] for a in p_attrs], dtype=np.float32),
    )
    rg = RoadGraph.from_edges(
        crs=crs,
        node_xy=node_xy,
        node_lonlat=node_ll,
        node_id=np.asarray(ids, dtype=np.int64),
        edge_u=np.asarray(us, dtype=np.int32),
        edge_v=np.asarray(vs, dtype=np.int32),
        edge_geoms=geoms,
        edge_way_id=np.asarray(ways, dtype=np.int64),
        edge_names=names,
        edge_highways=hws,
        edge_speed_kph=np.asarray(speeds, dtype=np.float32),
        restrictions=rrows,
        pieces=pieces,
        meta=meta,
    )
    return rg, info


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


# ---------------------------------------------------------------------- array pipeline
class _EndWays(Sequence[tuple[set[int], set[int]]]):
    """``end_ways`` for :func:`_map_restrictions` from two lists, without building the sets."""

    def __init__(self, first: list[int], last: list[int]) -> None:
        self.first, self.last = first, last

    def __len__(self) -> int:
        return len(self.first)

    def __getitem__(self, e: Any) -> Any:
        return ({self.first[e]}, {self.last[e]})


class RawNetwork(NamedTuple):
    """A raw road network as arrays: every vertex a node, one directed edge per straight piece.

    ``edge_feat`` indexes the feature tables (one row per OSM way or GIS feature run).
    """

    crs: str
    node_key: NDArray[np.int64]  # source node id (negative: generated)
    node_xy: NDArray[np.float64]  # (N, 2) metres
    node_lonlat: NDArray[np.float64]  # (N, 2)
    edge_src: NDArray[np.int64]  # (M,) node index
    edge_dst: NDArray[np.int64]
    edge_feat: NDArray[np.int64]
    edge_oneway: NDArray[np.bool_]
    feat_way_id: NDArray[np.int64]  # (F,)
    feat_name: Labels
    feat_highway: Labels
    feat_speed_kph: NDArray[np.float64]

    @property
    def n_nodes(self) -> int:
        return len(self.node_key)

    @property
    def n_edges(self) -> int:
        return len(self.edge_src)


def compact_raw(raw: RawNetwork) -> RawNetwork:
    """Drop nodes without edges (renumbering the rest in order)."""
    used = np.zeros(raw.n_nodes, dtype=bool)
    used[raw.edge_src] = True
    used[raw.edge_dst] = True
    if used.all():
        return raw
    new = np.cumsum(used) - 1
    return raw._replace(
        node_key=raw.node_key[used],
        node_xy=raw.node_xy[used],
        node_lonlat=raw.node_lonlat[used],
        edge_src=new[raw.edge_src],
        edge_dst=new[raw.edge_dst],
    )


def raw_to_nx(raw: RawNetwork) -> nx.MultiDiGraph:
    """The raw network as the osmnx-style MultiDiGraph (for osmnx, the reference path)."""
    import networkx as nx

    G = nx.MultiDiGraph(crs=raw.crs)
    keys = raw.node_key.tolist()
    G.add_nodes_from(
        (k, {"x": p[0], "y": p[1], "lon": q[0], "lat": q[1], "osmid": k})
        for k, p, q in zip(keys, raw.node_xy.tolist(), raw.node_lonlat.tolist(), strict=True)
    )
    d = raw.node_xy[raw.edge_dst] - raw.node_xy[raw.edge_src]
    seg_len = np.hypot(d[:, 0], d[:, 1]).tolist()
    feats = [
        {
            "osmid": int(w),
            "name": n,
            "highway": h,
            "speed_kph": float(s),
        }
        for w, n, h, s in zip(
            raw.feat_way_id.tolist(),
            raw.feat_name.values(),
            raw.feat_highway.values(),
            raw.feat_speed_kph.tolist(),
            strict=True,
        )
    ]
    G.add_edges_from(
        (keys[a], keys[b], {**feats[f], "oneway": bool(o), "length": L})
        for a, b, f, o, L in zip(
            raw.edge_src.tolist(),
            raw.edge_dst.tolist(),
            raw.edge_feat.tolist(),
            raw.edge_oneway.tolist(),
            seg_len,
            strict=True,
        )
    )
    return G


def _neighbour_keys(n: int, src: NDArray[np.int64], dst: NDArray[np.int64]) -> NDArray[np.int64]:
    """Sorted distinct ``node * n + neighbour`` over both directions of every edge (a
    self-loop makes a node its own neighbour)."""
    key = np.concatenate([src * n + dst, dst * n + src])
    return unique(key)


def _endpoints(
    n: int, src: NDArray[np.int64], dst: NDArray[np.int64], nbr_key: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """osmnx's endpoint rules 1-3 per node: self-loop, no in or no out edge, or not exactly
    two neighbours with degree 2 or 4."""
    nout = np.bincount(src, minlength=n)
    nin = np.bincount(dst, minlength=n)
    loop = np.zeros(n, dtype=bool)
    loop[src[src == dst]] = True
    cnt = np.bincount(nbr_key // n, minlength=n)
    d = nout + nin
    return loop | (nout == 0) | (nin == 0) | ~((cnt == 2) & ((d == 2) | (d == 4)))


class _Arcs(NamedTuple):
    """Distinct directed node pairs of the raw edges: ``key = a * n + b`` sorted, and the
    first raw edge (lowest index) of each."""

    key: NDArray[np.int64]
    first: NDArray[np.int64]

    def find(self, keys: NDArray[np.int64]) -> NDArray[np.int64]:
        """Position of each key in ``key``, -1 when absent."""
        at = np.searchsorted(self.key, keys)
        at = np.minimum(at, max(len(self.key) - 1, 0))
        ok = self.key[at] == keys if len(self.key) else np.zeros(len(keys), dtype=bool)
        return np.where(ok, at, -1)


def _arcs(n: int, src: NDArray[np.int64], dst: NDArray[np.int64]) -> _Arcs:
    key, first, _ = unique_inverse(src * n + dst)
    return _Arcs(key=key, first=first)


def _paths(
    n: int,
    src: NDArray[np.int64],
    dst: NDArray[np.int64],
    end: NDArray[np.bool_],
    nbr_key: NDArray[np.int64],
    *,
    on_step: Callable[[int], None] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """osmnx's ``_build_path`` from every endpoint through each successor that is not one,
    all paths at once (one numpy step per path position).

    A path from endpoint ``u`` through successor ``v`` goes on through non-endpoints: each
    has exactly two neighbours, and the path moves to the one it did not come from while an
    edge leads there; it stops after reaching an endpoint (``u`` itself included), or where
    no edge goes on. Paths come in osmnx's order: by ``u``, then by ``u``'s first raw edge to
    ``v``. Returns ``(path_ptr, path_nodes, path_edges)``: the nodes of each path, and per step
    the first raw edge between its two nodes (osmnx takes the first of parallel edges).
    """
    arcs = _arcs(n, src, dst)
    a_from, a_to = arcs.key // n, arcs.key % n
    # paths start on the arcs from an endpoint to a non-endpoint, in osmnx's order
    st = np.nonzero(end[a_from] & ~end[a_to])[0]
    st = st[np.lexsort((arcs.first[st], a_from[st]))]
    # the two neighbours of a non-endpoint sum to this: the other one is the sum minus one
    nb_node = nbr_key // n
    nbr_sum = np.bincount(nb_node, weights=(nbr_key % n).astype(np.float64), minlength=n).astype(np.int64)
    pid = np.arange(len(st), dtype=np.int64)
    prev, cur = a_from[st], a_to[st]
    rec_pid = [pid, pid]
    rec_node = [prev, cur]
    while len(pid):
        go = ~end[cur]
        pid, prev, cur = pid[go], prev[go], cur[go]
        nxt = nbr_sum[cur] - prev
        ok = arcs.find(cur * n + nxt) >= 0
        pid, prev, cur = pid[ok], cur[ok], nxt[ok]
        rec_pid.append(pid)
        rec_node.append(cur)
        if on_step is not None:
            on_step(len(pid))
    all_pid = np.concatenate(rec_pid)
    order = np.argsort(all_pid, kind="stable")  # path by path, each in walk order
    nodes = np.concatenate(rec_node)[order]
    counts = np.bincount(all_pid, minlength=len(st))
    path_ptr = np.zeros(len(st) + 1, dtype=np.int64)
    np.cumsum(counts, out=path_ptr[1:])
    # per step (every node but each path's last) the first raw edge to the next node
    step = np.ones(len(nodes), dtype=bool)
    step[path_ptr[1:] - 1] = False
    at = np.nonzero(step)[0]
    edges = arcs.first[arcs.find(nodes[at] * n + nodes[at + 1])]
    return path_ptr, nodes, edges


def ring_keep(raw: RawNetwork, end: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Two opposite nodes of every isolated ring (a component without endpoints), as
    :func:`mark_rings` picks them: walk from the smallest node id, preferring the smaller."""
    from mapmatch.graph.components import union_find

    keep = np.zeros(raw.n_nodes, dtype=bool)
    lab = union_find(raw.n_nodes, raw.edge_src, raw.edge_dst)
    has_end = np.zeros(raw.n_nodes, dtype=bool)
    has_end[lab[end]] = True
    size = np.bincount(lab, minlength=raw.n_nodes)
    ring_nodes = np.nonzero(~has_end[lab] & (size[lab] >= 3))[0]
    if not len(ring_nodes):
        return keep
    nbrs: dict[int, set[int]] = {}
    for a, b in zip(raw.edge_src.tolist(), raw.edge_dst.tolist(), strict=True):
        if not has_end[lab[a]] and size[lab[a]] >= 3:
            nbrs.setdefault(a, set()).add(b)
            nbrs.setdefault(b, set()).add(a)
    key = raw.node_key
    by_key = {int(key[i]): int(i) for i in ring_nodes}
    for comp in np.unique(lab[ring_nodes]):
        members = ring_nodes[lab[ring_nodes] == comp]
        start = int(members[np.argmin(key[members])])
        order = [start]
        prev, cur = -1, start
        while True:
            nxt = [int(key[n]) for n in nbrs[cur] if n != prev]
            if not nxt or by_key[min(nxt)] == start:
                break
            prev, cur = cur, by_key[min(nxt)]
            order.append(cur)
        keep[order[0]] = True
        keep[order[len(order) // 2]] = True
    return keep


class Simplified(NamedTuple):
    """Edges after simplification: each a node path through the raw network.

    Edge ``i`` runs through raw nodes ``nodes[ptr[i]:ptr[i+1]]`` along raw edges
    ``raw_edges[ptr[i]-i : ptr[i+1]-i-1]``; ``kept`` marks the raw nodes that remain.
    """

    ptr: NDArray[np.int64]
    nodes: NDArray[np.int64]
    raw_edges: NDArray[np.int64]
    kept: NDArray[np.bool_]


def simplify_arrays(raw: RawNetwork, *, on_step: Callable[[int], None] | None = None) -> Simplified:
    """Simplify to intersections and dead ends exactly as :func:`simplify` (osmnx) does,
    with whole-array numpy steps (no per-node Python).

    ``on_step`` is called now and then during the path walk with the number of paths
    still growing.
    """
    n = raw.n_nodes
    nbr_key = _neighbour_keys(n, raw.edge_src, raw.edge_dst)
    end = _endpoints(n, raw.edge_src, raw.edge_dst, nbr_key)
    keep = ring_keep(raw, end)
    if keep.any():
        log.info("kept %d isolated rings as two edges each", int(keep.sum()) // 2)
    end = end | keep
    pptr, pnodes, pedges = _paths(n, raw.edge_src, raw.edge_dst, end, nbr_key, on_step=on_step)
    del nbr_key
    # interior nodes go; raw edges between remaining nodes stay as they are
    removed = np.zeros(n, dtype=bool)
    inner = np.ones(len(pnodes), dtype=bool)
    if len(pptr) > 1:
        inner[pptr[:-1]] = False
        inner[pptr[1:] - 1] = False
    removed[pnodes[inner]] = True
    stay = np.nonzero(~removed[raw.edge_src] & ~removed[raw.edge_dst])[0]
    n_stay = len(stay)
    lens = np.concatenate([np.full(n_stay, 2, dtype=np.int64), np.diff(pptr)])
    ptr = np.zeros(len(lens) + 1, dtype=np.int64)
    np.cumsum(lens, out=ptr[1:])
    nodes = np.empty(int(ptr[-1]), dtype=np.int64)
    nodes[0 : 2 * n_stay : 2] = raw.edge_src[stay]
    nodes[1 : 2 * n_stay : 2] = raw.edge_dst[stay]
    nodes[2 * n_stay :] = pnodes
    raw_edges = np.concatenate([stay, pedges]).astype(np.int64)
    return Simplified(ptr=ptr, nodes=nodes, raw_edges=raw_edges, kept=~removed)


def raw_to_road_graph(
    raw: RawNetwork,
    simp: Simplified,
    *,
    restrictions: Iterable[tuple[int, int, int, int]] = (),
    meta: dict[str, Any] | None = None,
) -> tuple[RoadGraph, dict[str, Any]]:
    """The :class:`RoadGraph` of a simplified raw network (as :func:`to_road_graph` makes it
    from osmnx's result): loops split, way pieces from the raw edges, restrictions mapped."""
    kw, info = road_graph_arrays(raw, simp, restrictions=restrictions, meta=meta)
    return RoadGraph.from_edges(**kw), info


def road_graph_arrays(
    raw: RawNetwork,
    simp: Simplified,
    *,
    restrictions: Iterable[tuple[int, int, int, int]] = (),
    meta: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`raw_to_road_graph`'s arguments for :meth:`RoadGraph.from_edges` (so that a caller
    can let go of ``raw`` and ``simp`` before the graph is built), and the info counts."""
    info: dict[str, Any] = {"self_loops_split": 0, "self_loops_dropped": 0}
    kept = np.nonzero(simp.kept)[0]
    index = np.full(raw.n_nodes, -1, dtype=np.int64)
    index[kept] = np.arange(len(kept))
    ptr, nodes = simp.ptr, simp.nodes
    u_raw, v_raw = nodes[ptr[:-1]], nodes[ptr[1:] - 1]
    # loops: split at the vertex nearest half length (ties by node order), as to_road_graph
    loops = np.nonzero(u_raw == v_raw)[0]
    extra: dict[int, int] = {}
    split_u: list[int] = []
    split_v: list[int] = []
    split_a: list[int] = []
    split_b: list[int] = []
    drop = np.zeros(len(u_raw), dtype=bool)
    n_nodes = len(kept)
    order_key = {int(k): int(i) for i, k in enumerate(kept.tolist())}
    for e in loops.tolist():
        a, b = int(ptr[e]), int(ptr[e + 1])
        path = nodes[a:b]
        coords = raw.node_xy[path]
        k = _split_loop(coords, path.tolist(), order_key)
        drop[e] = True
        if k is None:
            info["self_loops_dropped"] += 1
            continue
        mid = int(path[k])
        if mid not in extra:
            extra[mid] = n_nodes + len(extra)
        m = extra[mid]
        iu = int(index[path[0]])
        split_u += [iu, m]
        split_v += [m, iu]
        split_a += [a, a + k]
        split_b += [a + k + 1, b]
        info["self_loops_split"] += 1
    keep_e = np.nonzero(~drop)[0]
    # vertex ranges of every final edge (into simp.nodes)
    va = np.concatenate([ptr[keep_e], np.asarray(split_a, dtype=np.int64)])
    vb = np.concatenate([ptr[keep_e + 1], np.asarray(split_b, dtype=np.int64)])
    eu = np.concatenate([index[u_raw[keep_e]], np.asarray(split_u, dtype=np.int64)])
    ev = np.concatenate([index[v_raw[keep_e]], np.asarray(split_v, dtype=np.int64)])
    counts = vb - va
    del ptr, u_raw, v_raw, drop, keep_e
    edge_seg_ptr = np.zeros(len(va) + 1, dtype=np.int64)
    np.cumsum(counts, out=edge_seg_ptr[1:])
    flat_v = np.repeat(va - edge_seg_ptr[:-1], counts) + np.arange(int(edge_seg_ptr[-1]))
    del va, vb
    seg_xy = raw.node_xy[nodes[flat_v]]
    pieces, best_feat, end_feat = _edge_pieces(raw, simp, flat_v, edge_seg_ptr, seg_xy)
    del flat_v
    extra_nodes = np.asarray(list(extra), dtype=np.int64)
    node_xy = np.vstack([raw.node_xy[kept], raw.node_xy[extra_nodes].reshape(-1, 2)])
    node_ll = np.vstack([raw.node_lonlat[kept], raw.node_lonlat[extra_nodes].reshape(-1, 2)])
    node_id = np.concatenate([raw.node_key[kept], raw.node_key[extra_nodes]])
    del kept, index
    restr = list(restrictions)
    if restr:  # per edge the way at its start and at its end (only where restrictions need them)
        first_w = raw.feat_way_id[end_feat[0]].tolist()
        last_w = raw.feat_way_id[end_feat[1]].tolist()
        end_ways = _EndWays(first_w, last_w)
        by_id = {int(k): i for i, k in enumerate(node_id.tolist())}
        rrows, info["restrictions_unmapped"] = _map_restrictions(
            restr, us=eu.tolist(), vs=ev.tolist(), end_ways=end_ways, by_id=by_id
        )
    else:
        rrows, info["restrictions_unmapped"] = [], 0
    kw = {
        "crs": raw.crs,
        "node_xy": node_xy,
        "node_lonlat": node_ll,
        "node_id": node_id,
        "edge_u": eu.astype(np.int32),
        "edge_v": ev.astype(np.int32),
        "seg_xy": seg_xy,
        "edge_seg_ptr": edge_seg_ptr,
        "edge_way_id": raw.feat_way_id[best_feat],
        "edge_names": raw.feat_name.take(best_feat),
        "edge_highways": raw.feat_highway.take(best_feat),
        "edge_speed_kph": raw.feat_speed_kph[best_feat].astype(np.float32),
        "restrictions": rrows,
        "pieces": pieces,
        "meta": meta,
        "copy": False,
    }
    # nearby roads at nearby indices (:mod:`mapmatch.graph.order`)
    return take_edges(kw, spatial_edge_order(node_xy, eu, ev)), info


def _edge_pieces(
    raw: RawNetwork,
    simp: Simplified,
    flat_v: NDArray[np.int64],
    edge_seg_ptr: NDArray[np.int64],
    seg_xy: NDArray[np.float64],
) -> tuple[Pieces, NDArray[np.int64], tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """The way pieces of the final edges (vertex ``i`` of the edges is ``simp.nodes[flat_v[i]]``):
    runs of equal feature attributes along each edge. Returns the pieces, each edge's
    longest piece's feature (the first on ties), and each edge's first and last step's feature."""
    e = len(edge_seg_ptr) - 1
    counts = np.diff(edge_seg_ptr)
    last = np.zeros(len(flat_v), dtype=bool)
    last[edge_seg_ptr[1:] - 1] = True
    step_at = np.nonzero(~last)[0]  # vertex -> the step to the next vertex
    del last
    # step from simp vertex i (not the last of its simp edge) -> raw edge raw_edges[i - its simp edge]
    step_v = flat_v[step_at]
    step_v -= np.searchsorted(simp.ptr, step_v, side="right") - 1
    step_feat = raw.edge_feat[simp.raw_edges[step_v]]
    del step_v
    step_key = _feature_keys(raw)[step_feat]
    step_edge = np.repeat(np.arange(e, dtype=np.int64), counts - 1)
    new_piece = np.ones(len(step_key), dtype=bool)
    if len(step_key) > 1:
        new_piece[1:] = (step_key[1:] != step_key[:-1]) | (step_edge[1:] != step_edge[:-1])
    del step_key
    dx = seg_xy[step_at + 1, 0] - seg_xy[step_at, 0]
    dy = seg_xy[step_at + 1, 1] - seg_xy[step_at, 1]
    del step_at
    cum = np.zeros(len(dx) + 1)
    np.cumsum(np.hypot(dx, dy), out=cum[1:])
    del dx, dy
    edge_first_step = edge_seg_ptr[:-1] - np.arange(e)
    edge_last_step = np.r_[edge_first_step[1:], len(step_feat)] - 1 if e else edge_first_step
    end_feat = (step_feat[edge_first_step], step_feat[edge_last_step])
    p_idx = np.nonzero(new_piece)[0]
    del new_piece
    p_edge = step_edge[p_idx]
    del step_edge
    p_start = cum[p_idx] - cum[edge_first_step[p_edge]]
    p_feat = step_feat[p_idx]
    del step_feat
    p_end_step = np.r_[p_idx[1:], len(cum) - 1]
    p_len = cum[p_end_step] - cum[p_idx]
    del cum, p_end_step
    # edge attributes: its longest piece (first on ties)
    order = np.lexsort((np.arange(len(p_idx)), -p_len, p_edge))
    first_of_edge = order[np.r_[True, p_edge[order][1:] != p_edge[order][:-1]]] if len(order) else order
    best_feat = p_feat[first_of_edge]
    pieces = Pieces(
        edge=p_edge,
        start=p_start,
        way_id=raw.feat_way_id[p_feat],
        name=raw.feat_name.take(p_feat),
        highway=raw.feat_highway.take(p_feat),
        speed_kph=raw.feat_speed_kph[p_feat].astype(np.float32),
    )
    return pieces, best_feat, end_feat


def _feature_keys(raw: RawNetwork) -> NDArray[np.int64]:
    """One id per distinct ``(way id, name, class, speed)`` of the feature table."""
    sp = np.where(np.isfinite(raw.feat_speed_kph), raw.feat_speed_kph, -1.0)
    cols = (sp, raw.feat_highway.codes, raw.feat_name.codes, raw.feat_way_id)
    order = np.lexsort(cols)
    new = np.ones(len(order), dtype=bool)
    if len(order) > 1:
        new[1:] = np.any([c[order][1:] != c[order][:-1] for c in cols], axis=0)
    out = np.empty(len(order), dtype=np.int64)
    out[order] = np.cumsum(new) - 1
    return out
