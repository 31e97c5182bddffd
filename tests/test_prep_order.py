"""The prepared map's edges in spatial order (:mod:`graph.order`): a Hilbert curve
through the roads, both directions of a road side by side, the same map as the source's order."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import helsinki_pbf

from graph.build import BuildOptions, build_map
from graph.order import hilbert_key, spatial_edge_order, take_edges
from graph.road_graph import Edges, Labels, Nodes, Pieces, Polylines, RoadGraph


def test_the_hilbert_curve_visits_every_cell_once_stepping_to_a_neighbour() -> None:
    x, y = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    x, y = x.ravel(), y.ravel()
    key = hilbert_key(x, y, bits=4)
    assert sorted(key.tolist()) == list(range(256))
    o = np.argsort(key)
    steps = np.abs(np.diff(x[o])) + np.abs(np.diff(y[o]))
    assert (steps == 1).all()
    assert (x[o[0]], y[o[0]]) == (0, 0) and (x[o[-1]], y[o[-1]]) == (15, 0)


def _neighbour_gap(g: RoadGraph, *, within: float = 150.0, sample: int = 400) -> float:
    """Median index distance between an edge and the edges whose midpoints lie within ``within``."""
    mid = (g.node_xy[g.edge_u] + g.node_xy[g.edge_v]) / 2
    pick = np.random.default_rng(0).choice(g.n_edges, size=min(sample, g.n_edges), replace=False)
    gaps = []
    for e in pick.tolist():
        near = np.nonzero(np.hypot(*(mid - mid[e]).T) <= within)[0]
        gaps.append(np.abs(near - e))
    return float(np.median(np.concatenate(gaps)))


def test_a_built_map_keeps_nearby_roads_at_nearby_indices() -> None:
    ordered = build_map(helsinki_pbf())
    source = build_map(
        helsinki_pbf(), options=BuildOptions(engine="osmnx")
    )  # osmnx's order: by node, as read
    assert ordered.n_edges == source.n_edges > 300
    # edges near each other in space are near each other in the arrays
    near_o, near_s = _neighbour_gap(ordered), _neighbour_gap(source)
    assert near_o < 0.05 * ordered.n_edges
    assert near_o < near_s / 4, (near_o, near_s)
    # both directions of a two-way road side by side
    two = np.nonzero(ordered.edge_reverse >= 0)[0]
    assert len(two) > 150
    # (all but a few: parallel roads between the same two nodes share a place in the order)
    assert np.mean(np.abs(ordered.edge_reverse[two] - two) == 1) > 0.95


def test_taking_edges_carries_geometry_attributes_pieces_and_restrictions() -> None:
    #   0 --a--> 1 --b--> 2, and c back from 2 to 0; a restriction a -> b
    kw = {
        "crs": "EPSG:32635",
        "nodes": Nodes(np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]])),
        "edges": Edges(
            u=np.array([0, 1, 2], dtype=np.int32),
            v=np.array([1, 2, 0], dtype=np.int32),
            geometry=Polylines(
                np.array([[0, 0], [50, 1], [100, 0], [100, 0], [100, 100], [100, 100], [0, 0]], dtype=float),
                np.array([0, 3, 5, 7]),
            ),
            way_id=np.array([10, 20, 30]),
            name=Labels.of(["A", "B", None]),
            highway=["primary", "residential", "service"],
            speed_kph=np.array([50, 30, 20], dtype=np.float32),
        ),
        "restrictions": [(0, 1, 1, 1)],
        "pieces": Pieces(
            edge=np.array([0, 0, 1, 2]),
            start=np.array([0.0, 50.0, 0.0, 0.0]),
            way_id=np.array([10, 11, 20, 30]),
            name=["A", "A2", "B", None],
            highway=Labels.of(["primary", "primary", "residential", "service"]),
            speed_kph=np.array([50, 40, 30, 20], dtype=np.float32),
        ),
    }
    order = np.array([2, 0, 1])
    g0 = RoadGraph.from_edges(**kw)
    g1 = RoadGraph.from_edges(**take_edges(kw, order))
    for new, old in enumerate(order.tolist()):
        np.testing.assert_array_equal(g1.edge_xy(new), g0.edge_xy(old))
        assert g1.edge_len[new] == pytest.approx(g0.edge_len[old], rel=1e-12)  # (summed along the array)
        assert (g1.edge_name(new), g1.edge_highway(new)) == (g0.edge_name(old), g0.edge_highway(old))
        assert g1.edge_way_id[new] == g0.edge_way_id[old]
        for off in (0.0, 60.0):
            assert g1.piece_fields(g1.piece_index(new, off)) == g0.piece_fields(g0.piece_index(old, off))
    # the restriction a -> b follows its edges: a is now 1, b is 2
    assert g1.restrictions.tolist() == [[1, 1, 2, 1]]
    assert g0.restrictions.tolist() == [[0, 1, 1, 1]]


def test_spatial_order_groups_roads_of_one_place_and_keeps_twins_together() -> None:
    # two towns 10 km apart, their streets alternating in the source's order
    rng = np.random.default_rng(1)
    town = np.vstack([rng.uniform(0, 500, (20, 2)), rng.uniform(10_000, 10_500, (20, 2))])
    u = np.array([i if k % 2 == 0 else 20 + i for k, i in enumerate(np.repeat(np.arange(0, 19), 2))])
    v = u + 1
    u, v = np.concatenate([u, v]), np.concatenate([v, u])  # and every street back
    order = spatial_edge_order(town, u, v)
    assert sorted(order.tolist()) == list(range(len(u)))
    first = (u[order] < 20)[: len(u) // 2]
    assert first.all() or (~first).all()
    # a street's two directions are neighbours
    pair = {(min(a, b), max(a, b)) for a, b in zip(u.tolist(), v.tolist(), strict=True)}
    assert len(pair) == len(u) // 2
    ends = [(min(a, b), max(a, b)) for a, b in zip(u[order].tolist(), v[order].tolist(), strict=True)]
    assert all(ends[k] == ends[k + 1] for k in range(0, len(ends), 2))
