"""The junction classes where matchers go wrong, each drawn as a tiny map: a Y fork at 15°, a
ramp leaving at 10° with the GPS biased across it, a three-way junction passed in a GPS outage at
1 Hz and at 10 Hz, and a dense 10 Hz track through a few junctions. Every case runs on five
seeds of the fix errors and asserts on all of them.

The drawings give the roads; :func:`bent` turns the branches to true angles (a drawing has only
0°, 63° and 90°). Distances are measured along the route from the junction node ``b``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.batch import BatchMatcher
from mapmatch.online import OnlineMatcher
from mapmatch.types import PointStatus, SnapResult, Track, TrackMatch, corrected_edges
from tests.ascii_helpers import names
from tests.junction_drives import Drive, Gps, Outage, bent, runs, settled_after, simulate

SEEDS = range(5)

#   c and d are turned to the angles of each case by ``bent``
FORK = """
a-----b-----c
       \\
        d
"""


def _fork(*, left: float, right: float, length: float = 250.0) -> AsciiMap:
    """a -> b due east (180 m), then b -> c ``left`` degrees left of straight on and b -> d
    ``right`` degrees right of it, both ``length`` metres."""
    m = parse_ascii_map(FORK, scale=30)
    return bent(m, {"c": ("b", length, 90.0 - left), "d": ("b", length, 90.0 + right)})


def _online(m: AsciiMap, drv: Drive) -> list[SnapResult]:
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    return [matcher.update(st, f) for f in drv.fixes]


def _batch(m: AsciiMap, drv: Drive, *, every: int = 1) -> TrackMatch:
    f = drv.fixes[::every]
    track = Track(
        "t",
        np.array([x.time for x in f]),
        np.array([x.lat for x in f]),
        np.array([x.lon for x in f]),
    )
    return BatchMatcher(m.graph).match(track)


def _fork_at(m: AsciiMap) -> float:
    return float(np.linalg.norm(m.xy("b") - m.xy("a")))


def _check_branch(m: AsciiMap, route: str, drv: Drive, *, settle: float) -> None:
    """The online answers after the fork settle on the branch driven within ``settle`` metres
    past it and stay there; none leaves a-b more than 5 m before the fork; with corrections
    applied every answer from 15 m past the fork is on the branch, and the path is a-b, branch."""
    res = _online(m, drv)
    at_b = _fork_at(m)
    inc, want = m.edge("a", "b"), m.edge(route[1], route[2])
    live = [r.edge for r in res]
    early = [
        round(float(s) - at_b, 1) for s, e in zip(drv.s, live, strict=True) if s < at_b - 5.0 and e != inc
    ]
    assert early == [], f"left a-b this many metres before the fork: {early}"
    assert settled_after(live, drv.s, want, since=at_b) <= settle
    rev = corrected_edges(res)
    wrong = [
        round(float(s) - at_b, 1) for s, e in zip(drv.s, rev, strict=True) if s > at_b + 15.0 and e != want
    ]
    assert wrong == [], f"corrected answers off the branch this many metres past the fork: {wrong}"
    assert names(m, runs(rev)) == ["ab", route[1:]]


def _check_batch(m: AsciiMap, route: str, drv: Drive) -> None:
    r = _batch(m, drv)
    assert [names(m, piece) for piece in r.routes] == [["ab", route[1:]]]
    assert all(p.status is not PointStatus.UNMATCHED for p in r.points)


@pytest.mark.parametrize("route", ["abc", "abd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_y_fork_at_15_degrees(route: str, seed: int) -> None:
    """Branches 7.5° either side of straight on (15° apart: 10 m apart 40 m past the fork);
    fixes at 1 Hz, 12 m/s, independent errors of σ 3 to 5 m (by seed), heading σ 3°. The live
    answers are on the branch driven by 40 m past the fork."""
    m = _fork(left=7.5, right=7.5)
    drv = simulate(m, route, gps=Gps(noise=3.0 + 0.5 * seed, heading_noise=3.0), seed=seed)
    _check_branch(m, route, drv, settle=40.0)
    _check_batch(m, route, drv)


@pytest.mark.parametrize(("route", "settle"), [("abc", 30.0), ("abd", 60.0)])
@pytest.mark.parametrize("seed", SEEDS)
def test_ramp_at_10_degrees_with_gps_biased_across_it(route: str, settle: float, seed: int) -> None:
    """A straight road a-b-c and a ramp b-d leaving it 10° to the right (south). The GPS is
    biased 3 to 4 m (by seed) towards the road not taken: south, towards the ramp, while the
    vehicle stays on the main road; north, towards the main road, when it takes the ramp. Fixes
    at 1 Hz, 12 m/s, independent errors of σ 1.5 m, heading σ 2°. Staying on, the answers are
    on the main road by 30 m past the fork (the ramp 5 m off it, less than the bias and noise
    together); taking the ramp, on the ramp by 60 m (10 m off the main road, 2.5 times the
    bias)."""
    m = _fork(left=0.0, right=10.0)
    bias = 3.0 + 0.25 * seed
    north = -1.0 if route == "abc" else 1.0
    drv = simulate(m, route, gps=Gps(noise=1.5, bias=(0.0, north * bias), heading_noise=2.0), seed=seed)
    _check_branch(m, route, drv, settle=settle)
    _check_batch(m, route, drv)


@pytest.mark.parametrize("route", ["abc", "abd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_y_fork_and_ramp_at_10_hz_batch(route: str, seed: int) -> None:
    """The batch matcher on the Y fork and the ramp at 10 Hz, the GPS errors correlated over
    5 s as a receiver's are: the route driven, nothing unmatched."""
    y = _fork(left=7.5, right=7.5)
    gps = Gps(noise=3.0 + 0.5 * seed, tau=5.0, heading_noise=3.0)
    _check_batch(y, route, simulate(y, route, gps=gps, seed=seed, dt=0.1))
    ramp = _fork(left=0.0, right=10.0)
    north = -1.0 if route == "abc" else 1.0
    gps = Gps(noise=1.5, tau=5.0, bias=(0.0, north * (3.0 + 0.25 * seed)), heading_noise=2.0)
    _check_batch(ramp, route, simulate(ramp, route, gps=gps, seed=seed, dt=0.1))


def _outage_drive(m: AsciiMap, route: str, *, seed: int, dt: float) -> Drive:
    """12 m/s with correlated GPS errors (σ 3 m, 5 s), heading σ 1°; GPS lost from 100 m before
    the junction to 150 m past it, the odometer reading 3 % high and the heading off by 1° (to
    the left on even seeds, the right on odd ones)."""
    at_b = _fork_at(m)
    outage = Outage(at_b - 100.0, at_b + 150.0, odo_scale=1.03, heading_bias=(-1.0, 1.0)[seed % 2])
    return simulate(m, route, gps=Gps(noise=3.0, tau=5.0, heading_noise=1.0), seed=seed, dt=dt, outage=outage)


THREE_WAY = {"left": 30.0, "right": 0.0}  # b-c 30° left, b-d straight on


@pytest.mark.parametrize("dt", [1.0, 0.1])
@pytest.mark.parametrize("route", ["abc", "abd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_three_way_junction_in_an_outage_right_road_when_gps_returns(
    dt: float, route: str, seed: int
) -> None:
    """Passed without GPS, at 1 Hz and at 10 Hz: every answer once GPS is back is on the road
    driven, and with corrections applied every answer given in the outage more than 10 m from
    the junction (the dead reckoning's lead there is 3 m) is on the right road."""
    m = _fork(**THREE_WAY)
    drv = _outage_drive(m, route, seed=seed, dt=dt)
    res = _online(m, drv)
    at_b = _fork_at(m)
    inc, want = m.edge("a", "b"), m.edge(route[1], route[2])
    lost = [i for i, f in enumerate(drv.fixes) if not f.gps_valid]
    back = lost[-1] + 1
    assert back < len(res) and drv.s[lost[0]] < at_b < drv.s[lost[-1]]
    after = [round(float(drv.s[i]) - at_b, 1) for i in range(back, len(res)) if res[i].edge != want]
    assert after == [], f"off the road driven this many metres past the junction with GPS back: {after}"
    rev = corrected_edges(res)
    wrong = [
        round(float(drv.s[i]) - at_b, 1)
        for i in lost
        if abs(drv.s[i] - at_b) > 10.0 and rev[i] != (want if drv.s[i] > at_b else inc)
    ]
    assert wrong == [], f"outage answers left wrong by the corrections (metres from the junction): {wrong}"


@pytest.mark.parametrize("route", ["abc", "abd"])
@pytest.mark.parametrize("seed", SEEDS)
def test_three_way_junction_in_an_outage_committed_path_at_1_hz(route: str, seed: int) -> None:
    """At 1 Hz the path the answers describe once corrected is a-b then the road driven."""
    m = _fork(**THREE_WAY)
    res = _online(m, _outage_drive(m, route, seed=seed, dt=1.0))
    assert names(m, runs(corrected_edges(res))) == ["ab", route[1:]]


DENSE = """
a-----------b-----------c
            |           |
            |           |
            d-----------e-----------f
            |
            g
"""


def _dense_drive(m: AsciiMap, seed: int) -> Drive:
    """a-b-d-e-f (1050 m) at 12 m/s and 10 Hz with correlated GPS errors (σ 3 m, 5 s)."""
    return simulate(m, "abdef", gps=Gps(noise=3.0, tau=5.0), seed=seed, dt=0.1)


def _stopped(drv: Drive, *, at: float, seconds: float, seed: int) -> Drive:
    """The drive with the vehicle standing ``seconds`` at ``at`` metres, its fixes wandering
    about the last one as a receiver's do at a standstill; later fixes shifted in time."""
    i = int(np.searchsorted(drv.s, at))
    dt = drv.fixes[1].time - drv.fixes[0].time
    k = round(seconds / dt)
    rng = np.random.default_rng(seed)
    f0 = drv.fixes[i]
    walk = np.cumsum(rng.normal(0.0, 2e-6, (k, 2)), axis=0)
    stand = [
        f0._replace(time=f0.time + (j + 1) * dt, lat=f0.lat + walk[j, 0], lon=f0.lon + 2.0 * walk[j, 1])
        for j in range(k)
    ]
    later = [f._replace(time=f.time + k * dt) for f in drv.fixes[i + 1 :]]
    return Drive(
        drv.fixes[: i + 1] + stand + later, np.concatenate([drv.s[: i + 1], np.full(k, at), drv.s[i + 1 :]])
    )


@pytest.mark.parametrize("stop", [False, True])
@pytest.mark.parametrize("seed", SEEDS)
def test_dense_full_rate_track_stays_one_piece(stop: bool, seed: int) -> None:
    """The batch matcher on a 10 Hz track (with and without a 30 s stop 100 m down b-d): one
    route piece, no point left unmatched, the route driven; the same track sampled every 1 s
    and every 10 s gives the same route."""
    m = parse_ascii_map(DENSE, scale=25)
    drv = _dense_drive(m, seed)
    if stop:
        drv = _stopped(drv, at=400.0, seconds=30.0, seed=seed)
    r = _batch(m, drv)
    assert r.splits == []
    assert [names(m, piece) for piece in r.routes] == [["ab", "bd", "de", "ef"]]
    unmatched = [
        round(float(drv.s[i]), 1) for i, p in enumerate(r.points) if p.status is PointStatus.UNMATCHED
    ]
    assert unmatched == [], f"unmatched at these metres along the route: {unmatched}"
    for every in (10, 100):
        assert [names(m, piece) for piece in _batch(m, drv, every=every).routes] == [["ab", "bd", "de", "ef"]]
    assert math.isfinite(r.length_m) and r.length_m == pytest.approx(1050.0, abs=25.0)
