"""Online matcher on tiny ASCII maps: one map per situation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from graph.ascii import AsciiMap, parse_ascii_map
from graph.index import project_to_edge
from graph.projection import to_lonlat
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.errors import ValidationError
from mapmatch.online import OnlineMatcher, SessionState
from mapmatch.types import Fix, SnapResult, State, Turn
from tests.online_helpers import DriveSpec, drive

CROSS = """
        n
        |
        |
a-------b-------c
        |
        |
        s
"""


def run(matcher: OnlineMatcher, fixes: list[Fix], state: SessionState | None = None) -> list[SnapResult]:
    st = state if state is not None else matcher.new_session()
    return [matcher.update(st, f) for f in fixes]


def edges_of(results: list[SnapResult]) -> list[int]:
    out: list[int] = []
    for r in results:
        if r.edge >= 0 and (not out or out[-1] != r.edge):
            out.append(r.edge)
    return out


def committed_edges(results: list[SnapResult]) -> list[int]:
    """Reported edges with corrections applied (what the matcher finally believes)."""
    seq = [(r.time, r.edge) for r in results]
    for r in results:
        c = r.correction
        if c is None:
            continue
        for i, (t, e) in enumerate(seq):
            if c.time_from <= t <= c.time_to and e in c.replaced_edges:
                seq[i] = (t, c.edges[0] if len(c.edges) == 1 else e)
    out: list[int] = []
    for _, e in seq:
        if e >= 0 and (not out or out[-1] != e):
            out.append(e)
    return out


def test_startup_without_heading_settles_on_the_direction_of_travel() -> None:
    m = parse_ascii_map("a-----------b", scale=20)
    matcher = OnlineMatcher(m.graph)
    fixes = [
        Fix(time=f.time, lat=f.lat, lon=f.lon, distance=f.distance, speed=f.speed)
        for f in drive(m, "ab", DriveSpec(speed=8))
    ]
    res = run(matcher, fixes)
    assert res[0].state is State.INITIALISING
    assert {c.edge for c in res[0].candidates} == {m.edge("a", "b"), m.edge("b", "a")}
    assert math.isclose(sum(c.probability for c in res[0].candidates), 1.0)
    assert res[5].state is State.ON_ROAD
    assert all(r.edge == m.edge("a", "b") for r in res[3:])
    # external ids: node ids of the ASCII map are the letters' code points
    assert (res[5].u, res[5].v) == (ord("a"), ord("b"))
    assert res[5].way_id == m.graph.edge_way_id[m.edge("a", "b")]


def test_startup_with_heading_is_on_road_at_once() -> None:
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    res = run(matcher, drive(m, "cb", DriveSpec(speed=10))[:3])
    assert res[0].state is State.ON_ROAD
    assert res[0].edge == m.edge("c", "b")
    assert res[0].bearing == pytest.approx(270.0)


def test_between_intersections_projects_onto_the_current_edge_only() -> None:
    m = parse_ascii_map("a---------------------------------b", scale=10)
    matcher = OnlineMatcher(m.graph)
    fixes = drive(m, "ab", DriveSpec(speed=10, noise=3.0, seed=3))
    st = matcher.new_session()
    first = matcher.update(st, fixes[0])
    assert first.edge == m.edge("a", "b")

    def no_search(*args: object, **kw: object) -> None:
        raise AssertionError("searched the index between intersections")

    matcher.index.query = no_search  # type: ignore[method-assign]
    for f in fixes[1:-3]:
        r = matcher.update(st, f)
        assert r.state is State.ON_ROAD and r.edge == m.edge("a", "b")
        assert r.candidates == ()
    xy = np.array(m.graph.edge_xy(m.edge("a", "b")))
    assert 0.0 <= r.offset <= np.hypot(*(xy[-1] - xy[0]))


@pytest.mark.parametrize(
    ("route", "turn"),
    [("abc", Turn.STRAIGHT), ("abn", Turn.LEFT), ("abs", Turn.RIGHT), ("cbs", Turn.LEFT), ("nbc", Turn.LEFT)],
)
def test_turns_at_a_crossing(route: str, turn: Turn) -> None:
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    res = run(matcher, drive(m, route, DriveSpec(speed=8, noise=2.0, seed=7, heading_noise=3.0)))
    assert committed_edges(res) == [m.edge(route[0], route[1]), m.edge(route[1], route[2])]
    turns = [r.turn for r in res if r.turn is not Turn.NONE]
    assert turns == [turn]
    assert any(r.state is State.AMBIGUOUS and len(r.candidates) >= 1 for r in res)


def test_ambiguous_then_corrected_on_leaving() -> None:
    # a fork: the vehicle drives a-b-c, but the first fix after b lies on the branch to d
    m = parse_ascii_map(
        """
        a-----b-----------c
               \\
                d
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    b, c, d = m.xy("b"), m.xy("c"), m.xy("d")
    east = (c - b) / np.linalg.norm(c - b)
    diag = (d - b) / np.linalg.norm(d - b)
    fixes = drive(m, "ab", DriveSpec(speed=8))
    t = fixes[-1].time
    pts = [(b + 8 * diag, 153.4)] + [(b + s * east, 90.0) for s in (16, 24, 32, 40)]
    for i, (p, hd) in enumerate(pts):
        lon, lat = to_lonlat(m.graph.crs, [p[0]], [p[1]])[0]
        fixes.append(Fix(time=t + i + 1, lat=lat, lon=lon, heading=hd, speed=8, distance=8, gps_valid=True))
    res = run(matcher, fixes)
    wrong = [r for r in res if r.edge == m.edge("b", "d")]
    assert len(wrong) == 1 and wrong[0].state is State.AMBIGUOUS
    assert {c.edge for c in wrong[0].candidates} >= {m.edge("b", "d"), m.edge("b", "c")}
    corrections = [r.correction for r in res if r.correction is not None]
    assert len(corrections) == 1
    corr = corrections[0]
    assert corr.edges == (m.edge("b", "c"),)
    assert corr.replaced_edges == (m.edge("b", "d"),)
    assert corr.time_from == corr.time_to == wrong[0].time
    assert corr.edge_times == (wrong[0].time,) and corr.edge_at(wrong[0].time) == m.edge("b", "c")
    assert res[-1].edge == m.edge("b", "c") and res[-1].state is State.ON_ROAD


PARALLEL = """
a-----------------------b

c-----------------------d
"""


def _jump_to_cd(m: AsciiMap) -> list[Fix]:
    on_ab = drive(m, "ab", DriveSpec(speed=10))[:8]
    # from t=8 the fixes run along c-d (40 m away): far beyond 4 sigma of a-b
    return on_ab + drive(m, "cd", DriveSpec(speed=10, t0=on_ab[-1].time + 1, start_offset=80.0))


def test_reinitialises_when_the_fix_stays_off_the_road() -> None:
    m = parse_ascii_map(PARALLEL, scale=10)
    matcher = OnlineMatcher(
        m.graph, config=DEFAULT_CONFIG.replace(soft_reinit_sigmas=1e9)
    )  # the hard rule alone
    res = run(matcher, _jump_to_cd(m))
    assert all(r.edge == m.edge("a", "b") and r.state is State.ON_ROAD for r in res[:8])
    states = [r.state for r in res[8:]]
    assert states[0] is State.OFF_ROAD
    k = states.index(State.REINITIALISED)
    assert 5 <= k <= 11  # reinit_time 10 s or reinit_distance 100 m
    assert all(s is State.OFF_ROAD for s in states[:k])
    assert all(r.edge == m.edge("c", "d") for r in res[8 + k :])
    assert res[-1].state is State.ON_ROAD


def test_soft_reinitialisation_switches_road_with_a_correction() -> None:
    m = parse_ascii_map(PARALLEL, scale=10)
    matcher = OnlineMatcher(m.graph)
    res = run(matcher, _jump_to_cd(m))
    after = res[8:]
    k = next(i for i, r in enumerate(after) if r.edge == m.edge("c", "d"))
    assert k <= 5
    assert all(r.edge == m.edge("c", "d") for r in after[k:])
    assert after[k].state in (State.AMBIGUOUS, State.OFF_ROAD, State.ON_ROAD)
    assert after[-1].state is State.ON_ROAD


def test_one_way_is_never_matched_against_its_direction() -> None:
    # a>b is one-way eastbound; the vehicle drives west exactly on it: it must be on d->c
    m = parse_ascii_map(
        """
        a>>>>>>>>>>>>>>>>>>>>>>b

        c----------------------d
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    fixes = drive(m, "ba", DriveSpec(speed=10, sigma=10.0))
    res = run(matcher, fixes)
    assert all(r.edge != m.edge("a", "b") for r in res)
    assert all(r.edge == m.edge("d", "c") for r in res)
    with pytest.raises(KeyError):
        m.edge("b", "a")


@pytest.mark.parametrize(("kind", "expected"), [("no", "c"), ("only", "d")])
def test_turn_restriction_decides_an_even_fork(kind: str, expected: str) -> None:
    # the vehicle drives exactly between b-c (east) and b-d (north) without heading
    drawing = """
          d
          |
    a-----b-----c
    """
    m = parse_ascii_map(drawing, scale=10, restrictions=[("a", "b", "d", kind)])
    matcher = OnlineMatcher(m.graph)
    b = m.xy("b")
    pts = [tuple(m.xy("a")), tuple(b), tuple(b + np.array([14.0, 14.0]))]
    fixes = [
        Fix(time=f.time, lat=f.lat, lon=f.lon, distance=f.distance, speed=f.speed)
        for f in drive(m, "", DriveSpec(speed=5), points=pts)  # type: ignore[arg-type]
    ]
    res = run(matcher, fixes)
    after = [r.edge for r in res if r.edge not in (m.edge("a", "b"), m.edge("b", "a"))]
    assert after and set(after) == {m.edge("b", expected)}


def test_u_turn_at_a_dead_end_and_at_a_crossing() -> None:
    m = parse_ascii_map(
        """
        a-------b-------c
                |
                d
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    res = run(matcher, drive(m, "abcba", DriveSpec(speed=8, noise=1.5, seed=2)))
    seq = committed_edges(res)
    assert seq == [m.edge("a", "b"), m.edge("b", "c"), m.edge("c", "b"), m.edge("b", "a")]
    assert [r.turn for r in res if r.turn is not Turn.NONE] == [Turn.STRAIGHT, Turn.U_TURN, Turn.STRAIGHT]
    # U-turn at the crossing b itself (legal, penalised)
    res = run(matcher, drive(m, "aba", DriveSpec(speed=6, noise=1.0, seed=4)))
    assert committed_edges(res) == [m.edge("a", "b"), m.edge("b", "a")]
    assert [r.turn for r in res if r.turn is not Turn.NONE] == [Turn.U_TURN]


def test_gps_outage_carries_the_vehicle_by_distance() -> None:
    m = parse_ascii_map(
        """
        a-----------------------------------------b
                                                  |
                                                  |
                                                  |
                                                  |
                                                  |
                                                  c
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    truth = drive(m, "abc", DriveSpec(speed=10))
    ahead = drive(m, "abc", DriveSpec(speed=11.5))  # dead reckoning runs 15 % ahead ...
    ab = m.edge("a", "b")
    fixes = truth[:5]
    for i in range(5, len(ahead)):
        f = ahead[i]
        x, y = to_xy_one(m, f)
        lon, lat = to_lonlat(m.graph.crs, [x], [y + 1.0 * (i - 5)])[0]  # ... and drifts 1 m/s north
        fixes.append(Fix(time=i, lat=lat, lon=lon, heading=f.heading, speed=10, distance=10, gps_valid=False))
    res = run(matcher, fixes)
    on_ab = [(i, r) for i, r in enumerate(res) if r.edge == ab]
    assert len(on_ab) >= 40
    for i, r in on_ab[5:]:
        assert r.offset == pytest.approx(10.0 * i, abs=3.0), i
        raw_x, _ = to_xy_one(m, fixes[i])
        if 11.5 * i < 415.0:
            assert raw_x - m.xy("a")[0] > 10.0 * i + 0.1 * 10.0 * i - 1.0  # the raw fix is well ahead
    assert committed_edges(res) == [ab, m.edge("b", "c")]
    assert all(r.state in (State.ON_ROAD, State.AMBIGUOUS) for r in res)


def test_dead_reckoning_at_10_hz_follows_the_odometer_not_a_lagging_fix() -> None:
    m = parse_ascii_map("a----------------------------------------b", scale=10)
    matcher = OnlineMatcher(m.graph)
    truth = drive(m, "ab", DriveSpec(speed=10, dt=0.1))
    fixes = truth[:50]
    for i in range(50, len(truth)):
        # the dead-reckoning fix runs 10 % slow: 0.1 m a step, far below any per-step tolerance
        x, y = to_xy_one(m, truth[i])
        lon, lat = to_lonlat(m.graph.crs, [x - 0.1 * (i - 50)], [y])[0]
        f = truth[i]
        fixes.append(
            Fix(time=f.time, lat=lat, lon=lon, heading=f.heading, speed=10, distance=1.0, gps_valid=False)
        )
    res = run(matcher, fixes)
    for i in range(100, len(res), 25):
        assert res[i].offset == pytest.approx(1.0 * i, abs=2.0), i


def test_dead_reckoning_turn_re_anchors_the_distance_carried() -> None:
    m = parse_ascii_map(
        """
        a------------------------------b----------d
                                       |
                                       |
                                       |
                                       |
                                       |
                                       |
                                       |
                                       |
                                       c
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    truth = drive(m, "abc", DriveSpec(speed=10))
    bc = m.edge("b", "c")
    fixes = truth[:3]
    for f in truth[3:]:  # GPS lost: the odometer over-reads by 8 %
        fixes.append(f._replace(speed=10.8, distance=10.8, gps_valid=False))
    res = run(matcher, fixes)
    ab_len = m.xy("b")[0] - m.xy("a")[0]
    late = [(i, r) for i, r in enumerate(res) if r.edge == bc and 10.0 * i - ab_len > 60.0]
    assert late, "never reached b-c"
    for i, r in late:
        true_off = 10.0 * i - ab_len
        # carried from the GPS loss alone it would also lead by 8 % of the ~280 m before b
        # (22 m); the anchor is as good as headings 10 m apart tell
        assert abs(r.offset - (true_off + 0.08 * true_off)) < 8.0, (i, r.offset, true_off)


def to_xy_one(m: AsciiMap, f: Fix) -> tuple[float, float]:
    from graph.projection import point_to_xy

    return point_to_xy(m.graph.crs, f.lon, f.lat)


def test_far_off_fix_is_off_road_and_keeps_tracking() -> None:
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    fixes = drive(m, "abc", DriveSpec(speed=10))
    matcher.update(st, fixes[0])
    r = matcher.update(st, Fix(time=fixes[1].time, lat=10.0, lon=10.0))
    assert r.state is State.OFF_ROAD and r.edge == -1
    assert matcher.update(st, fixes[2]).edge == m.edge("a", "b")


def test_validation_errors_leave_the_state_unchanged() -> None:
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    fixes = drive(m, "abc", DriveSpec(speed=10))
    matcher.update(st, fixes[0])
    matcher.update(st, fixes[1])
    before = st.to_bytes()
    bad = [
        Fix(time=fixes[1].time, lat=fixes[2].lat, lon=fixes[2].lon),  # repeated time
        Fix(time=fixes[0].time, lat=fixes[2].lat, lon=fixes[2].lon),  # backwards
        Fix(time=5.0, lat=math.nan, lon=fixes[2].lon),
        Fix(time=5.0, lat=91.0, lon=0.0),
        Fix(time=5.0, lat=0.0, lon=math.inf),
        Fix(time=5.0, lat=fixes[2].lat, lon=fixes[2].lon, heading=361.0),
        Fix(time=5.0, lat=fixes[2].lat, lon=fixes[2].lon, heading=-1.0),
        Fix(time=math.inf, lat=fixes[2].lat, lon=fixes[2].lon),
        Fix(time=5.0, lat=fixes[2].lat, lon=fixes[2].lon, speed=-3.0),
    ]
    for f in bad:
        with pytest.raises(ValidationError):
            matcher.update(st, f)
        assert st.to_bytes() == before


def test_state_round_trips_and_moves_between_matchers() -> None:
    m = parse_ascii_map(CROSS, scale=10)
    fixes = drive(m, "abn", DriveSpec(speed=8, noise=2.0, seed=11))
    one = OnlineMatcher(m.graph)
    ref = run(one, fixes)
    st = one.new_session()
    out = []
    for f in fixes:
        st = SessionState.from_bytes(st.to_bytes())
        out.append(OnlineMatcher(m.graph).update(st, f))
    assert [(r.edge, r.state, r.turn) for r in out] == [(r.edge, r.state, r.turn) for r in ref]
    assert len(st.to_bytes()) < 2000
    with pytest.raises(ValidationError):
        SessionState.from_bytes(b"not json")
    with pytest.raises(ValidationError):
        SessionState.from_bytes(b'{"v": 1}')


def test_projection_entries_agree_with_shapely() -> None:
    import shapely

    from graph.index import project_point_compiled, project_points

    m: AsciiMap = parse_ascii_map(CROSS, scale=10)
    g = m.graph
    matcher = OnlineMatcher(g)
    rng = np.random.default_rng(0)
    edges, pts, scalar = [], [], []
    for e in range(g.n_edges):
        line = shapely.LineString(g.edge_xy(e))
        for x, y in rng.normal(m.xy("b"), 60.0, size=(20, 2)):
            off, dist, px, py, _ = got = matcher.road.project(e, float(x), float(y))
            p = shapely.Point(x, y)
            assert (off, dist) == pytest.approx((line.project(p), line.distance(p)), abs=1e-9)
            assert (px, py) == pytest.approx(line.interpolate(off).coords[0], abs=1e-9)
            assert project_to_edge(g, e, float(x), float(y)) == pytest.approx(got[:4], abs=1e-12)
            lo, hi = int(g.edge_seg_ptr[e]), int(g.edge_seg_ptr[e + 1])
            comp = project_point_compiled(g.seg_xy, lo, hi, float(x), float(y), g.edge_len[e], 0.0)
            assert comp[:4] == pytest.approx(got[:4], abs=1e-12)
            edges.append(e)
            pts.append((x, y))
            scalar.append(got)
    assert project_points(g, edges, pts) == pytest.approx(np.array(scalar), abs=1e-12)


def test_one_matcher_serves_many_threads() -> None:
    from concurrent.futures import ThreadPoolExecutor

    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    routes = ["abc", "abn", "abs", "cba", "nbs", "sba", "nbc", "cbs"]
    drives = [drive(m, r, DriveSpec(speed=8, noise=2.0, seed=i)) for i, r in enumerate(routes)]
    expected = [[(x.edge, x.state, x.turn) for x in run(OnlineMatcher(m.graph), d)] for d in drives]

    def go(d: list[Fix]) -> list[tuple[int, State, Turn]]:
        return [(x.edge, x.state, x.turn) for x in run(matcher, d)]

    with ThreadPoolExecutor(max_workers=4) as pool:
        got = list(pool.map(go, drives * 4))
    assert got == expected * 4


def test_the_model_s_array_forms_are_its_scalar_formulas_over_arrays() -> None:
    """One formula each: the array forms give, element by element and broadcast, the scalar
    functions' floats, and the formulas' own cases (heading term only where known, unreachable
    is -inf, U-turn and speed penalties)."""
    import math

    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.model import emission_logp, emission_one, heading_kappa, heading_kappa_one, transition_logp

    C = DEFAULT_CONFIG.replace(beta_per_m=0.04)
    m = C.model
    rng = np.random.default_rng(1)
    d, s, h, b = (
        rng.uniform(0, 50, 200),
        rng.uniform(0.5, 20, 200),
        rng.uniform(0, 360, 200),
        rng.uniform(0, 360, 200),
    )
    h[:20] = np.nan
    got = emission_logp(d, s, h, b, 8.0)
    assert got.tolist() == [emission_one(*x, 8.0) for x in zip(d, s, h, b, strict=True)]
    assert emission_one(3.0, 2.0, np.nan, 90.0, 8.0) == -0.5 * 1.5**2 - math.log(2.0)  # no heading term
    assert emission_one(0.0, 1.0, 90.0, 270.0, 1.0) == -2.0  # facing against the road: κ(cos π - 1)
    # transitions: |route - travelled| / β, the speed penalty past max_speed, U-turns, -inf
    lp = transition_logp(
        [10.0, 10.0, np.inf, 200.0], 10.0, [1.0, 1.0, 1.0, 1.0], C, uturn=[False, True, False, False]
    )
    assert lp[0] == 0.0 and lp[1] == -m.uturn_penalty and lp[2] == -np.inf
    beta = m.beta + m.beta_per_m * 10.0
    assert lp[3] == pytest.approx(-190.0 / beta - m.speed_penalty * (200.0 - m.max_speed))
    # κ: floored heading σ, none where the heading is unknown or the fix too slow
    k = heading_kappa([90.0, np.nan, 90.0, 90.0], [0.1, 5.0, np.nan, 5.0], [5.0, 5.0, 5.0, 0.0], C)
    floor = C.batch.track.track_heading_sigma_floor_deg
    assert k.tolist() == [heading_kappa_one(0.1, floor), 0.0, heading_kappa_one(m.heading_sigma, floor), 0.0]
    assert heading_kappa_one(0.1, floor) == 1.0 / math.radians(floor) ** 2


def _fix_at(m: AsciiMap, xy: np.ndarray, t: float, heading: float, **kw: float) -> Fix:
    lon, lat = to_lonlat(m.graph.crs, [xy[0]], [xy[1]])[0]
    return Fix(time=t, lat=float(lat), lon=float(lon), heading=heading, gps_valid=True, **kw)


def test_stopped_vehicle_near_a_node_does_not_flip_edges() -> None:
    # the vehicle stops 3 m before the crossing b; its fixes scatter along the road and
    # several lie past b: a stopped vehicle must stay where it stopped
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    a, b = m.xy("a"), m.xy("b")
    east = (b - a) / np.linalg.norm(b - a)
    fixes = [f for f in drive(m, "ab", DriveSpec(speed=5)) if np.dot(m.xy("b") - to_xy_arr(m, f), east) > 8.0]
    t = fixes[-1].time
    stop = b - 3.0 * east
    for i, jitter in enumerate([2.0, 5.0, -1.0, 6.0, 4.5, 0.5, 5.5, 3.5, -0.5, 6.5] * 2):
        fixes.append(_fix_at(m, stop + jitter * east, t + 1 + i, 90.0, speed=0.0, distance=0.0))
    res = run(matcher, fixes)
    stopped = res[-20:]
    assert {r.edge for r in stopped} == {m.edge("a", "b")}
    # without the stop rule the scattered fixes would carry it past the node
    loose = run(OnlineMatcher(m.graph, config=DEFAULT_CONFIG.replace(stop_speed=0.0)), fixes)
    assert len({r.edge for r in loose[-20:]}) > 1
    # and it drives on through the crossing afterwards
    go = drive(m, "bc", DriveSpec(speed=5, t0=fixes[-1].time + 1, start_offset=0.0))
    st = matcher.new_session()
    out = run(matcher, fixes + go, st)
    assert committed_edges(out) == [m.edge("a", "b"), m.edge("b", "c")]


def to_xy_arr(m: AsciiMap, f: Fix) -> np.ndarray:
    return np.array(to_xy_one(m, f))


def test_fix_past_a_bend_is_not_held_back_at_the_node() -> None:
    # a bend a-b-c (not a junction); the fused heading lags the bend by several seconds and the
    # fixes are loose (σ 6 m): the vehicle must not be kept at b while it drives on along b-c
    m = parse_ascii_map(
        """
        c
        |
        |
        |
        |
        b-----------------a
        """,
        scale=10,
    )
    matcher = OnlineMatcher(m.graph)
    fixes = [
        Fix(
            time=f.time,
            lat=f.lat,
            lon=f.lon,
            heading=f.heading,
            pos_sigma=6.0,
            speed=f.speed,
            distance=f.distance,
        )
        for f in drive(m, "ab", DriveSpec(speed=5))
    ]
    b, c = m.xy("b"), m.xy("c")
    north = (c - b) / np.linalg.norm(c - b)
    t = fixes[-1].time
    for i in range(1, 9):  # heading turns from west (270) to north (360) only slowly
        hd = min(270.0 + 6.0 * i, 359.0)
        fixes.append(_fix_at(m, b + 5.0 * i * north, t + i, hd, pos_sigma=6.0, speed=5.0, distance=5.0))
    res = run(matcher, fixes)
    bc = m.edge("b", "c")
    far = [r for r, f in zip(res, fixes, strict=True) if np.dot(to_xy_arr(m, f) - b, north) > 12.0]
    assert far and all(r.edge == bc for r in far)


def test_crossing_at_10_hz_is_committed_without_flicker() -> None:
    m = parse_ascii_map(CROSS, scale=10)
    matcher = OnlineMatcher(m.graph)
    for seed in range(4):
        res = run(
            matcher, drive(m, "abc", DriveSpec(speed=10, dt=0.1, noise=2.0, seed=seed, heading_noise=2.0))
        )
        assert edges_of(res) == [m.edge("a", "b"), m.edge("b", "c")], seed
        assert committed_edges(res) == [m.edge("a", "b"), m.edge("b", "c")]


def test_online_tuning_constants_are_validated_config_fields() -> None:
    from mapmatch.errors import ConfigError

    cfg = DEFAULT_CONFIG.replace(max_hypotheses=8, stop_speed=0.3, node_hold_sigmas=2.0)
    assert (
        cfg.online.region.max_hypotheses,
        cfg.online.stop.stop_speed,
        cfg.online.stop.node_hold_sigmas,
    ) == (8, 0.3, 2.0)
    for bad in (
        {"max_hypotheses": 0},
        {"max_hypotheses": 2.5},
        {"turn_sigma": 0.0},
        {"drift_decay_time": 0.0},
        {"min_probability": 1.5},
    ):
        with pytest.raises(ConfigError):
            DEFAULT_CONFIG.replace(**bad)


TURN_THEN_CROSS = """
    d       n
    |       |
    |       |
e---a-------b-------c
            |
            s
"""


def biased_drive(
    amap: AsciiMap, route: str, *, bias_x: float, speed: float, dt: float
) -> tuple[list[Fix], np.ndarray]:
    """Exact odometer and heading; every fix ``bias_x`` metres east of the true position (a
    slowly varying GPS error). Returns the fixes and the true distance along the route."""
    pts = np.array([amap.xy(n) for n in route], dtype=float)
    seg = np.diff(pts, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    true_s = np.arange(10.0, cum[-1], speed * dt)
    fixes = []
    for i, s in enumerate(true_s):
        j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        x, y = pts[j] + (s - cum[j]) / (cum[j + 1] - cum[j]) * seg[j]
        lon, lat = to_lonlat(amap.graph.crs, [x + bias_x], [y])[0]
        fixes.append(
            Fix(
                time=i * dt,
                lat=float(lat),
                lon=float(lon),
                heading=math.degrees(math.atan2(seg[j, 0], seg[j, 1])) % 360.0,
                pos_sigma=3.0,
                speed=speed,
                distance=speed * dt if i else math.nan,
                gps_valid=True,
            )
        )
    return fixes, true_s


def test_along_track_error_learnt_before_a_turn_times_a_straight_crossing() -> None:
    # 8 m west: across the road going south (the map shows it), then along the road going
    # east after the left turn at a, where only the learnt bias and the turn's anchor carried
    # by the odometer can tell that the fix lags; the edge must switch at b on time
    m = parse_ascii_map(TURN_THEN_CROSS, scale=10)
    b = 60.0 + 80.0  # route distance of node b
    late = {}
    for name, cfg in (
        ("along", DEFAULT_CONFIG),
        ("off", DEFAULT_CONFIG.replace(turn_anchor_sigma=0.0, bias_time=0.0)),
    ):
        for bias in (0.0, -8.0):
            fixes, true_s = biased_drive(m, "dabc", bias_x=bias, speed=8.0, dt=0.25)
            res = run(OnlineMatcher(m.graph, config=cfg), fixes)
            assert edges_of(res) == [m.edge("d", "a"), m.edge("a", "b"), m.edge("b", "c")]
            assert [r.turn for r in res if r.turn != Turn.NONE] == [Turn.LEFT, Turn.STRAIGHT]
            e = np.array([r.edge for r in res])
            late[name, bias] = float(true_s[int(np.argmax(e == m.edge("b", "c")))] - b)
    # without the along-track correction the lag adds to the wait at the node; with it the
    # switch is at most three fixes (6 m) late, and earlier than without
    assert late["along", 0.0] <= 2.0
    assert late["along", -8.0] <= 6.0
    assert late["off", -8.0] >= late["off", 0.0] + 8.0
    assert late["along", -8.0] < late["off", -8.0]


def test_heading_profile_alignment_finds_the_turn() -> None:
    from mapmatch.turns import align_headings, bearing_profile

    # the path: 100 m south, then 60 m east (a left turn at path distance 100)
    knots = bearing_profile([100.0, 60.0], [180.0, 90.0])
    # the vehicle turned when its odometer read 1000 (heading ramps over ±4 m), sampled every 2 m
    # with a 2° wiggle; the position believed puts the odometer 7 m too far along the path
    odo = np.arange(960.0, 1030.0, 2.0)
    heading = 180.0 - 90.0 * np.clip((odo - 996.0) / 8.0, 0.0, 1.0) + 2.0 * np.sin(odo)
    samples = [[o, h % 360.0] for o, h in zip(odo, heading, strict=True)]
    offset, sd, rms = align_headings(samples, knots, -900.0 + 7.0, search=20.0, heading_sigma=3.0)
    assert offset == pytest.approx(-900.0, abs=0.5)
    assert sd < 1.0 and rms < 5.0
    # a path with the turn the other way fits badly
    wrong = bearing_profile([100.0, 60.0], [180.0, 270.0])
    assert align_headings(samples, wrong, -900.0, search=20.0, heading_sigma=3.0)[2] > 30.0
    # too few samples: no answer
    assert math.isnan(align_headings(samples[:2], knots, -900.0, search=20.0, heading_sigma=3.0)[0])


def test_corner_cut_matches_a_rounded_corner() -> None:
    from mapmatch.turns import corner_cut

    # a 90° corner rounded by an arc touching both legs 4 m from the node: 8 m of legs against
    # a quarter circle of radius 4 m
    assert corner_cut(90.0, 50.0, 50.0) == pytest.approx(8.0 - 2.0 * math.pi, abs=1e-9)
    assert corner_cut(-90.0, 50.0, 50.0) == corner_cut(90.0, 50.0, 50.0)
    assert corner_cut(0.0, 50.0, 50.0) == 0.0
    # a short edge limits the arc
    assert corner_cut(90.0, 4.0, 50.0) == pytest.approx(4.0 - math.pi, abs=1e-9)  # arc radius 2 m


def test_heading_samples_keep_their_own_odometer_reading() -> None:
    from mapmatch.turns import add_sample

    samples: list[list[float]] = []
    for i in range(30):  # 10 Hz at 3 m/s: 0.3 m per fix, heading turning 1° per fix
        add_sample(samples, 0.3 * i, float(i), window=30.0)
    for odo, heading in samples:  # each sample's heading is the one read at its odometer
        assert heading == pytest.approx(odo / 0.3)
    assert all(b[0] - a[0] >= 1.0 - 1e-9 for a, b in itertools.pairwise(samples))


def test_merged_corrections_keep_exact_times_only_when_their_spans_touch() -> None:
    from mapmatch.online import _merge
    from mapmatch.types import Correction

    a = Correction(time_from=1.0, time_to=3.0, edges=(4, 5), replaced_edges=(7,), edge_times=(1.0, 2.0))
    b = Correction(time_from=3.0, time_to=5.0, edges=(5, 6), replaced_edges=(8,), edge_times=(3.0, 4.0))
    m = _merge(a, b)
    assert (m.time_from, m.time_to, m.edges, m.edge_times) == (1.0, 5.0, (4, 5, 6), (1.0, 2.0, 4.0))
    assert [m.edge_at(t) for t in (1.0, 2.5, 3.5, 4.5)] == [4, 5, 5, 6]
    # a gap between the spans: a timeline would revise fixes in the gap that neither revised
    far = Correction(time_from=9.0, time_to=10.0, edges=(9,), replaced_edges=(8,), edge_times=(9.0,))
    g = _merge(far, a)
    assert (g.time_from, g.time_to, g.edges, g.edge_times) == (1.0, 10.0, (4, 5, 9), ())
    assert set(g.replaced_edges) == {7, 8}


CROSS_THEN_TURN = """
        n
        |
a-------b---------c
        |         |
        s         |
                  |
                  d
"""


def test_next_turn_revises_a_straight_crossing_passed_late() -> None:
    # the fixes lag 8 m along the road going east: the crossing at b is reported late; the turn
    # at c times the vehicle there, and carried back by the odometer it times the crossing too
    m = parse_ascii_map(CROSS_THEN_TURN, scale=10)
    fixes, true_s = biased_drive(m, "abcd", bias_x=-8.0, speed=8.0, dt=0.5)
    fixes = [f._replace(pos_sigma=10.0) for f in fixes]
    res = run(OnlineMatcher(m.graph), fixes)
    ab, bc = m.edge("a", "b"), m.edge("b", "c")
    b = m.xy("b")[0] - m.xy("a")[0]
    t_true = float(np.interp(b, true_s, [f.time for f in fixes]))
    live = np.array([r.edge for r in res])
    t_live = fixes[int(np.argmax(live == bc))].time
    assert t_live - t_true > 0.5  # reported late
    revised = [
        r.correction
        for r in res
        if r.correction is not None and (ab, bc) == tuple(r.correction.edges[:2]) and r.correction.edge_times
    ]
    assert revised, "no correction revised the crossing at b"
    t_new = revised[-1].edge_times[1]
    assert abs(t_new - t_true) < 0.5 < abs(t_live - t_true)
    assert revised[-1].edge_at(t_true - 0.6) == ab and revised[-1].edge_at(t_true + 0.6) == bc


def test_odometer_scale_is_learnt_between_turns() -> None:
    # a square loop of 540 m sides driven twice; the odometer under-reads by 3 % (the drive
    # takes its corners sharp, where the matcher expects them rounded: 1.7 m per corner less)
    m = parse_ascii_map(
        """
        a-----------------b
        |                 |
        |                 |
        |                 |
        |                 |
        |                 |
        |                 |
        |                 |
        d-----------------c
        """,
        scale=30,
    )
    fixes = drive(m, "abcdabcda", DriveSpec(speed=10.0, dt=1.0))
    fixes = [f._replace(distance=f.distance * 0.97, speed=9.7) for f in fixes]
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    for f in fixes:
        matcher.update(st, f)
    assert st.odo_k == pytest.approx(1.0 / 0.97 - 1.0, abs=0.01)
    assert st.odo_kvar < DEFAULT_CONFIG.online.odometer.odo_scale_sigma**2 / 4.0
    # the learnt scale survives a move to another server
    assert SessionState.from_bytes(st.to_bytes()).odo_k == st.odo_k


def test_odometer_trail_keeps_both_ends_of_a_stop() -> None:
    from mapmatch.online.anchor import add_trail
    from mapmatch.online.state import TrailPoint

    trail: list[TrailPoint] = []
    odo = 0.0
    for t in range(40):
        v = 0.0 if 10 <= t < 30 else 5.0  # a 20 s stop
        odo += v
        add_trail(trail, float(t), odo, v == 0.0, DEFAULT_CONFIG)
    t_tr = [x.time for x in trail]
    o_tr = [x.odo for x in trail]
    # the vehicle stood at odometer 50 from t = 9 to 29: just past it, the time is after the stop
    assert float(np.interp(50.5, o_tr, t_tr)) == pytest.approx(29.1, abs=0.05)
    assert float(np.interp(49.5, o_tr, t_tr)) == pytest.approx(8.9, abs=0.05)
    assert len(trail) < 30


def _stop_drive(m: AsciiMap, route: str, *, stop_s: float, bias_x: float, bias_y: float) -> list[Fix]:
    """Fixes every second at 5 m/s along ``route`` up to ``stop_s`` metres, then standing
    there for 20 s; each fix ``(bias_x, bias_y)`` metres off the true position."""
    pts = np.array([m.xy(n) for n in route], dtype=float)
    seg = np.diff(pts, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    true_s = [*np.arange(5.0, stop_s, 5.0).tolist(), stop_s, *[stop_s] * 20]
    fixes = []
    for i, s in enumerate(true_s):
        j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        x, y = pts[j] + (s - cum[j]) / (cum[j + 1] - cum[j]) * seg[j]
        lon, lat = to_lonlat(m.graph.crs, [x + bias_x], [y + bias_y])[0]
        moved = s - true_s[i - 1] if i else math.nan
        fixes.append(
            Fix(
                time=float(i),
                lat=float(lat),
                lon=float(lon),
                heading=math.degrees(math.atan2(seg[j, 0], seg[j, 1])) % 360.0,
                pos_sigma=3.0,
                speed=moved if i else 5.0,
                distance=moved,
                gps_valid=True,
            )
        )
    return fixes


@pytest.mark.parametrize(
    ("route", "stop_s", "beyond"),
    [
        ("abs", 85.0, "s"),  # turned right at b, stopped 5 m on: the heading shows the turn
        ("abc", 92.0, "c"),  # straight on, stopped 12 m past b
    ],
)
def test_vehicle_stopped_well_past_the_node_stays_there(route: str, stop_s: float, beyond: str) -> None:
    m = parse_ascii_map(CROSS, scale=10)
    past = m.edge("b", beyond)
    fixes = _stop_drive(m, route, stop_s=stop_s, bias_x=0.0, bias_y=0.0)
    res = run(OnlineMatcher(m.graph), fixes)
    assert [r.edge for r in res[-15:]] == [past] * 15
    assert all(past not in r.correction.replaced_edges for r in res if r.correction is not None)


BEND_AT_B = """
a-----------b
            |
            |
            |
            c
"""


def test_turn_anchor_re_times_the_turn_after_dead_reckoning_ran_ahead() -> None:
    # GPS is lost 80 m before the right turn at b and the odometer reads 10 % high: dead
    # reckoning carries the vehicle round the corner early; the turn's heading step times the
    # node, and the correction moves the fixes reported early on b-c back to a-b
    m = parse_ascii_map(BEND_AT_B, scale=10)
    ab, bc = m.edge("a", "b"), m.edge("b", "c")
    fixes, true_s = biased_drive(m, "abc", bias_x=0.0, speed=8.0, dt=1.0)
    fixes = [
        f._replace(gps_valid=False, distance=1.1 * f.distance) if s > 40.0 else f
        for f, s in zip(fixes, true_s, strict=True)
    ]
    res = run(OnlineMatcher(m.graph), fixes)
    t_true = float(np.interp(m.xy("b")[0] - m.xy("a")[0], true_s, [f.time for f in fixes]))
    early = [r.time for r in res if r.edge == bc and r.time < t_true]
    assert early, "dead reckoning did not run ahead"
    revised = [r.correction for r in res if r.correction is not None and r.correction.edges == (ab, bc)]
    assert revised and revised[0].edge_times
    c = revised[0]
    assert min(early) < c.edge_times[1] <= t_true  # moved towards the truth, never past it
    assert c.edge_at(max(early)) == ab and c.edge_at(t_true + 0.5) == bc


def test_stopped_vehicle_stays_on_its_road_while_its_fixes_wander_to_another() -> None:
    # a-b and c-d 20 m apart; the vehicle stops half-way along a-b for a minute and its fixes
    # (real receivers do this at a standstill) drift to lie on c-d: it has not left its road
    #
    #   a----------o------------b      o: where it stops
    #              :  fixes drift down to c-d while stopped
    #   c----------x------------d
    m = parse_ascii_map(
        """
a-----------------------b
c-----------------------d
""",
        scale=20,
    )
    ab, cd = m.edge("a", "b"), m.edge("c", "d")
    a, b, c = m.xy("a"), m.xy("b"), m.xy("c")
    east = (b - a) / np.linalg.norm(b - a)
    fixes = [f for f in drive(m, "ab", DriveSpec(speed=5)) if np.dot(to_xy_arr(m, f) - a, east) < 200.0]
    t = fixes[-1].time
    stop = a + 200.0 * east
    down = c - a
    for i in range(60):
        drift = min(1.0, i / 10.0)  # 10 s to drift onto c-d, then 50 s there
        fixes.append(_fix_at(m, stop + drift * down, t + 1 + i, 90.0, speed=0.0, distance=0.0))
    res = run(OnlineMatcher(m.graph), fixes)
    assert all(r.edge == ab for r in res[-60:])
    assert all(r.state is not State.REINITIALISED for r in res)
    # the same fixes from a vehicle that moves slowly: it has left a-b for c-d
    moving = [f._replace(speed=1.0, distance=1.0) if f.time > t else f for f in fixes]
    res = run(OnlineMatcher(m.graph), moving)
    assert res[-1].edge == cd


def test_odometer_scale_is_learnt_from_the_gps_on_a_straight_road() -> None:
    # a straight road 3 km long without a single turn to anchor on; the odometer reads 2 %
    # long: over straight baselines the GPS shows it (path metres = odometer * (1 + k))
    #
    #   a------------------------------------------------------------b   (3 km)
    m = parse_ascii_map("a" + "-" * 59 + "b", scale=50)
    fixes = [
        f._replace(distance=f.distance * 1.02)
        for f in drive(m, "ab", DriveSpec(speed=20, noise=3.0, seed=4, sigma=5.0))
    ]
    st = SessionState()
    run(OnlineMatcher(m.graph), fixes, st)
    assert abs(st.odo_k - (1.0 / 1.02 - 1.0)) < 0.005
    off = SessionState()
    run(OnlineMatcher(m.graph, config=DEFAULT_CONFIG.replace(scale_baseline=0.0)), fixes, off)
    assert off.odo_k == 0.0


TURN_THEN_CROSSING = """
n
|
|
|
|
b-----c-------d
      |
      s
"""


def test_vehicle_stopped_past_a_crossing_stays_past_it() -> None:
    # the odometer reads 10 % low: from the turn at b on, the position carried by it (the turn
    # anchor) lags the exact fixes. The vehicle stops 6 m past the straight crossing c, where
    # its fixes lie: it stands on c-d, not back before c.
    #
    #   n
    #   |
    #   b-----c-*-----d      *: stops 6 m past c (fixes there); the belief lags 3 m
    #         s
    m = parse_ascii_map(TURN_THEN_CROSSING, scale=10)
    cd = m.edge("c", "d")
    stop_s = float(m.xy("n")[1] - m.xy("b")[1]) + float(m.xy("c")[0] - m.xy("b")[0]) + 6.0
    fixes = [
        f._replace(distance=0.9 * f.distance, speed=0.9 * f.speed)
        for f in _stop_drive(m, "nbcd", stop_s=stop_s, bias_x=0.0, bias_y=0.0)
    ]
    res = run(OnlineMatcher(m.graph), fixes)
    assert [r.edge for r in res[-19:]] == [cd] * 19


def test_stopped_vehicle_faces_the_way_its_fused_heading_says() -> None:
    # a two-way road; the vehicle stands at o from the start, its gyro-fused heading (with its σ)
    # pointing west: it stands on b->a, not on a->b (on track 84 of the real drives, a vehicle
    # that turned round while standing at a node)
    #
    #   a-----------o-----------b      o: standing, facing a
    m = parse_ascii_map("a-----------------------b", scale=10)
    a, b = m.xy("a"), m.xy("b")
    stop = (a + b) / 2 + np.array([0.0, 1.0])
    rng = np.random.default_rng(3)
    fixes = [
        _fix_at(
            m,
            stop + rng.normal(0.0, 1.0, 2),
            float(i),
            270.0,
            speed=0.0,
            distance=0.0,
            heading_sigma=3.0,
            pos_sigma=3.0,
        )
        for i in range(30)
    ]
    res = run(OnlineMatcher(m.graph), fixes)
    assert all(r.edge == m.edge("b", "a") for r in res[-10:])
    facing_east = [f._replace(heading=90.0) for f in fixes]
    assert all(r.edge == m.edge("a", "b") for r in run(OnlineMatcher(m.graph), facing_east)[-10:])
    # neither a GPS course (no heading σ) nor the rule switched off can tell at a standstill
    off = DEFAULT_CONFIG.replace(stopped_heading_weight=0.0)
    for matcher, fs in (
        (OnlineMatcher(m.graph, config=off), fixes),
        (OnlineMatcher(m.graph), [f._replace(heading_sigma=math.nan) for f in fixes]),
    ):
        res = run(matcher, fs)
        assert [r.edge for r in res[-10:]] == [run(matcher, facing_east)[-1].edge] * 10
