"""Batch matching on tiny ASCII maps: one drawing per situation."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from ascii_helpers import at, names, track_from_xy

from graph.ascii import parse_ascii_map
from mapmatch import batch
from mapmatch.batch import BATCH_CONFIG as DEFAULT_CONFIG
from mapmatch.batch import BatchMatcher
from mapmatch.config import MatchConfig
from mapmatch.route_table import Ubodt
from mapmatch.routing import shortest_route
from mapmatch.types import PointStatus, Track, TrackMatch


def test_straight_drive_through_junctions() -> None:
    m = parse_ascii_map(
        """
        a-----b-----c
              |
              d-----e
        """,
        scale=20,
    )
    pts = [at(m, "a", 10, 3), at(m, "a", 60, -2), at(m, "b", 2, -15), at(m, "b", -3, -30), at(m, "d", 40, 4)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts))
    assert [names(m, piece) for piece in r.routes] == [["ab", "bd", "de"]]
    assert r.splits == []
    assert all(p.status == PointStatus.MATCHED for p in r.points)
    assert r.length_m == pytest.approx(110 + 80 + 40, abs=1.0)
    assert 0 < r.confidence <= 1
    assert len(r.route_lonlat) == 1 and len(r.route_lonlat[0]) >= 4


def test_uturn_in_the_middle_of_a_road() -> None:
    m = parse_ascii_map("a--------------b-----c", scale=10)
    xs = [10, 30, 50, 70, 90, 100, 85, 65, 45, 25]
    pts = [at(m, "a", x, 2) for x in xs]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts))
    assert [names(m, piece) for piece in r.routes] == [["ab", "ba"]]
    assert r.splits == []
    # from x = 10 out to the turn (~100 m) and back to x = 25
    assert r.length_m == pytest.approx(90 + 75, abs=8.0)
    assert names(m, [r.points[-1].edge]) == ["ba"]


def test_uturn_is_penalised_when_noise_alone_explains_the_fixes() -> None:
    m = parse_ascii_map("a--------------b-----c", scale=10)
    xs = [10, 30, 50, 48, 70, 90]  # one fix 2 m behind the previous: noise, not a U-turn
    r = BatchMatcher(m.graph).match(track_from_xy(m, [at(m, "a", x, 1) for x in xs]))
    assert [names(m, piece) for piece in r.routes] == [["ab"]]


def test_parallel_roads_stay_on_one_road() -> None:
    # two parallel roads 40 m apart, joined only at the ends
    m = parse_ascii_map(
        """
        a----------b
        |          |
        |          |
        c----------d
        """,
        scale=10,
    )
    # driving along a-b, with two fixes pulled 22 m south (closer to c-d than to a-b)
    offs = [-3, 2, -22, -23, 1, -2, 0]
    pts = [at(m, "a", 10 + 14 * i, off) for i, off in enumerate(offs)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=2.0))
    assert [names(m, piece) for piece in r.routes] == [["ab"]]


def test_one_way_road_is_not_driven_backwards() -> None:
    # the north road is one-way eastbound; a westbound car closer to it must be on the south road
    m = parse_ascii_map(
        """
        a>>>>>>>>>>>>>>>>>>>b
        |                   |
        c-------------------d
        """,
        scale=5,
    )  # the roads are 20 m apart
    pts = [at(m, "b", -10 - 12 * i, -7) for i in range(7)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=2.0))
    assert [names(m, piece) for piece in r.routes] == [["dc"]]
    # driving east on the same fixes uses the one-way road
    r2 = BatchMatcher(m.graph).match(track_from_xy(m, pts[::-1], dt=2.0))
    assert [names(m, piece) for piece in r2.routes] == [["ab"]]


def test_slow_dense_fixes_tell_their_direction_against_a_one_way() -> None:
    # fixes every 10 m (1 s) westbound on top of the eastbound one-way a-d; the westbound
    # road e-h is 20 m south. Standing still on a-d (each fix falling 10 m behind the last)
    # would explain them almost as well, but their direction of travel says west: on e-h.
    m = parse_ascii_map(
        """
        a>b>c>d
        | | | |
        e<f<g<h
        """,
        scale=5,
    )
    pts = [at(m, n) for n in "dcba"]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=1.0))
    assert [names(m, piece) for piece in r.routes] == [["hg", "gf", "fe"]]
    # without the direction of travel, the fixes stand on a-d
    old = BatchMatcher(m.graph).match(
        track_from_xy(m, pts, dt=1.0), DEFAULT_CONFIG.replace(straight_max_deg=0)
    )
    assert [names(m, piece) for piece in old.routes] == [["bc"]]


def test_turn_restriction_is_respected() -> None:
    drawing = """
        a---b---c
            |   |
            d---e
        """
    free = parse_ascii_map(drawing, scale=10)
    banned = parse_ascii_map(drawing, scale=10, restrictions=[("a", "b", "d", "no")])
    ab, bd = banned.edge("a", "b"), banned.edge("b", "d")
    assert shortest_route(free.graph, ab, 5.0, bd, 10.0) is not None
    assert shortest_route(banned.graph, ab, 5.0, bd, 10.0) is None
    only = parse_ascii_map(drawing, scale=10, restrictions=[("a", "b", "c", "only")])
    assert shortest_route(only.graph, ab, 5.0, only.edge("b", "d"), 10.0) is None
    assert shortest_route(only.graph, ab, 5.0, only.edge("b", "c"), 10.0) is not None
    # a car turning a -> b -> d: with the turn banned, the matched route never makes that turn
    pts = [at(banned, "a", 10, 1), at(banned, "a", 30, -1), at(banned, "b", 1, -15), at(banned, "b", -1, -30)]
    r = BatchMatcher(banned.graph).match(track_from_xy(banned, pts))
    for piece in r.routes:
        seq = names(banned, piece)
        assert not any(x == "ab" and y == "bd" for x, y in itertools.pairwise(seq))


def test_gap_splits_the_track_and_is_reported() -> None:
    # fixes 3 and 4 are 180 m apart, beyond the jump distance (split_speed 50 m/s times
    # max_skip_time, 2 s here: 100 m), and 2 s apart: too fast to drive, a jump, so the track
    # splits there
    m = parse_ascii_map("a-----------------------------b", scale=10)
    xs = [10, 30, 50, 230, 250, 270]
    cfg = DEFAULT_CONFIG.replace(max_skip_time=2.0)
    r = BatchMatcher(m.graph).match(track_from_xy(m, [at(m, "a", x, 1) for x in xs], dt=2.0), cfg)
    assert r.splits == [3]
    assert len(r.routes) == 2 and len(r.route_lonlat) == 2
    assert all(p.status == PointStatus.MATCHED for p in r.points)
    assert r.length_m == pytest.approx(40 + 40, abs=1.0)
    # one road, every fix on it: full confidence (both directions count as one road)
    assert r.confidence > 0.99


def test_a_gap_driven_at_road_speed_is_bridged_by_its_route() -> None:
    # a sparse track with the logger off for 200 s between fixes 3 and 4, 3.6 km apart (beyond
    # the jump distance, split_speed times max_skip_time: 3 km) and 3.9 km along an L-shaped
    # road (100 m per character): 20 m/s is a drive, not a jump, so the route bridges the gap
    # and the track stays one piece; the same 3.6 km in 15 s (240 m/s) splits
    #
    #   a----------------------------------------b
    #                                            |
    #                                            c
    m = parse_ascii_map(
        """
        a----------------------------------------b
                                                 |
                                                 c
        """,
        scale=100,
    )
    xy = [at(m, "a", 100, 3), at(m, "a", 300, -3), at(m, "a", 500, 2)]
    xy += [at(m, "b", -4, -300), at(m, "b", 3, -380)]
    split = DEFAULT_CONFIG.batch.split
    assert math.dist(xy[2], xy[3]) > split.split_speed * DEFAULT_CONFIG.batch.outliers.max_skip_time
    ll = np.array([m.lonlat(x, y) for x, y in xy])
    bridged = Track("t", np.array([0.0, 15.0, 30.0, 230.0, 240.0]), ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(bridged)
    assert r.splits == [] and [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert r.length_m == pytest.approx(4000 + 380, abs=5.0)
    jump = Track("t", np.array([0.0, 15.0, 30.0, 45.0, 55.0]), ll[:, 1], ll[:, 0])
    assert BatchMatcher(m.graph).match(jump).splits == [3]
    # max_skip_time 0: distance never splits, so even the jump is one piece
    never = BatchMatcher(m.graph).match(jump, DEFAULT_CONFIG.replace(max_skip_time=0.0))
    assert never.splits == [] and [names(m, piece) for piece in never.routes] == [["ab", "bc"]]


def test_outlier_is_unmatched_and_does_not_break_the_route() -> None:
    m = parse_ascii_map("a--------------b", scale=10)
    pts = (
        [at(m, "a", x, 2) for x in (10, 30, 50)]
        + [at(m, "a", 70, 300)]
        + [at(m, "a", x, 2) for x in (90, 110)]
    )
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts))
    assert [p.status for p in r.points].count(PointStatus.UNMATCHED) == 1
    assert r.points[3].status == PointStatus.UNMATCHED and r.points[3].edge == -1
    assert r.confidence == pytest.approx(5 / 6, abs=0.01)  # the matched fraction
    assert math.isnan(r.points[3].lat)
    assert r.splits == [] and [names(m, piece) for piece in r.routes] == [["ab"]]


def test_points_closer_than_the_noise_are_interpolated() -> None:
    m = parse_ascii_map("a--------------b", scale=10)
    xs = np.arange(5.0, 120.0, 3.0)
    cfg = DEFAULT_CONFIG.replace(gps_sigma=10.0)  # fixes within one σ are interpolated
    r = BatchMatcher(m.graph).match(track_from_xy(m, [at(m, "a", float(x), 2) for x in xs], dt=1.0), cfg)
    st = [p.status for p in r.points]
    assert st.count(PointStatus.INTERPOLATED) > len(xs) // 2
    assert st[0] == st[-1] == PointStatus.MATCHED
    for p, x in zip(r.points, xs, strict=True):
        assert p.edge == m.edge("a", "b")
        assert p.offset == pytest.approx(x, abs=0.5)
        assert p.dist == pytest.approx(2.0, abs=0.01)
    assert [names(m, piece) for piece in r.routes] == [["ab"]]
    # an interpolated point is a matched one: one road, every fix on it, full confidence
    assert r.confidence > 0.99


def test_track_partly_outside_the_map_and_bad_points() -> None:
    m = parse_ascii_map("a--------------b", scale=10)
    pts = [at(m, "a", x, 1) for x in (10, 40, 70)] + [at(m, "b", 500 + 100 * i, 0) for i in range(3)]
    t = track_from_xy(m, pts)
    t.lat[1] = np.nan  # a broken fix
    r = BatchMatcher(m.graph).match(t)
    st = [p.status for p in r.points]
    assert st == ["matched", "unmatched", "matched", "unmatched", "unmatched", "unmatched"]
    assert [names(m, piece) for piece in r.routes] == [["ab"]]


def test_empty_and_hopeless_tracks_do_not_fail() -> None:
    m = parse_ascii_map("a-----b", scale=10)
    bm = BatchMatcher(m.graph)
    empty = bm.match(Track("e", np.empty(0), np.empty(0), np.empty(0)))
    assert empty.points == [] and empty.routes == []
    nan = bm.match(Track("n", np.array([0.0, 1.0]), np.array([np.nan, 91.0]), np.array([0.0, 0.0])))
    assert [p.status for p in nan.points] == ["unmatched", "unmatched"] and nan.routes == []
    one = bm.match(track_from_xy(m, [at(m, "a", 20, 1)]))
    assert [p.status for p in one.points] == ["matched"] and len(one.routes) == 1


def test_turning_round_at_a_junction_after_a_stop() -> None:
    # along ab, a stop in a yard off the road just past b (next to bd), then back along ba:
    # the stop makes turning round at b likelier than a loop b-c-e-d-b
    m = parse_ascii_map(
        """
        a-------b-c
                | |
                d-e
        """,
        scale=10,
    )
    go = [at(m, "a", x, 1) for x in (5, 20, 35, 50, 65, 78)]
    stop = [at(m, "b", dx, -10) for dx in (1, 2, 1, 1.5, 2, 1)]
    back = [at(m, "a", x, -1) for x in (78, 65, 50, 35, 20, 5)]
    track = track_from_xy(m, go + stop + back)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "ba"]]
    assert r.length_m == pytest.approx(150, abs=12)
    # without the stop rule the full U-turn penalty makes the loop win (either way round: the
    # same length and the same turns)
    full = DEFAULT_CONFIG.replace(stop_uturn_penalty=DEFAULT_CONFIG.model.uturn_penalty)
    r = BatchMatcher(m.graph).match(track, full)
    loops = ([["ab", "bc", "ce", "ed", "db", "ba"]], [["ab", "bd", "de", "ec", "cb", "ba"]])
    assert [names(m, piece) for piece in r.routes] in loops


def test_drift_onto_a_dead_end_is_left_out_rather_than_splitting() -> None:
    # a few fixes drift onto the one-way dead end bd, from which the rest of the track (on bc)
    # cannot be reached: they are the outliers, not the many fixes after them
    m = parse_ascii_map(
        """
        a-----b-------------c
              v
              v
              v
              d
        """,
        scale=10,
    )
    pts = [at(m, "a", x, 1) for x in (5, 20, 35)]
    drift = [at(m, "b", 3, -55), at(m, "b", -3, -64), at(m, "b", 2, -73)]
    on = [at(m, "b", 15 + 12 * k, 1) for k in range(10)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts + drift + on))
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert r.splits == []
    status = [p.status for p in r.points]
    assert status[3:6] == [PointStatus.UNMATCHED] * 3
    assert all(s == PointStatus.MATCHED for s in status[:3] + status[6:])
    # fewer fixes may be left out (max_skip, per call, judged by the count alone) than drifted:
    # the track splits instead
    few = BatchMatcher(m.graph).match(
        track_from_xy(m, pts + drift + on), DEFAULT_CONFIG.replace(max_skip=2, max_skip_time=0.0)
    )
    assert few.splits == [6] and [names(m, piece) for piece in few.routes] == [["ab", "bd"], ["bc"]]


def test_a_dense_fast_track_off_the_road_for_a_stretch_is_one_piece_as_its_sparse_version() -> None:
    # a fast road (30 m/s, a fix a second); for 15 s the fixes lie 55 m north of it (beyond
    # 5 σ: off it), 25 m from a road the route cannot reach (xy, not joined to ab). Fifteen
    # fixes in a row are unreachable, more than ``max_skip``, but they last 15 s, under
    # ``max_skip_time``: they are left out and the route bridges them along ab, as it does
    # for the same drive sampled every 10 s (where one or two fixes lie off the road)
    m = parse_ascii_map(
        """
                                            x--------------------------------------------y



        a------------------------------------------------------------------------------------------------------------------------b
        """,
        scale=10,
    )
    pts = [at(m, "a", x, 55 if 450 <= x < 900 else 1) for x in range(0, 1200, 30)]
    full = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=1.0))
    assert [names(m, piece) for piece in full.routes] == [["ab"]] and full.splits == []
    off = [i for i, p in enumerate(full.points) if p.status != PointStatus.MATCHED]
    assert off == list(range(15, 30))
    sparse = BatchMatcher(m.graph).match(track_from_xy(m, pts[::10] + pts[-1:], dt=10.0))
    assert [names(m, piece) for piece in sparse.routes] == [["ab"]] and sparse.splits == []
    assert full.length_m == pytest.approx(sparse.length_m, abs=1.0)
    # judged by the count of fixes alone, the dense track splits where the sparse one does not
    by_count = DEFAULT_CONFIG.replace(max_skip_time=0.0)
    count = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=1.0), by_count)
    assert [names(m, piece) for piece in count.routes] == [["ab"], ["xy"], ["ab"]]
    assert count.splits == [15, 30]


def test_batch_tuning_constants_are_validated_config_fields() -> None:
    from mapmatch.errors import ConfigError

    cfg = DEFAULT_CONFIG.replace(emission_prune=5.0, max_skip=3, stop_uturn_penalty=2.0)
    assert (
        cfg.batch.outliers.emission_prune,
        cfg.batch.outliers.max_skip,
        cfg.batch.route.stop_uturn_penalty,
    ) == (5.0, 3, 2.0)
    bads = [{"max_skip": 2.5}, {"reverse_tolerance": -1.0}, {"route_lp_cut": math.inf}]
    for bad in [*bads, {"off_map_sigmas": -1.0}, {"off_map_cut_fixes": 1.5}]:
        with pytest.raises(ConfigError):
            DEFAULT_CONFIG.replace(**bad)


def test_deferred_lonlat_gives_the_same_result() -> None:
    m = parse_ascii_map(
        """
        a-----b-----c
              |
              d-----e
        """,
        scale=20,
    )
    pts = [at(m, "a", 10, 3), at(m, "a", 12, 2), at(m, "a", 60, -2), at(m, "b", -3, -30), at(m, "d", 40, 4)]
    matcher = BatchMatcher(m.graph)
    full = matcher.match(track_from_xy(m, pts))
    late = matcher.match(track_from_xy(m, pts), lonlat=False)
    assert late.points == [] and late.route_lonlat == [] and late.point_arrays is not None
    batch.fill_route_lonlat(late, m.graph.crs)
    assert late.point_arrays is None
    assert late.points == full.points and late.route_lonlat == full.route_lonlat
    assert [p.status for p in full.points].count(PointStatus.INTERPOLATED) == 1


def test_one_matcher_serves_many_threads() -> None:
    from concurrent.futures import ThreadPoolExecutor

    m = parse_ascii_map(
        """
        a-----b-----c
        |     |     |
        d-----e-----f
        """,
        scale=20,
    )
    rng = np.random.default_rng(3)
    routes = [["a", "b", "c", "f", "e", "d"], ["d", "e", "b", "c"], ["c", "b", "a", "d", "e", "f"]]
    tracks = []
    for i, nodes in enumerate(routes * 4):
        pts = []
        for u, v in itertools.pairwise(nodes):
            (x0, y0), (x1, y1) = at(m, u), at(m, v)
            for t in np.linspace(0.1, 0.9, 5):
                pts.append((x0 + t * (x1 - x0) + rng.normal(0, 3), y0 + t * (y1 - y0) + rng.normal(0, 3)))
        tracks.append(track_from_xy(m, pts, dt=2.0, tid=str(i)))
    matcher = BatchMatcher(m.graph)
    alone = [BatchMatcher(m.graph).match(t).routes for t in tracks]
    with ThreadPoolExecutor(4) as pool:
        shared = list(pool.map(lambda t: matcher.match(t).routes, tracks * 5))
    assert shared == alone * 5
    assert [names(m, r[0]) for r in alone[:3]] == [
        ["ab", "bc", "cf", "fe", "ed"],
        ["de", "eb", "bc"],
        ["cb", "ba", "ad", "de", "ef"],
    ]


def test_fixes_off_the_map_at_the_end_are_unmatched_not_routed_to_a_far_road() -> None:
    # the track ends in a car park 58 m north of ae, 42 m from cd: no road explains it (5 σ
    # is 40 m); it must not pull the route round e-d onto cd
    m = parse_ascii_map(
        """
        c------------d
        |            |
        |            |
        |            |
        |            |
        a------------e
        """,
        scale=10,
    )
    road = [at(m, "a", x, 1) for x in (10, 22, 34, 46, 58, 70)]
    park = [at(m, "a", x, 58 + dy) for x, dy in ((76, 0), (80, 2), (78, -1), (81, 1))]
    r = BatchMatcher(m.graph).match(track_from_xy(m, road + park))
    assert [names(m, piece) for piece in r.routes] == [["ae"]]
    assert [p.status for p in r.points][6:] == [PointStatus.UNMATCHED] * 4
    assert r.length_m == pytest.approx(60, abs=2)
    # with the off-map limit widened to the outlier distance (13 σ, 104 m) the car park is on
    # the map, and leaving a fix out costs the emission at that limit (½ 13²): it is routed
    # to cd
    track = track_from_xy(m, road + park)
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(off_map_sigmas=13))
    assert [names(m, piece) for piece in loose.routes] == [["ae", "ed", "dc"]]
    assert loose.length_m > 150


def test_a_run_off_the_map_cuts_the_route() -> None:
    # the track leaves ae up an unmapped lane, drives 200 m with no road within 40 m and comes
    # back onto cd: the route is cut there, never bridged by a guess
    m = parse_ascii_map(
        """
        c------------------------------d
        |                              |
        |                              |
        |                              |
        |                              |
        a------------------------------e
        """,
        scale=10,
    )
    go = [at(m, "a", x, 1) for x in (10, 22, 34, 46)]
    lane = [at(m, "a", x, 50) for x in (45, 89, 133, 177, 221, 265)]
    back = [at(m, "c", x, -1) for x in (280, 265, 250, 235)]
    track = track_from_xy(m, go + lane + back)
    r = BatchMatcher(m.graph).match(track)
    assert r.splits == [10]
    assert [names(m, piece) for piece in r.routes] == [["ae"], ["dc"]]
    assert [p.status for p in r.points][4:10] == [PointStatus.UNMATCHED] * 6
    # a short excursion (less than off_map_cut, lasting less than it takes at
    # spike_speed) is bridged
    r = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(off_map_cut=1000.0))
    assert r.splits == [] and len(r.routes) == 1


def test_fixes_off_the_map_at_speed_are_bridged_not_cut() -> None:
    # on a fast road (25 m/s, a fix a second) ten fixes in a row lie 60 m off it (beyond 5 σ:
    # off the map), moving with the car: GPS trouble on a road, not a car leaving the map,
    # which it does slowly. They travel 225 m, but at 25 m/s: the route bridges them
    m = parse_ascii_map("a" + "-" * 100 + "b", scale=10)
    pts = [at(m, "a", x, 1 if not 100 <= x < 350 else 60) for x in range(0, 1000, 25)]
    track = track_from_xy(m, pts, dt=1.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"]] and r.splits == []
    assert [p.status for p in r.points].count(PointStatus.UNMATCHED) == 10
    # at any speed (``spike_speed`` 0) the run cuts the route
    cut = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(spike_speed=0))
    assert cut.splits == [14] and len(cut.routes) == 2


def test_fixes_off_the_map_at_speed_are_not_bridged_by_a_long_way_round() -> None:
    # the map lacks the 525 m of fast road from b to c. The car drives on at 25 m/s, a fix a
    # second: 18 fixes off the map (beyond 5 σ of any road), too fast for a cut, so the route
    # may bridge them, but only near the path they trace (525 m): not round by e and f (1025 m,
    # which the time between the fixes and the detour limit allow)
    m = parse_ascii_map(
        """
        a------------b                    c------------d
                     |                    |
                     |                    |
                     |                    |
                     |                    |
                     e--------------------f
        """,
        scale=25,
    )
    pts = [at(m, "a", x, 1) for x in range(0, 1150, 25)]
    track = track_from_xy(m, pts, dt=1.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"], ["cd"]]
    off = [i for i, p in enumerate(r.points) if p.status == PointStatus.UNMATCHED]
    assert off == list(range(15, 33)) and r.splits == [33]
    # with no cut rules (and so no such limit: it is twice off_map_cut) the run is bridged
    # round by e and f
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(off_map_cut=0))
    assert [names(m, piece) for piece in loose.routes] == [["ab", "be", "ef", "fc", "cd"]]


def test_sparse_fixes_either_side_of_a_missing_road_split_rather_than_go_round_too_fast() -> None:
    # a highway whose 1050 m from b to c the map lacks; the car drives on at 25 m/s, a fix
    # every 30 s (150 m per character, 300 m per row). The fix between b and c is off the map,
    # and one fix is too few for a cut. The way round by e and f (3900 m from fix 1 to fix 3
    # in 60 s, or 4650 m to fix 4 in 90 s, leaving fix 3 out) needs over 50 m/s: impossible,
    # so the match splits and both sides keep their fixes
    m = parse_ascii_map(
        """
        a------b      c----------d
               |      |
               |      |
               |      |
               e------f
        """,
        scale=150,
    )
    track = track_from_xy(m, [at(m, "a", x, 2) for x in range(0, 3751, 750)], dt=30.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"], ["cd"]] and r.splits == [3]
    off = [i for i, p in enumerate(r.points) if p.status != PointStatus.MATCHED]
    assert off == [2]
    # at a top speed of 100 m/s the way round is taken and fix 3 left out
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(split_speed=100.0))
    assert [names(m, piece) for piece in loose.routes] == [["ab", "be", "ef", "fc", "cd"]]
    assert [i for i, p in enumerate(loose.points) if p.status != PointStatus.MATCHED] == [2, 3]


def test_fixes_on_a_road_the_route_cannot_reach_cut_the_route_not_a_way_round() -> None:
    # the map lacks the 60 m of road from b to c. The track drives east along ab, then slowly
    # along cd (a fix every 100 m, 20 s apart) and down df. No route reaches cd in the time of
    # one step; after a few steps the 1 km round by a, e, f fits the time. The fixes left out
    # on cd until then travel 200 m among themselves: the route is cut there, and cd starts a
    # piece, as where fixes run off the map (issue #14's class 1: a road missing from the map)
    m = parse_ascii_map(
        """
        a----------b     c--------------------------------------------d
        |                                                             |
        |                                                             |
        e-------------------------------------------------------------f
        """,
        scale=10,
    )
    drive = [at(m, "a", x, 1) for x in (10, 30, 50, 70, 90)]
    along = [at(m, "b", 30, 0)] + [at(m, "c", x, -2) for x in (20, 120, 220, 320, 420)]
    down = [at(m, "d", 2, -20), at(m, "d", 2, -40)]
    ll = np.array([m.lonlat(x, y) for x, y in drive + along + down])
    times = np.r_[np.arange(5) * 2.0, 8.0 + 20.0 * np.arange(1, 9)]
    track = Track("t", times, ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(track)
    assert r.splits == [6]
    assert [names(m, piece) for piece in r.routes] == [["ab"], ["cd", "df"]]
    assert set(p.status for p in r.points) == {PointStatus.MATCHED}
    # with no cut, the fixes on cd are left out and the route goes round to df
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(off_map_cut=0))
    assert len(loose.routes) == 1 and loose.length_m > 900
    assert [p.status for p in loose.points][6:10] == [PointStatus.UNMATCHED] * 4


def test_sparse_fixes_off_the_map_for_a_while_cut_the_route_though_they_travel_little() -> None:
    # the track drives east along ab (a fix every 10 s), turns into an unmapped yard (three
    # fixes 20 s apart, 70 m from every road, 70 m travelled) and comes out west along cd. The
    # time allows the 570 m round by b and d (15 β of detour, under ``detour_cost_max``), and
    # the run is too short in space to cut by ``off_map_cut``; but it lasted 40 s, longer than
    # ``off_map_cut`` takes at ``spike_speed`` (10 s), and with its legs from ab and to
    # cd it travels 210 m: the track left the roads, and the route is cut there
    m = parse_ascii_map(
        """
        c------------------------------------------------------------d
                                                                     |
                                                                     |
                                                                     |
                                                                     |
                                                                     |
                                                                     |
                                                                     |
                                                                     |
                                                                     |
        a------------------------------------------------------------b
        """,
        scale=10,
    )
    drive = [at(m, "a", x, 1) for x in (100, 200, 300, 400)]
    yard = [at(m, "a", 420, 70), at(m, "a", 440, 100), at(m, "a", 420, 130)]
    out = [at(m, "c", x, -1) for x in (450, 350, 250)]
    ll = np.array([m.lonlat(x, y) for x, y in drive + yard + out])
    times = np.array([0, 10, 20, 30, 50, 70, 90, 110, 120, 130], dtype=np.float64)
    track = Track("t", times, ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(track)
    assert r.splits == [7]
    assert [names(m, piece) for piece in r.routes] == [["ab"], ["dc"]]
    assert [p.status for p in r.points][4:7] == [PointStatus.UNMATCHED] * 3
    # where 200 m takes 100 s (``spike_speed`` 2 m/s) the run is too brief: round by b and d
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(spike_speed=2.0))
    assert [names(m, piece) for piece in loose.routes] == [["ab", "bd", "dc"]]
    assert loose.length_m > 1000


CAR_PARK_MAP = """
        d----------------------------------------e
                                                 |
                                                 |
                                                 |
                                                 |
        a----------------------------------------b
        """
"""Two roads 100 m apart, joined 400 m away: a car park between them is near de, off ab."""


def test_a_first_fix_in_a_car_park_by_another_road_is_left_out_not_a_piece() -> None:
    # the track starts 28 m south of de (within 5 σ), drives down an unmapped lane and east
    # along ab: no route joins de to ab in time, so the first fix, not the drive, is left out
    m = parse_ascii_map(CAR_PARK_MAP, scale=10)
    drive = [at(m, "a", x, 1) for x in range(25, 200, 25)]
    track = track_from_xy(m, [at(m, "d", 20, -28), at(m, "d", 22, -50), *drive])
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"]]
    assert [p.status for p in r.points][:2] == [PointStatus.UNMATCHED] * 2
    assert r.length_m == pytest.approx(175 - 25, abs=2)
    # without weighing the first fix against the next (outlier_lookahead) it is a piece alone
    r = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(outlier_lookahead=0))
    assert r.splits == [2] and [names(m, piece) for piece in r.routes] == [["de"], ["ab"]]


def test_fixes_in_a_car_park_are_not_joined_to_the_drive_by_a_long_way_round(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the track starts 28 m south of de and waits on an unmapped lane for a minute (fixes 20 s
    # apart, 50 m from each road) before driving west along ab. The time allows the 900 m
    # round by e and b, but that detour costs more than ``off_map_sigmas``² β: the car park's
    # fixes are left unmatched. The same at the end of a track.
    m = parse_ascii_map(CAR_PARK_MAP, scale=10)
    park = [at(m, "d", 20, -28)] + [at(m, "d", 30 + 20 * k, -50) for k in (1, 2, 3)]
    drive = [at(m, "a", x, -1) for x in range(140, 0, -12)]
    n = len(drive)

    def track(xy: list[tuple[float, float]], t: list[float]) -> Track:
        ll = np.array([m.lonlat(x, y) for x, y in xy])
        return Track("t", np.asarray(t, dtype=np.float64), ll[:, 1], ll[:, 0])

    start = track(park + drive, [0, 20, 40, 60] + [70 + 5 * k for k in range(n)])
    end_times = [5 * k for k in range(n)] + [5 * n + k for k in (5, 25, 45, 65)]
    end = track(drive[::-1] + [(x + 40, y) for x, y in park[::-1]], end_times)
    for trk, route, out in ((start, ["ba"], slice(0, 4)), (end, ["ab"], slice(n, None))):
        r = BatchMatcher(m.graph).match(trk)
        assert [names(m, piece) for piece in r.routes] == [route]
        assert set(p.status for p in r.points[out]) == {PointStatus.UNMATCHED}
        assert r.length_m == pytest.approx(132, abs=2)
    # with any detour the time allows (the limit off, as the matcher's joining call has it),
    # and every fix at the ends visited: round by e and b
    from mapmatch.batch import matcher as matcher_module

    with_limit = matcher_module.kernel_params
    monkeypatch.setattr(
        matcher_module, "kernel_params", lambda c, s: with_limit(c, s)._replace(detour_cost_max=0.0)
    )
    loose = DEFAULT_CONFIG.replace(outlier_lookahead=0)
    for trk in (start, end):
        assert BatchMatcher(m.graph).match(trk, loose).length_m > 800


def test_first_fixes_each_by_another_road_are_left_out_one_after_another() -> None:
    # the track starts in a car park: a fix 25 m south of de, two minutes later one 25 m
    # south of gh, then it drives east along ab. Each step out of those fixes needs a way
    # round (de by e, c and b to gh: 930 m for 100 m; gh by h and b to ab: 530 m for 75 m),
    # so each visit costs more than leaving it out: both go, and the route starts on ab
    m = parse_ascii_map(
        """
        d------------------------------------e
                                             |
                                             |
                                             |
                                             |
        g---------------------------h        |
                                    |        |
                                    |        |
                                    |        |
                                    |        |
        a---------------------------b--------c
        """,
        scale=10,
    )
    park = [at(m, "d", 40, -25), at(m, "g", 50, -25)]
    drive = [at(m, "a", x, 1) for x in range(60, 260, 20)]
    ll = np.array([m.lonlat(x, y) for x, y in park + drive])
    times = np.r_[0.0, 120.0, 240.0 + 4.0 * np.arange(len(drive))]
    track = Track("t", times, ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"]]
    assert [p.status for p in r.points][:3] == [PointStatus.UNMATCHED] * 2 + [PointStatus.MATCHED]
    assert r.length_m == pytest.approx(240 - 60, abs=2)
    # without the leave-out rules every fix is visited: round by e, c, b and h, turning at g,
    # then by h and b, turning at a
    loose = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(outlier_lookahead=0))
    routes = [["de", "ec", "cb", "bh", "hg", "gh", "hb", "ba", "ab"]]
    assert [names(m, piece) for piece in loose.routes] == routes


def test_a_lone_first_fix_before_a_run_off_the_map_is_left_out_not_a_piece() -> None:
    # the first fix lies 28 m south of de (within 5 σ); the track then runs 220 m east along an
    # unmapped lane 50 m from both roads (off the map: the route is cut) and drives along ab.
    # The cut leaves the first fix a piece of its own, which makes no route: it is left out
    m = parse_ascii_map(CAR_PARK_MAP, scale=10)
    lane = [at(m, "a", x, 50) for x in (30, 74, 118, 162, 206, 250)]
    drive = [at(m, "a", x, 1) for x in range(260, 400, 10)]
    track = track_from_xy(m, [at(m, "d", 20, -28), *lane, *drive])
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab"]] and r.splits == []
    assert [p.status for p in r.points][:7] == [PointStatus.UNMATCHED] * 7
    # without the leave-out rules (``outlier_lookahead`` 0) it is a piece alone
    r = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(outlier_lookahead=0))
    assert r.splits == [7] and [names(m, piece) for piece in r.routes] == [["de"], ["ab"]]


def test_a_last_fix_in_a_car_park_minutes_later_is_left_out_not_driven_to() -> None:
    # the track drives east along ab, crosses an unmapped lane (fixes 50 m from both roads)
    # and its last fix, five minutes later, lies in a car park 28 m south of de. The time
    # allows the 500 m round by b and e, but visiting the fix would cost its emission (3.5 σ)
    # plus that detour (9 β): more than ``leave_out_cost``, so the route ends on ab. The same
    # for a first fix minutes before the drive.
    m = parse_ascii_map(CAR_PARK_MAP, scale=10)
    drive = [at(m, "a", x, 1) for x in range(25, 225, 25)]
    n = len(drive)

    def track(xy: list[tuple[float, float]], t: list[float]) -> Track:
        ll = np.array([m.lonlat(x, y) for x, y in xy])
        return Track("t", np.asarray(t, dtype=np.float64), ll[:, 1], ll[:, 0])

    park_last = [at(m, "d", 215, -50), at(m, "d", 220, -50), at(m, "d", 225, -28)]
    end = track(drive + park_last, [5.0 * k for k in range(n)] + [5 * n + 5, 5 * n + 15, 5 * n + 300])
    park_first = [at(m, "d", 15, -28), at(m, "d", 20, -50), at(m, "d", 25, -50)]
    start = track(park_first + drive, [0, 285, 295] + [300 + 5 * k for k in range(n)])
    for trk, out in ((end, slice(n, None)), (start, slice(0, 3))):
        r = BatchMatcher(m.graph).match(trk)
        assert [names(m, piece) for piece in r.routes] == [["ab"]]
        assert set(p.status for p in r.points[out]) == {PointStatus.UNMATCHED}
        assert r.length_m == pytest.approx(175, abs=2)
        greedy = BatchMatcher(m.graph).match(trk, DEFAULT_CONFIG.replace(outlier_lookahead=0))
        assert greedy.length_m > 600  # round by b and e


def test_impossible_step_splits_the_match() -> None:
    # a peer's case: b and c are 60 m apart but 260 m of road round the block; a detour of
    # 200 m in 1 s is impossible: the match splits rather than drive it
    m = parse_ascii_map(
        """
        a-b----------x
                     |
                     |
        d-c----------y
        """,
        scale=10,
    )
    pts = [at(m, "a", 3, 1), at(m, "a", 17, 1), at(m, "c", 3, -1), at(m, "c", -13, -1)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=1.0))
    assert r.splits == [2]
    assert [names(m, piece) for piece in r.routes] == [["ab"], ["yc", "cd"]]
    # at 10 s a step the same road is plausible: one piece round the block
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=10.0))
    assert r.splits == [] and [names(m, piece) for piece in r.routes] == [["ab", "bx", "xy", "yc", "cd"]]


def test_fixes_too_fast_for_a_car_along_a_straight_road_are_one_match() -> None:
    # a peer's case: fixes 100 m apart 1 s apart, one of them 200 m off the road. Too fast
    # for a car, but the road between them is the straight line: it is their timestamps that
    # are wrong, not the route. One match; the fix far off the road is left out.
    m = parse_ascii_map("a----------b----------c----------d", scale=10)
    pts = [at(m, "a", 2, 1), at(m, "b", 0, -1), at(m, "c", 0, -200), at(m, "d", -2, 1)]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=1.0))
    assert r.splits == []
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc", "cd"]]
    # so is b: visiting it makes two steps too fast for a car (each paying the speed penalty)
    # instead of one, which costs clearly more than leaving it out (``leave_out_cost``)
    assert [p.status for p in r.points] == ["matched", "unmatched", "unmatched", "matched"]
    # 2 s apart the steps are still too fast, but visiting b costs less than leaving it out
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=2.0))
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc", "cd"]]
    assert [p.status for p in r.points] == ["matched", "matched", "unmatched", "matched"]


def test_the_route_begins_on_the_road_driven_not_on_one_ending_at_the_first_fix() -> None:
    # a peer's case: the first fix is on node e, where the one-way a->e ends and e->f begins;
    # the route starts on ef (no metre of ae is driven) and the fix is placed on ef
    m = parse_ascii_map(
        """
        a>>>>>>>b>>>>>>>c
        v       ^       v
        v       ^       v
        e>>>>>>>f>>>>>>>g
        """,
        scale=5,
    )
    pts = [at(m, "e"), at(m, "f"), at(m, "b"), at(m, "c")]
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=2.0))
    assert [names(m, piece) for piece in r.routes] == [["ef", "fb", "bc"]]
    assert names(m, [r.points[0].edge]) == ["ef"] and r.points[0].offset == pytest.approx(0.0, abs=1e-6)
    assert r.length_m == pytest.approx(40 + 30 + 40, abs=0.5)
    # and it ends on the road driven: the last fix is on node b, where bc begins
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts[:3], dt=2.0))
    assert [names(m, piece) for piece in r.routes] == [["ef", "fb"]]
    assert names(m, [r.points[-1].edge]) == ["fb"]


def test_a_fix_that_jumps_back_is_dropped_not_looped_round() -> None:
    # a peer's case: 100 m back after 2 s, then on: no U-turn loop, the jump is unmatched
    m = parse_ascii_map("a----------b----------c----------d", scale=10)
    xs, ts = [5, 105, 5, 215, 325], [0.0, 10.0, 12.0, 20.0, 30.0]
    ll = np.array([m.lonlat(*at(m, "a", x, 1)) for x in xs])
    track = Track("t", np.array(ts), ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc", "cd"]]
    assert r.length_m == pytest.approx(320, abs=2)
    assert [p.status for p in r.points] == ["matched", "matched", "unmatched", "matched", "matched"]
    # driving out and back slowly (a dead end at 30 s) is a real turn, kept
    back = np.array([m.lonlat(*at(m, "a", x, 1)) for x in (2, 220, 150)])
    r = BatchMatcher(m.graph).match(Track("s", np.array([0.0, 30.0, 60.0]), back[:, 1], back[:, 0]))
    assert [p.status for p in r.points] == ["matched"] * 3
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc", "cb"]]


def test_an_untimed_fix_that_jumps_back_is_dropped_not_looped_round() -> None:
    # the same without timestamps (as OSRM's requests may come): a fix 16 m back amid fixes
    # 16 m apart is left out as a visited stray, not driven to by turning round twice (or at
    # the road's dead end); no time is no gap between the fixes either side of it
    m = parse_ascii_map(
        "a-----------------------------------------------------------------------------d", scale=2
    )
    xs = [0, 16, 32, 48, 32, 64, 80, 96]
    ll = np.array([m.lonlat(*at(m, "a", x)) for x in xs])
    r = BatchMatcher(m.graph).match(Track("t", np.full(len(xs), np.nan), ll[:, 1], ll[:, 0]))
    assert [names(m, piece) for piece in r.routes] == [["ad"]]
    assert r.length_m == pytest.approx(96, abs=0.5)
    assert [p.status for p in r.points] == ["matched"] * 4 + ["unmatched"] + ["matched"] * 3


def test_a_multipath_burst_of_fixes_is_dropped_as_one_jump() -> None:
    # 1 Hz along a-b-c at 10 m/s; for 3 s the fixes jump 79 m onto d-e-f (multipath) and back
    #
    #   a----x----x----x----x----b----x----x----c
    #   |                        |              |
    #   |                        |              |
    #   |                        |              |
    #   d-------------------x-x-xe--------------f
    m = parse_ascii_map(
        """
        a---------b---------c
        |         |         |
        |         |         |
        |         |         |
        d---------e---------f
        """,
        scale=10,
    )
    pts = [at(m, "a", x, -78 if 8 <= k <= 10 else 1) for k, x in enumerate(range(5, 200, 10))]
    track = track_from_xy(m, pts, dt=1.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert [k for k, p in enumerate(r.points) if p.status == PointStatus.UNMATCHED] == [8, 9, 10]
    # counterfactual: single-fix jumps only, and the route goes down be and back for the burst
    single = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(spike_max_time=0.0))
    assert [names(m, piece) for piece in single.routes] == [["ab", "be", "eb", "bc"]]
    # a real drive down b-e and back at 10 m/s turns round in far more than a few seconds: kept
    drive = (
        [at(m, "a", x, 1) for x in range(5, 100, 10)]
        + [at(m, "b", 1, -y) for y in range(5, 80, 10)]
        + [at(m, "b", -1, -y) for y in range(75, 0, -10)]
        + [at(m, "b", x, 1) for x in range(5, 100, 10)]
    )
    r = BatchMatcher(m.graph).match(track_from_xy(m, drive, dt=1.0))
    assert [names(m, piece) for piece in r.routes] == [["ab", "be", "eb", "bc"]]
    assert all(p.status != PointStatus.UNMATCHED for p in r.points)


def test_a_stray_fix_by_a_side_road_is_dropped_not_the_good_fix_after_it() -> None:
    # fixes 10 s apart: one strays next to the side road hd, 55 m from bc; the next fix (on bc)
    # cannot be reached from there (back along hd and hb is too far for the step), the one
    # after it only by turning round on hd. Leaving out the stray fix explains both; leaving
    # out the good fix after it makes a trip up the side road.
    m = parse_ascii_map(
        """
                    h--------------------d
                    |
                    |
                    |
        a-----------b---------------------------------------------c
        """,
        scale=10,
    )
    stray = at(m, "b", 180, 55)
    pts = [at(m, "a", 10, 2), at(m, "a", 100, 2), stray, at(m, "b", 185, -2), at(m, "b", 400, 2)]
    track = track_from_xy(m, pts, dt=10.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert [p.status for p in r.points] == ["matched", "matched", "unmatched", "matched", "matched"]
    # always leaving out the unreachable fix instead: the good fix goes, the trip up hd comes
    greedy = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(outlier_lookahead=0))
    assert [p.status for p in greedy.points][2:4] == ["matched", "unmatched"]
    assert "hd" in names(m, greedy.routes[0])
    # 30 s apart the car could have driven up hd and back (``route_speed``: 25 m/s), but that
    # trip costs clearly more than leaving the stray fix out (``leave_out_cost``)
    sparse = track_from_xy(m, pts, dt=30.0)
    r = BatchMatcher(m.graph).match(sparse)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert [p.status for p in r.points][2] == "unmatched"
    # 60 s apart the trip costs less (β grows with the time between fixes): every fix is
    # explained, the trip turning at the dead end d
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=60.0))
    assert [names(m, piece) for piece in r.routes] == [["ab", "bh", "hd", "dh", "hb", "bc"]]
    assert all(p.status == PointStatus.MATCHED for p in r.points)
    # a route bounded by the distance alone cannot make the trip: the stray fix is left out
    r = BatchMatcher(m.graph).match(track_from_xy(m, pts, dt=60.0), DEFAULT_CONFIG.replace(route_speed=0.0))
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert [p.status for p in r.points][2] == "unmatched"


def test_a_stray_fix_followed_by_another_is_dropped_not_the_good_fixes_after_them() -> None:
    # fixes 15 s apart along ab and bc; two in a row stray (2 and 3 below, 20 m from the dead
    # ends hd and ge). 2 is reachable from 1 (up hd), but from 2 the car would have to drive
    # back along hd to reach 3, 4 or 5 in their time; 3 is reachable from 1, 4 not from 3.
    # Leaving out 3, 4 and 5 keeps the trip up hd; leaving out 2 and 3 explains the rest.
    #
    #               h-------------------------------------------------d
    #               |                             2
    #   a-----------b--------------------------------------4-----------5-----------6-----------7--c
    #    0          |  1                               3
    #               g-------------------------------------------------e
    m = parse_ascii_map(
        """
                h-------------------------------------------------d
                |
                |
                |
    a-----------b-----------------------------------------------------------------------------c
                |
                |
                |
                g-------------------------------------------------e
        """,
        scale=10,
    )
    pts = [
        at(m, "a", 10, 2), at(m, "b", 30, -2), at(m, "b", 300, 100), at(m, "b", 350, -100),
        at(m, "b", 390, 2), at(m, "b", 510, -2), at(m, "b", 630, 2), at(m, "b", 750, -2),
    ]  # fmt: skip
    track = track_from_xy(m, pts, dt=15.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert [p.status for p in r.points] == ["matched"] * 2 + ["unmatched"] * 2 + ["matched"] * 4
    # without trying the fix before a run left out, with the detours the time allows (a limit
    # of 400 β at 20 σ), and no
    # cut where the fixes left out travel ``off_map_cut``: the trip up hd, three good fixes lost
    # (the first fix's direction kept over its 140 m leg: else the way is made longer by
    # turning round at the dead end a, to fit the 140 m)
    loose = DEFAULT_CONFIG.replace(
        outlier_lookahead=0, off_map_sigmas=20.0, off_map_cut=0, motion_end_leg_max=0
    )
    greedy = BatchMatcher(m.graph).match(track, loose)
    assert names(m, greedy.routes[0]) == ["ab", "bh", "hd", "dh", "hb", "bc"]
    assert [p.status for p in greedy.points][2:6] == ["matched", "unmatched", "unmatched", "unmatched"]
    # the way back down hd to 4 is a detour of 630 m over 100 m: beyond ``off_map_sigmas``² β,
    # 4 is out of reach from 2 however the fixes are weighed: 2 is left out with 3
    greedy = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(outlier_lookahead=0))
    assert [names(m, piece) for piece in greedy.routes] == [["ab", "bc"]]


def test_far_apart_fixes_follow_the_near_road_though_another_is_shorter() -> None:
    # a straight road b-c and a parallel one b-e-f-c 40 m south of it, 80 m longer; one fix
    # every 30 s (about 480 m apart), the middle one 5 m from the southern road and 35 m from
    # the straight one. Over so long a step a route's length tells less than the fix does: β
    # grows with the distance travelled (``beta_per_m``), and the southern road is kept
    m = parse_ascii_map(
        """
        a-b----------------------------------------------------------------------------------------------c-d
          |                                                                                              |
          e----------------------------------------------------------------------------------------------f
        """,
        scale=10,
    )
    pts = [at(m, "a", 5, 1), at(m, "e", 480, 5), at(m, "d", -5, -1)]
    track = track_from_xy(m, pts, dt=30.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "be", "ef", "fc", "cd"]]
    # with a fixed β (growing neither with the distance nor with the time) the 80 m detour
    # costs more than the fix's 35 m off the straight road
    fixed = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(beta_per_m=0.0, beta_per_s=0.0))
    assert [names(m, piece) for piece in fixed.routes] == [["ab", "bc", "cd"]]


def test_the_longer_the_time_between_fixes_the_further_round_the_route_may_go() -> None:
    # a straight road b-c and a loop b-e-f-c 40 m north of it, 80 m longer; the middle fix lies
    # 27 m from bc and 13 m from ef. Seconds apart, the loop's length outweighs the fix; with
    # 20 s or more between the fixes the car may well have driven round it (``beta_per_s``)
    m = parse_ascii_map(
        """
                    e----------f
                    |          |
        a-----------b----------c-----------d
        """,
        scale=10,
    )
    mid = at(m, "b", 50, 27)
    pts = [at(m, "b", -30, 1), at(m, "b", -15, -1), mid, at(m, "c", 15, 1), at(m, "c", 30, -1)]
    loop, straight = [["ab", "be", "ef", "fc", "cd"]], [["ab", "bc", "cd"]]

    def routes(
        ts: list[float], xy: list[tuple[float, float]], cfg: MatchConfig = DEFAULT_CONFIG
    ) -> list[list[str]]:
        ll = np.array([m.lonlat(x, y) for x, y in xy])
        r = BatchMatcher(m.graph).match(Track("t", np.array(ts, dtype=float), ll[:, 1], ll[:, 0]), cfg)
        return [names(m, piece) for piece in r.routes]

    assert routes([0, 2, 4, 6, 8], pts) == straight
    assert routes([0, 30, 60, 90, 120], pts) == loop
    assert routes([0, 30, 60, 90, 120], pts, DEFAULT_CONFIG.replace(beta_per_s=0.0)) == straight
    # the same fixes 36 s apart after a logger gap: the loop; but after a stop of 30 s at each
    # of the first two (their fixes interpolated), the car drove only seconds: straight on
    assert routes([0, 2, 38, 74, 76], pts) == loop

    def jitter(p: tuple[float, float], i: int) -> tuple[float, float]:
        return p[0] + i % 3 - 1, p[1] + (i % 2) * 2 - 1

    ts = [0, 2, *range(3, 33), 38, *range(39, 69), 74, 76]
    stand_b = [jitter(pts[1], i) for i in range(30)]
    stand_mid = [jitter(mid, i) for i in range(30)]
    xy = [*pts[:2], *stand_b, mid, *stand_mid, *pts[3:]]
    assert routes(ts, xy) == straight


def test_of_two_routes_of_one_length_the_one_with_fewer_turns_wins() -> None:
    # from ab to gh, 10 s a fix: round the corner c (two right angles) or down the steps
    # d-e-f (four), both 200 m. The middle fix lies about as near to both (23 m from bc, 22 m
    # from e): the route that turns less wins (``turn_cost``); without it, the nearer one
    m = parse_ascii_map(
        """
        a-----b-----------c
              |           |
              d-----e     |
                    |     |
                    f-----g-----h
        """,
        scale=10,
    )
    pts = [at(m, "a", 10, 1), at(m, "a", 40, -1), at(m, "e", 14, 17), at(m, "g", 30, 1), at(m, "h", 0, -1)]
    track = track_from_xy(m, pts, dt=10.0)
    corner, steps = [["ab", "bc", "cg", "gh"]], [["ab", "bd", "de", "ef", "fg", "gh"]]
    assert [names(m, piece) for piece in BatchMatcher(m.graph).match(track).routes] == corner
    flat = DEFAULT_CONFIG.replace(turn_cost=0)
    assert [names(m, piece) for piece in BatchMatcher(m.graph).match(track, flat).routes] == steps
    # the same with a route table built with the turn costs, and one without them (not used)
    assert Ubodt.build(m.graph, 500.0).turn_cost == DEFAULT_CONFIG.batch.route.turn_cost  # the default's
    for cost in (DEFAULT_CONFIG.batch.route.turn_cost, 0.0):
        table = Ubodt.build(m.graph, 500.0, turn_cost=cost)
        r = BatchMatcher(m.graph, ubodt=table).match(track)
        assert [names(m, piece) for piece in r.routes] == corner


def test_sparse_fixes_either_side_of_a_dual_carriageway_drive_round_its_turning_point() -> None:
    # fixes two minutes apart: east on the one-way a>b, then back west on d<c, 80 m south; the
    # only way round is the turning point b-c, 1.5 km of road, far beyond three times the 80 m
    # between the fixes. Two minutes at 25 m/s (``route_speed``) allow it
    m = parse_ascii_map(
        """
        a>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>b
                                                                                    |
                                                                                    |
                                                                                    |
        d<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<c
        """,
        scale=10,
    )
    pts = [at(m, "a", 20, 2), at(m, "a", 60, -1), at(m, "d", 60, 2), at(m, "d", 20, -1)]
    ll = np.array([m.lonlat(x, y) for x, y in pts])
    track = Track("t", np.array([0.0, 4.0, 124.0, 128.0]), ll[:, 1], ll[:, 0])
    r = BatchMatcher(m.graph).match(track)
    assert r.splits == [] and [names(m, piece) for piece in r.routes] == [["ab", "bc", "cd"]]
    assert all(p.status == PointStatus.MATCHED for p in r.points)
    # bounded by the distance alone the back leg is out of reach: a split
    by_distance = DEFAULT_CONFIG.replace(route_speed=0.0)
    assert BatchMatcher(m.graph).match(track, by_distance).splits == [2]


def test_first_fix_near_a_crossing_takes_the_road_of_the_direction_of_travel() -> None:
    # the first fix lies 6 m from the cross road cb and 9 m from ab, the road the car drives
    # on (east, straight through b): the direction of travel from the fixes (no heading
    # column) puts it on ab, so the first road is not lost
    m = parse_ascii_map(
        """
                c
                |
        a-------b-------d
                |
                e
        """,
        scale=10,
    )
    pts = [at(m, "b", -6, 9), at(m, "b", 20, 1), at(m, "b", 40, -1), at(m, "b", 60, 1), at(m, "b", 75, 0)]
    track = track_from_xy(m, pts, dt=2.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bd"]]
    # without the direction of travel and the cost of turning at b, the nearer road wins and
    # ab is missing
    off = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(straight_max_deg=0, turn_cost=0))
    assert [names(m, piece) for piece in off.routes] == [["cb", "bd"]]
    # either alone puts the first fix on ab
    for cfg in (DEFAULT_CONFIG.replace(straight_max_deg=0), DEFAULT_CONFIG.replace(turn_cost=0)):
        assert [names(m, piece) for piece in BatchMatcher(m.graph).match(track, cfg).routes] == [["ab", "bd"]]


def test_a_sparse_first_fix_by_a_junction_stays_on_its_road_though_the_car_turns_soon_after() -> None:
    # one fix every 30 s: the first 15 m before the junction b on ab (1 m off it), then 300 and
    # 600 m down bc. Both legs point south and are straight, but the car turned at b soon
    # after the first fix: the direction they give is not the first fix's, and would put it on
    # bc across the corner (15 m off), losing ab. Over a leg of 300 m the first fix takes no
    # direction (``motion_end_leg_max``); the same for the last fix, driven the other way.
    # Dense fixes keep it (legs of a few metres): the test above
    #
    #   a-----------------------0-b
    #                             |
    #                             1
    #                             |
    #                             2
    #                             c
    m = parse_ascii_map(
        """
        a---------b
                  |
                  |
                  |
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
        scale=30,
    )
    pts = [at(m, "b", -15, 1), at(m, "b", 2, -300), at(m, "b", -2, -600)]
    ahead = track_from_xy(m, pts, dt=30.0)
    back = track_from_xy(m, pts[::-1], dt=30.0)
    unlimited = DEFAULT_CONFIG.replace(motion_end_leg_max=0)
    assert [names(m, p) for p in BatchMatcher(m.graph).match(ahead).routes] == [["ab", "bc"]]
    assert [names(m, p) for p in BatchMatcher(m.graph).match(back).routes] == [["cb", "ba"]]
    assert [names(m, p) for p in BatchMatcher(m.graph).match(ahead, unlimited).routes] == [["bc"]]
    assert [names(m, p) for p in BatchMatcher(m.graph).match(back, unlimited).routes] == [["cb"]]


def test_a_noisy_receiver_is_matched_with_its_own_sigma_not_cut_off_the_map() -> None:
    # one road; a worse receiver's fixes lie 12-27 m either side of it, 20 m apart:
    #
    #      x       x               x       x
    #   a-----------------b-----------------c
    #          x       x       x       x
    #
    # with the configured σ of 5 m most lie beyond the off-map limit (5 σ); the track's own σ
    # (1.4826 times the median distance to the road: about 30 m) keeps them all on the road,
    # and as fixes close together share their error they are thinned out (interpolated)
    m = parse_ascii_map("a-------------------b-------------------c", scale=10)
    side = [14, -22, 26, -12, 21, -27, 17, -24]
    pts = [at(m, "a", x, side[k % len(side)]) for k, x in enumerate(range(15, 390, 20))]
    track = track_from_xy(m, pts, dt=2.0)
    r = BatchMatcher(m.graph).match(track)
    assert [names(m, piece) for piece in r.routes] == [["ab", "bc"]]
    assert r.splits == []
    status = [p.status for p in r.points]
    assert PointStatus.UNMATCHED not in status
    assert 0 < status.count(PointStatus.INTERPOLATED) < len(pts) - 2
    # without the thinning every fix is matched, on the same route
    unthinned = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(thin_sigmas=0.0))
    assert [names(m, piece) for piece in unthinned.routes] == [["ab", "bc"]]
    assert all(p.status == PointStatus.MATCHED for p in unthinned.points)
    # counterfactual: the configured σ alone leaves most fixes off the map
    fixed = BatchMatcher(m.graph).match(track, DEFAULT_CONFIG.replace(track_sigma_max=0.0))
    assert sum(p.status == PointStatus.UNMATCHED for p in fixed.points) > len(pts) // 3


def test_a_fix_further_than_off_map_sigmas_from_every_road_is_off_the_map() -> None:
    # five fixes: off, near a road (35 m), off, on, on (σ 8 m: 40 m is off the map)
    from mapmatch.arena import Arena
    from mapmatch.batch.arrays import CandidateArrays
    from mapmatch.batch.lattice import PruneRule, prune

    dist = np.array([45.0, 35.0, 50.0, 3.0, 4.0])
    empty = np.zeros(0)
    c = CandidateArrays(
        point=np.arange(5), edge=np.zeros(5, dtype=np.int64), offset=np.zeros(5), xy=np.zeros((5, 2)),
        dist=dist, emis=-0.5 * (dist / 8.0) ** 2, sigma=empty,
    )  # fmt: skip
    *_, got = prune(5, c, c.emis, PruneRule(12.5, 100.0, 8.0, 5.0), Arena.new())
    assert got.tolist() == [False, True, False, True, True]


def test_an_answer_read_late_equals_one_read_at_once_and_pickles_as_a_track_match() -> None:
    """The answer's fields come from the kernel's typed result on first access: reading them in
    any order, setting one first, or pickling gives what the result's own fields give."""
    import pickle

    from mapmatch.batch.results import _LAZY, PackedMatch

    m = parse_ascii_map(
        """
        a-----b-----c
              |
              d-----e
        """,
        scale=20,
    )
    pts = [at(m, "a", 10, 3), at(m, "b", 12, 2), at(m, "b", -3, -30), at(m, "d", 40, 4), at(m, "e", -5, 3)]
    matcher = BatchMatcher(m.graph)
    track = track_from_xy(m, pts)
    first = matcher.match(track, lonlat=False)
    assert isinstance(first, PackedMatch) and first._result is not None
    eager = first._result
    assert first.confidence == eager.confidence and first._result is None  # one read fills every field
    assert first.routes == eager.routes() and first.splits == eager.splits.tolist()
    assert first.length_m == eager.length and len(first.route_xy) == len(eager.pieces_xy())
    assert first.routes and first.length_m > 0
    other = matcher.match(track, lonlat=False)
    other.length_m = -1.0  # a write fills the rest first, then wins
    assert other.length_m == -1.0 and other.routes == first.routes and other.splits == first.splits
    assert other.point_arrays is not None
    batch.fill_route_lonlat(other, m.graph.crs)
    full = matcher.match(track)
    back = pickle.loads(pickle.dumps(full))
    assert type(back) is TrackMatch
    assert back.points == full.points and back.routes == full.routes
    assert back.route_lonlat == full.route_lonlat
    assert other.points == full.points and other.route_lonlat == full.route_lonlat
    assert set(_LAZY) < {f.name for f in dataclasses.fields(TrackMatch)}
