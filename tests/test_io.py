"""Track files in and results out: CSV, GPX, Parquet/GeoParquet round trips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import shapely

from graph.ascii import parse_ascii_map
from mapmatch.batch import BatchMatcher
from mapmatch.io import (
    Columns,
    TrackInputError,
    points_frame,
    read_fixes,
    read_results,
    read_tracks,
    results_table,
    write_results,
    write_tracks,
)
from mapmatch.types import Track


def sample_tracks() -> list[Track]:
    rng = np.random.default_rng(1)
    a = Track(
        "car-1",
        time=np.arange(5, dtype=float) + 1_700_000_000,
        lat=60.1 + rng.random(5) * 1e-3,
        lon=24.9 + rng.random(5) * 1e-3,
        heading=np.array([0.0, 10.0, np.nan, 350.0, 90.0]),
        speed=np.array([1.0, 2.0, 3.0, np.nan, 5.0]),
    )
    b = Track(
        "car-2", time=np.arange(3, dtype=float), lat=np.full(3, 60.2), lon=np.array([24.0, 24.001, 24.002])
    )
    return [a, b]


def same(a: Track, b: Track, *, optional: bool = True) -> None:
    assert a.track_id == b.track_id
    for k in ("time", "lat", "lon") + (("heading", "speed") if optional else ()):
        x, y = getattr(a, k), getattr(b, k)
        if x is None:
            assert y is None or np.isnan(y).all()
        else:
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-9)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_tabular_round_trip(tmp_path: Path, suffix: str) -> None:
    tracks = sample_tracks()
    p = tmp_path / f"tracks{suffix}"
    write_tracks(p, tracks)
    back = read_tracks(p)
    assert [t.track_id for t in back] == ["car-1", "car-2"]
    for a, b in zip(tracks, back, strict=True):
        same(a, b)


def test_gpx_round_trip(tmp_path: Path) -> None:
    tracks = sample_tracks()
    p = tmp_path / "tracks.gpx"
    write_tracks(p, tracks)
    back = read_tracks(p)
    assert [t.track_id for t in back] == ["car-1", "car-2"]
    for a, b in zip(tracks, back, strict=True):
        same(a, b)


GPX_11_GARMIN = """<?xml version="1.0" encoding="UTF-8"?>
<gpx version="1.1" creator="logger" xmlns="http://www.topografix.com/GPX/1/1"
 xmlns:gpxtpx="http://www.garmin.com/xmlschemas/TrackPointExtension/v2">
 <trk><name>drive</name><trkseg>
  <trkpt lat="60.1" lon="24.9"><time>2024-05-01T10:00:00Z</time>
   <extensions><gpxtpx:TrackPointExtension>
    <gpxtpx:speed>12.5</gpxtpx:speed><gpxtpx:course>271.5</gpxtpx:course>
   </gpxtpx:TrackPointExtension></extensions></trkpt>
  <trkpt lat="60.1" lon="24.8999"><time>2024-05-01T10:00:01Z</time></trkpt>
  <trkpt lat="60.1" lon="24.8998"><time>2024-05-01T10:00:02Z</time>
   <extensions><gpxtpx:TrackPointExtension><gpxtpx:course>bad</gpxtpx:course>
   </gpxtpx:TrackPointExtension></extensions></trkpt>
 </trkseg></trk>
</gpx>
"""


def test_gpx_course_and_speed_from_garmin_extension(tmp_path: Path) -> None:
    p = tmp_path / "garmin.gpx"
    p.write_text(GPX_11_GARMIN, encoding="utf-8")
    (t,) = read_tracks(p)
    assert t.heading is not None and t.speed is not None
    np.testing.assert_array_equal(t.heading, [271.5, np.nan, np.nan])
    np.testing.assert_array_equal(t.speed, [12.5, np.nan, np.nan])


def test_gpx_without_course_has_no_heading(tmp_path: Path) -> None:
    p = tmp_path / "plain.gpx"
    write_tracks(p, [sample_tracks()[1]])
    assert "<course>" not in p.read_text(encoding="utf-8")
    (t,) = read_tracks(p)
    assert t.heading is None and t.speed is None


def test_csv_with_custom_columns_and_iso_times(tmp_path: Path) -> None:
    p = tmp_path / "fleet.csv"
    p.write_text(
        "vehicle,ts,y,x\n"
        "7,2024-05-01T10:00:00Z,60.1,24.9\n"
        "8,2024-05-01T10:00:00Z,60.2,24.8\n"
        "7,2024-05-01T10:00:05Z,60.1001,24.9001\n"
    )
    t = read_tracks(p, columns=Columns(id="vehicle", time="ts", lat="y", lon="x"))
    assert [x.track_id for x in t] == ["7", "8"]
    assert t[0].time[1] - t[0].time[0] == 5.0
    assert t[0].heading is None
    with pytest.raises(TrackInputError, match="missing column 'lat'"):
        read_tracks(p)


def test_csv_without_id_is_one_track(tmp_path: Path) -> None:
    p = tmp_path / "drive.csv"
    p.write_text("time,lat,lon\n0,60.1,24.9\n1,60.1001,24.9\n")
    (t,) = read_tracks(p)
    assert t.track_id == "drive" and len(t) == 2


def test_common_other_column_names_are_read_without_options(tmp_path: Path) -> None:
    # Kubicka's t, a GPS logger's Latitude/Lng/Timestamp, a fleet's trip_id: no --*-col needed
    p = tmp_path / "kubicka.csv"
    p.write_text("t,lat,lon\n1,43.3887,77.1221\n2,43.3888,77.1222\n")
    (t,) = read_tracks(p)
    assert list(t.time) == [1.0, 2.0] and t.lat[1] == 43.3888
    p = tmp_path / "logger.csv"
    p.write_text(
        "trip_id,Timestamp,Latitude,Lng,course\n"
        "a,2024-05-01T10:00:00Z,60.1,24.9,90\n"
        "b,2024-05-01T10:00:00Z,60.2,24.8,180\n"
        "a,2024-05-01T10:00:05Z,60.1001,24.9001,91\n"
    )
    a, b = read_tracks(p)
    assert (a.track_id, b.track_id) == ("a", "b")
    assert a.time[1] - a.time[0] == 5.0 and a.lon[1] == 24.9001
    assert a.heading is not None and list(a.heading) == [90.0, 91.0]
    pd.read_csv(p).to_parquet(tmp_path / "logger.parquet")
    assert [x.track_id for x in read_tracks(tmp_path / "logger.parquet")] == ["a", "b"]
    # a name the user chose is not replaced, and two candidates are no answer
    with pytest.raises(TrackInputError, match="missing column 'when'"):
        read_tracks(p, columns=Columns(time="when"))
    p.write_text("t,timestamp,lat,lon\n1,1,60.1,24.9\n")
    with pytest.raises(TrackInputError, match="missing column 'time'"):
        read_tracks(p)


def test_fused_fixes_with_common_other_column_names(tmp_path: Path) -> None:
    # mapmatch replay's input: a plain GPS log (id, t, Latitude, lng, course) needs no options
    p = tmp_path / "log.csv"
    p.write_text("id,t,Latitude,lng,course\nv1,1,60.1,24.9,90\nv2,1,60.2,24.8,180\nv1,2,60.1001,24.9001,91\n")
    fixes = read_fixes(p)
    assert sorted(fixes) == ["v1", "v2"]
    got = [(f.time, f.lat, f.lon, f.heading) for f in fixes["v1"]]
    assert got == [(1.0, 60.1, 24.9, 90.0), (2.0, 60.1001, 24.9001, 91.0)]


def test_geoparquet_points_input(tmp_path: Path) -> None:
    import geopandas as gpd

    gdf = gpd.GeoDataFrame(
        {"id": ["a", "a", "b"], "time": [0.0, 1.0, 0.0]},
        geometry=gpd.points_from_xy([24.9, 24.91, 25.0], [60.1, 60.11, 60.2]),
        crs="EPSG:4326",
    )
    p = tmp_path / "pts.geoparquet"
    gdf.to_parquet(p)
    a, b = read_tracks(p)
    np.testing.assert_allclose(a.lon, [24.9, 24.91])
    np.testing.assert_allclose(b.lat, [60.2])


def test_unknown_format_is_a_clear_error(tmp_path: Path) -> None:
    p = tmp_path / "x.txt"
    p.write_text("hello")
    with pytest.raises(TrackInputError, match="unknown track format"):
        read_tracks(p)


def test_results_written_as_geojson_csv_and_geoparquet(tmp_path: Path) -> None:
    m = parse_ascii_map("a-----------b-----c", scale=10)
    ll = np.array([m.lonlat(*(m.xy("a") + [x, 2.0])) for x in (10, 50, 90, 150)])
    t = Track("t1", np.arange(4.0) * 5, ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(t)
    table = results_table([r], m.graph)
    gj = tmp_path / "out.geojson"
    write_results(gj, table)
    fc = json.loads(gj.read_text())
    (f,) = fc["features"]
    assert f["geometry"]["type"] == "LineString"
    assert f["properties"]["track_id"] == "t1"
    assert f["properties"]["edges"] == [m.edge("a", "b"), m.edge("b", "c")]
    assert f["properties"]["way_ids"] == [int(m.graph.edge_way_id[e]) for e in f["properties"]["edges"]]
    assert f["properties"]["length_m"] == pytest.approx(140, abs=0.5)
    csv = tmp_path / "out.csv"
    write_results(csv, table)
    pts = pd.read_csv(csv)
    assert list(pts["status"]) == ["matched"] * 4
    np.testing.assert_allclose(pts["dist"], 2.0, atol=1e-6)
    pq = tmp_path / "out.parquet"
    write_results(pq, table)
    back = read_results(pq)
    pd.testing.assert_frame_equal(points_frame(back), points_frame(table))
    import geopandas as gpd

    g = gpd.read_parquet(pq)
    assert g.crs.to_epsg() == 4326
    assert shapely.equals(g.geometry.iloc[0], shapely.from_wkb(table["route_wkb"].iloc[0]))


def test_line_tracks_take_their_times_from_m_values_or_a_timestamp_field(tmp_path: Path) -> None:
    p = tmp_path / "trips.csv"
    p.write_text(
        "id;geom;timestamp\n"
        "a;LINESTRING M (24.9 60.1 100, 24.91 60.1 105, 24.92 60.1 111);\n"
        "b;LINESTRING (24.9 60.2, 24.91 60.2);2026-01-01T00:00:00Z,2026-01-01T00:00:02Z\n"
        "c;LINESTRING (24.9 60.3, 24.91 60.3);\n"
    )
    a, b, c = read_tracks(p)
    assert (a.track_id, b.track_id, c.track_id) == ("a", "b", "c")
    np.testing.assert_allclose(a.time, [100, 105, 111])
    np.testing.assert_allclose(a.lon, [24.9, 24.91, 24.92])
    assert b.time[1] - b.time[0] == 2.0 and np.isnan(c.time).all()
    p.write_text("id;geom;timestamp\na;LINESTRING (24.9 60.2, 24.91 60.2);1,2,3\n")
    with pytest.raises(TrackInputError, match="3 time\\(s\\) for 2 vertices"):
        read_tracks(p)
