"""`mapmatch match` end to end: real map file, real track files, real worker processes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from graph.artifact import save_map
from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.cli import main
from mapmatch.io import read_results, write_tracks
from mapmatch.parallel import RunOptions, parts_dir_for, run_batch
from mapmatch.types import Track

DRAWING = """
a-----------b-----------c
|           |           |
d-----------e-----------f
"""


def make_tracks(m: AsciiMap, n: int) -> list[Track]:
    rng = np.random.default_rng(7)
    routes = [("a", "c", 0.0), ("d", "f", 0.0), ("a", "c", 0.0)]
    out = []
    for i in range(n):
        s, e, _ = routes[i % len(routes)]
        x0, y0 = m.xy(s)
        x1, _ = m.xy(e)
        xs = np.linspace(x0 + 5, x1 - 5, 12)
        ys = y0 + rng.normal(0, 2, len(xs))
        ll = np.array([m.lonlat(x, y) for x, y in zip(xs, ys, strict=True)])
        out.append(Track(f"v{i:02d}", np.arange(len(xs)) * 3.0, ll[:, 1], ll[:, 0]))
    return out


@pytest.fixture()
def setup(tmp_path: Path) -> tuple[Path, Path, AsciiMap]:
    m = parse_ascii_map(DRAWING, scale=10)
    map_path = tmp_path / "city.map"
    save_map(m.graph, map_path)
    tracks_path = tmp_path / "fleet.csv"
    write_tracks(tracks_path, make_tracks(m, 7))
    return map_path, tracks_path, m


def test_match_command_writes_geojson(setup: tuple[Path, Path, AsciiMap], tmp_path: Path, capsys) -> None:
    map_path, tracks_path, m = setup
    out = tmp_path / "routes.geojson"
    rc = main(["match", "--map", str(map_path), str(tracks_path), "-o", str(out), "--workers", "1"])
    assert rc == 0
    assert "matched 7 track(s)" in capsys.readouterr().out
    fc = json.loads(out.read_text())
    assert [f["properties"]["track_id"] for f in fc["features"]] == [f"v{i:02d}" for i in range(7)]
    f0 = fc["features"][0]
    assert f0["geometry"]["type"] == "LineString"
    assert f0["properties"]["edges"] == [m.edge("a", "b"), m.edge("b", "c")]
    assert not parts_dir_for(out).exists()


@pytest.mark.slow  # the run in worker processes
def test_match_command_in_worker_processes_equals_in_process(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path
) -> None:
    map_path, tracks_path, _ = setup
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    assert main(["match", "--map", str(map_path), str(tracks_path), "-o", str(one), "--workers", "1",
                 "--partition-size", "2", "--no-progress"]) == 0  # fmt: skip
    assert main(["match", "--map", str(map_path), str(tracks_path), "-o", str(two), "--workers", "2",
                 "--partition-size", "2", "--no-progress"]) == 0  # fmt: skip
    a, b = pd.read_csv(one), pd.read_csv(two)
    assert len(a) == 7 * 12 and set(a["status"]) == {"matched"}
    pd.testing.assert_frame_equal(a, b)


def test_resumed_run_equals_uninterrupted_run(setup: tuple[Path, Path, AsciiMap], tmp_path: Path) -> None:
    map_path, tracks_path, _ = setup
    full = tmp_path / "full.parquet"
    run_batch(
        [tracks_path], map_path, full, options=RunOptions(workers=1, partition_size=2, ubodt_delta=300.0)
    )
    # interrupted run: stop after the second partition has been written
    out = tmp_path / "resumed.parquet"
    calls = {"n": 0}

    def boom(points: int, tracks: int) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(
            [tracks_path], map_path, out, progress=boom, options=RunOptions(workers=1, partition_size=2)
        )
    parts = sorted(parts_dir_for(out).glob("part-*.json"))  # a file output's parts: JSON lines
    assert len(parts) == 2 and not out.exists()
    s = run_batch([tracks_path], map_path, out, options=RunOptions(workers=1, partition_size=2))
    # only the 3 tracks of the 2 missing partitions were matched again
    assert s.skipped == 2 and s.partitions == 4 and s.tracks == 3
    assert not parts_dir_for(out).exists()
    pd.testing.assert_frame_equal(read_results(out), read_results(full))
    assert len(read_results(out)) == 7


def test_match_command_errors_are_one_line(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path, capsys
) -> None:
    map_path, tracks_path, _ = setup
    assert (
        main(["match", "--map", str(tmp_path / "nope.map"), str(tracks_path), "-o", str(tmp_path / "o.csv")])
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("mapmatch match: error:") and err.count("\n") == 1
    assert (
        main(["match", "--map", str(map_path), str(tmp_path / "none.csv"), "-o", str(tmp_path / "o.csv")])
        == 2
    )
    assert "no such input" in capsys.readouterr().err
    assert main(["match", "--map", str(map_path), str(tracks_path), "-o", str(tmp_path / "o.txt")]) == 2
    assert "unknown output format" in capsys.readouterr().err


def test_a_track_matched_nowhere_gets_a_hint_from_its_coordinates(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path, capsys
) -> None:
    # lat and lon swapped, projected metres, another city, and points on the map far from its roads
    map_path, _, m = setup
    good = make_tracks(m, 1)[0]
    lat, lon = np.asarray(good.lat), np.asarray(good.lon)
    x0, y0 = m.xy("a")
    cases = {
        "swapped": (lon, lat, "would lie on it with lat and lon swapped"),
        "metres": (np.full(len(lat), y0), np.full(len(lat), x0), "no point has lat/lon in degrees"),
        "elsewhere": (lat - 10.0, lon + 20.0, "lie off the map"),
    }
    for name, (la, lo, hint) in cases.items():
        f = tmp_path / f"{name}.csv"
        write_tracks(f, [Track(name, np.asarray(good.time), la, lo)])
        out = str(tmp_path / f"{name}.out.csv")
        assert main(["match", "--map", str(map_path), str(f), "-o", out, "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"entirely unmatched (first: {name}); track {name}: " in err, err
        assert hint in err, err
    # on the map but 1 km from every road: unmatched, and no coordinate mistake to point at
    far = tmp_path / "far.csv"
    ll = np.array([m.lonlat(x0 + 10.0 * i, y0 + 1000.0) for i in range(len(lat))])
    write_tracks(far, [Track("far", np.asarray(good.time), ll[:, 1], ll[:, 0])])
    out = str(tmp_path / "far.out.csv")
    assert main(["match", "--map", str(map_path), str(far), "-o", out, "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.rstrip().endswith("entirely unmatched (first: far)"), err


def test_match_command_sets_any_parameter_by_name(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path, capsys
) -> None:
    map_path, tracks_path, _ = setup
    base = ["match", "--map", str(map_path), str(tracks_path), "--workers", "1"]
    # every fix matched by default; with no road sought beyond 0.5 m of these noisy fixes (σ 2 m)
    # most are unmatched, and the run says so
    out = tmp_path / "points.csv"
    assert main([*base, "-o", str(out)]) == 0
    assert set(pd.read_csv(out)["status"]) == {"matched"}
    settings = ["--set", "batch.outliers.outlier_distance=0.5", "--set", "model.search_radius=0.5"]
    assert main([*base, "-o", str(out), *settings]) == 1
    assert (pd.read_csv(out)["status"] == "unmatched").mean() > 0.5
    capsys.readouterr()
    for bad, says in (
        ("model.nope=1", "unknown parameter(s): model.nope"),
        ("nosuch.gps_sigma=1", "nosuch: unknown section"),
        ("gps_sigma=1", "did you mean model.gps_sigma?"),
        ("batch.max_route_factor=300", "did you mean batch.route.max_route_factor?"),
        ("batch.split.max_route_factor=300", "did you mean batch.route.max_route_factor?"),
        ("model.gps_sigma=abc", "model.gps_sigma: 'abc' is not a number"),
        ("model.gps_sigma", "expected SECTION.FIELD=VALUE"),
        ("model.gps_sigma=-1", "gps_sigma must be a finite non-negative number"),
    ):
        assert main([*base, "-o", str(tmp_path / "bad.csv"), "--set", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("mapmatch match: error:") and says in err and err.count("\n") == 1
        assert not (tmp_path / "bad.csv").exists()


def test_tracks_drawn_as_lines_in_a_geopackage_or_fmm_csv_match_like_their_points(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path
) -> None:
    # FMM's inputs: trips as line features (trips.shp) or as WKT lines in a ';' CSV with times
    import geopandas as gpd
    import shapely

    map_path, _, m = setup
    tracks = make_tracks(m, 3)
    lines = [shapely.LineString(np.c_[t.lon, t.lat]) for t in tracks]
    gdf = gpd.GeoDataFrame({"id": [t.track_id for t in tracks]}, geometry=lines, crs=4326)
    gdf.to_crs(m.graph.crs).to_file(tmp_path / "trips.gpkg")  # in metres: brought back to lon/lat
    wkt = tmp_path / "trips.csv"
    rows = [f"{t.track_id};{shapely.to_wkt(g, rounding_precision=-1)};{','.join(map(str, t.time))}"
            for t, g in zip(tracks, lines, strict=True)]  # fmt: skip
    wkt.write_text("id;geom;timestamp\n" + "\n".join(rows) + "\n")
    points = tmp_path / "points.csv"
    write_tracks(points, tracks)
    outs = {}
    for src in (points, tmp_path / "trips.gpkg", wkt):
        out = tmp_path / f"{src.stem}-{src.suffix[1:]}.parquet"
        assert main(["match", "--map", str(map_path), str(src), "-o", str(out), "--workers", "1", "-q"]) == 0
        outs[src.name] = read_results(out)
    ref = outs["points.csv"]
    assert list(ref["track_id"]) == ["v00", "v01", "v02"]
    for got in outs.values():
        assert list(got["track_id"]) == list(ref["track_id"]) and list(got["edges"]) == list(ref["edges"])
        assert list(got["pt_edge"]) == list(ref["pt_edge"])
        np.testing.assert_allclose(np.concatenate(got["pt_lat"]), np.concatenate(ref["pt_lat"]), atol=1e-7)


def test_a_gis_file_of_points_is_not_a_track(tmp_path: Path, capsys) -> None:
    import geopandas as gpd
    import shapely

    m = parse_ascii_map(DRAWING, scale=10)
    save_map(m.graph, tmp_path / "city.map")
    pts = gpd.GeoDataFrame(geometry=[shapely.Point(m.lonlat(*m.xy("a")))], crs=4326)
    pts.to_file(tmp_path / "pts.geojson")
    args = ["match", "--map", str(tmp_path / "city.map"), str(tmp_path / "pts.geojson")]
    rc = main([*args, "-o", str(tmp_path / "o.csv")])
    assert rc == 2
    assert "a track is a line, but 1 feature(s) are Points" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_a_route_table_over_its_budget_is_built_shorter_with_the_same_results(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path, capsys, caplog
) -> None:
    map_path, tracks_path, _ = setup
    plain, tabled = tmp_path / "plain.csv", tmp_path / "tabled.csv"
    common = ["match", "--map", str(map_path), str(tracks_path), "--workers", "1", "--no-progress"]
    assert main([*common, "-o", str(plain)]) == 0
    # a budget of 1 kB is far below the 500 m table of this map: a shorter bound is built
    assert main([*common, "-o", str(tabled), "--ubodt", "500", "--ubodt-max-mb", "0.001"]) == 0
    from mapmatch.parallel import _MATCHERS  # one worker: this process's matcher

    (matcher,) = _MATCHERS.values()
    assert 0 < matcher.ubodt.delta < 500 and matcher.ubodt.nbytes <= int(0.001 * 2**20)
    assert "route table: 500 m would not fit in" in caplog.text and "MB; built for" in caplog.text
    pd.testing.assert_frame_equal(pd.read_csv(plain), pd.read_csv(tabled))
    capsys.readouterr()
    for bad in ("0", "-1", "nan"):
        assert main([*common, "-o", str(tmp_path / "x.csv"), "--ubodt", "500", "--ubodt-max-mb", bad]) == 2
        assert "--ubodt-max-mb must be a positive number of megabytes" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow  # worker processes and a route table built for them
def test_worker_processes_map_one_route_table_that_the_run_builds(
    setup: tuple[Path, Path, AsciiMap], tmp_path: Path
) -> None:
    from graph.artifact import load_map
    from mapmatch.route_table import Ubodt

    map_path, tracks_path, _ = setup
    plain = tmp_path / "plain.csv"
    run_batch([tracks_path], map_path, plain, options=RunOptions(workers=1, partition_size=2))
    out = tmp_path / "tabled.csv"

    def stop(points: int, tracks: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # interrupted after the first partition
        run_batch(
            [tracks_path],
            map_path,
            out,
            progress=stop,
            options=RunOptions(workers=2, partition_size=2, ubodt_delta=300.0),
        )
    (folder,) = parts_dir_for(out).glob("_route_table-*")
    shared, built = Ubodt.load(folder), Ubodt.build(load_map(map_path), 300.0)
    assert shared.delta == built.delta == 300.0 and shared.turn_cost == built.turn_cost
    for name in ("ptr", "tgt", "dist", "pred_pos"):
        np.testing.assert_array_equal(getattr(shared, name), getattr(built, name))
    # the resumed run maps the same table, and the finished run leaves nothing behind
    s = run_batch(
        [tracks_path], map_path, out, options=RunOptions(workers=2, partition_size=2, ubodt_delta=300.0)
    )
    assert s.skipped >= 1 and not parts_dir_for(out).exists()
    pd.testing.assert_frame_equal(pd.read_csv(out), pd.read_csv(plain))
    # a folder output keeps its parts, not the table
    folder_out = tmp_path / "parts"
    run_batch(
        [tracks_path],
        map_path,
        folder_out,
        options=RunOptions(workers=2, partition_size=2, ubodt_delta=300.0),
    )
    assert list(folder_out.glob("part-*.parquet")) and not list(folder_out.glob("_route_table-*"))
