"""Way pieces: an edge made of several ways (or GIS features) keeps each one, and every answer
(online, batch points, batch route, restrictions) names the way under the point.

The maps are real files built by the real pipeline (GeoJSON or OSM XML through ``build_map``)::

    A=====B=====C=====D        three features AB, BC, CD on one straight road: B and C are
                               not intersections, so the road is one edge each way
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from graph.artifact import load_map, save_map
from graph.build import build_map
from graph.projection import to_lonlat
from graph.road_graph import RoadGraph
from mapmatch.batch import BatchMatcher, point_ways, route_ways
from mapmatch.io import points_frame, results_table
from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix, Track

LON0, LAT0 = 24.94, 60.17
DLON = 0.002  # about 111 m at 60 N


def _write_geojson(path: Path, features: list[tuple[int, str, str, list[tuple[float, float]]]]) -> Path:
    fc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"id": fid, "name": name, "highway": hw, "maxspeed": 30 + 10 * i},
                "geometry": {"type": "LineString", "coordinates": [list(p) for p in coords]},
            }
            for i, (fid, name, hw, coords) in enumerate(features)
        ],
    }
    path.write_text(json.dumps(fc), encoding="utf-8")
    return path


def _pt(k: float, dy: float = 0.0) -> tuple[float, float]:
    return (LON0 + k * DLON, LAT0 + dy)


@pytest.fixture(scope="module")
def three_ways(tmp_path_factory: pytest.TempPathFactory) -> RoadGraph:
    d = tmp_path_factory.mktemp("pieces")
    src = _write_geojson(
        d / "road.geojson",
        [
            (101, "AB", "residential", [_pt(0), _pt(0.5), _pt(1)]),
            (102, "BC", "tertiary", [_pt(1), _pt(2)]),
            (103, "CD", "residential", [_pt(2), _pt(3)]),
        ],
    )
    return build_map(src)


def _edge_from_a(g: RoadGraph) -> int:
    west = int(np.argmin(g.node_lonlat[:, 0]))
    return int(g.out_of(west)[0])


def test_three_way_straight_road_keeps_each_way(three_ways: RoadGraph) -> None:
    g = three_ways
    assert g.n_edges == 2, "B and C are not intersections: one edge each way"
    e = _edge_from_a(g)
    p = np.arange(g.piece_ptr[e], g.piece_ptr[e + 1])
    assert g.piece_way_id[p].tolist() == [101, 102, 103]
    assert [g.names[i] for i in g.piece_name_idx[p]] == ["AB", "BC", "CD"]
    assert [g.highways[i] for i in g.piece_highway_idx[p]] == ["residential", "tertiary", "residential"]
    assert g.piece_speed_kph[p].tolist() == [30.0, 40.0, 50.0]
    third = float(g.edge_len[e]) / 3.0
    np.testing.assert_allclose(g.piece_start[p], [0.0, third, 2 * third], rtol=1e-6)
    np.testing.assert_allclose(g.piece_end(p), [third, 2 * third, 3 * third], rtol=1e-6)
    # the opposite direction runs through the same ways backwards
    r = int(g.edge_reverse[e])
    q = np.arange(g.piece_ptr[r], g.piece_ptr[r + 1])
    assert g.piece_way_id[q].tolist() == [103, 102, 101]
    # piece_at: vectorised, boundaries belong to the piece that begins there, ends clamp
    b1, b2 = g.piece_start[p[1]], g.piece_start[p[2]]
    offs = [-5.0, 0.0, b1 - 0.01, b1, b2 + 1.0, g.edge_len[e], g.edge_len[e] + 9.0]
    assert g.piece_way_id[g.piece_at(e, offs)].tolist() == [101, 101, 101, 102, 103, 103, 103]
    assert g.piece_at([-1, e], [0.0, 0.0]).tolist() == [-1, int(g.piece_ptr[e])]
    assert (g.way_id_at(e, 10.0), g.name_at(e, 10.0)) == (101, "AB")
    assert (g.way_id_at(r, 10.0), g.name_at(r, 10.0)) == (103, "CD")


def test_pieces_survive_the_map_file(three_ways: RoadGraph, tmp_path: Path) -> None:
    save_map(three_ways, tmp_path / "m.rgmap")
    h = load_map(tmp_path / "m.rgmap")
    assert h.equals(three_ways)
    assert h.n_pieces == 6


def _track(g: RoadGraph, ks: list[float], tid: str = "t") -> Track:
    lon = np.array([LON0 + k * DLON for k in ks])
    lat = np.full(len(ks), LAT0 + 0.00002)  # 2 m north of the road
    return Track(tid, np.arange(len(ks)) * 3.0, lat, lon)


def test_batch_route_and_points_name_every_way(three_ways: RoadGraph) -> None:
    g = three_ways
    ks = [0.1, 0.4, 0.8, 1.2, 1.6, 1.9, 2.3, 2.7, 2.9]
    r = BatchMatcher(g).match(_track(g, ks))
    assert route_ways(r, g) == ([101, 102, 103], ["AB", "BC", "CD"])
    pw, pn = point_ways(r, g)
    assert pw == [101, 101, 101, 102, 102, 102, 103, 103, 103]
    assert pn == ["AB"] * 3 + ["BC"] * 3 + ["CD"] * 3
    table = results_table([r], g)
    assert table["way_ids"][0] == [101, 102, 103] and table["names"][0] == ["AB", "BC", "CD"]
    pts = points_frame(table)
    assert pts["way_id"].tolist() == pw and pts["name"].tolist() == pn
    # driving back: the other direction, the ways in reverse order
    back = BatchMatcher(g).match(_track(g, ks[::-1]))
    assert route_ways(back, g) == ([103, 102, 101], ["CD", "BC", "AB"])


def test_batch_route_starting_and_ending_inside_one_way(three_ways: RoadGraph) -> None:
    g = three_ways
    r = BatchMatcher(g).match(_track(g, [1.2, 1.5, 1.8]))
    assert route_ways(r, g) == ([102], ["BC"])
    r = BatchMatcher(g).match(_track(g, [1.6, 2.2, 2.6]))
    assert route_ways(r, g) == ([102, 103], ["BC", "CD"])


@pytest.fixture(scope="module")
def two_ways(tmp_path_factory: pytest.TempPathFactory) -> RoadGraph:
    """A===B===C, two features on one straight road: one edge each way, two pieces."""
    d = tmp_path_factory.mktemp("two")
    src = _write_geojson(
        d / "road.geojson",
        [(201, "West Way", "residential", [_pt(0), _pt(1)]), (202, "East Way", "primary", [_pt(1), _pt(2)])],
    )
    return build_map(src)


def _fixes(g: RoadGraph, ks: list[float]) -> list[Fix]:
    out = []
    for i, k in enumerate(ks):
        out.append(Fix(time=float(i), lat=LAT0 + 0.00002, lon=LON0 + k * DLON, heading=90.0, speed=10.0))
    return out


def test_online_answers_at_both_ends_of_a_two_way_edge(two_ways: RoadGraph) -> None:
    g = two_ways
    assert g.n_edges == 2 and np.diff(g.piece_ptr).tolist() == [2, 2]
    m = OnlineMatcher(g)
    state = m.new_session()
    ks = [0.05 + 0.09 * i for i in range(22)]  # 10 m steps east from near A to near C
    res = [m.update(state, f) for f in _fixes(g, ks)]
    placed = [(k, r) for k, r in zip(ks, res, strict=True) if r.edge >= 0]
    assert placed, "the matcher places the vehicle"
    e = _edge_from_a(g)
    for k, r in placed:
        assert r.edge == e
        want = (201, "West Way", "residential") if k < 1.0 else (202, "East Way", "primary")
        if abs(k - 1.0) > 0.1:  # away from the boundary itself
            assert (r.way_id, r.name, r.road_class) == want, (k, r.offset)
        assert (r.way_id, r.name) == (g.way_id_at(r.edge, r.offset), g.name_at(r.edge, r.offset))
    first, last = placed[0][1], placed[-1][1]
    assert first.way_id == 201 and last.way_id == 202
    assert last.speed_kph == pytest.approx(40.0)
    for c in last.candidates:
        assert c.way_id == g.way_id_at(c.edge, c.offset)


def test_batch_answers_at_both_ends_of_a_two_way_edge(two_ways: RoadGraph) -> None:
    g = two_ways
    r = BatchMatcher(g).match(_track(g, [0.05, 0.3, 0.7, 1.3, 1.7, 1.95]))
    pw, pn = point_ways(r, g)
    assert pw == [201, 201, 201, 202, 202, 202]
    assert pn[0] == "West Way" and pn[-1] == "East Way"
    assert route_ways(r, g) == ([201, 202], ["West Way", "East Way"])


OSM_XML = """<?xml version="1.0" encoding="UTF-8"?>
<osm version="0.6" generator="hand">
  <node id="1" lat="60.1700" lon="24.9400"/>
  <node id="2" lat="60.1700" lon="24.9410"/>
  <node id="3" lat="60.1700" lon="24.9420"/>
  <node id="4" lat="60.1710" lon="24.9420"/>
  <node id="5" lat="60.1690" lon="24.9420"/>
  <node id="6" lat="60.1700" lon="24.9430"/>
  <way id="10"><nd ref="1"/><nd ref="2"/><tag k="highway" v="residential"/><tag k="name" v="Far"/></way>
  <way id="11"><nd ref="2"/><nd ref="3"/><tag k="highway" v="residential"/><tag k="name" v="Near"/></way>
  <way id="12"><nd ref="3"/><nd ref="4"/><tag k="highway" v="residential"/><tag k="name" v="North"/></way>
  <way id="13"><nd ref="3"/><nd ref="5"/><tag k="highway" v="residential"/><tag k="name" v="South"/></way>
  <way id="14"><nd ref="3"/><nd ref="6"/><tag k="highway" v="residential"/><tag k="name" v="East"/></way>
  <relation id="100">
    <member type="way" ref="11" role="from"/><member type="node" ref="3" role="via"/>
    <member type="way" ref="12" role="to"/>
    <tag k="type" v="restriction"/><tag k="restriction" v="no_left_turn"/>
  </relation>
  <relation id="101">
    <member type="way" ref="10" role="from"/><member type="node" ref="3" role="via"/>
    <member type="way" ref="13" role="to"/>
    <tag k="type" v="restriction"/><tag k="restriction" v="no_right_turn"/>
  </relation>
</osm>
"""


def test_restriction_across_a_way_boundary(tmp_path: Path) -> None:
    """Node 2 joins ways 10 and 11 but is no intersection: 1-2-3 is one edge of two pieces.
    ``11 -> 12`` at node 3 maps onto that edge (its last piece is way 11, which touches the
    via node); ``10 -> 13`` does not (way 10 does not reach node 3: a broken relation)."""
    src = tmp_path / "x.osm"
    src.write_text(OSM_XML, encoding="utf-8")
    g = build_map(src)
    node = {int(i): k for k, i in enumerate(g.node_id.tolist())}
    assert 2 not in node
    into3 = [int(e) for e in g.into(node[3]) if g.edge_u[e] == node[1]]
    assert len(into3) == 1
    e13 = into3[0]
    p = np.arange(g.piece_ptr[e13], g.piece_ptr[e13 + 1])
    assert g.piece_way_id[p].tolist() == [10, 11]
    to4 = next(int(e) for e in g.out_of(node[3]) if g.edge_v[e] == node[4])
    assert g.restrictions[:, :3].tolist() == [[e13, node[3], to4]]
    assert g.meta["report"]["restrictions_unmapped"] == 1
    # routing obeys it: from 1-3 to 3-4 only by going round (3-4 is a dead end: a U-turn at 4
    # or 5 or 6 is the only way), never straight from 1-3 onto 3-4
    from mapmatch.routing import shortest_route

    best = shortest_route(g, e13, 0.0, to4, 1.0)
    assert best is None or best[1][1] != to4
    to5 = next(int(e) for e in g.out_of(node[3]) if g.edge_v[e] == node[5])
    free = shortest_route(g, e13, 0.0, to5, 1.0)
    assert free is not None and free[1] == [e13, to5], "10 -> 13 was not mapped: the turn stays legal"


def test_lonlat_helpers_agree(three_ways: RoadGraph) -> None:
    g = three_ways
    e = _edge_from_a(g)
    xy = g.edge_xy(e)
    ll = to_lonlat(g.crs, xy[:, 0], xy[:, 1])
    assert ll[0, 0] == pytest.approx(LON0, abs=1e-7) and ll[-1, 0] == pytest.approx(LON0 + 3 * DLON, abs=1e-7)


def test_kubicka_way_ids_name_the_feature_under_the_point(kubicka_dir: Path) -> None:
    """REAL GPS: on Kubicka track 00000014 (448 fixes) every matched point's way id is a GIS
    feature within 1 m of the snapped point (the edge's own way id is not, for many)."""
    import geopandas as gpd
    import pandas as pd
    import shapely

    from graph.projection import to_xy

    d = kubicka_dir / "00000014"
    g = build_map(d / "roads.geojson")
    feats = gpd.read_file(d / "roads.geojson").to_crs(g.crs).set_index("id")
    tr = pd.read_csv(d / "track.csv")
    r = BatchMatcher(g).match(Track("k", tr.t.to_numpy(), tr.lat.to_numpy(), tr.lon.to_numpy()))
    ways, _ = point_ways(r, g)
    placed = [(p, w) for p, w in zip(r.points, ways, strict=True) if p.edge >= 0]
    assert len(placed) > 400
    ll = np.array([[p.lon, p.lat] for p, _ in placed])
    pts = shapely.points(to_xy(g.crs, ll[:, 0], ll[:, 1]))
    dist = shapely.distance(pts, feats.geometry.loc[[w for _, w in placed]].values)
    assert float(dist.max()) < 1.0
    edge_way = g.edge_way_id[[p.edge for p, _ in placed]]
    assert (shapely.distance(pts, feats.geometry.loc[edge_way].values) > 1.0).sum() > 50
