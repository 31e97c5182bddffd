"""The prepared map file: save -> load identity, atomic writes, verification, fast plain loading."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from graph.artifact import FORMAT_VERSION, MAGIC, load_map, read_manifest, save_map
from graph.ascii import parse_ascii_map
from graph.build import build_map
from graph.errors import ArtifactError
from graph.road_graph import RoadGraph

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).resolve().parents[1]

MAP = """
a---b>>>c
|   |
d---e
"""


@pytest.fixture()
def tiny() -> RoadGraph:
    return parse_ascii_map(MAP, restrictions=[("a", "b", "e", "no")]).graph


def test_save_load_identical(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "tiny.map"
    save_map(tiny, p)
    g = load_map(p)
    assert g.equals(tiny)
    assert g.restrictions.shape == (1, 4)
    assert not g.node_xy.flags.writeable  # memory-mapped read-only
    assert [f.name for f in tmp_path.iterdir()] == ["tiny.map"]


def test_save_load_built_osm_map(tmp_path: Path) -> None:
    g = build_map(DATA / "prep_tiny.osm")
    save_map(g, tmp_path / "m.map")
    h = load_map(tmp_path / "m.map")
    assert h.equals(g)
    assert h.names == g.names and h.highways == g.highways
    assert h.meta["report"]["restrictions_read"] == 2


def test_manifest_fields(tiny: RoadGraph, tmp_path: Path) -> None:
    g = build_map(DATA / "roads_ft_tf.geojson")
    save_map(g, tmp_path / "m.map")
    m = read_manifest(tmp_path / "m.map")
    assert m["format_version"] == FORMAT_VERSION
    assert m["crs"] == g.crs == "EPSG:32633"
    assert m["counts"] == {
        "nodes": g.n_nodes,
        "edges": g.n_edges,
        "segments": len(g.seg_xy),
        "restrictions": 0,
    }
    assert m["bbox"] == pytest.approx(list(g.bbox))
    assert len(m["source"]["sha256"]) == 64 and m["source"]["format"] == "gis"
    assert m["build"]["snap_tolerance"] == 0.01
    assert m["stats"]["edge_len_max_m"] == pytest.approx(float(g.edge_len.max()))
    assert len(m["stats"]["edge_len_p5_p25_p50_p75_p95_m"]) == 5


def test_overwrite_is_atomic_and_leaves_no_temp(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    other = build_map(DATA / "roads_ft_tf.geojson")
    save_map(other, p)
    assert load_map(p).equals(other)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["m.map"]


def test_corrupt_file_fails_checksum(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    raw = bytearray(p.read_bytes())
    hlen = int(np.frombuffer(bytes(raw[8:16]), dtype=np.uint64)[0])
    t = read_manifest(p)["arrays"]["edge_len"]
    raw[16 + hlen + t["offset"] + 3] ^= 0xFF  # a byte inside edge_len
    p.write_bytes(bytes(raw))
    with pytest.raises(ArtifactError, match="checksum mismatch in edge_len"):
        load_map(p)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "not a prepared map"),
        (b"hello world, not a map at all", "not a prepared map"),
        (MAGIC[:-1] + b"\x09" + b"\0" * 8, "unsupported map file version"),
    ],
)
def test_bad_files(tmp_path: Path, content: bytes, message: str) -> None:
    p = tmp_path / "bad.map"
    p.write_bytes(content)
    with pytest.raises(ArtifactError, match=message):
        load_map(p)


def test_truncated_and_missing(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    p.write_bytes(p.read_bytes()[:-200])
    with pytest.raises(ArtifactError, match="truncated"):
        load_map(p)
    with pytest.raises(ArtifactError, match="no such map file"):
        load_map(tmp_path / "absent.map")


def test_manifest_length_beyond_file_end(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    raw = bytearray(p.read_bytes())
    raw[8:16] = np.array([2**62], dtype="<u8").tobytes()
    p.write_bytes(bytes(raw))
    with pytest.raises(ArtifactError, match="truncated or corrupt"):
        load_map(p)


def test_newer_format_version_rejected(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    raw = p.read_bytes()
    hlen = int(np.frombuffer(raw[8:16], dtype=np.uint64)[0])
    head = json.loads(raw[16 : 16 + hlen])
    head["format_version"] = FORMAT_VERSION + 1
    new = json.dumps(head, separators=(",", ":")).encode().ljust(hlen)
    assert len(new) == hlen
    p.write_bytes(raw[:16] + new + raw[16 + hlen :])
    with pytest.raises(ArtifactError, match="unsupported map format"):
        load_map(p)


def test_loading_imports_neither_osmnx_nor_networkx(tiny: RoadGraph, tmp_path: Path) -> None:
    p = tmp_path / "m.map"
    save_map(tiny, p)
    code = (
        "import sys; from graph.artifact import load_map; g = load_map(sys.argv[1]); "
        "print(g.n_edges, 'osmnx' in sys.modules, 'networkx' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(p)], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == [str(tiny.n_edges), "False", "False"]


def test_map_files_from_before_way_pieces_still_load(
    tiny: RoadGraph, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file written without the piece arrays (as before they existed) loads with one piece
    per edge, taken from the edge attributes."""
    import graph.artifact as artifact
    from graph.road_graph import ARRAY_FIELDS, PIECE_FIELDS

    old = tuple(k for k in ARRAY_FIELDS if k not in PIECE_FIELDS)
    monkeypatch.setattr(artifact, "ARRAY_FIELDS", old)
    p = tmp_path / "old.map"
    save_map(tiny, p)
    assert not set(PIECE_FIELDS) & set(read_manifest(p)["arrays"])
    monkeypatch.undo()
    g = load_map(p)
    assert g.equals(tiny)
    assert g.n_pieces == g.n_edges and np.array_equal(g.piece_way_id, g.edge_way_id)
    assert g.way_id_at(0, 1.0) == int(g.edge_way_id[0])


def test_pieces_round_trip_through_the_file(tmp_path: Path) -> None:
    g = build_map(DATA / "prep_tiny.osm")
    assert g.n_pieces > g.n_edges  # the one-way chain is made of two ways
    save_map(g, tmp_path / "t.map")
    h = load_map(tmp_path / "t.map")
    assert h.equals(g) and np.array_equal(h.piece_ptr, g.piece_ptr)


def test_the_manifest_crs_is_checked_and_a_utm_zone_needs_no_pyproj(tiny: RoadGraph, tmp_path: Path) -> None:
    import dataclasses

    bad = tmp_path / "bad.map"
    save_map(dataclasses.replace(tiny, crs="EPSG:not-a-code"), bad)
    with pytest.raises(ArtifactError, match="not a valid CRS"):
        load_map(bad)
    other = tmp_path / "other.map"
    save_map(dataclasses.replace(tiny, crs="EPSG:3035"), other)
    assert load_map(other).crs == "EPSG:3035"
    utm = tmp_path / "utm.map"
    save_map(tiny, utm)
    code = "import sys; from graph.artifact import load_map; g = load_map(sys.argv[1]); "
    code += "print(g.crs, 'pyproj' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code, str(utm)], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == [tiny.crs, "False"]
