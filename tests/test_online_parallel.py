"""Online matcher where real GPS goes wrong: parallel roads, small-angle forks, outage ends.

Each map is drawn (or, for a 10° exit that ASCII cannot draw, laid out in metres) and the fixes
are drawn along it with the bias a real receiver has: minutes long, towards the wrong road.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.ascii import ASCII_CRS, AsciiMap, parse_ascii_map
from graph.projection import to_lonlat
from graph.road_graph import Edges, Nodes, RoadGraph
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix, SnapResult, corrected_edges
from tests.online_helpers import DriveSpec, drive

# a divided road: two one-way carriageways 20 m apart, with a median opening e-f
DIVIDED = """
a>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>e>>>>>>>>>>>>>>>>>>>>>>>>>>>>>>b
                               |
c<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<f<<<<<<<<<<<<<<<<<<<<<<<<<<<<<<d
"""
# a main road a-b with a frontage road c-d 20 m beside it (scale 5: lines are 10 m apart)
FRONTAGE = """
a-----------------------------------------------------------------b
 \\                                                               /
  c-------------------------------------------------------------d
"""


@pytest.fixture(params=[DEFAULT_CONFIG], ids=["default"])
def cfg(request: pytest.FixtureRequest) -> MatchConfig:
    """The matcher as shipped."""
    return request.param  # type: ignore[no-any-return]


def run(m: OnlineMatcher, fixes: list[Fix]) -> list[SnapResult]:
    st = m.new_session()
    return [m.update(st, f) for f in fixes]


def shifted(amap: AsciiMap, route: str, dx: float, dy: float, **kw: object) -> list[Fix]:
    """Fixes along ``route`` with a constant GPS bias (dx, dy) metres."""
    pts = [tuple(amap.xy(n) + (dx, dy)) for n in route]
    return drive(amap, route, DriveSpec(**kw), points=pts)  # type: ignore[arg-type]


def final_edges(results: list[SnapResult]) -> list[int]:
    """Reported edges, corrections applied, in order without repeats."""
    out: list[int] = []
    for x in corrected_edges(results):
        if x >= 0 and (not out or out[-1] != x):
            out.append(x)
    return out


def test_divided_road_with_gps_biased_towards_the_other_carriageway(cfg: MatchConfig) -> None:
    amap = parse_ascii_map(DIVIDED, scale=10.0)
    m = OnlineMatcher(amap.graph, config=cfg)
    res = run(m, shifted(amap, "aeb", 0.0, -9.0, speed=15.0, sigma=5.0, noise=1.0, seed=2))
    good = {amap.edge("a", "e"), amap.edge("e", "b")}
    assert all(r.edge in good for r in res[3:])


def test_u_turn_across_the_median_opening(cfg: MatchConfig) -> None:
    amap = parse_ascii_map(DIVIDED, scale=10.0)
    m = OnlineMatcher(amap.graph, config=cfg)
    res = run(m, drive(amap, "aefc", DriveSpec(speed=8.0, sigma=4.0, noise=1.5, seed=4)))
    assert final_edges(res)[-2:] == [amap.edge("e", "f"), amap.edge("f", "c")]
    assert res[-1].edge == amap.edge("f", "c")


@pytest.mark.parametrize("bias", [6.0, 9.0])
def test_main_road_with_gps_biased_towards_the_frontage_road(bias: float, cfg: MatchConfig) -> None:
    amap = parse_ascii_map(FRONTAGE, scale=5.0)
    m = OnlineMatcher(amap.graph, config=cfg)
    res = run(m, shifted(amap, "ab", 0.0, -bias, speed=12.0, sigma=5.0, noise=1.0, seed=1))
    assert all(r.edge == amap.edge("a", "b") for r in res[3:-2])


def test_frontage_road_with_gps_biased_towards_the_main_road(cfg: MatchConfig) -> None:
    amap = parse_ascii_map(FRONTAGE, scale=5.0)
    m = OnlineMatcher(amap.graph, config=cfg)
    res = run(m, shifted(amap, "acdb", 0.0, 6.0, speed=10.0, sigma=5.0, noise=1.0, seed=3))
    c, d = amap.xy("c"), amap.xy("d")
    x = np.array([to_xy(amap, r) for r in res])
    mid = (x[:, 0] > c[0] + 60.0) & (x[:, 0] < d[0] - 60.0)
    cd = amap.edge("c", "d")
    assert mid.sum() > 10
    assert np.mean([r.edge == cd for r, k in zip(res, mid, strict=True) if k]) >= 0.9
    assert cd in final_edges(res)


def to_xy(amap: AsciiMap, r: SnapResult) -> tuple[float, float]:
    from graph.projection import point_to_xy

    return point_to_xy(amap.graph.crs, r.raw_lon, r.raw_lat)


def _exit_map() -> tuple[RoadGraph, dict[str, int]]:
    """A straight road a-b-c and a 10° exit b-d, in metres."""
    x0, y0 = 385_000.0, 6_672_000.0
    ang = math.radians(10.0)
    xy = [
        (x0, y0),
        (x0 + 300.0, y0),
        (x0 + 800.0, y0),
        (x0 + 300.0 + 500.0 * math.cos(ang), y0 - 500.0 * math.sin(ang)),
    ]
    uv = [(0, 1), (1, 0), (1, 2), (2, 1), (1, 3), (3, 1)]
    g = RoadGraph.from_edges(ASCII_CRS, Nodes(xy), Edges([a for a, _ in uv], [b for _, b in uv]))
    return g, {"ab": 0, "bc": 2, "bd": 4}


@pytest.mark.parametrize("taken", [False, True])
def test_ten_degree_exit(taken: bool, cfg: MatchConfig) -> None:
    g, e = _exit_map()
    amap = AsciiMap(graph=g, nodes={"a": 0, "b": 1, "c": 2, "d": 3}, scale=1.0)
    route = "abd" if taken else "abc"
    res = run(
        OnlineMatcher(g, config=cfg),
        drive(amap, route, DriveSpec(speed=25.0, sigma=4.0, noise=2.0, seed=5, heading_noise=1.0)),
    )
    want = [e["ab"], e["bd"] if taken else e["bc"]]
    assert final_edges(res) == want
    assert res[-1].edge == want[-1]


def test_outage_ending_beside_a_parallel_road(cfg: MatchConfig) -> None:
    """Dead reckoning drifts onto the frontage road; the returning fix is on the main road."""
    amap = parse_ascii_map(FRONTAGE, scale=5.0)
    m = OnlineMatcher(amap.graph, config=cfg)
    fixes = drive(amap, "ab", DriveSpec(speed=10.0, sigma=4.0, noise=1.0, seed=6))
    n = len(fixes)
    i0, i1 = n // 4, n // 4 + 15  # 15 s of dead reckoning drifting 1.3 m/s south
    out: list[Fix] = []
    for i, f in enumerate(fixes):
        if i0 <= i < i1:
            lon, lat = to_lonlat(amap.graph.crs, *_offset(amap, f, 0.0, -1.3 * (i - i0 + 1)))[0]
            f = f._replace(
                lat=float(lat), lon=float(lon), gps_valid=False, pos_sigma=4.0 + 0.04 * 10.0 * (i - i0)
            )
        out.append(f)
    res = run(m, out)
    ab = amap.edge("a", "b")
    assert all(r.edge == ab for r in res[i1 : i1 + 3])  # at once when GPS is back
    assert final_edges(res) == [ab]


def _offset(amap: AsciiMap, f: Fix, dx: float, dy: float) -> tuple[list[float], list[float]]:
    from graph.projection import point_to_xy

    x, y = point_to_xy(amap.graph.crs, f.lon, f.lat)
    return [x + dx], [y + dy]


def _biased(g: RoadGraph, fixes: list[Fix], dy: float) -> list[Fix]:
    from graph.projection import point_to_xy

    out = []
    for f in fixes:
        x, y = point_to_xy(g.crs, f.lon, f.lat)
        lon, lat = to_lonlat(g.crs, [x], [y + dy])[0]
        out.append(f._replace(lon=float(lon), lat=float(lat)))
    return out


def _wrong_at_fork(
    g: RoadGraph, e: dict[str, int], cfg: MatchConfig, *, seeds: int, speed: float, bias: float, end: bool
) -> int:
    """Answers on the branch not taken, summed over both routes through the fork b (c and d)
    and ``seeds`` noisy drives, the fixes ``bias`` metres towards the other branch; with
    ``end``, every drive must end on the branch taken."""
    amap = AsciiMap(graph=g, nodes={"a": 0, "b": 1, "c": 2, "d": 3}, scale=1.0)
    m = OnlineMatcher(g, config=cfg)
    n = 0
    for taken in (False, True):
        route = "abd" if taken else "abc"
        other = e["bc"] if taken else e["bd"]
        for seed in range(seeds):
            fixes = drive(
                amap, route, DriveSpec(speed=speed, sigma=4.0, noise=2.0, seed=seed, heading_noise=1.0)
            )
            res = run(m, _biased(g, fixes, bias if taken else -bias) if bias else fixes)
            n += sum(r.edge == other for r in res)
            if end:
                assert res[-1].edge == (e["bd"] if taken else e["bc"])
    return n


def test_ten_degree_fork_stays_open_while_the_other_branch_is_probable() -> None:
    """The 10° exit with the GPS biased 5 m towards the other branch: the node is committed
    only once the other branch holds little of the probability, so the evidence, not the
    region's circle, decides the branch, and fewer answers are on the wrong one than when the
    circle commits (the fork-commit and bias rules off)."""
    g, e = _exit_map()
    circle = DEFAULT_CONFIG.replace(commit_hold_probability=0.0, bias_emission=0.0)
    wrong = {
        name: _wrong_at_fork(g, e, cfg, seeds=6, speed=25.0, bias=5.0, end=True)
        for name, cfg in (("circle", circle), ("default", DEFAULT_CONFIG))
    }
    assert wrong["default"] <= 0.6 * wrong["circle"]


def _split_map(deg: float) -> tuple[RoadGraph, dict[str, int]]:
    """A motorway a-b that splits at b into b-c straight on and b-d at ``deg``°, 1.5 km long,
    in metres."""
    x0, y0 = 385_000.0, 6_672_000.0
    ang = math.radians(deg)
    xy = [
        (x0, y0),
        (x0 + 400.0, y0),
        (x0 + 1900.0, y0),
        (x0 + 400.0 + 1500.0 * math.cos(ang), y0 - 1500.0 * math.sin(ang)),
    ]
    uv = [(0, 1), (1, 2), (1, 3)]
    g = RoadGraph.from_edges(ASCII_CRS, Nodes(xy), Edges([a for a, _ in uv], [b for _, b in uv]))
    return g, {"ab": 0, "bc": 1, "bd": 2}


def test_motorway_split_keeps_the_other_branch_after_a_forced_commit() -> None:
    """The branches of a 1.5° split run within 4 m for 150 m, where the region's radius forces
    the commit: the branch that is still probable then goes on as a path of its own, so when
    the branches are apart the evidence, not the coin toss, decides (and fewer fixes are on
    the wrong one than when the commit drops it).

        a-------------b=================c      (b-d leaves b-c at 1.5°)
                        ` ` ` ` ` ` ` ` d
    """
    g, e = _split_map(1.5)
    hold = DEFAULT_CONFIG.online.region.commit_hold_probability
    old = DEFAULT_CONFIG.replace(commit_hold_probability=0.0)
    dropped = _wrong_at_fork(g, e, old, seeds=4, speed=30.0, bias=0.0, end=False)
    kept = _wrong_at_fork(g, e, DEFAULT_CONFIG, seeds=4, speed=30.0, bias=0.0, end=True)
    assert hold > 0.0 and kept < 0.6 * dropped


def test_learnt_bias_is_no_evidence_for_the_branch_it_points_to() -> None:
    """The 10° exit with every fix 5 m towards the other branch, from the start: on a-b the
    offset across the road is learnt as the receiver's bias, and taken off the distances when
    the branches are weighed, so fewer answers are on the branch the bias points to.

        a----------------b----------------c
                           ` ` ` ` ` ` ` d      (fixes 5 m towards the branch not taken)
    """
    g, e = _exit_map()
    wrong = {
        share: _wrong_at_fork(
            g, e, DEFAULT_CONFIG.replace(bias_emission=share), seeds=6, speed=25.0, bias=5.0, end=False
        )
        for share in (0.0, DEFAULT_CONFIG.online.bias.bias_emission)
    }
    assert wrong[DEFAULT_CONFIG.online.bias.bias_emission] < 0.6 * wrong[0.0]
