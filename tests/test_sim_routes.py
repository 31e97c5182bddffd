"""Simulator routes and speed profile on ASCII maps."""

from __future__ import annotations

import numpy as np
import pytest

from graph.ascii import parse_ascii_map
from mapmatch.sim.profile import drive_profile
from mapmatch.sim.routes import (
    RouteError,
    check_route,
    random_route,
    route_from_edges,
    route_from_geometry,
    shortest_path,
)

GRID = """
a-------b-------c-------d
|       |       |       |
e------>f-------g-------h
|       |       |       |
i-------j-------k-------l
"""


@pytest.fixture(scope="module")
def grid():  # type: ignore[no-untyped-def]
    # no left turn from b->f into f->e... e->f is one-way anyway; forbid f->g->c
    return parse_ascii_map(GRID, scale=20.0, restrictions=[("f", "g", "c", "no")])


def test_route_from_edges_geometry_and_nodes(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    edges = [grid.edge("a", "b"), grid.edge("b", "c"), grid.edge("c", "g")]
    r = route_from_edges(g, edges, start_offset=40.0, end_offset=10.0)
    assert r.length == pytest.approx(160 - 40 + 160 + 10)
    assert [grid.nodes["b"], grid.nodes["c"]] == r.nodes(g).tolist()
    assert r.node_distance().tolist() == pytest.approx([120.0, 280.0])
    e, off = r.locate([0.0, 119.0, 121.0, 290.0])
    assert e.tolist() == [edges[0], edges[0], edges[1], edges[2]]
    assert off.tolist() == pytest.approx([40.0, 159.0, 1.0, 10.0])
    np.testing.assert_allclose(r.xy[0], grid.xy("a") + [40.0, 0.0])
    np.testing.assert_allclose(r.xy[-1], grid.xy("c") + [0.0, -10.0])


def test_illegal_routes_are_refused(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    with pytest.raises(RouteError, match="do not join"):
        check_route(g, [grid.edge("a", "b"), grid.edge("c", "d")])
    with pytest.raises(RouteError, match="U-turn or restricted"):
        check_route(g, [grid.edge("a", "b"), grid.edge("b", "a")])
    with pytest.raises(RouteError, match="U-turn or restricted"):
        check_route(g, [grid.edge("f", "g"), grid.edge("g", "c")])
    with pytest.raises(KeyError):
        grid.edge("f", "e")  # one-way e->f


def test_shortest_path_respects_restrictions(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    # from e->f to c: f->g->c is forbidden, so go f->b->c (same length) and never via g->c
    p = shortest_path(g, grid.edge("e", "f"), grid.nodes["c"])
    assert p is not None
    check_route(g, [grid.edge("e", "f"), *p])
    assert grid.edge("g", "c") not in p
    assert shortest_path(g, grid.edge("a", "b"), grid.nodes["b"]) == []


def test_random_route_is_legal_and_long_enough(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    for seed in range(5):
        r = random_route(g, length_m=3000.0, rng=np.random.default_rng(seed), leg_min_m=50.0, leg_max_m=400.0)
        assert r.length >= 3000.0
        check_route(g, r.edges.tolist())  # one-ways, restriction, no U-turn anywhere
        assert not np.any(g.edge_reverse[r.edges[:-1]] == r.edges[1:])


def test_route_from_geometry_recovers_the_edges(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    edges = [grid.edge("i", "e"), grid.edge("e", "f"), grid.edge("f", "b"), grid.edge("b", "c")]
    r = route_from_edges(g, edges, start_offset=5.0, end_offset=100.0)
    noisy = r.xy + np.random.default_rng(0).normal(0.0, 1.0, r.xy.shape)
    back = route_from_geometry(g, noisy)
    assert back.edges.tolist() == edges
    assert back.length == pytest.approx(r.length, abs=8.0)


def test_speed_profile_slows_at_turns_and_stops_at_ends(grid) -> None:  # type: ignore[no-untyped-def]
    g = grid.graph
    # a-b-c-d straight then d-h-l: a right-angle turn at d
    edges = [grid.edge(*p) for p in ("ab", "bc", "cd", "dh", "hl")]
    r = route_from_edges(g, edges)
    from mapmatch.sim.profile import ProfileConfig

    cfg = ProfileConfig(stop_probability=0.0, start_wait=2.0)
    tr = drive_profile(g, r, rng=np.random.default_rng(0), rate_hz=100.0, config=cfg)
    assert tr.speed[:150].max() < 0.5  # waiting at the start
    assert tr.speed[-1] < 1.5  # braking to a stop in the last metre
    assert tr.dist[-1] == pytest.approx(r.length, rel=0.03)
    corner = np.argmin(np.hypot(tr.x - grid.xy("d")[0], tr.y - grid.xy("d")[1]))
    straight = np.argmin(np.abs(tr.s - 240.0))  # middle of b-c
    assert tr.speed[corner] < 6.0 < tr.speed[straight]
    # the heading turns from east (90) to south (180) smoothly
    assert np.degrees(tr.psi[straight]) % 360 == pytest.approx(90.0, abs=2.0)
    assert np.degrees(tr.psi[-200]) % 360 == pytest.approx(180.0, abs=2.0)
    assert np.abs(np.degrees(tr.yaw_rate)).max() < 60.0


@pytest.mark.slow
def test_foreign_truth_geometry_becomes_a_legal_route(kubicka_dir) -> None:  # type: ignore[no-untyped-def]
    import json

    from graph.build import build_map
    from mapmatch.sim.drive import read_route

    track = kubicka_dir / "00000000"
    g = build_map(track / "roads.geojson")
    r = read_route(g, track / "truth.geojson")
    check_route(g, r.edges.tolist())
    meta = json.loads((track / "meta.json").read_text())
    assert r.length == pytest.approx(meta["route_length_m"], rel=0.01)
