"""Property tests of the online matcher: only ValidationError escapes; snaps lie on roads."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from graph.ascii import parse_ascii_map
from graph.index import project_to_edge
from graph.projection import point_to_xy, to_lonlat
from mapmatch.errors import ValidationError
from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix

MAP = parse_ascii_map(
    """
    a-----b-----c
    |      \\    |
    |       \\   |
    d-->--e--f--h
          |
          g
    """,
    scale=10,
    restrictions=[("a", "b", "f", "no")],
)
MATCHER = OnlineMatcher(MAP.graph)
LON0, LAT0 = to_lonlat(MAP.graph.crs, [MAP.xy("e")[0]], [MAP.xy("e")[1]])[0]

anyfloat = st.floats(allow_nan=True, allow_infinity=True)
near = st.floats(-0.002, 0.002)
opt = st.one_of(st.just(math.nan), anyfloat, st.floats(0, 50))


@st.composite
def fixes(draw: st.DrawFn) -> list[Fix]:
    n = draw(st.integers(1, 25))
    t = draw(st.floats(-1e9, 1e9))
    out = []
    for _ in range(n):
        wild = draw(st.integers(0, 9)) == 0
        t = draw(anyfloat) if wild else t + draw(st.floats(-0.5, 5.0))
        lat = draw(anyfloat) if draw(st.integers(0, 9)) == 0 else LAT0 + draw(near)
        lon = draw(anyfloat) if draw(st.integers(0, 9)) == 0 else LON0 + draw(near) * 2
        out.append(
            Fix(
                time=t,
                lat=lat,
                lon=lon,
                heading=draw(st.one_of(st.just(math.nan), st.floats(-10, 370), anyfloat)),
                pos_sigma=draw(opt),
                heading_sigma=draw(opt),
                speed=draw(opt),
                distance=draw(opt),
                gps_valid=draw(st.sampled_from([None, True, False])),
                pos_cov=draw(st.one_of(st.none(), st.tuples(opt, st.floats(-5, 5), opt))),
            )
        )
    return out


@pytest.mark.slow  # 300 generated fix sequences
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fixes())
def test_only_validation_errors_and_snaps_on_the_road(seq: list[Fix]) -> None:
    state = MATCHER.new_session()
    for f in seq:
        before = state.to_bytes()
        try:
            r = MATCHER.update(state, f)
        except ValidationError:
            assert state.to_bytes() == before
            continue
        if r.edge < 0:
            assert math.isnan(r.lat) and math.isnan(r.offset)
            continue
        g = MAP.graph
        assert 0 <= r.edge < g.n_edges
        assert 0.0 <= r.offset <= g.edge_len[r.edge] + 1e-9
        x, y = point_to_xy(g.crs, r.lon, r.lat)
        _, dist, _, _ = project_to_edge(g, r.edge, x, y)
        assert dist < 1e-6
        assert (r.u, r.v) == (int(g.node_id[g.edge_u[r.edge]]), int(g.node_id[g.edge_v[r.edge]]))
        if r.candidates:
            assert math.isclose(sum(c.probability for c in r.candidates), 1.0, rel_tol=1e-9)
        # the state always survives a round trip
        assert type(state).from_bytes(state.to_bytes()).to_bytes() == state.to_bytes()


def test_fixes_a_hair_apart_in_time_leave_a_session_that_can_be_exported() -> None:
    # found by the property above: 1 m in 2.4e-109 s made a speed no session import accepts
    state = MATCHER.new_session()
    for t in (0.0, 2.410831004492582e-109, 1e-9):
        MATCHER.update(state, Fix(time=t, lat=LAT0, lon=LON0, distance=1.0))
        assert math.isnan(state.speed) or state.speed <= 1_000.0
        assert type(state).from_bytes(state.to_bytes()).to_bytes() == state.to_bytes()


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-80, 80), st.floats(-80, 80)), min_size=2, max_size=60), st.integers(0, 3)
)
def test_random_walks_near_the_map_snap_onto_roads(steps: list[tuple[float, float]], seed: int) -> None:
    rng = np.random.default_rng(seed)
    state = MATCHER.new_session()
    x0, y0 = MAP.xy("b")
    for i, (dx, dy) in enumerate(steps):
        x, y = x0 + dx + rng.normal(0, 3), y0 + dy
        lon, lat = to_lonlat(MAP.graph.crs, [x], [y])[0]
        r = MATCHER.update(state, Fix(time=float(i), lat=lat, lon=lon, heading=float(rng.uniform(0, 360))))
        if r.edge >= 0:
            px, py = point_to_xy(MAP.graph.crs, r.lon, r.lat)
            assert project_to_edge(MAP.graph, r.edge, px, py)[1] < 1e-6
