"""The raw road network as arrays, simplified to intersections without networkx.

The array build path (``build_map``'s default engine): a :class:`RawNetwork` holds every
vertex as a node and one directed edge per straight piece, as the OSM and GIS readers make it;
:func:`simplify_arrays` keeps intersections and dead ends exactly as osmnx's
``simplify_graph`` would (:func:`graph.simplify.simplify`, the reference path), and
:func:`road_graph_arrays` turns the result into a :class:`RoadGraph`'s arrays, its edges in
spatial order. :func:`raw_to_nx` gives the same network to the osmnx path.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.keys import unique, unique_inverse
from graph.order import spatial_edge_order, take_edges
from graph.road_graph import Edges, Labels, Nodes, Pieces, Polylines, RoadGraph
from graph.simplify import _map_restrictions, _split_loop

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)


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
    from graph.components import union_find

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
    final = _final_edges(raw, simp, kept, index, info)
    counts = final.vb - final.va
    edge_seg_ptr = np.zeros(len(final.va) + 1, dtype=np.int64)
    np.cumsum(counts, out=edge_seg_ptr[1:])
    flat_v = np.repeat(final.va - edge_seg_ptr[:-1], counts) + np.arange(int(edge_seg_ptr[-1]))
    eu, ev, extra_nodes = final.eu, final.ev, final.extra_nodes
    del final, counts
    seg_xy = raw.node_xy[simp.nodes[flat_v]]
    pieces, best_feat, end_feat = _edge_pieces(raw, simp, flat_v, edge_seg_ptr, seg_xy)
    del flat_v
    node_xy = np.vstack([raw.node_xy[kept], raw.node_xy[extra_nodes].reshape(-1, 2)])
    node_ll = np.vstack([raw.node_lonlat[kept], raw.node_lonlat[extra_nodes].reshape(-1, 2)])
    node_id = np.concatenate([raw.node_key[kept], raw.node_key[extra_nodes]])
    del kept, index
    restr = list(restrictions)
    rrows, info["restrictions_unmapped"] = _edge_restrictions(raw, restr, (eu, ev), end_feat, node_id)
    kw = {
        "crs": raw.crs,
        "nodes": Nodes(node_xy, node_ll, node_id),
        "edges": Edges(
            u=eu.astype(np.int32),
            v=ev.astype(np.int32),
            geometry=Polylines(seg_xy, edge_seg_ptr),
            way_id=raw.feat_way_id[best_feat],
            name=raw.feat_name.take(best_feat),
            highway=raw.feat_highway.take(best_feat),
            speed_kph=raw.feat_speed_kph[best_feat].astype(np.float32),
        ),
        "restrictions": rrows,
        "pieces": pieces,
        "meta": meta,
        "copy": False,
    }
    # nearby roads at nearby indices (:mod:`graph.order`)
    return take_edges(kw, spatial_edge_order(node_xy, eu, ev)), info


class _FinalEdges(NamedTuple):
    """The final edges: vertex ranges ``va:vb`` into ``simp.nodes``, end nodes ``eu``/``ev``
    (indices of the graph's nodes), and the raw nodes added where loops were split (after the
    kept ones)."""

    va: NDArray[np.int64]
    vb: NDArray[np.int64]
    eu: NDArray[np.int64]
    ev: NDArray[np.int64]
    extra_nodes: NDArray[np.int64]


def _final_edges(
    raw: RawNetwork, simp: Simplified, kept: NDArray[np.int64], index: NDArray[np.int64], info: dict[str, Any]
) -> _FinalEdges:
    """The simplified edges with each loop split at the vertex nearest half its length (ties by
    node order) into two, as :func:`graph.simplify.to_road_graph` does; counted in ``info``."""
    ptr, nodes = simp.ptr, simp.nodes
    u_raw, v_raw = nodes[ptr[:-1]], nodes[ptr[1:] - 1]
    extra: dict[int, int] = {}
    split_u: list[int] = []
    split_v: list[int] = []
    split_a: list[int] = []
    split_b: list[int] = []
    drop = np.zeros(len(u_raw), dtype=bool)
    order_key = {int(k): int(i) for i, k in enumerate(kept.tolist())}
    for e in np.nonzero(u_raw == v_raw)[0].tolist():
        a, b = int(ptr[e]), int(ptr[e + 1])
        path = nodes[a:b]
        k = _split_loop(raw.node_xy[path], path.tolist(), order_key)
        drop[e] = True
        if k is None:
            info["self_loops_dropped"] += 1
            continue
        mid = int(path[k])
        if mid not in extra:
            extra[mid] = len(kept) + len(extra)
        m = extra[mid]
        iu = int(index[path[0]])
        split_u += [iu, m]
        split_v += [m, iu]
        split_a += [a, a + k]
        split_b += [a + k + 1, b]
        info["self_loops_split"] += 1
    keep_e = np.nonzero(~drop)[0]
    return _FinalEdges(
        va=np.concatenate([ptr[keep_e], np.asarray(split_a, dtype=np.int64)]),
        vb=np.concatenate([ptr[keep_e + 1], np.asarray(split_b, dtype=np.int64)]),
        eu=np.concatenate([index[u_raw[keep_e]], np.asarray(split_u, dtype=np.int64)]),
        ev=np.concatenate([index[v_raw[keep_e]], np.asarray(split_v, dtype=np.int64)]),
        extra_nodes=np.asarray(list(extra), dtype=np.int64),
    )


def _edge_restrictions(
    raw: RawNetwork,
    restrictions: list[tuple[int, int, int, int]],
    ends: tuple[NDArray[np.int64], NDArray[np.int64]],
    end_feat: tuple[NDArray[np.int64], NDArray[np.int64]],
    node_id: NDArray[np.int64],
) -> tuple[list[tuple[int, int, int, int]], int]:
    """The turn restrictions on the final edges (``ends``: their end nodes), and how many could
    not be mapped."""
    if not restrictions:
        return [], 0
    # per edge the way at its start and at its end (only where restrictions need them)
    end_ways = _EndWays(raw.feat_way_id[end_feat[0]].tolist(), raw.feat_way_id[end_feat[1]].tolist())
    by_id = {int(k): i for i, k in enumerate(node_id.tolist())}
    return _map_restrictions(
        restrictions, us=ends[0].tolist(), vs=ends[1].tolist(), end_ways=end_ways, by_id=by_id
    )


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
