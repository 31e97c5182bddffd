"""Whole simulated drives: fused fixes and truth, files, the simulate and eval commands."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from graph.artifact import save_map
from graph.ascii import parse_ascii_map
from mapmatch.cli import main
from mapmatch.fixes import read_fixes_csv, write_results_csv
from mapmatch.sim.drive import FIX_COLUMNS, position_error, read_route, simulate_drive, write_truth
from mapmatch.sim.routes import random_route
from mapmatch.types import SnapResult, State

GRID = """
a-------b-------c-------d
|       |       |       |
e-------f-------g-------h
|       |       |       |
i-------j-------k-------l
"""


@pytest.fixture(scope="module")
def grid():  # type: ignore[no-untyped-def]
    return parse_ascii_map(GRID, scale=25.0)


@pytest.fixture(scope="module")
def drive(grid):  # type: ignore[no-untyped-def]
    route = random_route(grid.graph, length_m=6000.0, rng=np.random.default_rng(4), leg_min_m=100.0)
    return simulate_drive(grid.graph, route, rate=1, outages="120:60", seed=4)


def test_fused_stream_columns_and_accuracy(drive) -> None:  # type: ignore[no-untyped-def]
    f = drive.fixes
    assert tuple(f.columns) == FIX_COLUMNS
    assert np.all(np.diff(f["time"]) == pytest.approx(1.0))
    assert f["distance"].sum() == pytest.approx(drive.route.length, rel=0.02)
    valid = f["gps_valid"].to_numpy() > 0
    assert not valid[121:180].any() and valid[185:200].all()
    err = position_error(drive)
    assert 1.0 < err[valid].mean() < 5.0
    # dead reckoning through the outage: the error stays within its start plus 3 % of the
    # distance driven (whether it grows in one drive is chance: see tests/test_kalman.py)
    driven = f["distance"].to_numpy()[121:180].sum()
    assert err[121:180].max() < err[116:121].mean() + 0.03 * driven + 1.0
    t = drive.truth
    assert set(t["gps_outage"].unique()) == {0, 1}
    # the true edge at each fix contains the true position (within corner rounding)
    g = drive.route
    assert set(t["edge"]) <= set(g.edges.tolist())
    assert len(drive.node_index) == len(drive.route.edges) - 1
    assert np.all(np.diff(drive.node_time) >= 0)


def test_reported_sigma_is_honest_on_a_drive_with_turns_and_an_outage(drive) -> None:  # type: ignore[no-untyped-def]
    f, t = drive.fixes, drive.truth
    z = position_error(drive) / f["pos_sigma"].to_numpy()
    head = np.abs((f["heading"].to_numpy() - t["heading"].to_numpy() + 180.0) % 360.0 - 180.0)
    hz = head / f["heading_sigma"].to_numpy()
    ok = f["time"].to_numpy() > 30.0
    # a fair σ: 39 % of fixes within 1σ (2-D), 86 % within 2σ; heading 68 % and 95 %
    assert 0.15 < np.mean(z[ok] <= 1.0) < 0.75 and np.mean(z[ok] <= 2.0) > 0.6
    assert 0.45 < np.mean(hz[ok] <= 1.0) < 0.95 and np.mean(hz[ok] <= 2.0) > 0.8
    out = t["gps_outage"].to_numpy() > 0
    assert np.mean(z[out] <= 2.0) > 0.6
    sig = f["pos_sigma"].to_numpy()
    assert sig[179] > 1.5 * sig[120]


def test_ten_hz_output(grid) -> None:  # type: ignore[no-untyped-def]
    route = random_route(grid.graph, length_m=1500.0, rng=np.random.default_rng(1), leg_min_m=100.0)
    d = simulate_drive(grid.graph, route, rate=10, outages="none", seed=1)
    assert np.diff(d.fixes["time"]).max() == pytest.approx(0.1)
    assert d.fixes["gps_valid"].mean() > 0.9  # only rejected multipath fixes are not GPS-aided
    assert len(d.fix_objects()) == len(d.fixes)


def test_files_round_trip(tmp_path: Path, grid, drive) -> None:  # type: ignore[no-untyped-def]
    csv_path, gj = write_truth(grid.graph, drive, tmp_path / "truth.geojson")
    assert csv_path == tmp_path / "truth.csv" and gj.exists()
    props = json.loads(gj.read_text())["properties"]
    assert props["edges"] == drive.route.edges.tolist()
    back = read_route(grid.graph, gj)
    assert back.edges.tolist() == drive.route.edges.tolist()
    # a plain LineString (no edges) is matched to the same path
    plain = json.loads(gj.read_text())
    plain["properties"] = {}
    (tmp_path / "plain.geojson").write_text(json.dumps(plain))
    assert read_route(grid.graph, tmp_path / "plain.geojson").edges.tolist() == drive.route.edges.tolist()


def test_simulate_and_eval_commands(tmp_path: Path, grid, capsys) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    save_map(g, tmp_path / "grid.map")
    rc = main(
        ["simulate", "--map", str(tmp_path / "grid.map"), "--random-route", "--length-km", "3",
         "--outages", "60:30", "--seed", "2", "-o", str(tmp_path / "fixes.csv"),
         "--truth", str(tmp_path / "truth.csv")]
    )  # fmt: skip
    assert rc == 0
    fixes = read_fixes_csv(tmp_path / "fixes.csv")["sim-1"]
    truth = pd.read_csv(tmp_path / "truth.csv")
    assert len(fixes) == len(truth)
    # a "matcher" that returns the truth itself: a perfect score
    rows = []
    for f, t in zip(fixes, truth.itertuples(), strict=True):
        e = int(t.edge)
        res = SnapResult(
            time=f.time, state=State.ON_ROAD, edge=e,
            u=int(g.node_id[g.edge_u[e]]), v=int(g.node_id[g.edge_v[e]]),
            way_id=int(g.edge_way_id[e]), offset=float(t.offset), lat=float(t.lat), lon=float(t.lon),
        )  # fmt: skip
        rows.append(("sim-1", f, res))
    write_results_csv(tmp_path / "matched.csv", rows, g)
    capsys.readouterr()
    rc = main(
        ["eval", "--map", str(tmp_path / "grid.map"), "--truth", str(tmp_path / "truth.geojson"),
         "--matched", str(tmp_path / "matched.csv"), "--fixes", str(tmp_path / "fixes.csv"),
         "--png", str(tmp_path / "m.png"), "--html", str(tmp_path / "m.html")]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    assert "intersection traversal accuracy             100.0 %" in out
    assert "correct edge, all fixes                     100.0 %" in out
    assert (tmp_path / "m.png").stat().st_size > 10_000
    assert "leaflet" in (tmp_path / "m.html").read_text().lower()


def test_command_errors_are_one_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    rc = main(
        ["simulate", "--map", str(tmp_path / "nope.map"), "--random-route", "-o", str(tmp_path / "f.csv")]
    )
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such" in err[0] and "file" in err[0]
    rc = main(["simulate", "--map", "x", "--random-route", "--outages", "bad", "-o", str(tmp_path / "f.csv")])
    assert rc == 2 and "outages" in capsys.readouterr().err
    assert not (tmp_path / "f.csv").exists()


def test_simulate_replays_to_a_running_server(tmp_path: Path, grid, capsys) -> None:  # type: ignore[no-untyped-def]
    from service.config import ServerConfig
    from service.server import start_server

    save_map(grid.graph, tmp_path / "grid.map")
    server, port = start_server(
        ServerConfig(address="127.0.0.1:0", grace=1.0, reuse_port=False), {"grid": grid.graph}
    )
    try:
        rc = main(
            ["simulate", "--map", str(tmp_path / "grid.map"), "--random-route", "--length-km", "1.5",
             "--outages", "none", "--seed", "5", "-o", str(tmp_path / "fixes.csv"),
             "--truth", str(tmp_path / "truth.csv"), "--server", f"127.0.0.1:{port}",
             "--realtime", "--speedup", "500"]
        )  # fmt: skip
    finally:
        server.stop(0)
    out = capsys.readouterr().out
    assert rc == 0, out
    matched = pd.read_csv(tmp_path / "fixes.matched.csv")
    fixes = pd.read_csv(tmp_path / "fixes.csv")
    assert len(matched) == len(fixes) and (matched["edge"] >= 0).mean() > 0.9
    rc = main(
        ["eval", "--map", str(tmp_path / "grid.map"), "--truth", str(tmp_path / "truth.csv"),
         "--matched", str(tmp_path / "fixes.matched.csv")]
    )  # fmt: skip
    assert rc == 0
    assert "correct edge, all fixes" in capsys.readouterr().out


def test_realtime_pacing(monkeypatch: pytest.MonkeyPatch) -> None:
    from mapmatch.commands import simulate
    from mapmatch.commands.simulate import paced
    from mapmatch.types import Fix

    clock = [0.0]  # a clock that moves only when the pacing sleeps: no wall time measured
    monkeypatch.setattr(simulate.time, "monotonic", lambda: clock[0])
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        clock[0] += s

    monkeypatch.setattr(simulate.time, "sleep", sleep)
    fixes = [("v", Fix(time=100.0 + i * 0.5, lat=60.0, lon=25.0)) for i in range(5)]
    assert list(paced(fixes, realtime=True, speedup=10.0)) == fixes
    assert slept == pytest.approx([0.05] * 4) and clock[0] == pytest.approx(0.2)  # 2 s of fixes at 10x
    slept.clear()
    assert list(paced(fixes, realtime=False)) == fixes
    assert slept == []
