"""Real-GPS fused drives: the real fixes are the GPS-aided positions, dead reckoning in outages."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from graph.ascii import parse_ascii_map
from graph.build import build_map
from graph.projection import to_lonlat
from mapmatch.errors import ValidationError
from mapmatch.evaluate import evaluate
from mapmatch.online import OnlineMatcher
from mapmatch.sim.drive import position_error, write_fixes_csv
from mapmatch.sim.realgps import RealGpsConfig, _route_heading, isotonic, real_drive

ELL = """
a---------------b
                |
                |
                |
                c
"""


def _write_track(tmp: Path, amap, pts: np.ndarray, t: np.ndarray, truth_nodes: str) -> None:  # type: ignore[no-untyped-def]
    ll = to_lonlat(amap.graph.crs, pts[:, 0], pts[:, 1])
    pd.DataFrame({"t": t, "lat": ll[:, 1], "lon": ll[:, 0]}).to_csv(
        tmp / "track.csv", index=False, float_format="%.8f"
    )
    xy = np.array([amap.xy(n) for n in truth_nodes])
    tll = to_lonlat(amap.graph.crs, xy[:, 0], xy[:, 1])
    feat = {
        "type": "Feature",
        "geometry": {"type": "MultiLineString", "coordinates": [tll.tolist()]},
        "properties": {},
    }
    (tmp / "truth.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [feat]}))


def _ell_track(tmp: Path):  # type: ignore[no-untyped-def]
    """The L-shaped map, driven a -> b -> c at 5 m/s with fixes 3 m north of (left of) the road."""
    amap = parse_ascii_map(ELL, scale=10.0)
    a, b, c = amap.xy("a"), amap.xy("b"), amap.xy("c")
    s = np.arange(0.0, 230.0, 5.0)
    leg = float(np.hypot(*(b - a)))
    pts = np.array(
        [
            a + (b - a) * min(x, leg) / leg if x <= leg else b + (c - b) * (x - leg) / np.hypot(*(c - b))
            for x in s
        ]
    )
    pts = pts + np.where(s[:, None] <= leg, [0.0, 3.0], [3.0, 0.0])
    t = 100.0 + np.arange(len(s), dtype=float)
    _write_track(tmp, amap, pts, t, "abc")
    return amap, pts, t


def test_real_fixes_are_the_gps_positions_and_dead_reckoning_covers_the_outage(tmp_path: Path) -> None:
    amap, pts, t = _ell_track(tmp_path)
    d = real_drive(amap.graph, tmp_path, rate_hz=1.0, outages=[(10.0, 12.0)], seed=3)
    f = d.fixes
    valid = f["gps_valid"].to_numpy() > 0
    assert len(f) == len(t) and f["time"].iloc[0] == 0.0
    # with GPS the fused position is the real fix, except while the outage's offset blends out
    ll = to_lonlat(amap.graph.crs, pts[:, 0], pts[:, 1])
    after = (f["time"].to_numpy() >= 22.0) & (f["time"].to_numpy() < 26.0)
    same = valid & ~after
    assert np.allclose(f["lat"].to_numpy()[same], ll[same, 1], atol=1e-7)
    assert np.allclose(f["lon"].to_numpy()[same], ll[same, 0], atol=1e-7)
    assert not valid[10:22].any() and valid[:10].all() and valid[22:].all()
    assert (d.truth["gps_outage"].to_numpy()[10:22] == 1).all()
    # dead reckoning from the last (biased) fix: near the road, off the held fix
    err = position_error(d)
    assert 1.0 < err[10:22].max() < 15.0
    assert np.hypot(*(np.array([d.fused.x[21], d.fused.y[21]]) - pts[9])) > 40.0
    # the truth: the route a->b->c, the turn at b, heading and odometer close to the truth
    g = amap.graph
    assert d.route.edges.tolist() == [amap.edge("a", "b"), amap.edge("b", "c")]
    assert d.node_index.tolist() == [amap.nodes["b"]]
    assert abs(f["distance"].sum() - d.route.length) < 0.05 * d.route.length
    he = np.abs((f["heading"].to_numpy() - d.truth["heading"].to_numpy() + 180.0) % 360.0 - 180.0)
    assert np.median(he[valid]) < 5.0
    assert f["heading_sigma"].to_numpy()[21] > f["heading_sigma"].to_numpy()[5]
    assert f["pos_sigma"].to_numpy()[21] > f["pos_sigma"].to_numpy()[9]
    assert set(d.truth["edge"].tolist()) == set(d.route.edges.tolist()) and g.n_edges > 0


def test_ten_hz_interpolates_between_real_fixes(tmp_path: Path) -> None:
    amap, _, _ = _ell_track(tmp_path)
    d1 = real_drive(amap.graph, tmp_path, rate_hz=1.0, outages=False, seed=1)
    d10 = real_drive(amap.graph, tmp_path, rate_hz=10.0, outages=False, seed=1)
    assert len(d10.fixes) == 10 * (len(d1.fixes) - 1) + 1
    assert np.allclose(d10.fixes["lat"].to_numpy()[::10], d1.fixes["lat"].to_numpy(), atol=1e-9)
    mid = d10.fixes.iloc[5]
    assert d1.fixes["lon"].iloc[0] < mid["lon"] < d1.fixes["lon"].iloc[1]
    assert np.isclose(d10.fixes["distance"].sum(), d1.fixes["distance"].sum(), rtol=0.02)


def test_ten_hz_uses_no_fix_an_outage_hides(tmp_path: Path) -> None:
    """At 10 Hz the positions next to an outage are not interpolated towards (before) or from
    (after) the fixes it hides: up to the last fix before it and from the first fix after it."""
    amap, _, _ = _ell_track(tmp_path)
    # fixes every second from 0; the outage hides fixes 10.5 ... 21.5, i.e. 11 to 21
    d = real_drive(amap.graph, tmp_path, rate_hz=10.0, outages=[(10.5, 11.0)], seed=2)
    tm = d.fixes["time"].to_numpy()
    valid = d.fixes["gps_valid"].to_numpy() > 0
    assert valid[tm <= 10.0 + 1e-6].all()  # up to the last fix the outage leaves
    assert not valid[(tm > 10.0 + 1e-6) & (tm < 22.0 - 1e-6)].any()  # 21.5-22: from fix 21, hidden
    assert valid[tm >= 22.0 - 1e-6].all()
    assert (d.truth["gps_outage"].to_numpy() == ~valid).all()


def test_track_gaps_are_dead_reckoned(tmp_path: Path) -> None:
    amap, pts, t = _ell_track(tmp_path)
    keep = np.ones(len(t), dtype=bool)
    keep[20:25] = False
    ll = to_lonlat(amap.graph.crs, pts[keep, 0], pts[keep, 1])
    pd.DataFrame({"t": t[keep], "lat": ll[:, 1], "lon": ll[:, 0]}).to_csv(tmp_path / "track.csv", index=False)
    d = real_drive(amap.graph, tmp_path, rate_hz=1.0, outages=False)
    v = d.fixes["gps_valid"].to_numpy()
    assert len(v) == len(t) and not v[20:25].any() and v[:20].all()


def test_truth_is_unknown_in_long_gaps_and_off_the_route(tmp_path: Path) -> None:
    """A stretch parked 80 m off the road and a gap of 15 s in the track (the truth only holds a
    place on the route there): those fixes are not known; a short gap, the fixes an injected
    outage hides and the rest are."""
    amap, pts, t = _ell_track(tmp_path)
    pts = pts.copy()
    pts[5:21] += [0.0, 80.0]  # 16 s in a yard north of a-b
    keep = np.ones(len(t), dtype=bool)
    keep[22:25] = False  # 4 s between fixes: interpolated
    keep[26:41] = False  # 16 s without fixes
    ll = to_lonlat(amap.graph.crs, pts[keep, 0], pts[keep, 1])
    pd.DataFrame({"t": t[keep], "lat": ll[:, 1], "lon": ll[:, 0]}).to_csv(tmp_path / "track.csv", index=False)
    d = real_drive(amap.graph, tmp_path, rate_hz=1.0, outages=[(41.0, 3.0)])
    known = d.truth["truth_known"].to_numpy()
    assert len(known) == len(t)
    assert known[:5].all() and not known[5:21].any() and known[21:26].all()
    assert not known[26:41].any() and known[41:].all()


def test_isotonic_fit_does_not_carry_a_forward_excursion() -> None:
    """A stop whose GPS wanders 10 m forward for one fix: the running maximum would hold the
    vehicle 10 m ahead for the whole stop; the least-squares monotone fit moves it 1 m."""
    y = np.array([0.0, 5.0, 10.0, 20.0, 10.0, 10.0, 10.0, 10.0, 10.0, 10.0, 10.0, 10.0, 30.0])
    fit = isotonic(y)
    assert np.all(np.diff(fit) >= 0.0)
    assert np.allclose(fit[:3], y[:3]) and fit[-1] == 30.0
    assert np.allclose(fit[3:12], 11.111111, atol=1e-5)
    assert np.allclose(isotonic(np.arange(5.0)), np.arange(5.0))


def test_bad_input_is_named(tmp_path: Path) -> None:
    amap, _, _ = _ell_track(tmp_path)
    with pytest.raises(ValidationError, match="rate_hz"):
        real_drive(amap.graph, tmp_path, rate_hz=5.0)
    with pytest.raises(ValidationError, match="blend_keep"):
        RealGpsConfig(blend_keep=1.5)
    with pytest.raises(ValidationError, match="gyro_bias_dps"):
        RealGpsConfig(gyro_bias_dps=float("nan"))
    with pytest.raises(ValidationError, match="track"):
        real_drive(amap.graph, tmp_path / "missing")


def test_kubicka_drive_replays_and_scores(kubicka_dir: Path, tmp_path: Path) -> None:
    folder = kubicka_dir / "00000014"
    g = build_map(folder / "roads.geojson")
    d = real_drive(g, folder, rate_hz=1.0, outages=True, seed=14)
    track = pd.read_csv(folder / "track.csv")
    assert len(d.outages) == 5 and [b for _, b in d.outages] == [60.0, 90.0, 92.0, 83.0, 48.0]
    v = d.fixes["gps_valid"].to_numpy() > 0
    times = d.fixes["time"].to_numpy() + float(track["t"].iloc[0])
    real = track.set_index("t").reindex(times)
    blended = np.zeros(len(v), dtype=bool)
    for a, b in d.outages:
        blended |= (times - track["t"].iloc[0] >= a + b) & (times - track["t"].iloc[0] < a + b + 5.0)
    exact = v & ~blended & real["lat"].notna().to_numpy()
    assert exact.sum() > 150
    assert np.allclose(d.fixes["lat"].to_numpy()[exact], real["lat"].to_numpy()[exact], atol=1e-6)
    write_fixes_csv(d, tmp_path / "fixes.csv")
    assert len(pd.read_csv(tmp_path / "fixes.csv")) == len(d.fixes)
    m = OnlineMatcher(g)
    st = m.new_session()
    res = [m.update(st, f) for f in d.fix_objects()]
    matched = pd.DataFrame(
        {
            "time": [r.time for r in res],
            "edge": [r.edge for r in res],
            "lat": [r.lat for r in res],
            "lon": [r.lon for r in res],
        }
    )
    met = evaluate(g, truth=d.truth, matched=matched, truth_path=d.route.edges.tolist())
    # the drive is scored like a simulated one (the matcher's accuracy here is the benchmark's business)
    assert met.intersections.true > 20 and met.intersections.correct >= 0.9 * met.intersections.true
    assert met.correct_edge_rate > 0.6


def test_truth_through_map_nodes_keeps_a_u_turn(tmp_path: Path) -> None:
    """A real drive may turn round at a dead end: the truth's nodes give the path, U-turn and all."""
    amap = parse_ascii_map(ELL, scale=10.0)
    a, b, c = amap.xy("a"), amap.xy("b"), amap.xy("c")
    leg1, leg2 = float(np.hypot(*(b - a))), float(np.hypot(*(c - b)))
    s = np.arange(0.0, leg1 + 2 * leg2 - 20.0, 5.0)

    def at(x: float) -> np.ndarray:
        if x <= leg1:
            return a + (b - a) * x / leg1
        if x <= leg1 + leg2:
            return b + (c - b) * (x - leg1) / leg2
        return c + (b - c) * (x - leg1 - leg2) / leg2

    pts = np.array([at(x) for x in s])
    _write_track(tmp_path, amap, pts, np.arange(len(s), dtype=float), "abcb")
    d = real_drive(amap.graph, tmp_path, outages=False)
    assert d.route.edges.tolist() == [amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("c", "b")]
    assert d.truth["edge"].iloc[-1] == amap.edge("c", "b")


def test_the_odometer_measures_the_rounded_path_not_the_centre_line(tmp_path: Path) -> None:
    """At the 90° turn at b the vehicle cuts the corner (as the simulator's vehicles do): the
    odometer reads a metre or two less than the centre line; without rounding it reads the line."""
    _ell_track(tmp_path)
    amap = parse_ascii_map(ELL, scale=10.0)
    exact = RealGpsConfig(odo_scale_sigma=0.0, odo_noise_m=0.0)
    line = real_drive(
        amap.graph,
        tmp_path,
        outages=False,
        config=RealGpsConfig(odo_scale_sigma=0.0, odo_noise_m=0.0, corner_smooth_m=0.0),
    )
    cut = real_drive(amap.graph, tmp_path, outages=False, config=exact)
    length = line.route.length
    assert abs(line.fixes["distance"].sum() - length) < 0.01
    assert 0.5 < length - cut.fixes["distance"].sum() < 4.0


def test_the_true_heading_through_a_u_turn_is_the_way_in_then_the_way_out(tmp_path: Path) -> None:
    """Where the route turns back (a U-turn at a dead end, after a stop there), the chord over
    ±``heading_base_m`` is about nothing and its direction the rounding's: the heading is the
    way in until the turning point, then the way out, never a direction across the road, and
    the same when the fixes move by a micrometre."""
    bend = """
a---------b
           \\
            \\
             \\
              \\
               c
"""
    heads = []
    for shift in (0.0, 1e-6):
        amap = parse_ascii_map(bend, scale=10.0)
        a, b, c = (amap.xy(n) + shift for n in "abc")
        leg1, leg2 = float(np.hypot(*(b - a))), float(np.hypot(*(c - b)))
        # 1 m/s to the dead end c, 10 s standing 3 m beyond its end (a yard: every fix of the stop
        # projects onto c itself, the turning point), and back
        x = np.concatenate([np.arange(0.0, leg1 + leg2, 1.0), np.full(10, leg1 + leg2 + 3.0)])
        x = np.concatenate([x, leg1 + leg2 + 6.0 + np.arange(1.0, leg2 - 10.0, 1.0)])

        def at(v: float, a=a, b=b, c=c, leg1=leg1, leg2=leg2) -> np.ndarray:  # type: ignore[no-untyped-def]
            if v <= leg1:
                return a + (b - a) * v / leg1
            if v <= leg1 + leg2 + 3.0:
                return b + (c - b) * (v - leg1) / leg2
            return c + (b - c) * (v - leg1 - leg2 - 6.0) / leg2

        sub = tmp_path / str(shift)
        sub.mkdir()
        _write_track(sub, amap, np.array([at(v) for v in x]), np.arange(len(x), dtype=float), "abcb")
        d = real_drive(amap.graph, sub, outages=False)
        tr = d.truth
        e, off = tr["edge"].to_numpy(), tr["offset"].to_numpy()
        # on the dead-end leg, away from the bend at b
        cb = ((e == amap.edge("b", "c")) & (off > 5.0)) | ((e == amap.edge("c", "b")) & (off < leg2 - 5.0))
        heads.append(tr["heading"].to_numpy()[cb])
    for h in heads:
        hin = np.degrees(np.arctan2(*(c - b))) % 360.0  # b to c (south-east); out: c to b
        way_in = np.abs((h - hin + 180.0) % 360.0 - 180.0) < 1.0
        way_out = np.abs((h - hin + 360.0) % 360.0 - 180.0) < 1.0
        assert len(h) > 20 and (way_in | way_out).all()
        # in, then out from the turning point on: one change of direction
        assert way_in[0] and way_out[-1] and np.count_nonzero(np.diff(way_in.astype(int))) == 1
    assert len(heads[0]) == len(heads[1])
    np.testing.assert_allclose(heads[0], heads[1], atol=1e-3)
    # at the turning point itself (a stop whose fixes project onto c: on 00000084 the chord's
    # rounding gave 311 degrees on one edge order and 53 on another), and a hair either side
    assert d.route.edges.tolist() == [amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("c", "b")]
    fold = float(d.route.edge_start[2])  # where c -> b begins
    h = np.degrees(_route_heading(d.route, fold + np.array([-1e-9, 0.0, 1e-9]), 4.0)) % 360.0
    hin = np.degrees(np.arctan2(*(c - b))) % 360.0
    off = np.minimum(np.abs((h - hin + 180.0) % 360.0 - 180.0), np.abs((h - hin) % 360.0 - 180.0))
    assert (off < 1e-6).all(), h
