"""Map preparation from GIS road centre lines: tiny committed GeoJSON, generated Shapefile and
GeoPackage, and Kubicka roads.geojson files."""

from __future__ import annotations

import json
from pathlib import Path

import geopandas as gpd
import networkx as nx
import numpy as np
import pytest
import shapely
from prep_checks import check_map, to_nx

from graph.build import BuildOptions, build_map
from graph.errors import InputError
from graph.gis import BOTH, FORWARD, REVERSE, GisOptions, OnewayConvention, lines_to_graph
from graph.road_graph import RoadGraph

DATA = Path(__file__).parent / "data"
FT_TF = DATA / "roads_ft_tf.geojson"
ORIGIN = (14.42, 50.08)  # origin of the tiny map; one unit is 0.001 degree


def _node(g: RoadGraph, x: float, y: float) -> int:
    ll = np.array([ORIGIN[0] + x * 0.001, ORIGIN[1] + y * 0.001])
    d = np.hypot(*(g.node_lonlat - ll).T)
    i = int(np.argmin(d))
    assert d[i] < 1e-7, (x, y)
    return i


def _edges(g: RoadGraph, a: tuple[float, float], b: tuple[float, float]) -> list[int]:
    u, v = _node(g, *a), _node(g, *b)
    return [int(e) for e in g.out_of(u) if g.edge_v[e] == v]


def test_ft_tf_oneways_and_fields() -> None:
    g = build_map(FT_TF)
    assert g.n_nodes == 8 and g.n_edges == 10
    # DIR=FT: only in digitised direction; DIR=TF: only against it
    assert len(_edges(g, (2, 0), (3, 0))) == 1 and _edges(g, (3, 0), (2, 0)) == []
    assert len(_edges(g, (2, 0), (2, 1))) == 1 and _edges(g, (2, 1), (2, 0)) == []
    (ft,) = _edges(g, (2, 0), (3, 0))
    assert g.edge_reverse[ft] == -1 and g.edge_name(ft) == "Main" and g.edge_speed_kph[ft] == 50
    (tf,) = _edges(g, (2, 0), (2, 1))
    assert g.edge_speed_kph[tf] == pytest.approx(30 * 1.609344, rel=1e-6)
    # B, and a null value, are two-way; the MultiLineString's two parts become one bent edge
    (bend,) = _edges(g, (3, 0), (4, -1))
    assert g.edge_reverse[bend] >= 0 and len(g.edge_xy(bend)) == 3 and g.edge_way_id[bend] == 4
    assert len(_edges(g, (3, 1), (3, 0))) == 1
    # the first line's middle vertex is simplified away
    (main,) = _edges(g, (0, 0), (2, 0))
    assert len(g.edge_xy(main)) == 3
    # the bridge crosses Main without a shared vertex: not connected by default
    assert nx.number_weakly_connected_components(to_nx(g)) == 2
    rep = g.meta["report"]
    assert rep["dropped"] == {"not a line": 1}
    assert rep["fields"]["oneway_field"] == "DIR" and rep["fields"]["name_field"] == "NAME"
    raw, _, _, _ = lines_to_graph(FT_TF, GisOptions())
    check_map(g, raw)


def test_noding_at_crossings_is_an_option() -> None:
    g = build_map(FT_TF, gis=GisOptions(node_crossings=True))
    assert nx.number_weakly_connected_components(to_nx(g)) == 1
    assert g.n_nodes == 9 and g.n_edges == 14
    raw, _, _, _ = lines_to_graph(FT_TF, GisOptions(node_crossings=True))
    check_map(g, raw)
    # one-way pieces keep their direction after noding
    assert _edges(g, (3, 0), (2, 0)) == []


def test_oneway_conventions() -> None:
    c = OnewayConvention()
    assert [c.code(v) for v in (True, "yes", 1, "FT", "T")] == [FORWARD] * 5
    assert [c.code(v) for v in (-1, "-1", "TF", "reverse")] == [REVERSE] * 4
    assert [c.code(v) for v in (False, "no", 0, "B", None, float("nan"), "F")] == [BOTH] * 7
    assert c.code("sometimes") is None
    custom = OnewayConvention.parse("forward=N;reverse=S;both=NS")
    assert (custom.code("n"), custom.code("S"), custom.code("ns")) == (FORWARD, REVERSE, BOTH)
    with pytest.raises(InputError, match="unknown group"):
        OnewayConvention.parse("up=1")
    # a convention that reads FT as two-way and B as one-way changes the graph
    g = build_map(FT_TF, gis=GisOptions(oneway_convention=OnewayConvention.parse("forward=B;both=FT,TF")))
    assert len(_edges(g, (3, 0), (2, 0))) == 1 and _edges(g, (4, -1), (3, 0)) == []


def test_missing_field_is_an_error() -> None:
    with pytest.raises(InputError, match="one-way field 'ONEWAY'"):
        build_map(FT_TF, gis=GisOptions(oneway_field="ONEWAY"))


def _frame() -> gpd.GeoDataFrame:
    df = gpd.read_file(FT_TF)
    return df[df.geometry.geom_type != "Point"]


def test_shapefile_in_projected_crs_matches_geojson(tmp_path: Path) -> None:
    shp = tmp_path / "roads.shp"
    _frame().to_crs("EPSG:3035").to_file(shp)
    g = build_map(shp)
    ref = build_map(FT_TF)
    assert (g.n_nodes, g.n_edges) == (ref.n_nodes, ref.n_edges)
    assert g.crs == ref.crs
    assert np.sort(g.edge_len) == pytest.approx(np.sort(ref.edge_len), abs=1e-3)
    assert int((g.edge_reverse < 0).sum()) == int((ref.edge_reverse < 0).sum()) == 2


@pytest.mark.filterwarnings("ignore:.crs. was not provided")
def test_geopackage_without_crs(tmp_path: Path) -> None:
    projected = _frame().to_crs("EPSG:3035").set_crs(None, allow_override=True)
    p = tmp_path / "nocrs.gpkg"
    projected.to_file(p, driver="GPKG")
    with pytest.raises(InputError, match="no readable CRS"):
        build_map(p)
    assert build_map(p, gis=GisOptions(crs="EPSG:3035")).n_edges == 10
    with pytest.raises(InputError, match="unreadable CRS"):
        build_map(p, gis=GisOptions(crs="EPSG:not-a-crs"))
    lonlat = tmp_path / "lonlat.gpkg"
    _frame().set_crs(None, allow_override=True).to_file(lonlat, driver="GPKG")
    assert build_map(lonlat).n_edges == 10  # coordinates fit lon/lat: assumed WGS84


def test_snap_tolerance(tmp_path: Path) -> None:
    # two lines whose ends are ~0.4 m apart
    a = shapely.LineString([(14.42, 50.08), (14.421, 50.08)])
    b = shapely.LineString([(14.421005, 50.08), (14.422, 50.08)])
    p = tmp_path / "gap.geojson"
    gpd.GeoDataFrame({"oneway": [False, False]}, geometry=[a, b], crs="EPSG:4326").to_file(p)
    assert build_map(p).n_nodes == 4
    g = build_map(p, gis=GisOptions(snap_tolerance=1.0))
    assert g.n_nodes == 2 and g.n_edges == 2  # joined, and the joint simplified away
    assert g.meta["report"]["fields"]["merged_endpoints"] == 1


def test_topology_from_node_ids(tmp_path: Path) -> None:
    # a bridge: two roads whose ends meet at one position but are different nodes (u/v ids)
    c = (14.421, 50.08)
    lines = [
        shapely.LineString([(14.42, 50.08), c]),
        shapely.LineString([c, (14.422, 50.08)]),
        shapely.LineString([(14.421, 50.079), c]),
        shapely.LineString([c, (14.421, 50.081)]),
    ]
    df = gpd.GeoDataFrame(
        {"u": [1, 2, 4, 5], "v": [2, 3, 5, 6], "oneway": [False] * 4}, geometry=lines, crs=4326
    )
    p = tmp_path / "bridge.geojson"
    df.to_file(p)
    g = build_map(p)
    assert g.meta["report"]["fields"]["topology"] == "node id fields"
    assert nx.number_weakly_connected_components(to_nx(g)) == 2
    assert sorted(g.node_id.tolist()) == [1, 3, 4, 6]  # 2 and 5 only continue their road
    raw, _, _, _ = lines_to_graph(p, GisOptions())
    check_map(g, raw)
    joined = build_map(p, gis=GisOptions(topology="endpoints"))
    assert nx.number_weakly_connected_components(to_nx(joined)) == 1 and joined.n_nodes == 5
    assert joined.meta["report"]["fields"]["node_ids"] == "generated"
    # ids that name far-apart ends are not node ids
    df["v"] = [2, 3, 5, 2]
    df.to_file(p)
    assert build_map(p).meta["report"]["fields"]["topology"] == "shared endpoints"
    with pytest.raises(InputError, match="not node ids"):
        build_map(p, gis=GisOptions(topology="ids"))
    with pytest.raises(InputError, match="needs integer u/v"):
        build_map(FT_TF, gis=GisOptions(topology="ids"))


def test_no_line_features(tmp_path: Path) -> None:
    p = tmp_path / "points.geojson"
    p.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "Point", "coordinates": [1, 2]},
                    }
                ],
            }
        )
    )
    with pytest.raises(InputError, match="no line features"):
        build_map(p)


@pytest.mark.parametrize("track", ["00000021", "00000070", "00000007"])
def test_kubicka_maps(kubicka_dir: Path, track: str) -> None:
    src = kubicka_dir / track / "roads.geojson"
    meta = json.loads((kubicka_dir / track / "meta.json").read_text())
    g = build_map(src)
    raw, _, _, _ = lines_to_graph(src, GisOptions())
    assert raw.number_of_nodes() == meta["nodes"] and raw.number_of_edges() == meta["arcs"]
    check_map(g, raw)
    G = to_nx(g)
    assert nx.number_weakly_connected_components(G) == meta["weak_components"]
    # the source's strong components are those of the raw graph; check_map compared them
    # with the built map's on the nodes it keeps
    assert nx.number_strongly_connected_components(raw) == meta["strong_components"]
    assert g.meta["report"]["fields"]["topology"] == "node id fields"
    # one-way length: every one-way feature, and nothing else, has no reverse
    feats = gpd.read_file(src).to_crs(g.crs)
    oneway_len = float(feats.length[feats["oneway"].astype(bool)].sum())
    assert float(g.edge_len[g.edge_reverse < 0].sum()) == pytest.approx(oneway_len, rel=1e-6)
    assert (g.edge_way_id >= 0).all()
    # node ids are the source's node indices (the u/v fields)
    assert g.meta["report"]["fields"]["node_ids"] == "u/v fields"
    assert set(g.node_id.tolist()) <= set(feats["u"]) | set(feats["v"])
    ll = gpd.read_file(src)
    for _, f in ll.iloc[:50].iterrows():
        hit = np.nonzero(g.node_id == f["u"])[0]
        if len(hit):
            x, y = f.geometry.coords[0]
            assert g.node_lonlat[hit[0]] == pytest.approx([x, y], abs=1e-9)


def test_progress_within_the_long_steps(tmp_path: Path) -> None:
    # a GeoPackage knows its feature count: the reading step says how far it has come
    p = tmp_path / "roads.gpkg"
    _frame().to_file(p, driver="GPKG")
    said: list[str] = []
    g = build_map(p, options=BuildOptions(progress_interval=0.0), progress=said.append)
    assert g.n_edges == 10
    assert "reading roads.gpkg: 6 of 6 features (100%)" in said
    walk = [m for m in said if m.startswith("simplifying: ")]
    assert walk and all(m.endswith(" paths still growing") for m in walk)
    assert said.index("reading GIS lines from roads.gpkg") < said.index(walk[0])


def test_directed_lines_are_one_way_arcs(tmp_path: Path) -> None:
    # a network of directed arcs (FMM's format): the two-way road a-b is two lines, b->c one
    a, b, c = (14.42, 50.08), (14.421, 50.08), (14.421, 50.081)
    lines = [shapely.LineString([a, b]), shapely.LineString([b, a]), shapely.LineString([b, c])]
    # ids as integer text, as a DBF character field holds them
    df = gpd.GeoDataFrame({"id": ["11", "12", "13"], "name": ["x", "x", "y"]}, geometry=lines, crs=4326)
    p = tmp_path / "arcs.geojson"
    df.to_file(p)
    g = build_map(p, gis=GisOptions(directed=True))
    assert g.n_edges == 3
    ab, ba, bc = (_edges(g, x, y) for x, y in (((0, 0), (1, 0)), ((1, 0), (0, 0)), ((1, 0), (1, 1))))
    assert [g.edge_way_id[e] for e in ab + ba + bc] == [11, 12, 13]
    assert _edges(g, (1, 1), (1, 0)) == []
    assert g.meta["report"]["fields"]["directed"] is True
    # the two arcs of a-b are one road's two directions (a U-turn on it is possible), b-c has none
    assert g.edge_reverse[ab[0]] == ba[0] and g.edge_reverse[ba[0]] == ab[0] and g.edge_reverse[bc[0]] == -1
    # without the option every line is two-way: a-b is drawn twice
    assert build_map(p).n_edges == 6
    with pytest.raises(InputError, match="not both"):
        build_map(p, gis=GisOptions(directed=True, oneway_field="id"))
    with pytest.raises(InputError, match="GIS input option"):
        build_map(DATA / "prep_tiny.osm", gis=GisOptions(directed=True))
    with pytest.raises(InputError, match="id field 'name' does not hold integers"):
        build_map(p, gis=GisOptions(id_field="name"))
