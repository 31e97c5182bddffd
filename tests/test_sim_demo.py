"""The demo's non-service parts: simulate, match with a given function, score, draw."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from graph.ascii import parse_ascii_map
from mapmatch.sim.demo import demo_drive, evaluate_and_draw, prepare_helsinki
from mapmatch.types import Fix, SnapResult, State

GRID = """
a-------b-------c-------d
|       |       |       |
e-------f-------g-------h
|       |       |       |
i-------j-------k-------l
"""


def test_evaluate_and_draw_with_a_perfect_snapper(tmp_path: Path) -> None:
    amap = parse_ascii_map(GRID, scale=25.0)
    g = amap.graph
    drive = demo_drive(g, length_km=2.0, outages="60:20", seed=3)
    truth = drive.truth

    def snap(fixes: Sequence[Fix]) -> list[SnapResult | None]:
        out: list[SnapResult | None] = []
        for f, t in zip(fixes, truth.itertuples(), strict=True):
            e = int(t.edge)
            out.append(
                SnapResult(time=f.time, state=State.ON_ROAD, edge=e, lat=float(t.lat), lon=float(t.lon))
            )
        return out

    rep = evaluate_and_draw(g, drive, snap, tmp_path)
    m = rep.metrics
    assert m.correct_edge_rate == 1.0 and m.intersections.accuracy == 1.0
    assert m.rmf.fraction == pytest.approx(0.0, abs=0.01)
    for p in (rep.png, rep.html, rep.fixes_csv, rep.truth_csv, rep.truth_geojson, rep.matched_csv):
        assert p.exists() and p.stat().st_size > 0
    assert len(pd.read_csv(rep.matched_csv)) == len(drive.fixes)


@pytest.mark.slow
def test_helsinki_drive_through_the_online_matcher(tmp_path: Path) -> None:
    from mapmatch.online import OnlineMatcher

    graph, path = prepare_helsinki(tmp_path)
    assert path.exists()
    drive = demo_drive(graph, length_km=4.0, seed=11)
    valid = drive.fixes["gps_valid"].to_numpy() > 0
    err = np.hypot(drive.fused.x - drive.truth["x"], drive.fused.y - drive.truth["y"]).to_numpy()
    assert 1.0 < err[valid].mean() < 5.0
    matcher = OnlineMatcher(graph)

    def snap(fixes: Sequence[Fix]) -> list[SnapResult | None]:
        st = matcher.new_session()
        return [matcher.update(st, f) for f in fixes]

    rep = evaluate_and_draw(graph, drive, snap, tmp_path / "out")
    # loose floors: this checks the pipeline on a real map, not the matcher's accuracy
    assert rep.metrics.correct_edge_rate > 0.6
    assert rep.metrics.intersections.accuracy > 0.6
    assert rep.png.stat().st_size > 50_000
