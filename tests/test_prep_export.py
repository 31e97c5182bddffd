"""``mapmatch export`` / ``graph.export``: every format round-trips through ``prep`` into the same
map (each two-way road once, with its one-way flag; way pieces kept), and ``mapmatch info``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio
import pytest
from prep_checks import assert_same_map

from graph.artifact import load_map, save_map
from graph.build import build_map
from graph.export import ROAD_COLUMNS, export_map, roads_frame
from graph.road_graph import RoadGraph
from mapmatch.cli import main

DATA = Path(__file__).parent / "data"
FORMATS = (".gpkg", ".geojson", ".parquet", ".fgb")


@pytest.fixture(scope="module")
def tiny() -> RoadGraph:
    return build_map(DATA / "prep_tiny.osm")


@pytest.mark.parametrize("suffix", FORMATS)
def test_export_round_trips_through_prep(tiny: RoadGraph, tmp_path: Path, suffix: str) -> None:
    out = tmp_path / f"tiny{suffix}"
    export_map(tiny, out)
    assert_same_map(tiny, build_map(out))


def test_each_two_way_road_once_with_its_oneway_flag(tiny: RoadGraph) -> None:
    roads = roads_frame(tiny)
    assert tuple(c for c in roads.columns if c != "geometry") == ROAD_COLUMNS
    two_way = int((tiny.edge_reverse >= 0).sum())
    one_way = tiny.n_edges - two_way
    per_edge = roads.groupby("edge").size()
    assert len(per_edge) == two_way // 2 + one_way
    assert roads["oneway"].sum() == int(roads[roads["reverse_edge"] < 0].shape[0])
    lens = roads.groupby("edge")["length_m"].sum()
    np.testing.assert_allclose(lens.to_numpy(), tiny.edge_len[lens.index.to_numpy()], atol=0.01)


def test_round_trip_keeps_way_pieces(tmp_path: Path) -> None:
    """A road of two features: the export has two lines with a fresh node id between them,
    and the re-prepped map joins them into one edge of two pieces again."""
    import json

    src = tmp_path / "two.geojson"
    fc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"id": i, "name": n, "oneway": ow},
                "geometry": {"type": "LineString", "coordinates": c},
            }
            for i, n, ow, c in [
                (7, "West", "no", [[24.94, 60.17], [24.941, 60.17], [24.942, 60.1701]]),
                (8, "East", "no", [[24.942, 60.1701], [24.944, 60.17]]),
                (9, "Spur", "yes", [[24.944, 60.17], [24.944, 60.171]]),
                (10, "Stub", "no", [[24.944, 60.17], [24.945, 60.169]]),
            ]
        ],
    }
    src.write_text(json.dumps(fc), encoding="utf-8")
    g = build_map(src)
    assert sorted(np.diff(g.piece_ptr).tolist()) == [1, 1, 1, 2, 2]
    out = tmp_path / "two.gpkg"
    export_map(g, out)
    roads = pyogrio.read_dataframe(out, layer="roads")
    assert len(roads) == 4  # West, East and Stub once each; Spur one way
    assert sorted(roads["oneway"].tolist()) == [False, False, False, True]
    assert sorted(roads["way_id"].tolist()) == [7, 8, 9, 10]
    inner = set(roads["u"]) & set(roads["v"]) - set(g.node_id.tolist())
    assert len(inner) == 1, "one fresh id where West meets East"
    assert_same_map(g, build_map(out))
    nodes = pyogrio.read_dataframe(out, layer="nodes")
    assert sorted(nodes["osm_id"]) == sorted(g.node_id.tolist())


def test_andorra_round_trips(osm_dir: Path, tmp_path: Path) -> None:
    pbf = osm_dir / "andorra.osm.pbf"
    if not pbf.exists():
        pytest.skip(f"needs {pbf}")
    g = build_map(pbf)
    out = tmp_path / "andorra.fgb"
    export_map(g, out)
    assert_same_map(g, build_map(out))


def test_export_and_info_commands(
    tiny: RoadGraph, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    m = tmp_path / "tiny.map"
    save_map(tiny, m)
    for suffix in FORMATS:
        out = tmp_path / f"x{suffix}"
        assert main(["export", str(m), "-o", str(out)]) == 0
        assert out.exists()
    assert "roads" in pyogrio.list_layers(tmp_path / "x.gpkg")[:, 0].tolist()
    capsys.readouterr()
    assert main(["info", str(m)]) == 0
    text = capsys.readouterr().out
    assert "nodes: 5" in text and "edges: 9" in text and "checksums: ok" in text
    assert "prep_tiny.osm" in text
    # unknown format, missing map: one line, exit 2, nothing written
    assert main(["export", str(m), "-o", str(tmp_path / "x.txt")]) == 2
    assert not (tmp_path / "x.txt").exists()
    assert main(["info", str(tmp_path / "missing.map")]) == 2
    # a corrupt array: info names it and fails
    from graph.artifact import read_manifest

    raw = bytearray(m.read_bytes())
    hlen = int(np.frombuffer(bytes(raw[8:16]), dtype="<u8")[0])
    raw[16 + hlen + read_manifest(m)["arrays"]["edge_len"]["offset"]] ^= 0xFF
    bad = tmp_path / "bad.map"
    bad.write_bytes(bytes(raw))
    capsys.readouterr()
    assert main(["info", str(bad)]) == 2
    assert "checksum mismatch" in capsys.readouterr().err
    assert load_map(m).equals(tiny)
