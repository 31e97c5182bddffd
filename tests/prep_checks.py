"""Checks shared by the map-preparation tests: a built RoadGraph against its raw source graph."""

from __future__ import annotations

from collections import Counter
from typing import Any

import networkx as nx
import numpy as np
import pytest

from graph.road_graph import RoadGraph


def to_nx(g: RoadGraph) -> nx.MultiDiGraph:
    G = nx.MultiDiGraph()
    G.add_nodes_from(range(g.n_nodes))
    G.add_edges_from(zip(g.edge_u.tolist(), g.edge_v.tolist(), strict=True))
    return G


def _partition(comps: Any, keep: dict[Any, int]) -> set[frozenset[int]]:
    """Components restricted to the kept nodes, as sets of RoadGraph node indices."""
    out = set()
    for c in comps:
        s = frozenset(keep[n] for n in c if n in keep)
        if s:
            out.add(s)
    return out


def check_connectivity(g: RoadGraph, raw: nx.MultiDiGraph) -> None:
    """Weak and strong components of ``g`` are those of the raw graph, restricted to g's nodes."""
    key_of_id = {int(d.get("osmid", n)): n for n, d in raw.nodes(data=True)}
    keep = {key_of_id[int(i)]: k for k, i in enumerate(g.node_id.tolist())}
    assert len(keep) == g.n_nodes, "every node maps to a source node"
    G = to_nx(g)
    raw_weak = _partition(nx.weakly_connected_components(raw), keep)
    assert nx.number_weakly_connected_components(raw) == nx.number_weakly_connected_components(G)
    assert raw_weak == {frozenset(c) for c in nx.weakly_connected_components(G)}
    raw_strong = _partition(nx.strongly_connected_components(raw), keep)
    assert raw_strong == {frozenset(c) for c in nx.strongly_connected_components(G)}


def unneeded_degree2(g: RoadGraph) -> list[int]:
    """Nodes that only continue one road: a two-way road (both neighbours joined by reverse
    edge pairs) or a one-way chain (one edge in, one edge out). Nodes where a one-way changes
    direction (no in or no out edge), loop splits (one neighbour) and nodes where a road splits
    into two one-way carriageways with their own geometry are needed and not listed.
    """
    bad = []
    for n in range(g.n_nodes):
        outs, ins = g.out_of(n), g.into(n)
        nbrs = set(g.edge_v[outs].tolist()) | set(g.edge_u[ins].tolist())
        if n in nbrs or len(outs) == 0 or len(ins) == 0 or len(nbrs) != 2:
            continue
        chain = len(outs) == 1 and len(ins) == 1
        two_way = len(outs) == 2 and len(ins) == 2 and set(g.edge_reverse[outs].tolist()) == set(ins.tolist())
        if chain or two_way:
            bad.append(n)
    return bad


def raw_length(raw: nx.MultiDiGraph) -> float:
    """Total directed length of the raw graph's straight pieces, in metres."""
    x = {n: (d["x"], d["y"]) for n, d in raw.nodes(data=True)}
    return float(sum(np.hypot(x[u][0] - x[v][0], x[u][1] - x[v][1]) for u, v in raw.edges()))


def oneway_ways(raw: nx.MultiDiGraph) -> tuple[set[int], set[int]]:
    """Way ids whose pieces are one-way, and those that are two-way, in the raw graph."""
    one, two = set(), set()
    for _, _, d in raw.edges(data=True):
        (one if d["oneway"] else two).add(int(d["osmid"]))
    return one, two


def check_map(g: RoadGraph, raw: nx.MultiDiGraph) -> None:
    """The structural checks of issue 2: connectivity, degree 2, one-ways, total length."""
    check_connectivity(g, raw)
    assert unneeded_degree2(g) == []
    total, src = float(g.edge_len.sum()), raw_length(raw)
    assert abs(total / src - 1.0) < 0.01, (total, src)
    one, two = oneway_ways(raw)
    n_oneway = 0
    for e in range(g.n_edges):
        w = int(g.edge_way_id[e])
        if w not in one or w in two:
            continue
        n_oneway += 1
        assert g.edge_reverse[e] == -1, f"one-way edge {e} (way {w}) has a reverse"
        u, v, xy = g.edge_u[e], g.edge_v[e], g.edge_xy(e)
        for f in g.out_of(v):
            fxy = g.edge_xy(f)
            if g.edge_v[f] == u and len(fxy) == len(xy):
                assert not np.allclose(fxy[::-1], xy, rtol=0.0, atol=0.01), (
                    f"one-way edge {e} has a reverse twin {f}"
                )
    assert n_oneway == int((g.edge_reverse < 0).sum()) or not one
    # two-way roads have their reverse: the same polyline backwards
    has = g.edge_reverse >= 0
    r = g.edge_reverse[has]
    assert np.array_equal(g.edge_reverse[r], np.nonzero(has)[0])
    assert np.array_equal(g.edge_u[r], g.edge_v[has])
    assert np.allclose(g.edge_len[r], g.edge_len[has])


def _edge_keys(g: RoadGraph) -> Counter[tuple[int, int, float, tuple[int, ...], tuple[str, ...], bool]]:
    out: Counter[tuple[int, int, float, tuple[int, ...], tuple[str, ...], bool]] = Counter()
    for e in range(g.n_edges):
        p = range(int(g.piece_ptr[e]), int(g.piece_ptr[e + 1]))
        out[
            (
                int(g.node_id[g.edge_u[e]]),
                int(g.node_id[g.edge_v[e]]),
                round(float(g.edge_len[e]), 2),
                tuple(int(g.piece_way_id[i]) for i in p),
                tuple(g.names[g.piece_name_idx[i]] if g.piece_name_idx[i] >= 0 else "" for i in p),
                bool(g.edge_reverse[e] >= 0),
            )
        ] += 1
    return out


def assert_same_map(a: RoadGraph, b: RoadGraph) -> None:
    """Same nodes (ids and places), same directed edges (ends, length, ways, names, two-way)."""
    assert (a.n_nodes, a.n_edges, a.n_pieces) == (b.n_nodes, b.n_edges, b.n_pieces)
    pa = {int(i): xy for i, xy in zip(a.node_id.tolist(), a.node_lonlat, strict=True)}
    pb = {int(i): xy for i, xy in zip(b.node_id.tolist(), b.node_lonlat, strict=True)}
    assert pa.keys() == pb.keys()
    for k, xy in pa.items():
        np.testing.assert_allclose(xy, pb[k], atol=1e-7)
    assert _edge_keys(a) == _edge_keys(b)
    np.testing.assert_allclose(np.sort(a.edge_len), np.sort(b.edge_len), rtol=1e-6)
    assert a.stats()["road_km"] == pytest.approx(b.stats()["road_km"], rel=1e-6)
    assert int((a.edge_reverse < 0).sum()) == int((b.edge_reverse < 0).sum())
    sa = np.sort(a.piece_speed_kph[np.isfinite(a.piece_speed_kph)])
    sb = np.sort(b.piece_speed_kph[np.isfinite(b.piece_speed_kph)])
    np.testing.assert_allclose(sa, sb, rtol=1e-5)
