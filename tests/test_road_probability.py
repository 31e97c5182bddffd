"""The reported road's probability: the path's, times the along-track position's share on the
edge when the answer is dead-reckoned or held at a node (``mapmatch.measurement``)."""

from __future__ import annotations

import math

import pytest

from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.measurement import AlongEvidence, Placement, map_aided_measurement, on_edge_share
from mapmatch.types import MapAidedMeasurement, State

# a crossing at b: a-b is 200 m, then on to c
CROSSING = """
a--------b--------c
         |
         d
"""


def _map() -> AsciiMap:
    return parse_ascii_map(CROSSING, scale=25)


def _evidence(*, gps: bool, sigma: float) -> AlongEvidence:
    """What the matcher knows along the road: with GPS a fix of σ ``sigma`` (no bias learnt),
    in dead reckoning a carry of σ ``sigma`` (no odometer growth)."""
    return AlongEvidence(
        gps=gps,
        fix_sigma=sigma,
        bias_cov=(math.nan, math.nan, math.nan),
        white_share=1.0,
        anchor_sd=math.nan,
        odo_sigma=0.0,
        dr_distance=0.0,
        gps_sigma=sigma,
    )


def _measure(
    m: AsciiMap, offset: float, evidence: AlongEvidence, *, beyond: float = 0.0
) -> MapAidedMeasurement:
    e = m.edge("a", "b")
    lon, lat = m.lonlat(*m.xy("a"))
    place = Placement(State.ON_ROAD, e, offset, lat, lon, 90.0, 1.0, 1000.0, beyond)
    return map_aided_measurement(m.graph, place, evidence)


def test_dead_reckoned_answer_just_before_a_crossing_with_a_large_sigma_is_not_sure_of_its_road() -> None:
    m = _map()
    length = float(m.graph.edge_len[m.edge("a", "b")])
    near = _measure(m, length - 3.0, _evidence(gps=False, sigma=25.0))
    assert near.along_sigma == pytest.approx(25.0)
    # about half the position's spread is past b, on b-c or b-d
    assert 0.4 < near.probability < 0.7
    assert not near.usable and near.reason == "low_probability"


def test_dead_reckoned_answer_mid_edge_with_a_small_sigma_keeps_its_path_probability() -> None:
    m = _map()
    length = float(m.graph.edge_len[m.edge("a", "b")])
    mid = _measure(m, 0.5 * length, _evidence(gps=False, sigma=3.0))
    assert mid.probability == pytest.approx(1.0, abs=1e-9)
    assert mid.usable


def test_gps_answer_held_at_a_node_with_the_fix_past_it_is_not_usable() -> None:
    m = _map()
    length = float(m.graph.edge_len[m.edge("a", "b")])
    held = _measure(m, length, _evidence(gps=True, sigma=4.0), beyond=10.0)
    assert held.probability < 0.1
    assert not held.usable
    # held at the node with the fix on it: the vehicle straddles the crossing
    on_node = _measure(m, length, _evidence(gps=True, sigma=4.0))
    assert 0.6 < on_node.probability < 0.9


def test_gps_answer_inside_its_edge_keeps_its_path_probability_near_a_node() -> None:
    m = _map()
    length = float(m.graph.edge_len[m.edge("a", "b")])
    inside = _measure(m, length - 1.0, _evidence(gps=True, sigma=4.0))
    assert inside.probability == pytest.approx(1.0)
    assert inside.usable


def test_on_edge_share_is_the_normal_mass_on_the_widened_edge() -> None:
    straddle = DEFAULT_CONFIG.measurement.straddle
    assert on_edge_share(50.0, 100.0, 1.0, straddle) == pytest.approx(1.0)
    assert on_edge_share(100.0 + straddle, 100.0, 5.0, straddle) == pytest.approx(0.5)
    assert on_edge_share(-straddle, 100.0, 5.0, straddle) == pytest.approx(0.5)
    assert on_edge_share(50.0, 100.0, 0.0, straddle) == 1.0
    assert on_edge_share(120.0, 100.0, 0.0, straddle) == 0.0
