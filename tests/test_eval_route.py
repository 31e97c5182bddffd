"""`mapmatch eval --route`: matched routes (batch and online output) scored against a true route."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from graph.artifact import save_map
from graph.ascii import parse_ascii_map
from mapmatch.cli import main
from mapmatch.route_score import read_route_geojson, score_route

GRID = """
a-----------b-----------c
|           |           |
d-----------e-----------f
"""


def _feature(lonlat: list[list[float]], **props: object) -> dict[str, object]:
    return {"type": "Feature", "geometry": {"type": "LineString", "coordinates": lonlat}, "properties": props}


def test_score_route_counts_missing_and_extra_metres(tmp_path: Path) -> None:
    m = parse_ascii_map(GRID, scale=10)
    ll = {k: list(m.lonlat(*m.xy(k))) for k in "abcdef"}
    truth = tmp_path / "truth.geojson"
    truth.write_text(json.dumps(_feature([ll["a"], ll["b"], ll["c"]], track="t1")))
    # matched: a-b right, then down b-e and along e-f instead of b-c
    routes = tmp_path / "routes.geojson"
    feats = [
        _feature([ll["a"], ll["b"], ll["e"], ll["f"]], track_id="t1"),
        _feature([ll["d"], ll["e"]], track_id="t2"),
    ]
    routes.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    _, t_parts, _ = read_route_geojson(truth)
    tid, m_parts, _ = read_route_geojson(routes, track_id="t1")
    s = score_route(t_parts, m_parts, tolerance_m=2.0)
    assert tid == "t1" and s.crs == m.graph.crs
    length = {k: float(m.graph.edge_len[m.edge(k[0], k[1])]) for k in ("ab", "bc", "be", "ef")}
    assert s.truth_m == pytest.approx(length["ab"] + length["bc"], abs=0.5)
    # b-c missed and b-e-f extra, less the 2 m tolerance around b
    assert s.rmf.missing_m == pytest.approx(length["bc"] - 2.0, abs=1.5)
    assert s.rmf.extra_m == pytest.approx(length["be"] + length["ef"] - 2.0, abs=1.5)
    perfect = score_route(t_parts, t_parts)
    assert perfect.rmf.fraction == 0.0
    # several tracks and none named: a one-line usage error
    rc = main(["eval", "--route", str(truth), "--matched", str(routes)])
    assert rc == 2
    assert main(["eval", "--route", str(truth), "--matched", str(routes), "--track-id", "t1"]) == 0


@pytest.mark.slow
def test_eval_route_scores_a_kubicka_track_batch_and_online(
    kubicka_dir: Path, tmp_path: Path, capsys
) -> None:
    """REAL GPS (Kubicka track 00000007): batch and online output against the hand-checked route."""
    from graph.build import build_map

    track = kubicka_dir / "00000007"
    map_path = tmp_path / "k.map"
    save_map(build_map(track / "roads.geojson"), map_path)
    routes = tmp_path / "routes.geojson"
    assert main(["match", "--map", str(map_path), str(track / "track.csv"), "--time-col", "t",
                 "-o", str(routes), "--workers", "1", "-q"]) == 0  # fmt: skip
    online = tmp_path / "online.csv"
    assert main(["replay", "--map", str(map_path), str(track / "track.csv"), "--time-col", "t", "-o",
                 str(online), "-q"]) == 0  # fmt: skip
    capsys.readouterr()
    rmf = {}
    for name, matched, extra in (("batch", routes, []), ("online", online, ["--map", str(map_path)])):
        assert main(["eval", "--route", str(track / "truth.geojson"), "--matched", str(matched), *extra]) == 0
        out = capsys.readouterr().out
        assert "EPSG:32643" in out  # the zone named by the truth file (utm_epsg)
        found = re.search(r"route mismatch fraction \(tol 2 m\)\s+([0-9.]+) %", out)
        assert found, out
        rmf[name] = float(found.group(1))
    # measured 0.99 % (batch) and 2.38 % (online) on this track; both well under 5 %
    assert rmf["batch"] < 5.0 and rmf["online"] < 5.0, rmf
