"""Online matcher at 1 and 10 Hz and in GPS outages, on tiny ASCII maps: rate-independent rules
(evidence per second and metre, not per fix) and the vehicle carried through an outage."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from graph.ascii import AsciiMap, parse_ascii_map
from graph.projection import to_lonlat
from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix, SnapResult
from tests.online_helpers import DriveSpec, drive

if TYPE_CHECKING:
    from mapmatch.online.state import FixBias, Step

TURN = """
a-----------b
            |
            |
            |
            |
            |
            |
            |
            |
            c
"""


def _shifted(m: AsciiMap, fixes: list[Fix], dx: float, dy: float, **kw: float) -> list[Fix]:
    """The fixes moved by (dx, dy) metres, with other fields replaced."""
    out = []
    for f in fixes:
        x, y = _xy(m, f)
        lon, lat = to_lonlat(m.graph.crs, [x + dx], [y + dy])[0]
        out.append(f._replace(lon=float(lon), lat=float(lat), **kw))
    return out


def _xy(m: AsciiMap, f: Fix) -> tuple[float, float]:
    from graph.projection import point_to_xy

    return point_to_xy(m.graph.crs, f.lon, f.lat)


def _run(matcher: OnlineMatcher, fixes: list[Fix]) -> list[SnapResult]:
    st = matcher.new_session()
    return [matcher.update(st, f) for f in fixes]


def test_speed_is_judged_over_a_second_at_any_fix_rate() -> None:
    """A position that catches up with its fix by 10 m in one step: in a step of 1 s a plausible
    speed, and in a step of 0.1 s (10 Hz) no less plausible, for the same motion over a second
    (the transition's speed penalty once held a vehicle behind a node for 35 s at 10 Hz)."""
    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.road import RoadModel
    from mapmatch.online.state import FixBias, Step

    m = parse_ascii_map(TURN, scale=10)
    road = RoadModel(m.graph)

    def step(dt: float) -> Step:
        nan = float("nan")
        return Step(
            time=0.0,
            x=0.0,
            y=0.0,
            sigma=5.0,
            heading=nan,
            kappa=0.0,
            travelled=10.0 * dt,
            odo=0.0,
            odo_known=True,
            dt=dt,
            gps=True,
            weight=1.0,
            stopped=False,
            r_a=10.0,
            dr=0.0,
            bias=FixBias(),
            odo_sigma=0.01,
        )

    cfg = DEFAULT_CONFIG
    one = road.transition(11.0, step(1.0), cfg)
    tenth = road.transition(11.0, step(0.1), cfg)
    assert one == pytest.approx(-1.0 / cfg.model.beta, abs=0.01)
    assert tenth == pytest.approx(-10.0 / cfg.model.beta, abs=0.01)  # the distance, no speed term
    # a real impossibility is still one: 200 m where the odometer drove 1 m
    assert road.transition(200.0, step(0.1), cfg) < -30.0


BESIDE = """
a-------------b------------------------------------c
               \\
                f----------------------------------d
"""


def _outage_beside(m: AsciiMap) -> tuple[list[Fix], int]:
    """a -> b -> f -> d at 10 m/s with GPS lost 10 s before b for 35 s. The dead reckoning
    drifts north (4 m/s) onto b-c, 40 m north of f-d, heading east (the fused heading smooths the
    short jog b-f away): the matcher follows b-c. The fusion filter then blends the offset out
    slowly: the first fix back keeps 80 % of it (8 m from b-c), each next one half the one
    before. Returns the fixes and the index of the first fix back."""
    truth = drive(m, "abfd", DriveSpec(speed=10, sigma=3.0))
    bx = m.xy("b")[0]
    gap = m.xy("b")[1] - m.xy("f")[1]
    lost = next(i for i, f in enumerate(truth) if _xy(m, f)[0] > bx - 100.0)
    back = lost + 35
    out: list[Fix] = []
    for i, f in enumerate(truth):
        if lost <= i < back:
            dy = min(4.0 * (i - lost + 1), gap)
            out += _shifted(m, [f], 0.0, dy, gps_valid=False, pos_sigma=float("nan"), heading=90.0)
        elif i >= back:
            out += _shifted(m, [f], 0.0, 0.8 * gap * 0.5 ** (i - back))
        else:
            out.append(f)
    return out, back


def test_outage_that_ends_beside_a_parallel_road_is_decided_by_the_returning_gps() -> None:
    """Dead reckoning put the vehicle on b-c, 40 m beside the road it drives (f-d). The first
    fix back lies 8 m from b-c (nothing to search for yet), the next ones come ever closer to
    f-d, still within the drift's σ of b-c: the returning GPS decides within 4 s, not once the
    drift has decayed (8 s and more)."""
    m = parse_ascii_map(BESIDE, scale=10)
    fixes, back = _outage_beside(m)
    res = _run(OnlineMatcher(m.graph), fixes)
    assert res[back - 1].edge == m.edge("b", "c")  # the dead reckoning's road
    fd = m.edge("f", "d")
    assert all(r.edge == fd for r in res[back + 4 :]), [r.edge for r in res[back:]]


CROSSING = """
        n
        |
        |
a-------b-------c
        |
        |
        s
"""


def _up_to_b(m: AsciiMap, *, dt: float, before: float) -> tuple[Any, Any, list[Fix]]:
    """The crossing map's b, the unit vector from a to b, and a drive from a at 5 m/s (one fix
    every ``dt`` s) up to ``before`` metres short of b."""
    import numpy as np

    a, b = m.xy("a"), m.xy("b")
    east = (b - a) / np.linalg.norm(b - a)
    fixes = drive(m, "ab", DriveSpec(speed=5, dt=dt))
    return b, east, [f for f in fixes if np.dot(b - np.array(_xy(m, f)), east) > before]


def test_stopped_vehicle_stays_stopped_through_odometer_noise_at_10_hz() -> None:
    """A vehicle stops 1 m before the crossing b and stands there 30 s while its fixes drift
    15 m up the side road b-n (on track 84 of the real drives a parked vehicle's fixes did).
    At 10 Hz its odometer's noise of a few centimetres per fix reads as walking pace over
    0.1 s: judged over ``stop_time`` the vehicle stays stopped, before b, as it does at 1 Hz."""
    import numpy as np

    from mapmatch.config import DEFAULT_CONFIG

    #           n
    #           |   fixes drift up here while the vehicle stands at o
    #   a------ob-------c
    #           s
    m = parse_ascii_map(CROSSING, scale=10)
    a, b, n = m.xy("a"), m.xy("b"), m.xy("n")
    east = (b - a) / np.linalg.norm(b - a)
    north = (n - b) / np.linalg.norm(n - b)
    moving = [
        f for f in drive(m, "ab", DriveSpec(speed=5, dt=0.1)) if np.dot(b - np.array(_xy(m, f)), east) > 1.0
    ]
    t = moving[-1].time
    stop = b - 1.0 * east
    rng = np.random.default_rng(1)
    noise = np.maximum(rng.normal(0.0, 0.02, 300), 0.0)  # metres per fix, as odometers read
    standing = []
    for i in range(300):
        xy = stop + min(1.0, i / 30.0) * 15.0 * north
        lon, lat = to_lonlat(m.graph.crs, [xy[0]], [xy[1]])[0]
        d = float(noise[i])
        standing.append(
            Fix(time=t + 0.1 * (i + 1), lat=float(lat), lon=float(lon), heading=90.0, speed=10.0 * d,
                distance=d, gps_valid=True)
        )  # fmt: skip
    stop_speed = DEFAULT_CONFIG.online.stop.stop_speed
    assert (noise > 0.1 * stop_speed).any()  # some fixes alone read as moving
    ab = m.edge("a", "b")
    res = _run(OnlineMatcher(m.graph), moving + standing)
    assert {r.edge for r in res[-300:]} == {ab}
    # judged per fix (the old rule: a stop_time of one fix interval) it moves up b-n
    per_fix = _run(OnlineMatcher(m.graph, config=DEFAULT_CONFIG.replace(stop_time=0.1)), moving + standing)
    assert per_fix[-1].edge == m.edge("b", "n")
    # at 1 Hz the same stop is one either way
    slow = moving[::10] + standing[9::10]
    slow = [f._replace(distance=0.0, speed=0.0) if f in standing else f for f in slow]
    assert {r.edge for r in _run(OnlineMatcher(m.graph), slow)[-30:]} == {ab}


def test_fix_beside_a_looping_ramp_is_placed_on_the_part_reached(tmp_path: Path) -> None:
    """A ramp leaves the road at b, loops round and comes back 6 m beside its own start. Fixes
    4.5 m off its start lie nearer its far end (1.5 m), which the vehicle cannot have reached
    since the last fix: the position stays on the part of the ramp reached (on track 56 of the
    real drives a 10 Hz position once jumped 326 m ahead along a looping edge)."""
    import json

    from graph.build import build_map

    #   a---------------------b--------+      (the ramp: east, south, west, north, west)
    #                  c------------+  |
    #                               +--+
    crs = "EPSG:32635"
    x0, y0 = 385_000.0, 6_672_000.0
    road = [(0.0, 0.0), (400.0, 0.0)]
    ramp = [(400.0, 0.0), (500.0, 0.0), (500.0, -50.0), (440.0, -50.0), (440.0, -6.0), (300.0, -6.0)]

    def lonlat(pts: list[tuple[float, float]]) -> list[list[float]]:
        ll = to_lonlat(crs, [x0 + x for x, _ in pts], [y0 + y for _, y in pts])
        return [[float(a), float(b)] for a, b in ll]

    feats = [
        {
            "type": "Feature",
            "properties": {"id": i + 1},
            "geometry": {"type": "LineString", "coordinates": lonlat(p)},
        }
        for i, p in enumerate((road, ramp))
    ]
    src = tmp_path / "ramp.geojson"
    src.write_text(json.dumps({"type": "FeatureCollection", "features": feats}), encoding="utf-8")
    graph = build_map(src)
    matcher = OnlineMatcher(graph)
    fixes, truth = [], []
    for i in range(470):  # 10 Hz at 10 m/s: along the road and 70 m into the ramp
        x = 1.0 * i
        y = -4.5 if 410.0 <= x <= 490.0 else 0.0
        lon, lat = lonlat([(x, y)])[0]
        fixes.append(
            Fix(time=0.1 * i, lat=lat, lon=lon, heading=90.0, speed=10.0, distance=1.0 if i else math.nan,
                gps_valid=True)
        )  # fmt: skip
        truth.append(x)
    res = _run(matcher, fixes)
    # b joins two roads only: the map has one edge a-b-ramp (a loop of 794 m)
    assert graph.n_edges == 2 and all(r.edge == res[0].edge for r in res)
    assert max(abs(r.offset - x) for r, x in zip(res, truth, strict=True)) < 10.0


def test_parked_vehicle_in_an_outage_does_not_creep_forward_at_10_hz() -> None:
    """A vehicle stops 3 m before the crossing b in a GPS outage and stands there 2 min, its
    dead-reckoned fixes still. Its odometer's noise, never negative, sums at 10 Hz to ~5 m a
    minute: below ``zero_speed`` the distance counts as zero and the vehicle stays where it
    stopped; without the rule (``zero_speed`` 0) it creeps up to b and on across it (the
    odometer's distance carries a stopped vehicle across a node)."""
    import numpy as np

    from mapmatch.config import DEFAULT_CONFIG

    #   a-----o-b-------c     o: the vehicle stands here, 3 m before b, without GPS
    m = parse_ascii_map(CROSSING, scale=10)
    b, east, moving = _up_to_b(m, dt=0.1, before=3.0)
    t = moving[-1].time
    stop = b - 3.0 * east
    rng = np.random.default_rng(2)
    noise = np.maximum(rng.normal(0.0, 0.02, 1200), 0.0)  # metres per fix, as odometers read
    lon, lat = to_lonlat(m.graph.crs, [stop[0]], [stop[1]])[0]
    standing = [
        Fix(time=t + 0.1 * (i + 1), lat=float(lat), lon=float(lon), heading=90.0, speed=10.0 * float(d),
            distance=float(d), gps_valid=False)
        for i, d in enumerate(noise)
    ]  # fmt: skip
    assert noise.sum() > 6.0  # the noise alone would carry it past b
    ab = m.edge("a", "b")
    res = _run(OnlineMatcher(m.graph), moving + standing)
    assert {r.edge for r in res[-1200:]} == {ab}
    assert max(r.offset for r in res[-1200:]) < 78.0  # stands ~3 m before b (ab is 80 m)
    off = _run(OnlineMatcher(m.graph, config=DEFAULT_CONFIG.replace(zero_speed=0.0)), moving + standing)
    assert off[-1].edge != ab or off[-1].offset > 79.5  # crept up to b, or past it


def test_vehicle_creeping_across_a_node_in_an_outage_is_carried_by_the_odometer() -> None:
    """A vehicle stops 2 m before the crossing b in a GPS outage, then creeps on at 0.3 m/s
    (below ``stop_speed``: stopped) for 30 s, 7 m past b, its dead-reckoned fixes following.
    The stop hold keeps the fixes' noise from moving a stopped vehicle on across a node, not
    the distance its odometer gives: it ends on bc."""

    #   a-------o-b-->--c     o: stops 2 m before b, then creeps 9 m on, without GPS
    m = parse_ascii_map(CROSSING, scale=10)
    b, east, moving = _up_to_b(m, dt=1.0, before=2.0)
    t = moving[-1].time
    creeping = []
    for i in range(30):
        at = b + (-2.0 + 0.3 * (i + 1)) * east
        lon, lat = to_lonlat(m.graph.crs, [at[0]], [at[1]])[0]
        creeping.append(
            Fix(time=t + i + 1.0, lat=float(lat), lon=float(lon), heading=90.0, speed=0.3,
                distance=0.3, gps_valid=False)
        )  # fmt: skip
    res = _run(OnlineMatcher(m.graph), moving + creeping)
    bc = m.edge("b", "c")
    assert res[-1].edge == bc
    assert 2.0 < res[-1].offset < 9.0


def _east_step(x: float, y: float, *, travelled: float, dt: float, weight: float, bias: FixBias) -> Step:
    """A GPS-aided step heading east (σ 8 m, heading σ 10°) with the odometer known."""
    from mapmatch.online.state import Step

    return Step(
        time=1.0,
        x=float(x),
        y=float(y),
        sigma=8.0,
        heading=90.0,
        kappa=1.0 / math.radians(10.0) ** 2,
        travelled=travelled,
        odo=100.0,
        odo_known=True,
        dt=dt,
        gps=True,
        weight=weight,
        stopped=False,
        r_a=16.0,
        dr=0.0,
        bias=bias,
        odo_sigma=0.01,
        fix_sigma=8.0,
    )


def test_fix_past_a_crossing_is_placed_on_the_next_edge_at_10_hz_as_at_1_hz() -> None:
    """The vehicle's position is at the crossing b, its fix 2 to 4.5 m past it on b-c. At 10 Hz
    the odometer moved 0.7 m since the last fix: the position goes on to b-c at the fix's
    projection, as at 1 Hz, where the step from 7 m before b covers the 9 m driven."""
    import numpy as np

    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.placement import place_all
    from mapmatch.online.road import RoadModel
    from mapmatch.online.state import FixBias, Hypothesis

    m = parse_ascii_map(CROSSING, scale=10)
    road = RoadModel(m.graph)
    ab, bc = m.edge("a", "b"), m.edge("b", "c")
    le = float(road.elen[ab])

    def place(before: float, past: float, travelled: float, dt: float) -> tuple[int, float]:
        px, py, brg = road.locate(ab, le - before)
        h = Hypothesis([ab, bc], 0, le - before, le - before, 0.0, [0.0], 0.0, px, py, brg)
        x, y = m.xy("b") + np.array([past, 0.0])
        step = _east_step(x, y, travelled=travelled, dt=dt, weight=1.0, bias=FixBias())
        place_all(road, [h], step, DEFAULT_CONFIG)
        return h.edges[h.k], h.off

    for past in (2.0, 3.5, 4.5):
        edge, off = place(0.0, past, 0.7, 0.1)
        assert edge == bc and off == pytest.approx(past, abs=0.01)
    edge, off = place(7.0, 2.0, 9.0, 1.0)  # 1 Hz
    assert edge == bc and off == pytest.approx(2.0, abs=0.01)


def test_step_is_judged_between_corrected_places_at_10_hz() -> None:
    """The fixes lie 3 m ahead of the vehicle along a-b-c (a learnt bias along the road), so
    the vehicle's place is 3 m behind each fix's projection: 1 m before the crossing b. The next
    10 Hz fix, 0.7 m on, lies 2.7 m past b. Judged from that place to the candidates' corrected
    places, the point on b-c (corrected 0.3 m before b) is the 0.7 m the odometer drove and
    the place moves on by that, not back."""
    import numpy as np

    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.placement import place_all
    from mapmatch.online.road import RoadModel
    from mapmatch.online.state import FixBias, Hypothesis

    m = parse_ascii_map(CROSSING, scale=10)
    road = RoadModel(m.graph)
    ab, bc = m.edge("a", "b"), m.edge("b", "c")
    le = float(road.elen[ab])

    def place() -> float:
        px, py, brg = road.locate(ab, le - 1.0)
        h = Hypothesis([ab, bc], 0, le - 1.0, le - 1.0, 0.0, [0.0], 0.0, px, py, brg)
        x, y = m.xy("b") + np.array([2.7, 0.0])
        bias = FixBias(3.0, 0.0, 1.0, 0.0, 1.0)  # 3 m east: ahead along a-b-c
        step = _east_step(x, y, travelled=0.7, dt=0.1, weight=0.1, bias=bias)
        place_all(road, [h], step, DEFAULT_CONFIG)
        return h.s

    assert place() == pytest.approx(le - 0.3, abs=0.01)  # on by the 0.7 m driven


def test_twin_hypothesis_on_the_same_path_is_merged_at_10_hz() -> None:
    """A second hypothesis on the vehicle's own path, 3 m ahead of it and 9 log units less
    probable (as a road that joined the filter, or a branch kept past a commit, comes to be):
    the GPS-aided fix places both on the same road, so the pair never separates and nothing
    prunes the twin. On REAL track 42 at 10 Hz most fixes carried one: reported ambiguous for
    an hour, and the fix's residuals and bias, learnt only from a single hypothesis, never
    learnt. The twin merges into the vehicle's hypothesis at once (their probabilities added);
    without GPS only exact twins do (the dead-reckoned places are each its own)."""
    import copy

    from mapmatch.types import State

    m = parse_ascii_map("\na--------------------b\n", scale=10)
    fixes = drive(m, "ab", DriveSpec(speed=10, dt=0.1, noise=1.0, seed=3))
    matcher = OnlineMatcher(m.graph)
    st = matcher.new_session()
    before = [matcher.update(st, f) for f in fixes[:50]]
    assert before[-1].state == State.ON_ROAD and len(st.hyps) == 1
    twin = copy.deepcopy(st.hyps[0])
    twin.s += 3.0
    twin.off += 3.0
    twin.logp = -9.0
    st.hyps.append(twin)
    res2 = 25.0  # the residual's prior (m²): learnt down only while on one hypothesis
    assert st.res_pos2 < res2
    learnt = st.res_pos2
    after = [matcher.update(st, f) for f in fixes[50:]]
    assert all(r.state == State.ON_ROAD for r in after) and len(st.hyps) == 1
    assert st.res_pos2 < learnt  # the learning goes on (σ of the fixes: 1.4 m)
    assert st.hyps[0].logp == pytest.approx(0.0)
    # merge_identical itself: probabilities add; without GPS, a twin elsewhere stays apart
    from mapmatch.online.hypotheses import merge_identical

    a, b, c = copy.deepcopy(st.hyps[0]), copy.deepcopy(st.hyps[0]), copy.deepcopy(st.hyps[0])
    b.logp = -1.0
    c.s += 3.0
    out = merge_identical([a, b, c])
    assert len(out) == 2 and out[0].logp == pytest.approx(math.log1p(math.exp(-1.0)))
    assert len(merge_identical([a, c], by_path=True)) == 1
