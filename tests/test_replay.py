"""``mapmatch replay`` end to end: a CSV of fused fixes in, one result row per fix out."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from graph.artifact import save_map
from graph.ascii import parse_ascii_map
from mapmatch.cli import main
from mapmatch.fixes import RESULT_COLUMNS, read_fixes_csv
from tests.online_helpers import DriveSpec, drive

CROSS = """
        n
        |
a-------b-------c
        |
        s
"""


def write_fixes(path: Path, rows: list[dict[str, object]]) -> None:
    cols = ["vehicle_id", "time", "lat", "lon", "heading", "pos_sigma", "speed", "distance", "gps_valid"]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()})


def fix_rows(vid: str, fixes: list) -> list[dict[str, object]]:  # type: ignore[type-arg]
    return [
        {
            "vehicle_id": vid,
            "time": f.time,
            "lat": f.lat,
            "lon": f.lon,
            "heading": f.heading,
            "pos_sigma": 4.0,
            "speed": f.speed,
            "distance": f.distance,
            "gps_valid": 1,
        }
        for f in fixes
    ]


def test_replay_two_vehicles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = parse_ascii_map(CROSS, scale=10)
    save_map(m.graph, tmp_path / "cross.map")
    one = fix_rows("car-1", drive(m, "abs", DriveSpec(speed=8, noise=1.0, seed=1)))
    two = fix_rows("car-2", drive(m, "cbn", DriveSpec(speed=8, noise=1.0, seed=2, t0=100.0)))
    bad = dict(two[3], time=two[2]["time"])  # repeated time: rejected, session continues
    rows = [r for pair in zip(one, two[:3] + [bad] + two[3:], strict=False) for r in pair]
    write_fixes(tmp_path / "fixes.csv", rows)

    rc = main(["replay", "--map", str(tmp_path / "cross.map"), str(tmp_path / "fixes.csv"),
               "-o", str(tmp_path / "out.csv")])  # fmt: skip
    assert rc == 1  # done, with one fix rejected (exit status 1)
    cap = capsys.readouterr()
    assert "2 vehicle(s)" in cap.out and "1 of" in cap.err
    with open(tmp_path / "out.csv") as fh:
        out = list(csv.DictReader(fh))
    assert tuple(out[0]) == RESULT_COLUMNS
    assert len(out) == len(rows)
    car1 = [r for r in out if r["vehicle_id"] == "car-1"]
    car2 = [r for r in out if r["vehicle_id"] == "car-2"]
    assert [r["turn"] for r in car1 if r["turn"] != "none"] == ["right"]
    assert [r["turn"] for r in car2 if r["turn"] != "none"] == ["right"]
    rejected = [r for r in car2 if r["state"] == "rejected"]
    assert len(rejected) == 1 and "time" in rejected[0]["error"]
    last = car1[-1]
    assert last["state"] == "on_road"
    assert (int(last["u"]), int(last["v"])) == (ord("b"), ord("s"))
    assert int(last["edge"]) == m.edge("b", "s")
    assert abs(float(last["lat"]) - float(last["raw_lat"])) < 1e-4
    assert any(r["state"] == "ambiguous" and ":" in r["candidates"] for r in car1)


def test_replay_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = parse_ascii_map(CROSS, scale=10)
    save_map(m.graph, tmp_path / "cross.map")
    (tmp_path / "bad.csv").write_text("vehicle_id,time,lat\n1,0,60\n")
    rc = main(["replay", "--map", str(tmp_path / "cross.map"), str(tmp_path / "bad.csv"), "-o",
               str(tmp_path / "o.csv")])  # fmt: skip
    err = capsys.readouterr().err
    assert rc != 0 and err.count("\n") == 1 and "lon" in err
    assert not (tmp_path / "o.csv").exists()
    rc = main(["replay", "--map", str(tmp_path / "nope.map"), str(tmp_path / "bad.csv"), "-o", "x.csv"])
    assert rc != 0


def test_read_fixes_csv_optional_columns_and_iso_times(tmp_path: Path) -> None:
    p = tmp_path / "f.csv"
    p.write_text(
        "vehicle_id,time,lat,lon,heading,gps_valid\n"
        "v1,2024-05-01T10:00:00Z,60.1,24.9,,true\n"
        "v1,2024-05-01T10:00:01Z,60.1,24.9,90,0\n"
    )
    fixes = read_fixes_csv(p)["v1"]
    assert fixes[1].time - fixes[0].time == 1.0
    assert math.isnan(fixes[0].heading) and fixes[1].heading == 90.0
    assert fixes[0].gps_valid is True and fixes[1].gps_valid is False
    assert math.isnan(fixes[0].distance)


@pytest.mark.slow
def test_replay_on_a_real_map(tmp_path: Path, kubicka_dir: Path) -> None:
    from graph.build import build_map
    from mapmatch.sim.drive import simulate_drive, write_fixes_csv
    from mapmatch.sim.routes import random_route

    g = build_map(kubicka_dir / "00000000" / "roads.geojson")
    save_map(g, tmp_path / "k.map")
    drv = simulate_drive(
        g, random_route(g, length_m=3000.0, rng=np.random.default_rng(1)), rate=1.0, outages="none", seed=1
    )
    write_fixes_csv(drv, tmp_path / "fixes.csv")
    assert main(["replay", "--map", str(tmp_path / "k.map"), str(tmp_path / "fixes.csv"), "-o",
                 str(tmp_path / "out.csv")]) == 0  # fmt: skip
    with open(tmp_path / "out.csv") as fh:
        out = list(csv.DictReader(fh))
    assert len(out) == len(drv.fixes)
    truth = drv.truth["edge"].to_numpy()
    good = sum(int(r["edge"]) == int(e) for r, e in zip(out, truth, strict=True))
    assert good / len(out) > 0.9
