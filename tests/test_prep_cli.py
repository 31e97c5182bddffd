"""``mapmatch prep``: summary, export, --help, and one-line errors with no artifact left behind."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import geopandas as gpd
import pyogrio
import pytest
from conftest import helsinki_pbf

from graph.artifact import load_map
from graph.export import ROAD_COLUMNS
from mapmatch.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapmatch", "prep", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )


def test_prep_osm_with_summary_and_gpkg_export(tmp_path: Path) -> None:
    out, exp = tmp_path / "tiny.map", tmp_path / "tiny.gpkg"
    r = _run(str(DATA / "prep_tiny.osm"), "-o", str(out), "--export", str(exp))
    assert r.returncode == 0, r.stderr
    assert "nodes: 5   edges: 9 (1 one-way)" in r.stdout
    assert "components: 1 weak" in r.stdout
    assert "turn restrictions: 2 read, 2 rows on edges" in r.stdout
    assert "1 dangling node references" in r.stdout
    assert "reading OSM XML" in r.stderr  # progress
    g = load_map(out)
    roads = pyogrio.read_dataframe(exp, layer="roads")
    nodes = pyogrio.read_dataframe(exp, layer="nodes")
    assert len(nodes) == g.n_nodes
    # every road once: a two-way road along its lower-numbered edge, a one-way in its direction
    e = roads["edge"].to_numpy()
    assert sorted(set(e.tolist())) == [
        i for i in range(g.n_edges) if g.edge_reverse[i] < 0 or i < g.edge_reverse[i]
    ]
    first = roads[roads["piece"] == 0]
    assert first["u"].tolist() == g.node_id[g.edge_u[first["edge"]]].tolist()
    assert roads["way_id"].tolist() == g.piece_way_id[g.piece_ptr[e] + roads["piece"].to_numpy()].tolist()
    assert roads["oneway"].tolist() == (g.edge_reverse[e] < 0).tolist()
    assert sorted(nodes["osm_id"]) == [1, 3, 4, 5, 6]
    assert set(roads["name"]) >= {"West Street", "North Road"}


def test_prep_gis_with_options_and_geojson_export(tmp_path: Path) -> None:
    out, exp = tmp_path / "g.map", tmp_path / "g.geojson"
    args = [str(DATA / "roads_ft_tf.geojson"), "-o", str(out), "--export", str(exp), "-q"]
    args += [
        "--oneway-field",
        "DIR",
        "--oneway-convention",
        "forward=FT;reverse=TF;both=B",
        "--node-crossings",
    ]
    assert main(["prep", *args]) == 0
    g = load_map(out)
    assert g.n_edges == 14 and g.meta["build"]["node_crossings"] is True
    fc = json.loads(exp.read_text())
    two_way = int((g.edge_reverse >= 0).sum())
    assert len({f["properties"]["edge"] for f in fc["features"]}) == two_way // 2 + g.n_edges - two_way
    e0 = fc["features"][0]
    assert set(e0["properties"]) == set(ROAD_COLUMNS)
    assert gpd.read_file(exp).crs.to_epsg() == 4326


def test_help_explains_every_option(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["prep", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    prep = sub.choices["prep"]
    opts = [a for a in prep._actions if a.option_strings and a.dest != "help"]
    assert len(opts) >= 18
    for a in opts:
        assert a.help and len(a.help) > 15, a.option_strings
        assert a.option_strings[-1] in text
    for word in ("--place", "--export", "--node-id-fields", "forward=FT;reverse=TF"):
        assert word in text


def _corrupt_pbf(tmp: Path) -> Path:
    p = tmp / "broken.osm.pbf"
    p.write_bytes(helsinki_pbf().read_bytes()[:3000])
    return p


def _garbage_pbf(tmp: Path) -> Path:
    p = tmp / "garbage.osm.pbf"
    p.write_bytes(b"\x00\x00\x00\x0dnot a pbf at all" * 50)
    return p


def _footways(tmp: Path) -> Path:
    p = tmp / "footways.osm"
    p.write_text(
        '<osm version="0.6"><node id="1" lat="60.17" lon="24.94"/><node id="2" lat="60.171" lon="24.94"/>'
        '<way id="5"><nd ref="1"/><nd ref="2"/><tag k="highway" v="footway"/></way></osm>'
    )
    return p


def _points(tmp: Path) -> Path:
    p = tmp / "points.geojson"
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
    return p


def _no_crs(tmp: Path) -> Path:
    df = gpd.read_file(DATA / "roads_ft_tf.geojson")
    df = df[df.geometry.geom_type != "Point"].to_crs("EPSG:3035")
    p = tmp / "nocrs.shp"
    df.to_file(p)
    p.with_suffix(".prj").unlink()
    return p


def _unknown(tmp: Path) -> Path:
    p = tmp / "roads.csv"
    p.write_text("a,b\n1,2\n")
    return p


def _missing(tmp: Path) -> Path:
    return tmp / "nowhere.osm.pbf"


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (_missing, "no such file"),
        (_unknown, "unknown input format"),
        (_footways, "no drivable roads"),
        (_corrupt_pbf, "corrupt or unreadable OSM file"),
        (_garbage_pbf, "corrupt or unreadable OSM file"),
        (_points, "no line features"),
        (_no_crs, "no readable CRS"),
    ],
)
def test_bad_input_one_line_error_no_artifact(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object, message: str
) -> None:
    src = make(tmp_path)  # type: ignore[operator]
    outdir = tmp_path / "out"
    outdir.mkdir()
    code = main(["prep", str(src), "-o", str(outdir / "m.map"), "--export", str(outdir / "m.gpkg"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("mapmatch prep: error: ") and message in err, err
    assert list(outdir.iterdir()) == []


def test_failed_build_keeps_the_old_map_and_no_traceback(tmp_path: Path) -> None:
    out = tmp_path / "m.map"
    assert _run(str(DATA / "prep_tiny.osm"), "-o", str(out), "-q").returncode == 0
    before = out.read_bytes()
    r = _run(str(_corrupt_pbf(tmp_path)), "-o", str(out), "-q")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.osm.pbf", "m.map"]


def test_usage_errors(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["prep", "-o", str(tmp_path / "m.map")]) == 2
    assert "give a SOURCE file" in capsys.readouterr().err
    assert main(["prep", str(DATA / "prep_tiny.osm"), "-o", str(tmp_path / "m.map"), "--bbox", "1,2,3"]) == 2
    assert "--bbox must be" in capsys.readouterr().err
    assert (
        main(["prep", str(DATA / "prep_tiny.osm"), "-o", str(tmp_path / "m.map"), "--export", "x.kml"]) == 2
    )
    assert "--export: unknown format" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # two prep processes building a map from a GIS file
def test_quiet_prep_says_nothing_on_stderr(tmp_path: Path) -> None:
    out = tmp_path / "tiny.map"
    r = _run(str(DATA / "roads_ft_tf.geojson"), "-o", str(out), "-q")
    assert r.returncode == 0 and out.exists()
    assert r.stderr == ""
    loud = _run(str(DATA / "roads_ft_tf.geojson"), "-o", str(out))
    assert "reading GIS lines from roads_ft_tf.geojson" in loud.stderr
