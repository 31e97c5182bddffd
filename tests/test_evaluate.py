"""Evaluation metrics on constructed examples with known answers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from graph.ascii import parse_ascii_map
from mapmatch.evaluate import Scoring, edge_path, evaluate, intersection_score, matched_junctions, path_nodes
from mapmatch.route_score import path_geometry, route_mismatch

# b, c and f are junctions (three neighbours); e and the ends are not
MAP = """
a-------b-------c-------d
        |       |
        e-------f-------g
"""


@pytest.fixture(scope="module")
def amap():  # type: ignore[no-untyped-def]
    return parse_ascii_map(MAP, scale=20.0)


def _frames(amap, truth_edges, matched_edges):  # type: ignore[no-untyped-def]
    """Per-fix truth and match: fixes at the middle of their edge, snapped exactly there."""
    g = amap.graph
    rows_t, rows_m = [], []
    for i, (te, me) in enumerate(zip(truth_edges, matched_edges, strict=True)):
        txy = g.edge_xy(te).mean(axis=0)
        tll = amap.lonlat(*txy)
        rows_t.append({"time": float(i), "edge": te, "x": txy[0], "y": txy[1], "offset": g.edge_len[te] / 2})
        if me < 0:
            rows_m.append({"time": float(i), "edge": -1, "lat": np.nan, "lon": np.nan})
        else:
            mxy = g.edge_xy(me).mean(axis=0)
            mll = amap.lonlat(*mxy)
            rows_m.append({"time": float(i), "edge": me, "lat": mll[1], "lon": mll[0]})
        del tll
    return pd.DataFrame(rows_t), pd.DataFrame(rows_m)


def test_perfect_match_scores_100_percent(amap) -> None:  # type: ignore[no-untyped-def]
    ab, bc, cd = amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("c", "d")
    edges = [ab] * 4 + [bc] * 4 + [cd] * 4
    truth, matched = _frames(amap, edges, edges)
    m = evaluate(amap.graph, truth=truth, matched=matched, scoring=Scoring(tolerance_m=0.1))
    assert m.intersections.accuracy == 1.0
    assert m.intersections.precision == 1.0
    assert m.intersections.true == 2  # b and c
    assert m.correct_edge_rate == 1.0
    assert m.rmf.fraction == pytest.approx(0.0, abs=1e-9)
    assert m.snap_error_mean == pytest.approx(0.0, abs=0.01)
    assert "100.0 %" in m.table()


def test_one_wrong_turn_gives_its_known_value(amap) -> None:  # type: ignore[no-untyped-def]
    g = amap.graph
    ab, bc, cd = amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("c", "d")
    be, ef, fg = amap.edge("b", "e"), amap.edge("e", "f"), amap.edge("f", "g")
    truth_edges = [ab] * 4 + [bc] * 4 + [cd] * 4
    matched_edges = [ab] * 4 + [be] * 2 + [ef] * 3 + [fg] * 3
    truth, matched = _frames(amap, truth_edges, matched_edges)
    m = evaluate(
        g,
        truth=truth,
        matched=matched,
        truth_path=[ab, bc, cd],
        truth_xy=path_geometry(g, [ab, bc, cd]),
        scoring=Scoring(tolerance_m=0.1),
    )
    # true junctions b, c; matched b, f: one of two found
    assert (m.intersections.true, m.intersections.matched, m.intersections.correct) == (2, 2, 1)
    assert m.intersections.accuracy == 0.5
    assert m.correct_edge_rate == pytest.approx(4 / 12)
    # matched route runs from the middle of a-b (first fix) to the middle of f-g (last fix)
    lab, lbc, lcd = g.edge_len[[ab, bc, cd]]
    lbe, lef = g.edge_len[[be, ef]]
    lfg_half = g.edge_len[fg] / 2
    missing = lab / 2 + lbc + lcd
    extra = lbe + lef + lfg_half
    assert m.rmf.truth_m == pytest.approx(lab + lbc + lcd, abs=0.5)
    assert m.rmf.missing_m == pytest.approx(missing, abs=1.0)
    assert m.rmf.extra_m == pytest.approx(extra, abs=1.0)
    assert m.rmf.fraction == pytest.approx((missing + extra) / (lab + lbc + lcd), abs=0.01)


def test_reverse_twin_is_a_wrong_edge(amap) -> None:  # type: ignore[no-untyped-def]
    ab, ba = amap.edge("a", "b"), amap.edge("b", "a")
    truth, matched = _frames(amap, [ab] * 5, [ab, ab, ba, ba, -1])
    m = evaluate(amap.graph, truth=truth, matched=matched)
    assert m.correct_edge_rate == pytest.approx(2 / 5)
    assert m.unmatched_fraction == pytest.approx(1 / 5)


def test_alignment_counts_matching_blocks() -> None:
    assert intersection_score([1, 2, 3, 4], [1, 2, 3, 4]).accuracy == 1.0
    s = intersection_score([1, 2, 3, 4], [1, 9, 3, 4])
    assert (s.correct, s.accuracy, s.precision) == (3, 0.75, 0.75)
    s = intersection_score([1, 2, 3], [1, 2, 7, 8, 3])
    assert (s.correct, s.precision) == (3, 0.6)
    assert np.isnan(intersection_score([], []).accuracy)


def test_alignment_is_optimal_on_a_route_that_drives_a_loop_twice() -> None:
    loop = [10, 11, 12, 13, 14, 15]
    true = [1, 2, *loop, *loop, 3, 4]
    # the first pass misses 13 and 15 and reports a wrong 99; the second is right; 3 is missed.
    # difflib's greedy longest block (10..15 of the second pass paired with the first) found 9
    matched = [1, 2, 10, 11, 12, 14, 99, 10, 11, 12, 13, 14, 15, 4]
    s = intersection_score(true, matched)
    assert (s.true, s.matched, s.correct) == (16, 14, 13)
    found = matched_junctions(true, matched)
    assert found.sum() == 13 and not found[5] and not found[7] and not found[14]
    # an extra report (a brief wrong branch) costs precision, not accuracy
    s = intersection_score(true, [1, 2, 10, 50, 11, 12, 13, 14, 15, *loop, 3, 4])
    assert (s.correct, s.accuracy, s.matched) == (16, 1.0, 17)


def test_gap_in_per_fix_edges_is_closed_by_shortest_path(amap) -> None:  # type: ignore[no-untyped-def]
    g = amap.graph
    ab, bc, cd = amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("c", "d")
    # a fix rate too low to see b->c: the path still passes b and c
    assert edge_path(g, [ab, ab, -1, cd]) == [ab, bc, cd]
    assert [amap.nodes["b"], amap.nodes["c"]] == path_nodes(g, [ab, bc, cd])


def test_route_mismatch_tolerance() -> None:
    truth = np.array([[0.0, 0.0], [100.0, 0.0]])
    shifted = truth + [0.0, 1.5]
    assert route_mismatch(truth, shifted, tolerance_m=2.0).fraction == pytest.approx(0.0)
    assert route_mismatch(truth, shifted, tolerance_m=1.0).fraction == pytest.approx(2.0)
    half = np.array([[0.0, 0.0], [50.0, 0.0]])
    r = route_mismatch(truth, half, tolerance_m=0.1)
    assert r.missing_m == pytest.approx(50.0, abs=1.0) and r.extra_m == 0.0
    assert route_mismatch(truth, np.empty((0, 2))).fraction == pytest.approx(1.0)


def test_corrections_are_applied_in_the_corrected_score(amap) -> None:  # type: ignore[no-untyped-def]
    ab, bc, be = amap.edge("a", "b"), amap.edge("b", "c"), amap.edge("b", "e")
    truth_edges = [ab] * 4 + [bc] * 4
    truth, _ = _frames(amap, truth_edges, truth_edges)
    # live: two fixes reported on b->e (wrong), then corrected at the next fix
    _, matched = _frames(amap, truth_edges, [ab] * 4 + [be, be, bc, bc])
    # raw positions: the true ones
    g = amap.graph
    raw = [amap.lonlat(*g.edge_xy(e).mean(axis=0)) for e in truth_edges]
    matched["raw_lon"] = [r[0] for r in raw]
    matched["raw_lat"] = [r[1] for r in raw]
    matched["correction"] = ["", "", "", "", "", "", str(bc), ""]
    matched["correction_from"] = [np.nan] * 6 + [4.0, np.nan]
    matched["correction_to"] = [np.nan] * 6 + [5.0, np.nan]
    m = evaluate(g, truth=truth, matched=matched, scoring=Scoring(tolerance_m=0.1))
    assert m.correct_edge_rate == pytest.approx(6 / 8)
    assert m.corrections == 1
    assert m.corrected is not None
    assert m.corrected.correct_edge_rate == 1.0
    assert m.corrected.intersections.precision == 1.0
    assert "after corrections: correct edge" in m.table()


def test_correction_times_assign_each_revised_fix_by_its_time(amap) -> None:  # type: ignore[no-untyped-def]
    ab, bc = amap.edge("a", "b"), amap.edge("b", "c")
    truth_edges = [ab] * 4 + [bc] * 4
    truth, _ = _frames(amap, truth_edges, truth_edges)
    # live: fixes 2 and 3 ran ahead onto b->c (their raw positions lie on b->c too)
    lead = [ab, ab, bc, bc, bc, bc, bc, bc]
    _, matched = _frames(amap, truth_edges, lead)
    g = amap.graph
    raw = [amap.lonlat(*g.edge_xy(e).mean(axis=0)) for e in lead]
    matched["raw_lon"] = [r[0] for r in raw]
    matched["raw_lat"] = [r[1] for r in raw]
    matched["correction"] = [""] * 5 + [f"{ab};{bc}", "", ""]
    matched["correction_from"] = [np.nan] * 5 + [2.0, np.nan, np.nan]
    matched["correction_to"] = [np.nan] * 5 + [4.0, np.nan, np.nan]
    # by position alone the revision cannot say which fixes were still on a->b
    m = evaluate(g, truth=truth, matched=matched, scoring=Scoring(tolerance_m=0.1))
    assert m.corrected is not None and m.corrected.correct_edge_rate == pytest.approx(6 / 8)
    matched["correction_times"] = [""] * 5 + ["2.0;4.0", "", ""]
    m = evaluate(g, truth=truth, matched=matched, scoring=Scoring(tolerance_m=0.1))
    assert m.correct_edge_rate == pytest.approx(6 / 8)
    assert m.corrected is not None and m.corrected.correct_edge_rate == 1.0
