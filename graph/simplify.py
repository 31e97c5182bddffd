"""Pure graph -> graph steps on osmnx-style MultiDiGraphs, and the conversion to RoadGraph.

The input graph ("raw graph") is a ``networkx.MultiDiGraph`` in a projected CRS whose nodes
carry ``x``, ``y`` (metres), ``lon``, ``lat`` and ``osmid`` (the source's node id), with one
edge per straight piece between consecutive vertices. Edges carry ``osmid`` (way or feature
id), and optionally ``name``, ``highway`` and ``speed_kph``. Every vertex is a node, as osmnx
expects before :func:`osmnx.simplify_graph`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from typing import Any

import networkx as nx
import numpy as np
import osmnx as ox
from numpy.typing import NDArray

from graph.road_graph import RoadGraph

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


def to_road_graph(
    G: nx.MultiDiGraph,
    *,
    crs: str,
    restrictions: Iterable[tuple[int, int, int, int]] = (),
    meta: dict[str, Any] | None = None,
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
    way_sets: list[set[int]] = []

    def _add(u: int, v: int, g: NDArray[np.float64], d: dict[str, Any], path: list[Any] | None) -> None:
        us.append(u)
        vs.append(v)
        geoms.append(g)
        way = _first(d.get("osmid"))
        ways.append(int(way) if way is not None else -1)
        names.append(_first(d.get("name")))
        hws.append(_first(d.get("highway")))
        sp = d.get("speed_kph")
        if isinstance(sp, list | tuple | set):
            vals = [float(x) for x in sp if x is not None and x == x]
            sp = min(vals) if vals else None
        speeds.append(float(sp) if sp is not None else np.nan)
        w = d.get("osmid")
        way_sets.append({int(x) for x in (w if isinstance(w, list | tuple | set) else [w]) if x is not None})

    for u, v, d in G.edges(data=True):
        geom = d.get("geometry")
        if geom is not None:
            coords = np.asarray(geom.coords, dtype=np.float64)[:, :2]
        else:
            coords = np.array([xy[node_order[u]], xy[node_order[v]]], dtype=np.float64)
        path = _path_nodes(u, d)
        iu, iv = node_order[u], node_order[v]
        if u != v:
            _add(iu, iv, coords, d, path)
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
        p1 = path[: k + 1] if path is not None and len(path) == len(coords) else None
        p2 = path[k:] if path is not None and len(path) == len(coords) else None
        _add(iu, m, coords[: k + 1], d, p1)
        _add(m, iv, coords[k:], d, p2)
        info["self_loops_split"] += 1

    node_xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    node_ll = np.asarray(lonlat, dtype=np.float64).reshape(-1, 2)
    if np.isnan(node_ll).any():
        from graph.projection import to_lonlat

        bad = np.isnan(node_ll).any(axis=1)
        node_ll[bad] = to_lonlat(crs, node_xy[bad, 0], node_xy[bad, 1])
    rrows, info["restrictions_unmapped"] = map_restrictions(
        restrictions, us=us, vs=vs, way_sets=way_sets, node_keys=node_keys, node_ids=ids, G=G
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
        meta=meta,
    )
    return rg, info


def map_restrictions(
    restrictions: Iterable[tuple[int, int, int, int]],
    *,
    us: Sequence[int],
    vs: Sequence[int],
    way_sets: Sequence[set[int]],
    node_keys: Sequence[Any],
    node_ids: Sequence[int],
    G: nx.MultiDiGraph,
) -> tuple[list[tuple[int, int, int, int]], int]:
    """Map ``(from_way, via_node_id, to_way, kind)`` onto ``(from_edge, via_node, to_edge, kind)``.

    The via node must be a node of the simplified graph (an intersection). ``from_edge`` is
    an edge entering it that runs along ``from_way`` (a way touching the via node is the last
    piece of any simplified edge that contains it); ``to_edge`` one leaving it along
    ``to_way``. Returns the rows and how many could not be mapped.
    """
    rows: list[tuple[int, int, int, int]] = []
    unmapped = 0
    restr = list(restrictions)
    if not restr:
        return rows, 0
    # node id -> node index, including ids merged by consolidation
    by_id: dict[int, int] = {}
    for i, key in enumerate(node_keys):
        orig = G.nodes[key].get("osmid_original", G.nodes[key].get("osmid", key))
        for o in orig if isinstance(orig, list | tuple | set) else [orig]:
            by_id[int(o)] = i
    for i, nid in enumerate(node_ids[len(node_keys) :]):
        by_id.setdefault(int(nid), len(node_keys) + i)

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
        froms = [e for e in into.get(via, []) if from_way in way_sets[e]]
        tos = [e for e in outof.get(via, []) if to_way in way_sets[e]]
        if not froms or not tos:
            unmapped += 1
            continue
        pairs = [(fe, te) for fe in froms for te in tos]
        if from_way == to_way:  # e.g. no_u_turn: only the turn back onto the same way
            pairs = [(fe, te) for fe, te in pairs if vs[te] == us[fe]]
        rows.extend((fe, via, te, kind) for fe, te in pairs)
    return rows, unmapped
