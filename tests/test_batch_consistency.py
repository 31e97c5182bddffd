"""Checks that need no truth: the full-rate batch route covers the route of the same track
sampled every 10 s and 30 s (``bench/bench_consistency.py``), on real shared tracks, and the
geometry it rests on (``mapmatch.route_score.uncovered_stretches``, ``trim_route_ends``)."""

from __future__ import annotations

import numpy as np
import pytest
from bench_modules import bench_module
from shared_data import KUBICKA, SHARED, reason

from mapmatch.route_score import farthest_from, trim_route_ends, uncovered_stretches


def test_a_detour_the_covering_route_lacks_is_one_stretch_of_its_length() -> None:
    covering = [np.array([[0.0, 0.0], [100.0, 0.0]])]
    covered = [np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 80.0], [100.0, 80.0]])]
    (gap,) = uncovered_stretches(covering, covered, buffer_m=5.0, min_length_m=30.0)
    assert gap.length_m == pytest.approx(75.0 + 50.0)
    assert gap.xy[0] == pytest.approx([50.0, 5.0]) and gap.xy[-1] == pytest.approx([100.0, 80.0])
    assert farthest_from(covering, gap.xy) == pytest.approx(80.0)
    assert farthest_from(covered, gap.xy) == pytest.approx(0.0)
    assert uncovered_stretches(covered, covered, buffer_m=5.0, min_length_m=30.0) == []
    # a stretch no longer than the minimum is not one
    short = [np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 20.0]])]
    assert uncovered_stretches(covering, short, buffer_m=5.0, min_length_m=30.0) == []


def test_an_empty_covering_route_covers_nothing() -> None:
    covered = [np.array([[0.0, 0.0], [40.0, 0.0]]), np.array([[0.0, 10.0], [0.0, 20.0]])]
    gaps = uncovered_stretches([], covered, buffer_m=5.0, min_length_m=30.0)
    assert [g.length_m for g in gaps] == [40.0]


def test_route_ends_are_cut_at_the_projections_of_the_first_and_last_fix() -> None:
    one = [np.array([[0.0, 0.0], [100.0, 0.0]])]
    (cut,) = trim_route_ends(one, first_xy=(10.0, 3.0), last_xy=(70.0, -2.0))
    assert cut[0] == pytest.approx([10.0, 0.0]) and cut[-1] == pytest.approx([70.0, 0.0])
    two = [np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([[200.0, 0.0], [300.0, 0.0]])]
    a, b = trim_route_ends(two, first_xy=(20.0, 1.0), last_xy=(250.0, 1.0))
    assert a[0] == pytest.approx([20.0, 0.0]) and a[-1] == pytest.approx([100.0, 0.0])
    assert b[0] == pytest.approx([200.0, 0.0]) and b[-1] == pytest.approx([250.0, 0.0])


def test_a_stretch_counts_as_lost_only_for_its_part_on_the_true_route() -> None:
    # the sparse route's stretch the full-rate route lacks: 40 m along the truth, then 60 m off
    # it (a detour); only the 40 m on the truth are a lost stretch of the true route
    bench = bench_module("bench_consistency")
    options = bench.CoverOptions()
    truth = [np.array([[0.0, 0.0], [200.0, 0.0]])]
    (gap,) = uncovered_stretches(
        [np.array([[0.0, -20.0], [200.0, -20.0]])],
        [np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 60.0]])],
        buffer_m=options.buffer_m,
        min_length_m=options.min_length_m,
    )
    assert bench.on_route_m(truth, gap, options) == pytest.approx(40.0 + options.buffer_m)
    r = bench.TrackCover(track="t", fixes=10, full_pieces=1)
    r.on_truth_m[10] = [bench.on_route_m(truth, gap, options)]
    r.on_truth_m[30] = [bench.on_route_m([np.array([[500.0, 0.0], [600.0, 0.0]])], gap, options)]
    assert bench.lost_on_truth(r, 10, options) == 1
    assert bench.lost_on_truth(r, 30, options) == 0  # all of it off the truth: a detour


@pytest.mark.slow
@pytest.mark.parametrize("track", ["00000007", "00000028", "00000045", "00000052"])
def test_the_full_rate_route_covers_the_routes_at_10_and_30_s(track: str) -> None:
    d = KUBICKA / track
    for needed in (d / "track.csv", SHARED / "peers" / "engines_kubicka.py"):
        if not needed.is_file():
            pytest.skip(reason(needed))
    bench = bench_module("bench_consistency")
    r = bench.check_track(d, [10, 30], bench.CoverOptions())
    assert r.missing_m == {10: [], 30: []}, r
