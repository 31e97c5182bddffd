"""The map-aided measurement and the closed loop: bounded error in an outage, a wrong road not
pulling the filter, the measurement's fields and its proto round trip."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from graph.ascii import parse_ascii_map
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.measurement import DEFAULT_MEASUREMENT, cross_track_sigma, road_width
from mapmatch.online import OnlineMatcher
from mapmatch.sim.closed_loop import closed_loop_drive, in_process
from mapmatch.sim.drive import DriveConfig, position_error, simulate_drive
from mapmatch.sim.routes import route_from_edges
from mapmatch.sim.sensors import DEFAULT_SENSORS
from mapmatch.types import MapAidedMeasurement, SnapResult, State
from service import convert

STRAIGHT = "a" + "-" * 100 + "b"  # 2.5 km at 25 m a character
# a drifting gyro: dead reckoning alone goes well off the road in a minute and a half
DRIFTY = replace(DEFAULT_SENSORS, gyro_bias=1.0, multipath_rate=0.0)


def _straight_drive(rate: float, seed: int):  # type: ignore[no-untyped-def]
    m = parse_ascii_map(STRAIGHT, scale=25)
    route = route_from_edges(m.graph, [m.edge("a", "b")], start_offset=20.0)
    drive = simulate_drive(
        m.graph, route, rate=rate, outages=[(40.0, 90.0)], seed=seed, config=DriveConfig(sensors=DRIFTY)
    )
    return m, drive


@pytest.mark.parametrize("rate", [1.0, 10.0])
def test_straight_road_outage_error_stays_within_the_measurement_sigmas(rate: float) -> None:
    m, drive = _straight_drive(rate, seed=4)
    run = closed_loop_drive(m.graph, drive, in_process(OnlineMatcher(m.graph)))
    cl, t = run.drive, run.drive.fused.time
    inside = np.flatnonzero((t >= 40.0) & (t < 130.0))
    assert len(inside) > 60
    tx, ty = drive.truth["x"].to_numpy(), drive.truth["y"].to_numpy()
    # the road runs east: along = x, across = y
    open_cross = np.abs(drive.fused.y - ty)[inside]
    cross = np.abs(cl.fused.y - ty)[inside]
    along = np.abs(cl.fused.x - tx)[inside]
    aided = [run.results[i].map_aided for i in inside]  # type: ignore[union-attr]
    cross_sigma = np.array([a.cross_sigma for a in aided])
    along_sigma = np.array([a.along_sigma for a in aided])
    assert all(a.usable for a in aided)
    assert open_cross.max() > 3.0 * cross_sigma.max()  # without the map it drifts off
    assert np.all(cross <= 3.0 * cross_sigma)
    assert np.all(along <= 3.0 * along_sigma)
    assert run.accepted[inside].mean() > 0.9
    end = inside[-1]
    assert position_error(cl)[end] < 0.5 * position_error(drive)[end]


@pytest.mark.parametrize("apart", [15.0, 30.0])
def test_a_wrong_road_is_not_fed_back_or_is_gated_and_does_not_pull_the_filter(apart: float) -> None:
    # the vehicle drives a-b; the matcher's map lacks that road and has only c-d, ``apart`` m
    # south (one drawing row is twice the scale)
    road = "-" * 80
    truth_map = parse_ascii_map(f"a{road}b", scale=apart / 2)
    wrong_map = parse_ascii_map(f".\nc{road}d", scale=apart / 2)
    assert truth_map.xy("a")[1] - wrong_map.xy("c")[1] == pytest.approx(apart)
    route = route_from_edges(truth_map.graph, [truth_map.edge("a", "b")], start_offset=10.0)
    drive = simulate_drive(
        truth_map.graph,
        route,
        rate=1.0,
        outages="none",
        seed=2,
        config=DriveConfig(sensors=replace(DEFAULT_SENSORS, multipath_rate=0.0)),
    )
    matcher = OnlineMatcher(wrong_map.graph)
    # the matcher's answers are on c-d (in the truth map's CRS both maps coincide)
    run = closed_loop_drive(truth_map.graph, drive, in_process(matcher))
    placed = [r for r in run.results if r is not None and r.edge >= 0]
    assert placed and all(r.map_aided.heading == pytest.approx(90.0, abs=1.0) for r in placed)
    usable = np.array([r is not None and r.map_aided.usable for r in run.results])
    # every answer is either not usable or rejected by the filter's χ² gate (the last one is
    # never used: no next fix)
    assert (run.fed == usable)[:-1].all()
    assert (~usable | run.rejected)[:-1].all() and run.accepted.sum() == 0
    diff = np.hypot(run.drive.fused.x - drive.fused.x, run.drive.fused.y - drive.fused.y)
    assert diff.max() < 2.0  # the filter is not pulled towards c-d


def test_measurement_fields_and_usable_gating_on_a_drive() -> None:
    m, drive = _straight_drive(1.0, seed=7)
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    res = [matcher.update(st, f) for f in drive.fix_objects()]
    # not usable while initialising (two directions of the road), nor on the road until the
    # settling distance is driven (the standing start's fused heading picks the direction
    # before the vehicle moves); usable from then on
    states = [r.state for r in res]
    assert states[0] == State.INITIALISING and states[-1] == State.ON_ROAD
    assert all(r.map_aided.reason == "initialising" for r in res if r.state == State.INITIALISING)
    on_road = [r.map_aided for r in res if r.state == State.ON_ROAD]
    first = next(i for i, a in enumerate(on_road) if a.usable)
    assert all(a.reason == "settling" for a in on_road[:first])
    assert all(a.usable for a in on_road[first:])
    a = res[-1].map_aided
    r = res[-1]
    assert (a.lat, a.lon, a.heading) == (r.lat, r.lon, r.bearing)
    # east-running road: var_e is the along-track variance, var_n the cross-track one
    assert a.var_e == pytest.approx(a.along_sigma**2) and a.var_n == pytest.approx(a.cross_sigma**2)
    assert abs(a.cov_en) < 1e-6 * (a.var_e + a.var_n)
    assert a.cross_sigma == pytest.approx(
        cross_track_sigma(m.graph.edge_highway(r.edge), one_way=False), rel=1e-9
    )
    # the along-track σ grows in the outage (odometer carry) and shrinks once GPS is back
    t = drive.fused.time
    mid = int(np.flatnonzero(t >= 120.0)[0])
    before = int(np.flatnonzero(t >= 35.0)[0])
    assert res[mid].map_aided.along_sigma > res[before].map_aided.along_sigma
    # a settling distance longer than the drive: never usable, and the matcher's answers
    # (edges, offsets, states) do not change
    strict = OnlineMatcher(m.graph, config=DEFAULT_CONFIG.replace(settle_distance=1e9))
    st2 = strict.new_session()
    res2 = [strict.update(st2, f) for f in drive.fix_objects()]
    assert not any(r.map_aided.usable for r in res2)
    assert {r.map_aided.reason for r in res2} == {"initialising", "settling"}
    assert [(r.edge, r.offset, r.state) for r in res2] == [(r.edge, r.offset, r.state) for r in res]


def test_road_width_from_tags_or_class() -> None:
    assert road_width("residential") == 5.5
    assert road_width("nosuchclass") == DEFAULT_MEASUREMENT.default_width
    assert road_width("residential", lanes=4) == pytest.approx(13.0)
    assert road_width("residential", width=9.0, lanes=4) == 9.0
    # a one-way road's vehicle may be anywhere across it, a two-way road's on its half
    w = 7.0
    assert cross_track_sigma("primary", one_way=True) == pytest.approx(math.hypot(w / math.sqrt(12), 1.0))
    assert cross_track_sigma("primary", one_way=False) == pytest.approx(
        math.hypot(0.5 * w / math.sqrt(3), 1.0)
    )


def test_proto_round_trip_of_the_measurement() -> None:
    aided = MapAidedMeasurement(
        lat=60.1,
        lon=24.9,
        var_e=12.5,
        cov_en=-3.25,
        var_n=4.0,
        along_sigma=3.7,
        cross_sigma=1.9,
        heading=123.4,
        heading_sigma=2.5,
        probability=0.97,
        usable=True,
        reason="",
    )
    r = SnapResult(time=5.0, state=State.ON_ROAD, edge=3, lat=60.1, lon=24.9, map_aided=aided)
    msg = convert.snap_result_to_proto(r)
    back = convert.snap_result_from_proto(type(msg).FromString(msg.SerializeToString()))
    assert back.map_aided == aided
    # an answer without a road: not usable, NaN position, survives the trip too
    off = convert.snap_result_from_proto(
        convert.snap_result_to_proto(SnapResult(time=1.0, state=State.OFF_ROAD))
    )
    assert not off.map_aided.usable and off.map_aided.reason == "off_road" and math.isnan(off.map_aided.lat)
