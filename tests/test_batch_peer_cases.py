"""The peers' own map-matching cases, drawn as ASCII maps: OSRM's
(``features/testbot/matching.feature``) and Valhalla's (``test/gurka/test_match.cc``,
``test/gurka/test_trace_attributes.cc``); and
FMM's example network and trips (``example/data``), built from lines as FMM's files are.

They draw nodes on a grid and list the ways through them; here the roads are drawn and the
fixes placed on the map in metres. They send these traces without timestamps, and so do the
tests (every time NaN, unknown): the fixes' order and positions alone must give their answer.
Where a peer's answer rests on a convention this project does not share, the test says so and
checks this project's answer (``docs/benchmarks/batch_ends.md``, "Peers' cases").
"""

from __future__ import annotations

import itertools
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import shapely
from ascii_helpers import at, names

from graph.ascii import ASCII_CRS, AsciiMap, parse_ascii_map
from graph.build import build_map
from graph.gis import GisOptions
from graph.projection import to_lonlat, to_xy
from mapmatch.batch import BATCH_CONFIG, BatchMatcher
from mapmatch.batch.results import route_ways
from mapmatch.config import MatchConfig
from mapmatch.types import PointStatus, Track, TrackMatch


def routes(amap: AsciiMap, r: TrackMatch) -> list[list[str]]:
    return [names(amap, list(piece)) for piece in r.routes]


def untimed(amap: AsciiMap, xy: list[tuple[float, float]], config: MatchConfig | None = None) -> TrackMatch:
    """The match of fixes at ``xy`` with no timestamps (every time NaN), as OSRM sends them."""
    ll = np.array([amap.lonlat(x, y) for x, y in xy])
    return BatchMatcher(amap.graph, config=config).match(
        Track("t", np.full(len(xy), np.nan), ll[:, 1], ll[:, 0])
    )


ONE_WAYS_SIDE_BY_SIDE = """
a>>>>>>>b>>>>>>>c>>>>>>>d

e<<<<<<<f<<<<<<<g<<<<<<<h
"""
"""Two one-way roads 10 m apart (scale 2.5: 20 m between letters), opposite ways."""


@pytest.mark.parametrize(("trace", "route"), [("dcba", ["hg", "gf", "fe"]), ("efgh", ["ab", "bc", "cd"])])
def test_a_trace_against_a_one_way_takes_the_one_way_beside_it(trace: str, route: list[str]) -> None:
    # "Matching with oneway streets": the fixes lie on the nodes of the one-way the car cannot
    # drive that way; the route is the one-way beside it, 10 m off
    m = parse_ascii_map(ONE_WAYS_SIDE_BY_SIDE, scale=2.5)
    r = untimed(m, [at(m, c) for c in trace])
    assert routes(m, r) == [route]
    assert all(p.status == PointStatus.MATCHED for p in r.points)


def test_a_fix_off_the_start_of_a_one_way_loop_stays_on_the_through_road() -> None:
    # "Map matching with small distortion": the second fix lies 10 m from b, on the one-way
    # b->f->h->k->e; driving it and back from e is a 160 m loop for a fix the through road
    # explains at 10 m
    m = parse_ascii_map(
        """
        a-------b-------c-------d-------e
                v                       ^
                f                       ^
                v                       ^
                v                       ^
                v                       ^
                v                       ^
                v                       ^
                v                       ^
                v                       ^
                h>>>>>>>>>>>>>>>>>>>>>>>k
        """,
        scale=2.5,
    )
    r = untimed(m, [at(m, c) for c in "afcde"])
    assert routes(m, r) == [["ab", "bc", "cd", "de"]]


def test_a_one_way_block_is_driven_round_the_way_it_allows() -> None:
    # OSRM's regression test for its issue 3037: one-ways round two blocks; e f b c is driven
    # e->f, up f->b, b->c
    m = parse_ascii_map(
        """
        a>>>>>>>b>>>>>>>c
        v       ^       v
        v       ^       v
        v       ^       v
        e>>>>>>>f>>>>>>>g
        """,
        scale=5,
    )
    r = untimed(m, [at(m, c) for c in "efbc"])
    assert routes(m, r) == [["ef", "fb", "bc"]]


CROSSING = """
      e
      |
      |
a-----b-----c
      |
      |
      d
"""


@pytest.mark.parametrize(
    ("trace", "route"),
    [
        ("abc", ["ab", "bc"]),
        ("abd", ["ab", "bd"]),
        ("abe", ["ab", "be"]),
        ("ahd", ["ab", "bd"]),
        ("ahe", ["ab", "be"]),
    ],
)
def test_a_fix_just_before_a_crossing_turns_there_without_a_u_turn(trace: str, route: list[str]) -> None:
    # OSRM's regression test for its issue 4919 ("non-uturn maneuver preferred over uturn"):
    # h lies 10 m before the crossing b on ab; from h the route turns at b, never turning
    # round on ab
    m = parse_ascii_map(CROSSING, scale=10)
    r = untimed(m, [at(m, "b", -10) if c == "h" else at(m, c) for c in trace])
    assert routes(m, r) == [route]
    assert r.length_m == pytest.approx(120, abs=1)


@pytest.mark.parametrize("reverse", [False, True])
def test_fixes_amid_edges_are_placed_where_they_lie_both_ways(reverse: bool) -> None:
    # "add source phantoms properly": fixes inside ab, bc and de, then inside one edge, driven
    # either way: the route runs from the first fix's place to the last's, none snapped to a node
    m = parse_ascii_map("a-----b-----c-d-----e", scale=10)
    xy = [at(m, "a", 30), at(m, "b", 10), at(m, "d", 10)]
    r = untimed(m, xy[::-1] if reverse else xy)
    assert routes(m, r) == [["ed", "dc", "cb", "ba"] if reverse else ["ab", "bc", "cd", "de"]]
    assert r.length_m == pytest.approx(120, abs=0.5)
    m = parse_ascii_map("a--------------b", scale=10)
    xs = [40.0, 50.0, 60.0, 70.0]
    r = untimed(m, [at(m, "a", x) for x in (xs[::-1] if reverse else xs)])
    assert routes(m, r) == [["ba"] if reverse else ["ab"]]
    assert r.length_m == pytest.approx(30, abs=0.5)
    assert [round(p.offset) for p in r.points] == ([150 - x for x in xs[::-1]] if reverse else xs)


def test_fixes_along_two_roads_and_round_a_corner_give_the_route_between_them() -> None:
    # Valhalla's BasicMatch: the first fix 10 m off ab, three on ab and bc, the last 10 m off
    # cd: the route runs a -> b -> c -> d from the first fix's place to the last's, 100 m
    m = parse_ascii_map(
        """
        a----b----c
                  |
                  |
                  d
        """,
        scale=10,
    )
    r = untimed(m, [at(m, "a", 20, 10), at(m, "a", 40), at(m, "a", 70), at(m, "a", 90), at(m, "c", 10, -20)])
    assert routes(m, r) == [["ab", "bc", "cd"]]
    assert r.length_m == pytest.approx(100, abs=0.5)


def test_a_fix_back_along_the_road_is_a_u_turn_where_u_turns_cost_nothing() -> None:
    # Valhalla's UturnMatch: fixes 30, 60 and 30 m along a 90 m road, with its U-turn penalty
    # turned off (``penalize_immediate_uturn: false``; here ``uturn_penalty`` 0): the route
    # turns round at the second fix, 60 m, and ends facing back, not turning again at the end
    m = parse_ascii_map("a--------b", scale=10)
    r = untimed(m, [at(m, "a", x) for x in (30, 60, 30)], BATCH_CONFIG.replace(uturn_penalty=0.0))
    assert routes(m, r) == [["ab", "ba"]]
    assert r.length_m == pytest.approx(60, abs=0.5)
    assert [names(m, [p.edge]) for p in r.points] == [["ab"], ["ab"], ["ba"]]
    assert all(p.status == PointStatus.MATCHED for p in r.points)
    # its later form: 1, 2, 1, 2, turning round at each fix ("via"), 90 m
    r = untimed(m, [at(m, "a", x) for x in (30, 60, 30, 60)], BATCH_CONFIG.replace(uturn_penalty=0.0))
    assert routes(m, r) == [["ab", "ba", "ab"]]
    assert r.length_m == pytest.approx(90, abs=0.5)


def _ends(amap: AsciiMap, r: TrackMatch, node: str) -> list[tuple[float, float]]:
    """The route's first and last vertex in metres east and north of intersection ``node``."""
    (lon0, lat0), (lon1, lat1) = r.route_lonlat[0][0], r.route_lonlat[-1][-1]
    xy = to_xy(amap.graph.crs, np.array([lon0, lon1]), np.array([lat0, lat1])) - amap.xy(node)
    return [(float(x), float(y)) for x, y in xy]


def test_fixes_past_a_corner_keep_the_whole_route_to_the_last_fix() -> None:
    # OSRM's "waypoints trimming too much geometry" (first case): fixes beside a road down to
    # the corner b, one 10 m past it, then along bc and 10 m past c; the route is the whole
    # of ab and bc, 135 m, from a (the first fix's place) to c (the last's)
    m = parse_ascii_map(
        """
        a
        |
        |
        |
        |
        |
        b--------------c
        """,
        scale=5,
    )
    r = untimed(
        m, [at(m, "a", 5), at(m, "a", 5, -50), at(m, "b", 0, -10), at(m, "b", 25, 10), at(m, "c", 0, -10)]
    )
    assert routes(m, r) == [["ab", "bc"]]
    assert r.length_m == pytest.approx(135, abs=0.5)
    assert _ends(m, r, "a") == [
        (pytest.approx(0, abs=0.5), pytest.approx(0, abs=0.5)),
        (pytest.approx(75, abs=0.5), pytest.approx(-60, abs=0.5)),
    ]


def test_a_route_round_a_bend_ends_where_the_last_fix_lies_along_the_road() -> None:
    # OSRM's "waypoints trimming too much geometry" (second case): the first fix 5 m beside h,
    # the last 10 m west of f, beside the diagonal cf: the route is all of hc and cf up to the
    # last fix's place, (28, -56) m from c (the diagonal is 30 m east and 60 m down)
    m = parse_ascii_map(
        """
        h
        |
        |
        |
        c
         \\
          \\
           \\
            \\
             \\
              f
        """,
        scale=5,
    )
    r = untimed(m, [at(m, "h", -5), at(m, "c", 0, -10), at(m, "c", 15, -20), at(m, "f", -10)])
    assert routes(m, r) == [["hc", "cf"]]
    along = (20 * 30 + 60 * 60) / 4500**0.5  # the last fix's place along cf (62.6 m)
    assert r.length_m == pytest.approx(40 + along, abs=0.5)
    assert _ends(m, r, "h") == [
        (pytest.approx(0, abs=0.5), pytest.approx(0, abs=0.5)),
        (pytest.approx(28, abs=0.5), pytest.approx(-40 - 56, abs=0.5)),
    ]


def test_an_untimed_fix_a_little_back_along_the_road_is_standing_not_a_u_turn() -> None:
    # OSRM's "trace tidying, dirty case by dist": nodes a q b c d 8 m apart, fixes at a b c b d
    # with no timestamps; the fix back at b (8 m, within the noise) is no U-turn: the route
    # runs a to d once, every fix on it
    m = parse_ascii_map("a---------------d", scale=2)
    r = untimed(m, [at(m, "a", x) for x in (0, 16, 24, 16, 32)])
    assert routes(m, r) == [["ad"]]
    assert r.length_m == pytest.approx(32, abs=0.5)
    assert [p.status for p in r.points] == [PointStatus.MATCHED] * 5


# FMM's example (``example/data``: ``edges.shp``, ``trips.csv``, and the paths of ``mr.txt``):
# a network of directed arcs one unit apart, drawn here at 100 m a unit; the arcs' ids are FMM's
FMM_NODES = {1: (2, 1), 2: (2, 0), 3: (3, 1), 4: (4, 1), 5: (2, 2), 6: (3, 2), 7: (0, 2), 8: (1, 2)}
FMM_NODES |= {9: (4, 2), 10: (2, 3), 11: (3, 3), 12: (4, 3), 13: (2, 4)}
FMM_NODES |= {14: (0.5, 3.5), 15: (2, 3.5), 16: (3.5, 4), 17: (3.5, 2.3)}  # two roads apart, one over 11->12
FMM_ARCS = [
    (1, 2),
    (2, 1),
    (3, 1),
    (4, 3),
    (1, 5),
    (5, 1),
    (3, 6),
    (7, 8),
    (8, 7),
    (5, 8),
    (8, 5),
    (6, 5),
    (5, 6),
]
FMM_ARCS += [
    (6, 9),
    (9, 6),
    (10, 5),
    (5, 10),
    (6, 11),
    (10, 11),
    (11, 12),
    (13, 10),
    (10, 13),
    (9, 12),
    (12, 9),
]
FMM_ARCS += [(9, 4), (4, 9), (14, 15), (15, 14), (16, 17), (17, 16)]  # arc i + 1 is FMM's edge id i + 1
FMM_TRIPS = {  # each trip's fixes in units, and the path FMM gives it
    (2, 5, 13, 14, 23): [(1.659, 0.251), (1.655, 0.702), (2.493, 1.766), (3.549, 1.888), (4.131, 2.458)],
    (25, 4, 3, 5, 17, 19): [
        (4.150, 1.604),
        (3.470, 0.923),
        (2.406, 0.923),
        (2.145, 1.532),
        (2.086, 2.576),
        (2.497, 2.988),
    ],
    (8, 11, 13, 18, 20, 24): [
        (0.201, 2.141),
        (1.443, 2.149),
        (3.064, 2.161),
        (3.064, 2.710),
        (3.709, 2.979),
        (4.116, 2.623),
    ],
}


FMM_ORIGIN, FMM_UNIT = (385_000.0, 6_672_000.0), 100.0


def _fmm_xy(x: float, y: float) -> tuple[float, float]:
    return FMM_ORIGIN[0] + x * FMM_UNIT, FMM_ORIGIN[1] + y * FMM_UNIT


def _fmm_trip(fixes: list[tuple[float, float]]) -> Track:
    """A trip of FMM's example, untimed as its trips are."""
    xy = np.array([_fmm_xy(x, y) for x, y in fixes])
    lonlat = to_lonlat(ASCII_CRS, xy[:, 0], xy[:, 1])
    return Track("t", np.full(len(fixes), np.nan), lonlat[:, 1], lonlat[:, 0])


def test_fmm_example_trips_take_fmm_paths(tmp_path: Path) -> None:
    # every trip runs along the arcs FMM's answer lists (a node between two arcs only, as 8
    # between 7->8 and 8->5, joins them into one edge)
    arcs = gpd.GeoDataFrame(
        {
            "id": range(1, len(FMM_ARCS) + 1),
            "source": [u for u, _ in FMM_ARCS],
            "target": [v for _, v in FMM_ARCS],
        },
        geometry=[shapely.LineString([_fmm_xy(*FMM_NODES[u]), _fmm_xy(*FMM_NODES[v])]) for u, v in FMM_ARCS],
        crs=ASCII_CRS,
    )
    arcs.to_file(tmp_path / "edges.geojson")
    g = build_map(
        tmp_path / "edges.geojson",
        gis=GisOptions(directed=True, id_field="id", node_id_fields=("source", "target")),
    )
    matcher = BatchMatcher(g)
    for path, fixes in FMM_TRIPS.items():
        r = matcher.match(_fmm_trip(fixes))
        assert len(r.routes) == 1
        assert route_ways(r, g)[0] == list(path)
    # its partial-match example: the first trip with a fix far off every road, then with two
    # beside a road the grid does not reach; FMM's --partial-match breaks its path there, here
    # they are left out and the route runs on
    first = next(iter(FMM_TRIPS.values()))
    for odd in ([(5.0, 5.0)], [(5.0, 5.0), (3.7, 3.8)], [(3.4, 3.9), (3.7, 3.8)]):
        r = matcher.match(_fmm_trip(first[:3] + odd + first[3:]))
        assert len(r.routes) == 1
        assert route_ways(r, g)[0] == [2, 5, 13, 14, 23]
        assert [p.status for p in r.points[3 : 3 + len(odd)]] == [PointStatus.UNMATCHED] * len(odd)


STAR = """
o   a   c
 \\  |  /
  \\ | /
   \\|/
m---x---e
   /|\\
  / | \\
 /  |  \\
k   i   g
"""
"""Eight roads out of x (OSRM's "Turn directions" map, matched)."""


def test_two_untimed_fixes_at_the_ends_of_any_two_roads_give_the_route_through_their_crossing() -> None:
    # OSRM's "Turn directions" (its turns feature, "When I match"): one fix at the far end of
    # each of two of the roads, no timestamps. Between neighbouring roads (a and c: 80 m apart,
    # 339 m by road) the detour once left the second fix out and the match with one fix had no
    # route; a track the rules would leave with one fix is matched without them
    m = parse_ascii_map(STAR, scale=20)
    for start, end in itertools.permutations("acegikmo", 2):
        r = untimed(m, [at(m, start), at(m, end)])
        assert routes(m, r) == [[start + "x", "x" + end]], (start, end)
        assert all(p.status == PointStatus.MATCHED for p in r.points)


ONE_WAY_AFTER_A_SIDE_ROAD = """
d
|
a>>>>>>>>>>>>>>>>>>>>>>>b
"""
"""Valhalla's map for traces that step backwards on a one-way edge: a two-way side road da
(40 m) into the one-way ab (240 m), which ends at b."""


def _along_ab(amap: AsciiMap, trace: str) -> list[tuple[float, float]]:
    """Valhalla's fixes: 1, 2, 3, 4 at 30, 60, 180 and 210 m along ab; 0 halfway down da."""
    places = {"1": 30.0, "2": 60.0, "3": 180.0, "4": 210.0}
    return [at(amap, "a", 0, 20) if c == "0" else at(amap, "a", places[c]) for c in trace]


@pytest.mark.parametrize(("trace", "length"), [("2431", 150), ("02431", 230)])
def test_a_fix_a_little_back_along_a_one_way_is_standing_and_keeps_the_route_end(
    trace: str, length: float
) -> None:
    # Valhalla's BackwardTraceOnOnewayEdge, "forward then backward (shifted)": after 2 and 4,
    # the fix 3 lies 30 m back along the one-way; no car drives it backwards, so 3 is noise
    # about the place the car stands at (4), not a fix whose keeping cuts the route at 3 and
    # leaves 4 out. Valhalla's answer: ab driven from 2 to 4, 1 (150 m back) not matched
    m = parse_ascii_map(ONE_WAY_AFTER_A_SIDE_ROAD, scale=10)
    r = untimed(m, _along_ab(m, trace))
    assert routes(m, r) == [(["da"] if trace[0] == "0" else []) + ["ab"]]
    assert r.length_m == pytest.approx(length, abs=0.5)
    assert r.points[-1].status == PointStatus.UNMATCHED  # 1: 150 m back, beyond a fix's noise
    assert [p.status for p in r.points[:-1]] == [PointStatus.MATCHED] * (len(trace) - 1)


def test_a_jump_back_along_a_one_way_splits_the_route() -> None:
    # Valhalla's BackwardTraceOnOnewayEdge, "forward then backward": 3, 4, then 1, 2 150 m
    # back on the one-way: two pieces of ab, both kept
    m = parse_ascii_map(ONE_WAY_AFTER_A_SIDE_ROAD, scale=10)
    r = untimed(m, _along_ab(m, "3412"))
    assert routes(m, r) == [["ab"], ["ab"]]
    assert r.length_m == pytest.approx(60, abs=0.5)


@pytest.mark.parametrize("trace", ["1324", "01324"])
def test_one_fix_far_back_along_a_one_way_is_left_out_where_valhalla_splits(trace: str) -> None:
    # Valhalla's "backward middle step": 1, 3, then 2 (120 m back), then 4. Valhalla breaks the
    # trace at 2 and answers two pieces, 1-3 and 2-4; a convention this project does not share:
    # one fix that cannot be driven to is left out as an outlier, and the route runs 1 to 4
    # once, covering the same road
    m = parse_ascii_map(ONE_WAY_AFTER_A_SIDE_ROAD, scale=10)
    r = untimed(m, _along_ab(m, trace))
    assert routes(m, r) == [(["da"] if trace[0] == "0" else []) + ["ab"]]
    assert r.length_m == pytest.approx(230 if trace[0] == "0" else 180, abs=0.5)
    assert r.points[-2].status == PointStatus.UNMATCHED


def test_a_trace_backwards_along_a_one_way_drives_none_of_it() -> None:
    # Valhalla's fully reversed trace 4, 3, 2, 1: Valhalla finds no route and fails; here each
    # fix 30 m back is standing at the one before, 2 (120 m back) starts a new piece, and not a
    # metre of the one-way is driven backwards
    m = parse_ascii_map(ONE_WAY_AFTER_A_SIDE_ROAD, scale=10)
    r = untimed(m, _along_ab(m, "4321"))
    assert r.length_m == 0.0
    assert all(piece == ["ab"] for piece in routes(m, r))


def test_a_jump_back_along_a_one_way_after_a_side_road_keeps_both_stretches() -> None:
    # Valhalla's "forward then backward" with 0 on the side road first: 0, 3, 4, then 1, 2
    # 150 m back. Valhalla answers da + ab to 4, then ab 1 to 2. Leaving out 3 and 4 would
    # reach 1 from 0, but it drops as many fixes as it keeps (each reading keeps three): the
    # fixes are two stretches of one drive, and the route splits at 1, every fix kept
    m = parse_ascii_map(ONE_WAY_AFTER_A_SIDE_ROAD, scale=10)
    r = untimed(m, _along_ab(m, "03412"))
    assert routes(m, r) == [["da", "ab"], ["ab"]]
    assert r.splits == [3]
    assert r.length_m == pytest.approx(20 + 210 + 30, abs=0.5)
    assert [p.status for p in r.points] == [PointStatus.MATCHED] * 5


def test_a_dense_fix_back_along_the_road_is_left_out_where_osrm_tidies_it() -> None:
    # OSRM's "trace tidying, dirty case by ts": a, b, a, c, d on a 300 m road, 10 s apart but
    # for the second a, 2 s after b. OSRM's tidying drops the fix 2 s after the one before; here
    # the way back to a and on to c in 10 s is no route (the time allows none): the fix is
    # left out as an outlier, and the route runs a to d once
    m = parse_ascii_map("a-------b-------c-------d", scale=12.5)
    ll = np.array([m.lonlat(*at(m, c)) for c in "abacd"])
    r = BatchMatcher(m.graph).match(Track("t", np.array([0.0, 10, 12, 20, 30]), ll[:, 1], ll[:, 0]))
    assert routes(m, r) == [["ab", "bc", "cd"]]
    assert r.length_m == pytest.approx(300, abs=0.5)
    assert [p.status for p in r.points] == [PointStatus.MATCHED] * 2 + [PointStatus.UNMATCHED] + [
        PointStatus.MATCHED
    ] * 2


def test_an_untimed_fix_far_back_along_a_two_way_road_is_a_u_turn() -> None:
    # the same trace without times: a fix 100 m back on a two-way road is far beyond the
    # noise, and nothing tells it came 2 s after the one before; here the car turns round
    # (OSRM's answer, a to d once, rests on its tidying by time, which an untimed trace lacks)
    m = parse_ascii_map("a-------b-------c-------d", scale=12.5)
    r = untimed(m, [at(m, c) for c in "abacd"])
    assert routes(m, r) == [["ab", "ba", "ab", "bc", "cd"]]


CORNER = """
a
|
|
b--------------c
"""


def test_a_first_fix_beside_a_corner_is_placed_on_the_road_the_next_fix_confirms() -> None:
    # OSRM's "waypoints trimming too much geometry" started at its second fix e: e lies 10 m
    # from ab and 10 m from bc, by the corner b; the next fix f lies 10 m past b down ab's
    # line, then fixes along bc. The car came down ab: the route should start on ab, not cut
    # the corner onto bc with f placed behind the route's start. Four fixes 10 m off their
    # roads give no estimate of the receiver's σ (15 m, which thinned out f and g and left the
    # choice to e and the last fix alone): the track keeps the model's
    m = parse_ascii_map(CORNER, scale=10)
    r = untimed(m, [at(m, "a", 10, -50), at(m, "a", 0, -70), at(m, "a", 50, -50), at(m, "a", 140, -70)])
    assert routes(m, r) == [["ab", "bc"]]
    assert r.length_m == pytest.approx(150, abs=0.5)
    assert [p.status for p in r.points] == [PointStatus.MATCHED] * 4
