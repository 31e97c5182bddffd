"""RoadGraph arrays, derived fields and ASCII maps."""

from __future__ import annotations

import numpy as np
import pytest

from graph.ascii import parse_ascii_map
from graph.errors import GraphError, InputError
from graph.index import EdgeIndex, project_to_edge
from graph.road_graph import RESTRICTION_NO, Edges, Nodes, RoadGraph

CROSS = """
    a
    |
b---c>>>d
    |
    e
"""


def test_ascii_map_builds_directed_edges_with_one_ways() -> None:
    m = parse_ascii_map(CROSS, restrictions=[("b", "c", "e", "no")])
    g = m.graph
    assert g.n_nodes == 5
    # c-a, c-b, c-e two-way (6 edges) and c->d one-way (1 edge)
    assert g.n_edges == 7
    cd = m.edge("c", "d")
    assert g.edge_reverse[cd] == -1
    with pytest.raises(KeyError):
        m.edge("d", "c")
    bc = m.edge("b", "c")
    assert g.edge_reverse[bc] == m.edge("c", "b")
    assert g.edge_len[bc] == pytest.approx(40.0)
    assert g.edge_bearing_start[bc] == pytest.approx(90.0)
    assert g.edge_bearing_start[m.edge("c", "a")] == pytest.approx(0.0)
    assert g.edge_bearing_end[m.edge("c", "e")] == pytest.approx(180.0)
    assert g.restrictions.tolist() == [[bc, m.nodes["c"], m.edge("c", "e"), RESTRICTION_NO]]
    c = m.nodes["c"]
    assert sorted(g.edge_v[g.out_of(c)].tolist()) == sorted(m.nodes[x] for x in "abde")
    assert sorted(g.edge_u[g.into(c)].tolist()) == sorted(m.nodes[x] for x in "abe")


def test_stats_count_two_way_roads_once() -> None:
    g = parse_ascii_map(CROSS).graph
    s = g.stats()
    assert s["road_km"] == pytest.approx((40 + 40 + 40 + 40) / 1000)
    assert s["oneway_edges"] == 1
    assert s["edge_len_max_m"] == pytest.approx(40.0)


def test_polyline_geometry_length_and_bearings() -> None:
    g = RoadGraph.from_edges(
        "EPSG:32635",
        Nodes([[0.0, 0.0], [30.0, 40.0]]),
        Edges([0], [1], geometry=[np.array([[0.0, 0.0], [0.0, 40.0], [30.0, 40.0]])]),
    )
    assert g.edge_len[0] == pytest.approx(70.0)
    assert g.edge_bearing_start[0] == pytest.approx(0.0)
    assert g.edge_bearing_end[0] == pytest.approx(90.0)
    off, dist, px, py = project_to_edge(g, 0, 10.0, 45.0)
    assert (off, dist, px, py) == pytest.approx((50.0, 5.0, 10.0, 40.0))


def test_bad_edges_are_rejected() -> None:
    with pytest.raises(GraphError):
        RoadGraph.from_edges("EPSG:32635", Nodes([[0, 0]]), Edges([0], [3]))
    with pytest.raises(InputError):
        parse_ascii_map("a---")


def test_index_returns_both_directions_nearest_first() -> None:
    m = parse_ascii_map(CROSS)
    idx = EdgeIndex(m.graph)
    p = m.xy("c") + [-20.0, 3.0]  # beside b-c, 20 m before c
    cand = idx.query(p[None], 10.0)
    assert set(cand.edge.tolist()) == {m.edge("b", "c"), m.edge("c", "b")}
    assert cand.dist == pytest.approx([3.0, 3.0])
    by_edge = dict(zip(cand.edge.tolist(), cand.offset.tolist(), strict=True))
    assert by_edge[m.edge("b", "c")] == pytest.approx(20.0)
    assert by_edge[m.edge("c", "b")] == pytest.approx(20.0)
    far = idx.query(np.add(m.xy("a"), [500.0, 500.0])[None], 50.0)
    assert len(far) == 0
