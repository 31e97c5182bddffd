"""The array build pipeline against the reference (``osmnx.simplify_graph``): same nodes, same
edges, lengths within 1e-6, same way pieces and restrictions; and the osmnx conversions."""

from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np
import osmnx as ox
import pytest
from conftest import helsinki_pbf
from prep_checks import assert_same_map

from graph.build import BuildOptions, build_map
from graph.road_graph import RoadGraph
from graph.simplify import from_osmnx, to_osmnx

DATA = Path(__file__).parent / "data"


def _restriction_keys(g: RoadGraph) -> list[tuple[int, int, int, int, int]]:
    r = g.restrictions
    return sorted(
        (
            int(g.node_id[g.edge_u[a]]),
            int(g.node_id[v]),
            int(g.node_id[g.edge_v[b]]),
            round(float(g.edge_len[a] + g.edge_len[b]), 2),
            int(k),
        )
        for a, v, b, k in r.tolist()
    )


def _same_as_osmnx(src: Path) -> RoadGraph:
    a = build_map(src)
    b = build_map(src, options=BuildOptions(engine="osmnx"))
    assert_same_map(a, b)
    assert _restriction_keys(a) == _restriction_keys(b)
    ra, rb = a.meta["report"], b.meta["report"]
    for k in ("weak_components", "strong_components", "source_weak_components", "source_strong_components"):
        assert ra[k] == rb[k], k
    for k in ("restrictions_unmapped", "self_loops_split", "self_loops_dropped", "raw_nodes", "raw_edges"):
        assert ra[k] == rb[k], k
    return a


@pytest.mark.parametrize("src", ["prep_tiny.osm", "roads_ft_tf.geojson"])
def test_tiny_maps_equal_osmnx(src: str) -> None:
    _same_as_osmnx(DATA / src)


def test_helsinki_equals_osmnx() -> None:
    g = _same_as_osmnx(helsinki_pbf())
    assert g.n_edges > 300 and len(g.restrictions) > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["monaco", "andorra"])
def test_osm_extracts_equal_osmnx(osm_dir: Path, name: str) -> None:
    g = _same_as_osmnx(osm_dir / f"{name}.osm.pbf")
    assert g.n_edges > 1000


@pytest.mark.slow
@pytest.mark.parametrize("track", ["00000021", "00000070", "00000007"])
@pytest.mark.parametrize("kind", ["roads.geojson", "map.osm.pbf"])
def test_kubicka_maps_equal_osmnx(kubicka_dir: Path, track: str, kind: str) -> None:
    _same_as_osmnx(kubicka_dir / track / kind)


def test_loop_road_is_split_like_osmnx(tmp_path: Path) -> None:
    """A closed two-way loop hanging off a road, and an isolated ring: both paths split the
    loop into two edges at the same vertex and keep the ring as two edges."""
    import json

    ring = [[24.95 + 0.001 * np.cos(t), 60.18 + 0.0005 * np.sin(t)] for t in np.linspace(0, 2 * np.pi, 9)]
    ring[-1] = ring[0]
    loop = [[24.94, 60.17], [24.941, 60.171], [24.942, 60.17], [24.941, 60.169], [24.94, 60.17]]
    feats = [
        {"type": "Feature", "properties": {"id": 1}, "geometry": {"type": "LineString", "coordinates": ring}},
        {"type": "Feature", "properties": {"id": 2}, "geometry": {"type": "LineString", "coordinates": loop}},
        {
            "type": "Feature",
            "properties": {"id": 3},
            "geometry": {"type": "LineString", "coordinates": [[24.94, 60.17], [24.939, 60.17]]},
        },
    ]
    src = tmp_path / "loops.geojson"
    src.write_text(json.dumps({"type": "FeatureCollection", "features": feats}), encoding="utf-8")
    g = _same_as_osmnx(src)
    assert g.meta["report"]["self_loops_split"] == 2 and (g.edge_u != g.edge_v).all()


@pytest.fixture(scope="module")
def tiny() -> RoadGraph:
    return build_map(DATA / "prep_tiny.osm")


def test_to_osmnx_and_back(tiny: RoadGraph) -> None:
    G = to_osmnx(tiny)
    assert isinstance(G, nx.MultiDiGraph) and G.graph["crs"] == tiny.crs
    assert G.number_of_nodes() == tiny.n_nodes and G.number_of_edges() == tiny.n_edges
    _, _, d = next(iter(G.edges(data=True)))
    assert {"osmid", "name", "highway", "length", "geometry", "oneway", "reversed", "speed_kph"} <= set(d)
    assert d["length"] == pytest.approx(d["geometry"].length)
    # osmnx's own tools accept it
    gdf_nodes, gdf_edges = ox.graph_to_gdfs(G)
    assert len(gdf_edges) == tiny.n_edges and len(gdf_nodes) == tiny.n_nodes
    back = from_osmnx(G)
    assert_same_map(tiny, back)


def test_from_osmnx_of_an_osmnx_graph(tmp_path: Path) -> None:
    """osmnx's own simplified graph (unprojected, as downloads give it) converts with its
    nodes, edges and way ids, and converts back to the same graph."""
    from test_prep_pieces import OSM_XML

    src = tmp_path / "x.osm"
    src.write_text(OSM_XML, encoding="utf-8")
    G = ox.graph_from_xml(src, simplify=True, retain_all=True)
    g = from_osmnx(G)
    assert g.crs == "EPSG:32635"
    assert sorted(g.node_id.tolist()) == sorted(G.nodes)
    want = sorted((u, v) for u, v, _ in G.edges(keys=True) if u != v)
    assert sorted(zip(g.node_id[g.edge_u].tolist(), g.node_id[g.edge_v].tolist(), strict=True)) == want
    lens = sorted(d["length"] for u, v, d in G.edges(data=True) if u != v)
    # osmnx measures great-circle metres, the map UTM grid metres (scale factor up to 0.4 %)
    np.testing.assert_allclose(np.sort(g.edge_len), lens, rtol=5e-3)
    H = to_osmnx(g)
    assert sorted(H.nodes) == sorted(G.nodes)
    assert sorted((u, v) for u, v, _ in H.edges(keys=True)) == want
