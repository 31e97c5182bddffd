"""The probability an online answer reports (``confidence``) and the ``usable`` flag built on
it, on ASCII maps through the real matcher."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from graph.ascii import parse_ascii_map
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.errors import ConfigError
from mapmatch.measurement import Agreement, confidence
from mapmatch.online import OnlineMatcher
from mapmatch.online.parallel import ParallelRoads, alongside_table, stretch_roads
from tests.online_helpers import DriveSpec, drive

# a road that ends at b, and the same with a road alongside it one row north (two scale units)
DEAD_END = """
a--------b
"""
ALONGSIDE = """
c--------d
a--------b
"""
# roads alongside, across junctions and at angles: a divided road with a median opening and a
# frontage road, and a diagonal
STREETS = """
a>>>>>>>>>>e>>>>>>>>>>b
           |
c<<<<<<<<<<f<<<<<<<<<<d
 \\                   /
  g-----------------h
"""


def test_a_vehicle_held_at_a_node_with_its_fix_past_it_is_not_usable_mid_edge_it_is() -> None:
    m = parse_ascii_map(DEAD_END, scale=25)
    a, b = m.xy("a"), m.xy("b")
    past = b + np.array([12.0, 0.0])
    fixes = drive(m, [], DriveSpec(speed=10.0, sigma=3.0), points=[tuple(a), tuple(b), tuple(past)])
    matcher = OnlineMatcher(m.graph)
    state = matcher.new_session()
    res = [matcher.update(state, f) for f in fixes]
    e = m.edge("a", "b")
    length = float(m.graph.edge_len[e])
    mid = [r for r in res if r.edge == e and 120.0 <= r.offset <= length - 30.0]
    assert mid and all(r.map_aided.usable for r in mid)
    assert all(r.map_aided.probability > 0.99 for r in mid)
    last = res[-1]
    assert last.edge == e and last.offset == pytest.approx(length)  # held at b
    assert not last.map_aided.usable
    assert last.map_aided.reason == "low_probability"
    assert last.map_aided.probability < DEFAULT_CONFIG.measurement.min_probability


def test_a_road_alongside_nearer_to_the_fix_lowers_the_confidence() -> None:
    model = DEFAULT_CONFIG.confidence
    alone = confidence(1.0, Agreement(2.0, 0.5), model)
    far = confidence(1.0, Agreement(2.0, 0.5, 8.0), model)
    near = confidence(1.0, Agreement(2.0, 2.0, 0.5), model)
    assert alone > far > near
    assert confidence(1.0, Agreement(40.0, 0.5), model) < alone  # the fix heads off the road


def test_the_identity_model_reports_the_road_probability() -> None:
    ident = DEFAULT_CONFIG.with_settings(
        [
            "confidence.coef_intercept=0",
            "confidence.coef_log_odds=1",
            "confidence.coef_heading=0",
            "confidence.coef_parallel=0",
            "confidence.coef_parallel_gap=0",
        ]
    ).confidence
    for p in (0.01, 0.3, 0.9, 0.999):
        assert confidence(p, Agreement(30.0, 3.0, 0.1), ident) == pytest.approx(p)


def test_roads_alongside_are_found_mid_edge_and_not_across_a_junction() -> None:
    m = parse_ascii_map(ALONGSIDE, scale=15)  # 30 m apart
    road = OnlineMatcher(m.graph)
    par = ParallelRoads(road.road, road.index)
    cfg = DEFAULT_CONFIG
    e = m.edge("a", "b")
    length = float(m.graph.edge_len[e])
    beside = par.alongside(e, 0.5 * length, cfg)
    assert m.edge("c", "d") in beside
    a, b = m.xy("a"), m.xy("b")
    mid = 0.5 * (a + b)
    assert par.nearest(e, 0.5 * length, float(mid[0]), float(mid[1]) + 5.0, cfg) == pytest.approx(
        float(m.xy("c")[1] - a[1]) - 5.0, abs=0.5
    )
    lone = parse_ascii_map(DEAD_END, scale=25)
    solo = OnlineMatcher(lone.graph)
    e1 = lone.edge("a", "b")
    assert ParallelRoads(solo.road, solo.index).alongside(e1, 10.0, cfg) == ()
    assert math.isinf(ParallelRoads(solo.road, solo.index).nearest(e1, 10.0, 0.0, 0.0, cfg))


@pytest.mark.parametrize(
    "settings",
    [
        [],
        [
            "confidence.parallel_radius=60",
            "model.straight_max_deg=50",
            "confidence.parallel_spacing=7",
            "measurement.map_sigma=4",
        ],
    ],
    ids=["default", "wider"],
)
def test_the_map_table_of_roads_alongside_is_each_edge_looked_up_alone(
    settings: list[str], kubicka_dir: Path
) -> None:
    """The table made in one pass for every edge (REAL roads of Kubicka 00000007 and an ASCII
    map) gives every stretch of every edge the roads its own look-up gives."""
    from graph.build import build_map

    cfg = DEFAULT_CONFIG.with_settings(settings)
    graphs = [parse_ascii_map(STREETS, scale=10).graph, build_map(kubicka_dir / "00000007" / "roads.geojson")]
    for g in graphs:
        m = OnlineMatcher(g)
        table = alongside_table(m.road, m.index, cfg)
        assert table.nbytes > 0
        found = 0
        for e in range(g.n_edges):
            alone = stretch_roads(m.road, m.index, e, cfg)
            assert table.stretches(e) == alone, e
            found += sum(map(len, alone))
        assert found > 0
        assert len(table.roads) == found


def test_the_matcher_makes_the_table_of_its_settings_once_and_answers_from_it() -> None:
    m = parse_ascii_map(ALONGSIDE, scale=15)
    matcher = OnlineMatcher(m.graph)
    cfg = DEFAULT_CONFIG
    made = matcher.parallel.prepare(cfg)
    assert matcher.parallel.prepare(cfg) is made  # made with the matcher, not again
    e = m.edge("a", "b")
    assert matcher.parallel.alongside(e, 10.0, cfg) == made.stretches(e)[0]
    other = DEFAULT_CONFIG.with_settings(["measurement.map_sigma=3"])
    assert matcher.parallel.prepare(other) is not made  # every setting of a road alongside counts


@pytest.mark.parametrize(
    ("setting", "field"),
    [
        ("confidence.probability_floor=0.5", "confidence.probability_floor"),
        ("confidence.gap_cap=0", "confidence.gap_cap"),
        ("confidence.coef_heading=nan", "confidence.coef_heading"),
    ],
)
def test_a_bad_confidence_setting_names_its_field(setting: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        DEFAULT_CONFIG.with_settings([setting])


def test_the_distance_from_the_road_counts_only_against_a_road_alongside() -> None:
    model = DEFAULT_CONFIG.confidence
    # alone, a fix 4 σ off the road is as sure as one on it: the term lost out of fold
    assert confidence(1.0, Agreement(2.0, 4.0), model) == confidence(1.0, Agreement(2.0, 0.2), model)
    # beside another road, it is the gap to that road that counts
    assert confidence(1.0, Agreement(2.0, 4.0, 6.0), model) < confidence(1.0, Agreement(2.0, 0.2, 6.0), model)


def _mid_edge_probabilities(amap_text: str, shift: float) -> list[float]:
    """The reported probabilities of the answers in the middle of a-b, for fixes driven along
    a-b shifted ``shift`` metres north (towards c-d where there is one)."""
    m = parse_ascii_map(amap_text, scale=15)
    a, b = m.xy("a"), m.xy("b")
    up = np.array([0.0, shift])
    fixes = drive(m, [], DriveSpec(speed=10.0, sigma=3.0), points=[tuple(a + up), tuple(b + up)])
    matcher = OnlineMatcher(m.graph)
    state = matcher.new_session()
    res = [matcher.update(state, f) for f in fixes]
    e = m.edge("a", "b")
    length = float(m.graph.edge_len[e])
    mid = [r for r in res if r.edge == e and 0.3 * length <= r.offset <= 0.7 * length]
    assert mid
    return [r.map_aided.probability for r in mid]


def test_fixes_off_the_road_lower_the_probability_only_towards_a_road_alongside() -> None:
    # a lone road: fixes 9 m (3 σ) north of it report what fixes on it report
    on = _mid_edge_probabilities(DEAD_END, 0.0)
    off = _mid_edge_probabilities(DEAD_END, 9.0)
    assert min(off) == pytest.approx(max(on)) and min(on) == pytest.approx(max(off))
    # with c-d 30 m north, the same fixes are nearer to it: less sure than on a-b, which is
    # less sure than a lone road
    beside_on = _mid_edge_probabilities(ALONGSIDE, 0.0)
    beside_off = _mid_edge_probabilities(ALONGSIDE, 9.0)
    assert max(beside_off) < min(beside_on) < min(on)
