"""Map preparation from OpenStreetMap: the tiny committed extract, Helsinki, Monaco, Andorra."""

from __future__ import annotations

import bz2
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from conftest import helsinki_pbf
from prep_checks import assert_same_map, check_map

from graph.build import BuildOptions, OsmOptions, build_map
from graph.errors import InputError
from graph.gis import GisOptions
from graph.osm import TagFilter, is_oneway, network_filter, read_osm
from graph.road_graph import RESTRICTION_NO, RESTRICTION_ONLY, RoadGraph

DATA = Path(__file__).parent / "data"
TINY = DATA / "prep_tiny.osm"


def _edge(g: RoadGraph, a: int, b: int) -> int:
    """The edge between OSM nodes a and b."""
    ia, ib = (int(np.nonzero(g.node_id == x)[0][0]) for x in (a, b))
    es = [int(e) for e in g.out_of(ia) if g.edge_v[e] == ib]
    assert len(es) == 1, (a, b, es)
    return es[0]


def test_tiny_extract_structure() -> None:
    g = build_map(TINY)
    # nodes 2 (a bend) and 7 (inside a one-way chain) are simplified away; 8 is on a footway
    assert sorted(g.node_id.tolist()) == [1, 3, 4, 5, 6]
    assert g.n_edges == 9
    e = _edge(g, 1, 3)
    assert g.edge_way_id[e] == 10 and g.edge_name(e) == "West Street" and g.edge_highway(e) == "residential"
    assert len(g.edge_xy(e)) == 3  # keeps the vertex of node 2
    assert g.edge_reverse[e] == _edge(g, 3, 1)
    # 4 -> 7 is oneway=yes, 6 -> 7 is oneway=-1 (traffic 7 -> 6): one edge 4 -> 6, no way back
    e46 = _edge(g, 4, 6)
    assert g.edge_reverse[e46] == -1
    assert not any(
        g.edge_v[f] == g.edge_u[e46] for f in g.out_of(g.edge_v[e46]) if g.edge_way_id[f] in (13, 15)
    )
    # way 11 references node 999, missing from the file: kept up to node 4
    e34 = _edge(g, 3, 4)
    assert g.edge_speed_kph[e34] == pytest.approx(30 * 1.609344, rel=1e-6)
    assert g.edge_speed_kph[_edge(g, 3, 5)] == 40
    lonlat = g.node_lonlat[np.nonzero(g.node_id == 5)[0][0]]
    assert lonlat.tolist() == pytest.approx([24.9420, 60.1710])
    rep = g.meta["report"]
    assert rep["dropped"]["dangling node references (missing from the extract)"] == 1
    assert rep["dropped"]["way not drivable (osmnx network filter)"] == 1
    assert rep["dropped"]["restriction not from-way/via-node/to-way"] == 1


def test_tiny_extract_restrictions() -> None:
    g = build_map(TINY)
    via = int(np.nonzero(g.node_id == 3)[0][0])
    rows = sorted(map(tuple, g.restrictions.tolist()))
    assert rows == sorted(
        [
            (_edge(g, 1, 3), via, _edge(g, 3, 5), RESTRICTION_NO),  # no_left_turn
            (_edge(g, 6, 3), via, _edge(g, 3, 5), RESTRICTION_ONLY),  # only_straight_on
        ]
    )


def test_tiny_extract_checks_and_bz2(tmp_path: Path) -> None:
    raw, _, _, _ = read_osm(TINY)
    g = build_map(TINY)
    check_map(g, raw)
    packed = tmp_path / "tiny.osm.bz2"
    packed.write_bytes(bz2.compress(TINY.read_bytes()))
    assert build_map(packed).equals(g)


def test_bbox_clips_the_extract() -> None:
    g = build_map(TINY, osm=OsmOptions(bbox=(24.9395, 60.1695, 24.9445, 60.1705)))
    # nodes 5, 6, 7 fall outside: node 3 becomes a bend of the road 1 - 4
    assert sorted(g.node_id.tolist()) == [1, 4]
    assert g.n_edges == 2 and len(g.edge_xy(0)) == 4
    assert g.meta["report"]["dropped"]["node references outside the bbox"] > 0
    # an OSM build records the OSM options; the GIS ones do not apply
    assert g.meta["build"] == {
        "network_type": "drive",
        "consolidate_tolerance": None,
        "place": None,
        "bbox": [24.9395, 60.1695, 24.9445, 60.1705],
    }


def test_options_that_do_not_fit_the_source_are_refused_before_any_reading() -> None:
    with pytest.raises(InputError, match="place name or a bounding box"):
        build_map(None)
    with pytest.raises(InputError, match="a download is OpenStreetMap data"):
        build_map(None, osm=OsmOptions(place="Monaco"), gis=GisOptions(directed=True))
    with pytest.raises(InputError, match="unknown build engine 'networkx'"):
        build_map(TINY, options=BuildOptions(engine="networkx"))


def test_consolidation(helsinki: tuple[RoadGraph, nx.MultiDiGraph]) -> None:
    plain, _ = helsinki
    g = build_map(helsinki_pbf(), options=BuildOptions(consolidate_tolerance=10.0))
    assert g.n_nodes < 0.9 * plain.n_nodes
    assert g.meta["build"]["consolidate_tolerance"] == 10.0
    assert np.isfinite(g.node_lonlat).all() and (g.edge_u != g.edge_v).all()
    r = g.restrictions
    assert (
        len(r) and np.array_equal(g.edge_v[r[:, 0]], r[:, 1]) and np.array_equal(g.edge_u[r[:, 2]], r[:, 1])
    )
    assert g.stats()["road_km"] == pytest.approx(plain.stats()["road_km"], rel=0.1)
    # merged nodes keep one of their OSM ids
    assert set(g.node_id.tolist()) <= set(_real_ids(helsinki[1]))
    # the tiny map has no nodes closer than 111 m: 40 m changes nothing, 60 m merges everything
    assert_same_map(build_map(TINY, options=BuildOptions(consolidate_tolerance=40.0)), build_map(TINY))
    with pytest.raises(InputError, match="no roads left"):
        build_map(TINY, options=BuildOptions(consolidate_tolerance=60.0))


def _real_ids(raw: nx.MultiDiGraph) -> list[int]:
    return [int(n) for n in raw.nodes]


def test_filters_are_osmnx_own() -> None:
    """The owned filters equal the installed osmnx's (kept in its private module: a release
    that moves them skips this comparison; the build never imports it)."""
    from osmnx import _overpass

    from graph.osm import _DRIVE_FILTERS

    theirs = getattr(_overpass, "_get_network_filter", None)
    if theirs is None:
        pytest.skip("this osmnx has no _overpass._get_network_filter to compare with")
    for kind, text in _DRIVE_FILTERS.items():
        assert text == theirs(kind), kind
    with pytest.raises(InputError, match="unsupported network type 'walk' \\(use drive or drive_service\\)"):
        network_filter("walk")


def test_osmnx_filter_and_oneway_rules() -> None:
    drive = network_filter("drive")
    assert drive({"highway": "residential"})
    assert not drive({"highway": "footway"})
    assert not drive({"highway": "service"})
    assert not drive({"highway": "residential", "access": "private"})
    assert not drive({"highway": "primary", "motor_vehicle": "no"})
    assert not drive({"name": "no highway"})
    assert network_filter("drive_service")({"highway": "service"})
    assert TagFilter.from_overpass('["a"~"^x$"]')({"a": "x"})
    assert is_oneway({"oneway": "yes"}) and is_oneway({"junction": "roundabout"})
    assert not is_oneway({"oneway": "no"}) and not is_oneway({"oneway": "reversible"})


def test_no_drivable_roads(tmp_path: Path) -> None:
    p = tmp_path / "paths.osm"
    p.write_text(
        '<osm version="0.6"><node id="1" lat="60.17" lon="24.94"/><node id="2" lat="60.171" lon="24.94"/>'
        '<way id="5"><nd ref="1"/><nd ref="2"/><tag k="highway" v="footway"/></way></osm>'
    )
    with pytest.raises(InputError, match="no drivable roads"):
        build_map(p)


def _real(path: Path) -> tuple[RoadGraph, nx.MultiDiGraph]:
    raw, _, _, _ = read_osm(path)
    return build_map(path), raw


@pytest.fixture(scope="module")
def helsinki() -> tuple[RoadGraph, nx.MultiDiGraph]:
    return _real(helsinki_pbf())


@pytest.fixture(scope="module", params=["monaco", "andorra"])
def clipped(request: pytest.FixtureRequest, osm_dir: Path) -> tuple[RoadGraph, nx.MultiDiGraph]:
    return _real(osm_dir / f"{request.param}.osm.pbf")


def test_helsinki(helsinki: tuple[RoadGraph, nx.MultiDiGraph]) -> None:
    g, raw = helsinki
    check_map(g, raw)
    assert g.crs == "EPSG:32635"
    assert g.n_edges > 300 and g.stats()["road_km"] > 20
    assert "trail" not in g.highways
    assert len(g.restrictions) > 0
    r = g.restrictions
    assert np.array_equal(g.edge_v[r[:, 0]], r[:, 1]) and np.array_equal(g.edge_u[r[:, 2]], r[:, 1])
    assert np.isin(r[:, 3], [RESTRICTION_NO, RESTRICTION_ONLY]).all()
    assert (g.edge_way_id > 0).all() and (g.node_id > 0).all()
    assert "residential" in g.highways and len(g.names) > 10
    # this extract is clipped: highway ways reference nodes that are not in the file
    assert g.meta["report"]["dropped"]["dangling node references (missing from the extract)"] > 50


@pytest.mark.slow
def test_clipped_extracts_build(clipped: tuple[RoadGraph, nx.MultiDiGraph]) -> None:
    g, raw = clipped
    check_map(g, raw)
    assert g.n_edges > 1000
    ll = g.node_lonlat
    assert np.isfinite(ll).all()
