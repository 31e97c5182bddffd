"""The compiled kernels agree with their reference: grid candidate search vs EdgeIndex.query,
the compiled transition vs the shared model's vectorised one, the routing moves vs the old rule."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from graph.ascii import parse_ascii_map
from graph.index import EdgeIndex
from graph.road_graph import RESTRICTION_ONLY, Edges, Nodes, RoadGraph
from mapmatch import model
from mapmatch.batch import BATCH_CONFIG
from mapmatch.gridindex import GridIndex

PLAIN = BATCH_CONFIG.replace(motion_heading_sigma=0.0, spike_speed=0.0)
"""The batch rules on the fixes (direction of travel, jumps) switched off."""

DRAWING = """
a-----b-----c---------d
|    / \\    |         |
|   /   \\   |         |
e--f-----g--h>>>>>>>>>i
   |        |
   j--------k
"""


@pytest.mark.parametrize("dense", [True, False])
@pytest.mark.parametrize(("radius", "k"), [(15.0, 2), (50.0, 8), (120.0, None)])
def test_grid_index_equals_edge_index(
    radius: float, k: int | None, dense: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mapmatch.gridindex as gridindex

    if not dense:  # the binary-search layout used for very large maps
        monkeypatch.setattr(gridindex, "DENSE_MAX_CELLS", 0)
    m = parse_ascii_map(DRAWING, scale=7)
    ix = EdgeIndex(m.graph)
    grid = GridIndex(ix, cell=40.0)
    assert (len(grid.cell_ptr) > 0) == dense
    rng = np.random.default_rng(3)
    lo, hi = m.graph.node_xy.min(axis=0) - 80, m.graph.node_xy.max(axis=0) + 80
    pts = lo + rng.random((600, 2)) * (hi - lo)
    pts[::7] = m.graph.node_xy[rng.integers(0, m.graph.n_nodes, len(pts[::7]))]  # exact ties at nodes
    pts[5] = np.nan
    for _ in range(2):  # a second query on the same index gives the same answer
        a, b = ix.query(pts[np.isfinite(pts).all(axis=1)], radius, k=k), grid.query(pts, radius, k=k)
        keep = np.flatnonzero(np.isfinite(pts).all(axis=1))
        np.testing.assert_array_equal(keep[a.point], b.point)
        np.testing.assert_array_equal(a.edge, b.edge)
        np.testing.assert_allclose(a.dist, b.dist, atol=1e-9)
        np.testing.assert_allclose(a.offset, b.offset, atol=1e-6)
        np.testing.assert_allclose(a.xy, b.xy, atol=1e-9)
    assert len(b) > 100


def test_compiled_transition_equals_the_shared_model() -> None:
    rng = np.random.default_rng(5)
    route = np.r_[rng.random(200) * 500, np.inf, 0.0]
    trav = rng.random(len(route)) * 400
    dt = np.r_[rng.random(len(route) - 3) * 30, np.nan, 0.0, 2.0]
    params = model.transition_params(BATCH_CONFIG)
    for uturn in (False, True):
        ref = model.transition_logp(route, trav, dt, BATCH_CONFIG, uturn=uturn)
        got = [
            model.transition_logp_one(r, d, t, params, uturn, params[0])
            for r, d, t in zip(route, trav, dt, strict=True)
        ]
        np.testing.assert_allclose(got, ref)


def test_ubodt_gives_the_same_matches_as_the_search() -> None:
    from mapmatch.batch import BatchMatcher
    from mapmatch.route_table import Ubodt
    from mapmatch.types import Track

    m = parse_ascii_map(DRAWING, scale=7, restrictions=[("b", "c", "h", "no")])
    table = Ubodt.build(m.graph, 400.0)
    assert table.nbytes > 0 and len(table.ptr) == m.graph.n_edges + 1
    plain, fast = BatchMatcher(m.graph), BatchMatcher(m.graph, ubodt=table)
    rng = np.random.default_rng(11)
    for _ in range(10):  # random walks through the map, noisy fixes
        node = int(rng.integers(m.graph.n_nodes))
        xy = [m.graph.node_xy[node]]
        for _ in range(6):
            out = m.graph.out_of(node)
            if not len(out):
                break
            e = int(rng.choice(out))
            node = int(m.graph.edge_v[e])
            xy.append(m.graph.node_xy[node])
        pts = np.array([a + (b - a) * f for a, b in itertools.pairwise(xy) for f in (0.3, 0.7)])
        if not len(pts):
            continue
        pts = pts + rng.normal(0, 3, pts.shape)
        ll = np.array([m.lonlat(x, y) for x, y in pts])
        t = Track("w", np.arange(len(pts)) * 3.0, ll[:, 1], ll[:, 0])
        a, b = plain.match(t), fast.match(t)
        assert a.routes == b.routes and a.splits == b.splits
        assert [p.edge for p in a.points] == [p.edge for p in b.points]


def test_a_route_table_look_up_finds_what_a_plain_search_of_its_row_finds() -> None:
    """The look-up searches the rows' block heads, then one block: on rows of every length and
    place against the block boundaries, each target is found where a plain search finds it."""
    from mapmatch.route_table import Ubodt, path_place
    from mapmatch.routing import TABLE_BLOCK, RouteTable

    def place(table: RouteTable, e: int, f: int) -> int:
        return int(path_place(table, e, f)[0])

    rng = np.random.default_rng(5)
    b = TABLE_BLOCK
    lengths = [0, 1, 2, b - 1, b, b + 1, 3, 2 * b, 5 * b + 7, 0, 40]
    rows = [np.sort(rng.choice(500, size=n, replace=False)).astype(np.int32) for n in lengths]
    ptr = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    tgt = np.concatenate(rows).astype(np.int32)
    n = len(tgt)
    table = RouteTable(
        1.0, ptr, tgt, np.ascontiguousarray(tgt[::TABLE_BLOCK]), np.zeros(n), np.full(n, -1, np.int32)
    )
    for e, row in enumerate(rows):
        for f in range(-1, 501):
            k = int(np.searchsorted(row, f))
            want = int(ptr[e]) + k if k < len(row) and row[k] == f else -1
            assert place(table, e, f) == want
    m = parse_ascii_map(DRAWING, scale=7)  # and a built table's rows, through its own head
    ub = Ubodt.build(m.graph, 400.0)
    real = ub.table
    assert np.array_equal(real.head, ub.tgt[::TABLE_BLOCK])
    for e in range(m.graph.n_edges):
        row = ub.tgt[ub.ptr[e] : ub.ptr[e + 1]]
        for f in range(m.graph.n_edges):
            k = int(np.searchsorted(row, f))
            want = int(ub.ptr[e]) + k if k < len(row) and row[k] == f else -1
            assert place(real, e, f) == want


def test_a_route_table_entry_reads_back_the_route_its_distance_is_of(tmp_path) -> None:
    """Each entry's path, read back through ``pred_pos`` hop by hop, costs the entry's distance
    (lengths between plus each move's turn cost), with a turn restriction and turn costs; a saved
    table maps back the same, and a folder of another layout version is refused by name."""
    import json

    from mapmatch.route_table import TABLE_FILE_VERSION, Ubodt, path_into, path_place
    from mapmatch.routing import route_graph

    m = parse_ascii_map(DRAWING, scale=7, restrictions=[("b", "c", "h", "no")])
    g = m.graph
    ub = Ubodt.build(g, 400.0, turn_cost=20.0)
    rg = route_graph(g, turn_cost=20.0)
    move = {
        (e, int(rg.move_to[k])): float(rg.move_cost[k])
        for e in range(g.n_edges)
        for k in range(rg.move_ptr[e], rg.move_ptr[e + 1])
    }
    out = np.zeros(g.n_edges + 2, dtype=np.int64)
    checked = 0
    for e in range(g.n_edges):
        for k in range(ub.ptr[e], ub.ptr[e + 1]):
            f = int(ub.tgt[k])
            place, n = path_place(ub.table, e, f)
            assert place == k
            path_into(ub.table, e, place, n, out, 0)
            hops = [e, *(int(x) for x in out[:n]), f]
            turns = sum(move[a, b] for a, b in itertools.pairwise(hops))
            want = sum(g.edge_len[x] for x in hops[1:-1]) + turns
            assert ub.dist[k] == pytest.approx(want, abs=1e-9), (e, f, hops)
            checked += 1
    assert checked == len(ub.tgt) > 2 * g.n_edges
    ub.save(tmp_path / "t")
    back = Ubodt.load(tmp_path / "t")
    for name in ("ptr", "tgt", "dist", "pred_pos"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ub, name))
    meta = json.loads((tmp_path / "t" / "table.json").read_text())
    (tmp_path / "t" / "table.json").write_text(json.dumps({**meta, "version": TABLE_FILE_VERSION - 1}))
    with pytest.raises(ValueError, match=f"route table version {TABLE_FILE_VERSION - 1}"):
        Ubodt.load(tmp_path / "t")


def test_grid_index_with_many_roads_near_one_point() -> None:
    # 150 short one-way spokes around the origin: more roads near a point than the first buffer
    ang = np.linspace(0, 2 * np.pi, 150, endpoint=False)
    inner = np.column_stack([np.cos(ang), np.sin(ang)]) * 5 + [385_000.0, 6_672_000.0]
    outer = np.column_stack([np.cos(ang), np.sin(ang)]) * 30 + [385_000.0, 6_672_000.0]
    g = RoadGraph.from_edges(
        "EPSG:32635", Nodes(np.vstack([inner, outer])), Edges(np.arange(150), np.arange(150) + 150)
    )
    ix = EdgeIndex(g)
    grid = GridIndex(ix, cell=10.0)
    pts = np.array([[385_000.0, 6_672_000.0], [385_003.0, 6_672_001.0], [385_100.0, 6_672_000.0]])
    for _ in range(2):
        a, b = ix.query(pts, 40.0), grid.query(pts, 40.0)
        np.testing.assert_array_equal(a.point, b.point)
        np.testing.assert_array_equal(a.edge, b.edge)
        np.testing.assert_allclose(a.offset, b.offset, atol=1e-6)
    assert np.sum(b.point == 0) == 150


def test_a_diagonal_road_is_listed_only_in_the_cells_it_crosses() -> None:
    # one road at 45 degrees through cell corners, one at a shallow angle: their boxes cover
    # 100 and 40 cells of 10 m, their lines far fewer; fixes all around them (on the lines,
    # at the corners, beside them) still find exactly what the plain index finds
    o = np.array([385_000.0, 6_672_000.0])
    g = RoadGraph.from_edges(
        "EPSG:32635",
        Nodes(np.array([o, o + [100.0, 100.0], o + [0.0, 200.0], o + [100.0, 237.0]])),
        Edges(np.array([0, 2]), np.array([1, 3])),
    )
    ix = EdgeIndex(g)
    grid = GridIndex(ix, cell=10.0)
    boxes = 11 * 11 + 11 * 5  # the cells of each segment's box (edges of cells included)
    assert len(grid.cell_seg) < boxes * 0.45
    rng = np.random.default_rng(5)
    pts = o + rng.random((2000, 2)) * [130.0, 260.0] - 15.0
    pts[:40] = o + np.arange(40)[:, None] * 2.5  # on the diagonal, every fourth one at a corner
    for radius in (0.5, 7.0, 30.0):
        a, b = ix.query(pts, radius), grid.query(pts, radius)
        np.testing.assert_array_equal(a.point, b.point)
        np.testing.assert_array_equal(a.edge, b.edge)
        np.testing.assert_allclose(a.dist, b.dist, atol=1e-9)
        np.testing.assert_allclose(a.offset, b.offset, atol=1e-6)
    on = b.point < 40  # the fixes on the diagonal found it, at no distance
    np.testing.assert_array_equal(b.point[on], np.arange(40))
    assert (b.edge[on] == 0).all() and (b.dist[on] < 1e-9).all()


@pytest.mark.parametrize("with_table", [True, False])
def test_a_route_of_many_more_edges_than_fixes_is_whole(with_table: bool) -> None:
    # a straight road of 79 edges, 10 m each, and two fixes 780 m apart: the route's pieces
    # outgrow their first arrays (sized by the fixes), from the route table or from a search
    from pyproj import Transformer

    from mapmatch.batch import BatchMatcher
    from mapmatch.route_table import Ubodt
    from mapmatch.types import Track

    x0, y0 = 385_000.0, 6_672_000.0
    g = RoadGraph.from_edges(
        "EPSG:32635",
        Nodes(np.column_stack([x0 + 10.0 * np.arange(80), np.full(80, y0)])),
        Edges(np.arange(79), np.arange(1, 80)),
    )
    matcher = BatchMatcher(g, ubodt=Ubodt.build(g, 2000.0) if with_table else None)
    to_lonlat = Transformer.from_crs(g.crs, 4326, always_xy=True)
    lon, lat = to_lonlat.transform([x0 + 5, x0 + 785], [y0 + 1, y0 + 1])
    res = matcher.match(Track("long", np.array([0.0, 60.0]), np.asarray(lat), np.asarray(lon)))
    assert res.splits == [] and len(res.routes) == 1
    route = list(res.routes[0])
    assert len(route) == 79
    assert int(g.edge_u[route[0]]) == 0 and int(g.edge_v[route[-1]]) == 79
    assert all(int(g.edge_v[a]) == int(g.edge_u[b]) for a, b in itertools.pairwise(route))


def _old_routing_rule(g: RoadGraph, e: int, f: int) -> bool:
    """The rule the compiled routing applied before the legal-moves table (#13), written out:
    the reverse twin only at a dead end, then the from-edge's turn restrictions."""
    v = int(g.edge_v[e])
    if f == g.edge_reverse[e] and any(o != f for o in g.out_of(v)):
        return False
    rows = [r for r in g.restrictions.tolist() if r[0] == e]
    only = [r[2] for r in rows if r[3] == RESTRICTION_ONLY]
    banned = [r[2] for r in rows if r[3] != RESTRICTION_ONLY]
    return f not in banned and (not only or f in only)


@pytest.mark.parametrize(
    "restrictions",
    [[], [("b", "c", "h", "no"), ("f", "b", "c", "only"), ("k", "h", "c", "no"), ("j", "f", "e", "only")]],
)
def test_routing_moves_are_the_old_dead_end_rule(restrictions: list[tuple[str, str, str, str]]) -> None:
    from mapmatch.routing import route_graph

    m = parse_ascii_map(DRAWING + "   |\n   l\n", scale=7, restrictions=restrictions)
    g = m.graph
    rg = route_graph(g)
    dead_ends = 0
    for e in range(g.n_edges):
        outs = [int(f) for f in g.out_of(int(g.edge_v[e]))]
        want = [f for f in outs if _old_routing_rule(g, e, f)]  # in the graph's order
        assert rg.move_to[rg.move_ptr[e] : rg.move_ptr[e + 1]].tolist() == want
        dead_ends += outs == [g.edge_reverse[e]]
    # turning back is the only move at the spur's end l and, coming from d, at i (h>i one-way)
    assert dead_ends == 2
    assert len(g.restrictions) == (4 if restrictions else 0)


def test_a_move_costs_its_share_of_the_turn_cost_by_its_angle() -> None:
    from mapmatch.routing import Workspace, _reset, _search, route_graph

    # from ab: straight on to bc, right angles to bd and be, back at the dead end c (cb)
    m = parse_ascii_map(
        """
              d
              |
        a-----b-----c
              |
              e
        """,
        scale=10,
    )
    g = m.graph
    rg = route_graph(g, turn_cost=30.0)

    def cost(e: str, f: str) -> float:
        i = m.edge(*e)
        moves = rg.move_to[rg.move_ptr[i] : rg.move_ptr[i + 1]].tolist()
        return float(rg.move_cost[rg.move_ptr[i] + moves.index(m.edge(*f))])

    assert cost("ab", "bc") == pytest.approx(0.0, abs=1e-9)
    assert cost("ab", "bd") == pytest.approx(15.0) and cost("ab", "be") == pytest.approx(15.0)
    assert cost("bc", "cb") == pytest.approx(30.0)  # turning back at a dead end
    assert not route_graph(g).move_cost.any()  # none by default
    # the search adds them to the metres: from the end of ab, bc starts at 0, bd at 15 (a right
    # angle), cb at 90 (60 m of bc, then turning back at c)
    ws = Workspace.new(g.n_edges)
    nt = _search(m.edge("a", "b"), 0.0, 1e9, -1, rg, ws)
    assert ws.dist[m.edge("b", "c")] == pytest.approx(0.0, abs=1e-9)
    assert ws.dist[m.edge("b", "d")] == pytest.approx(15.0)
    assert ws.dist[m.edge("c", "b")] == pytest.approx(90.0)
    _reset(nt, ws)


def test_compiled_entry_point_sees_the_types_it_was_compiled_for() -> None:
    """The batch kernels are called through their entry points, which do not check types: every
    kind of input (read-only arrays, integer coordinates, lists, headings, σ, odometer, no time)
    must reach each kernel with the types of its first call."""
    import numba

    from mapmatch.batch import BatchMatcher
    from mapmatch.batch.run import CompiledRun
    from mapmatch.types import Track

    m = parse_ascii_map(DRAWING, scale=7)
    matcher = BatchMatcher(m.graph)
    ll = np.array([m.lonlat(*m.xy(c)) for c in "abcd"])
    seen: dict[int, list[tuple[object, ...]]] = {}
    inner = CompiledRun.__call__

    def spy(self, *args):  # type: ignore[no-untyped-def]
        seen.setdefault(id(self), []).append(tuple(numba.typeof(a) for a in args))
        return inner(self, *args)

    frozen = ll.copy()
    frozen.flags.writeable = False
    tracks = [
        Track("plain", np.arange(4.0), ll[:, 1], ll[:, 0]),
        Track("frozen", np.arange(4), frozen[:, 1], frozen[:, 0]),
        Track("strided", np.arange(8.0)[::2], np.repeat(ll[:, 1], 2)[::2], np.repeat(ll[:, 0], 2)[::2]),
        Track("no time", None, ll[:, 1].tolist(), ll[:, 0].tolist()),  # type: ignore[arg-type]
        Track("odometer", np.arange(4.0), ll[:, 1], ll[:, 0], distance=np.full(4, 10.0)),
        Track(
            "rich",
            np.arange(4.0),
            ll[:, 1],
            ll[:, 0],
            heading=np.array([90.0, 90, 180, 180]),
            speed=np.full(4, 5.0),
            pos_sigma=np.full(4, 4.0),
            distance=np.full(4, 10.0),
        ),
        Track("sigma", np.arange(4), frozen[:, 1], frozen[:, 0], pos_sigma=np.full(4, 4.0)),
    ]
    import unittest.mock

    with unittest.mock.patch.object(CompiledRun, "__call__", spy):
        for t in tracks:
            assert matcher.match(t).routes and matcher.match(t, PLAIN).routes
    kernels = {id(matcher._run_track): matcher._run_track}
    assert set(seen) == set(kernels)
    assert len(seen[id(matcher._run_track)]) == 2 * len(tracks)  # every match() is one call
    for k, sigs in seen.items():
        assert all(s == kernels[k].signature for s in sigs), sigs


def test_a_map_read_from_its_file_and_one_built_in_memory_share_one_compile(tmp_path) -> None:
    """A map file's arrays are read-only, a map built in memory has writable ones, and numba
    compiles a kernel once per argument type: the kernels' map arrays go in read-only either
    way, so both maps reach each kernel with the same types (one compile, not two), batch and
    online."""
    import unittest.mock

    import numba

    from graph.artifact import load_map, save_map
    from mapmatch.batch import BatchMatcher
    from mapmatch.batch.run import CompiledRun
    from mapmatch.types import Track

    m = parse_ascii_map(DRAWING, scale=7)
    save_map(m.graph, tmp_path / "m.map")
    loaded = load_map(tmp_path / "m.map")
    assert not loaded.seg_xy.flags.writeable and m.graph.seg_xy.flags.writeable
    ll = np.array([m.lonlat(*m.xy(c)) for c in "abcd"])
    track = Track("t", np.arange(4.0), ll[:, 1], ll[:, 0])
    seen: list[tuple[object, ...]] = []
    inner = CompiledRun.__call__

    def spy(self, *args):  # type: ignore[no-untyped-def]
        seen.append(tuple(numba.typeof(a) for a in args))
        return inner(self, *args)

    with unittest.mock.patch.object(CompiledRun, "__call__", spy):
        results = [BatchMatcher(g).match(track) for g in (m.graph, loaded)]
    assert len(seen) == 2 and seen[0] == seen[1]
    assert results[0].routes == results[1].routes == [[m.edge("a", "b"), m.edge("b", "c"), m.edge("c", "d")]]
    # the online matcher's road arrays too
    from mapmatch.online import OnlineMatcher

    online = [OnlineMatcher(g).road.arrays_tuple for g in (m.graph, loaded)]
    assert numba.typeof(online[0]) == numba.typeof(online[1])


def test_goal_directed_search_settles_the_targets_as_the_search_does() -> None:
    """The A* search the Viterbi step runs finds every target within the bound at the distance
    the plain bounded search finds (same edges, same floats), on a map with turn restrictions."""
    from mapmatch.routing import INF, Workspace, _reset, _search, _search_toward, route_graph

    m = parse_ascii_map(DRAWING + "   |\n   l\n", scale=9, restrictions=[("b", "c", "h", "no")])
    g = m.graph
    rg = route_graph(g)
    ws = Workspace.new(g.n_edges)
    rng = np.random.default_rng(2)
    reached = cut = 0
    for _ in range(400):
        src = int(rng.integers(g.n_edges))
        targets = rng.choice(g.n_edges, size=int(rng.integers(1, 6)), replace=False).astype(np.int64)
        base = float(rng.random() * g.edge_len[src])
        bound = float(rng.random() * 600.0)
        ws.tgt[targets] = 1
        nt = _search(src, base, bound, len(targets), rg, ws)
        want = ws.dist[targets].copy()
        _reset(nt, ws)
        nt = _search_toward(src, base, bound, len(targets), targets, rg, ws)
        got = ws.dist[targets].copy()
        _reset(nt, ws)
        ws.tgt[targets] = 0
        np.testing.assert_array_equal(got, want)  # the distance within the bound, else INF
        reached += int(np.sum(want <= bound))
        cut += int(np.sum(want == INF))
    assert ws.dist.min() == INF and not ws.done.any()  # the workspace is left clean
    assert reached > 300 and cut > 100  # both cases are exercised


def test_a_track_s_sigma_is_the_robust_spread_of_its_distances_to_the_roads() -> None:
    """1.4826 times the median distance to the nearest road, never below the configured σ,
    never above the most, and the configured σ when the most is 0."""
    d = np.array([3.0, 20.0, 10.0, 12.0, 40.0])
    assert model.track_sigma(d, 5.0, 30.0) == pytest.approx(1.4826 * 12.0)
    assert model.track_sigma(d, 20.0, 30.0) == 20.0  # a good receiver keeps the configured σ
    assert model.track_sigma(d * 3, 5.0, 30.0) == 30.0  # capped
    assert model.track_sigma(d, 5.0, 0.0) == 5.0  # off
    assert model.track_sigma(np.zeros(0), 5.0, 30.0) == 5.0  # no fix near any road
    # normal noise across a road: the estimate finds its σ
    rng = np.random.default_rng(1)
    assert model.track_sigma(np.abs(rng.normal(0, 15.0, 4000)), 5.0, 30.0) == pytest.approx(15.0, rel=0.05)


def test_a_column_of_the_wrong_length_is_refused() -> None:
    """The compiled call reads the columns unchecked: a track whose columns disagree in length
    is refused with an error naming the column."""
    from mapmatch.batch import BatchMatcher
    from mapmatch.types import Track

    m = parse_ascii_map(DRAWING, scale=7)
    ll = np.array([m.lonlat(*m.xy(c)) for c in "abcd"])
    matcher = BatchMatcher(m.graph)
    with pytest.raises(ValueError, match="heading"):
        matcher.match(Track("h", np.arange(4.0), ll[:, 1], ll[:, 0], heading=np.zeros(3)))
    with pytest.raises(ValueError, match="time"):
        matcher.match(Track("t", np.arange(3.0), ll[:, 1], ll[:, 0]))
    with pytest.raises(ValueError, match="lon"):
        matcher.match(Track("l", np.arange(4.0), ll[:, 1], ll[:3, 0]))


def _bearing_by_walking(e: int, off: float, seg_xy: np.ndarray, seg_ptr: np.ndarray) -> float:
    """The bearing at an offset by walking the polyline from the edge's start (the reference)."""
    acc, b = 0.0, 0.0
    for q in range(seg_ptr[e], seg_ptr[e + 1] - 1):
        dx, dy = seg_xy[q + 1] - seg_xy[q]
        L = float(np.hypot(dx, dy))
        if L > 0:
            b = float(np.degrees(np.arctan2(dx, dy)) % 360.0)
        acc += L
        if acc >= off:
            break
    return b


def test_bearing_by_binary_search_is_the_walk_along_the_polyline() -> None:
    """Headings are scored against the bearing of the segment under each candidate: found by a
    binary search over the segments' end distances, it is the walk's answer, with repeated
    vertices, offsets at vertices, beyond the edge, negative and NaN, and one-vertex edges."""
    from mapmatch.batch.lattice import along_lengths, bearing_on, segment_bearings

    rng = np.random.default_rng(7)
    counts = rng.integers(1, 9, size=60)
    seg_ptr = np.r_[0, np.cumsum(counts)].astype(np.int64)
    seg_xy = np.cumsum(rng.normal(0, 20, (int(seg_ptr[-1]), 2)), axis=0)
    dup = rng.random(len(seg_xy)) < 0.2
    seg_xy[1:][dup[1:]] = seg_xy[:-1][dup[1:]]  # zero-length segments
    ends = along_lengths(seg_xy, seg_ptr)
    edges = rng.integers(0, 60, size=2000).astype(np.int64)
    total = np.array([ends[seg_ptr[e + 1] - 2] if counts[e] > 1 else 0.0 for e in edges])
    offs = rng.random(2000) * (total * 1.2 + 1) - 1
    offs[:50] = np.nan
    at_vertex = [e for e in edges[50:100] if counts[e] > 2]
    edges[50 : 50 + len(at_vertex)] = at_vertex
    offs[50 : 50 + len(at_vertex)] = [ends[seg_ptr[e]] for e in at_vertex]  # at the first inner vertex
    table = segment_bearings(seg_xy, seg_ptr)
    got = bearing_on(edges, offs, seg_ptr, ends, table, np.empty(len(edges)))
    want = [_bearing_by_walking(int(e), float(o), seg_xy, seg_ptr) for e, o in zip(edges, offs, strict=True)]
    # the same segment's bearing: equal to the last bits the compiled atan2 may round differently
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_the_projection_that_skips_far_pieces_gives_project_point_s_floats() -> None:
    """A fix thinned out of a stop is projected onto a long edge by looking closely only at the
    pieces that can be as near as the nearest so far, and summing the offset on from the last
    answer's piece: the same offset, distance and position as the full walk, bit for bit, with
    or without a hint, in UTM-sized coordinates, with repeated vertices, points equally near two
    pieces (the first wins) and one-vertex edges."""
    from graph.index import project_point_compiled, project_point_near
    from mapmatch.batch.lattice import segment_lengths

    rng = np.random.default_rng(11)
    counts = rng.integers(1, 200, size=40)
    counts[:3] = 1
    seg_ptr = np.r_[0, np.cumsum(counts)].astype(np.int64)
    seg_xy = np.cumsum(rng.normal(0, 15, (int(seg_ptr[-1]), 2)), axis=0) + [612_000.0, 5_393_000.0]
    dup = rng.random(len(seg_xy)) < 0.1
    seg_xy[1:][dup[1:]] = seg_xy[:-1][dup[1:]]  # zero-length pieces
    # an edge folded back on itself: its middle point is equally near two pieces
    seg_ptr = np.r_[seg_ptr, seg_ptr[-1] + 3]
    seg_xy = np.vstack([seg_xy, [[0.0, 0.0], [10.0, 0.0], [0.0, 0.0]]])
    seg_len = segment_lengths(seg_xy, seg_ptr)
    n_edges = len(seg_ptr) - 1
    checked = unhinted = 0
    for e in range(n_edges):
        lo, hi = int(seg_ptr[e]), int(seg_ptr[e + 1])
        hint, hint_acc = -1, 0.0
        # a walk along the edge and back, in small steps (a stop) and jumps, some far off it
        for k in range(80):
            if e == n_edges - 1:
                x, y = 5.0, float(k % 4)
            else:
                v = seg_xy[lo + (k * 7 // 3) % (hi - lo)]
                x, y = v + rng.normal(0, [0.5, 5.0, 60.0][k % 3], 2)
            want = project_point_compiled(seg_xy, lo, hi, x, y, np.inf, 0.0)[:4]
            cold = project_point_near(seg_xy, seg_len, lo, hi, x, y, -1, 0.0)
            got = project_point_near(seg_xy, seg_len, lo, hi, x, y, hint, hint_acc)
            assert cold[:4] == want, (e, k, cold, want)
            assert got[:4] == want, (e, k, hint, got, want)
            assert got[4:] == cold[4:]  # the piece it lies on and that piece's start
            if hi - lo >= 2:
                assert lo < got[4] < hi
            unhinted += not (lo < hint <= got[4])
            hint, hint_acc = got[4], got[5]
            checked += 1
    assert checked == 80 * n_edges
    assert unhinted < checked / 2  # the offset was summed on from a hint in most of them


def test_the_in_place_projection_back_to_lonlat_equals_to_lonlat() -> None:
    """The answer's geometry goes back to lon/lat through pyproj's in-place call: the same
    numbers, bit for bit, as :func:`graph.projection.to_lonlat`, missing values too."""
    from graph.projection import rows_to_lonlat, to_lonlat

    rng = np.random.default_rng(6)
    xy = np.c_[rng.uniform(3e5, 7e5, 40), rng.uniform(4.4e6, 6.6e6, 40)]
    xy[3] = np.nan
    want = to_lonlat("EPSG:32633", xy[:, 0], xy[:, 1])
    buf = np.ascontiguousarray(xy.T)
    rows_to_lonlat("EPSG:32633", buf)
    np.testing.assert_array_equal(buf.T, want)
    empty = np.zeros((2, 0))
    rows_to_lonlat("EPSG:32633", empty)
    assert empty.shape == (2, 0)


def test_the_in_place_projection_equals_pyproj_s_public_call() -> None:
    """The matcher projects fixes through pyproj's in-place call: the same numbers, bit for bit,
    as :meth:`Transformer.transform`, for good, out-of-range and missing coordinates."""
    from pyproj import Transformer

    from mapmatch.batch.matcher import _projector

    tr = Transformer.from_crs("EPSG:4326", "EPSG:32633", always_xy=True)
    rng = np.random.default_rng(5)
    lon = np.r_[rng.uniform(10, 20, 50), np.nan, 200.0, 15.0, -181.0]
    lat = np.r_[rng.uniform(40, 60, 50), 50.0, 50.0, np.nan, 95.0]
    want = np.array(tr.transform(lon, lat))
    buf = np.array((lon, lat, lon, lat))  # as the matcher's: rows 2 and 3 are projected
    _projector(tr)(buf)
    np.testing.assert_array_equal(buf[2:], want)
    np.testing.assert_array_equal(buf[:2], np.array((lon, lat)))
    assert np.isfinite(buf[2:, :50]).all()


def test_borrowed_views_share_the_data_and_refuse_what_they_cannot_borrow() -> None:
    """:func:`mapmatch.arena.borrowed` views (no owner, so no reference counting) read and write
    the caller's arrays, nested in named tuples too; anything that is not arrays and numbers is
    refused at compile time."""
    from numba import njit
    from numba.core.errors import TypingError

    from mapmatch.arena import Arena, borrowed, take_f8
    from mapmatch.routing import NO_TABLE, RouteTable

    @njit
    def write(a, table, ar):  # type: ignore[no-untyped-def]
        b = borrowed(a)
        t = borrowed(table)
        arb = borrowed(ar)
        piece = take_f8(arb, 3)  # a piece of a borrowed arena writes into the arena
        piece[:] = 2.0
        b[0] = 5.0
        return b.sum() + t.ptr.size + t.delta + piece.sum()

    a = np.ones(4)
    ar = Arena.new(8)
    assert write(a, NO_TABLE, ar) == 8.0 + 1 - 1.0 + 6.0
    assert a.tolist() == [5.0, 1.0, 1.0, 1.0] and ar.f8[:3].tolist() == [2.0] * 3 and ar.top[0] == 3
    assert isinstance(NO_TABLE, RouteTable)

    @njit
    def bad(x):  # type: ignore[no-untyped-def]
        return borrowed(x)

    with pytest.raises(TypingError):
        bad([1.0, 2.0])


def test_a_ref_hands_a_kernel_the_callers_tuple_by_one_pointer() -> None:
    """:func:`mapmatch.arena.ref`: a named tuple of arrays and numbers, made once in the caller,
    reaches a kernel without reference counting as one argument, a pointer, through which the
    kernel reads the numbers and writes the caller's arrays on every call; ``deref`` of anything
    else is refused at compile time."""
    from numba import njit
    from numba.core.errors import TypingError

    from mapmatch.arena import UNCOUNTED, Ref, deref, ref
    from mapmatch.batch.step import StepRules
    from mapmatch.routing import NO_TABLE

    @njit(**{**UNCOUNTED, "cache": False})
    def add(i, r):  # type: ignore[no-untyped-def]
        out, rules, table = deref(r)
        out[i] += rules.reverse_tol * i + table.delta
        return out[i]

    @njit
    def caller(out, rules, table):  # type: ignore[no-untyped-def]
        r = ref((out, rules, table))
        total = 0.0
        for i in range(len(out)):
            total += add(i, r)
        return total

    out = np.ones(5)
    total = caller(out, StepRules(2.0, 50.0), NO_TABLE)
    assert out.tolist() == [1.0 + 2.0 * i - 1.0 for i in range(5)]
    assert total == pytest.approx(out.sum())
    (sig,) = add.signatures
    assert isinstance(sig[1], Ref) and len(sig) == 2

    @njit
    def bad(x):  # type: ignore[no-untyped-def]
        return deref(x)

    with pytest.raises(TypingError):
        bad(np.ones(2))


def test_the_jump_rule_drops_a_burst_not_the_good_fixes_around_it() -> None:
    """Runs of jumps (``drop_spikes_into``): at 30 m/s a two-fix burst 190 m to the side is dropped
    and the fixes before it are kept (their legs are as long as the burst's inner one); a stopped
    vehicle's burst is dropped though its thinned fixes leave the kept neighbours far apart in
    time; a drive that turns round over 20 s is not a jump."""
    from mapmatch.batch.lattice import drop_spikes_into, thin_into

    def dropped(xy: np.ndarray, t: np.ndarray, min_dist: float = 0.0) -> list[int]:
        valid = np.ones(len(t), dtype=np.bool_)
        kidx = np.flatnonzero(thin_into(xy, valid, min_dist, np.zeros(len(t), dtype=np.bool_)))
        out = drop_spikes_into(xy, t, kidx, 5.0, 3.0, 20.0, 5.0, valid.copy())
        return np.flatnonzero(~out).tolist()

    t = np.arange(12, dtype=np.float64)
    fast = np.column_stack([30.0 * t, np.zeros(12)])
    burst = fast.copy()
    burst[7:9] += (0.0, 190.0)
    assert dropped(burst, t) == [7, 8]
    assert dropped(fast, t) == []
    # stopped 28 s, the fixes thinned out: the visit starts at the last fix before the burst
    ts = np.arange(40, dtype=np.float64)
    stopped = np.zeros((40, 2))
    stopped[28:30] = (180.0, 60.0)
    assert dropped(stopped, ts, min_dist=16.0) == [28]  # 29 is thinned out: it follows 28
    # out along a side road at 10 m/s and back: 20 s to turn round, kept
    u = np.arange(30, dtype=np.float64)
    drive = np.column_stack([np.zeros(30), 10.0 * np.minimum(u, 29 - u)])
    assert dropped(drive, u) == []


def test_a_grown_arena_is_sized_from_the_last_call_and_has_its_pages_mapped_in() -> None:
    """``Arena.grown``: twice the most any buffer needed, None while it fits; the part of each
    buffer the last call used is mapped in already, so writing it in the next call takes no
    page faults (counted for this thread), where a fresh arena's first writes do."""
    import mmap
    import resource

    from mapmatch.arena import Arena

    small = Arena.new(1024)
    small.top[:] = (1000, 10, 10)
    assert small.grown() is None
    n = 1 << 19  # 4 MB of floats
    small.top[:] = (n, n // 2, 10)
    big = small.grown()
    assert big is not None and len(big.f8) == len(big.i8) == len(big.b1) == 2 * n

    def faults_writing(buf: np.ndarray) -> int:
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        buf[:] = 1
        return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before

    # memory never written (the allocator might hand out pages an earlier test mapped in)
    fresh = np.frombuffer(mmap.mmap(-1, 8 * n), dtype=np.float64)
    mapped, unmapped = faults_writing(big.f8[:n]), faults_writing(fresh)
    assert unmapped > 0 and 10 * mapped < unmapped
    assert 10 * faults_writing(big.i8[: n // 2]) < unmapped


def test_the_direction_of_travel_reaches_the_end_fixes_only_over_short_legs() -> None:
    """``motion_heading_into``: every fix of a straight drive east gets 90°; the first and last take
    it only where their own leg is at most ``end_leg_max`` (0: any length), while the fixes
    inside keep theirs; a turn of more than ``max_turn`` at a fix leaves it and its end
    neighbour without one."""
    from mapmatch.batch.lattice import motion_heading_into

    east = np.column_stack([np.array([0.0, 100.0, 120.0, 140.0, 300.0]), np.zeros(5)])

    def heading(xy: np.ndarray, end_leg_max: float) -> list[float]:
        out = np.full(len(xy), np.nan)
        return motion_heading_into(xy, np.arange(len(xy)), 8.0, 30.0, end_leg_max, out).round(6).tolist()

    assert heading(east, 0.0) == [90.0] * 5
    assert heading(east, 160.0) == [90.0] * 5
    got = heading(east, 50.0)  # first leg 100 m, last 160 m: both ends lose it
    assert np.isnan(got[0]) and np.isnan(got[4]) and got[1:4] == [90.0] * 3
    got = heading(east, 120.0)  # the first leg is short enough, the last is not
    assert got[:4] == [90.0] * 4 and np.isnan(got[4])
    turn = east.copy()
    turn[4] = (140.0, -160.0)  # a right angle at fix 3
    got = heading(turn, 0.0)
    assert got[:3] == [90.0] * 3 and np.isnan(got[3]) and np.isnan(got[4])
    assert all(np.isnan(heading(east[:2], 0.0)))  # two fixes: no two legs


def test_a_route_table_over_its_memory_budget_gets_a_shorter_bound_and_the_same_matches() -> None:
    from mapmatch.batch import BatchMatcher
    from mapmatch.route_table import Ubodt
    from mapmatch.types import Track

    m = parse_ascii_map(DRAWING, scale=7, restrictions=[("b", "c", "h", "no")])
    whole = Ubodt.build(m.graph, 400.0)
    budget = whole.nbytes // 3
    small = Ubodt.build(m.graph, 400.0, max_bytes=budget)
    assert 0 < small.delta < 400.0 and 0 < small.nbytes <= budget
    assert Ubodt.build(m.graph, 400.0, max_bytes=10 * whole.nbytes).delta == 400.0
    # the bound the table was built for is exact: its rows are the full table's rows up to it
    for e in range(m.graph.n_edges):
        row = slice(whole.ptr[e], whole.ptr[e + 1])
        keep = whole.dist[row] <= small.delta
        got = slice(small.ptr[e], small.ptr[e + 1])
        np.testing.assert_array_equal(small.tgt[got], whole.tgt[row][keep])
        np.testing.assert_array_equal(small.dist[got], whole.dist[row][keep])
    plain, fast = BatchMatcher(m.graph), BatchMatcher(m.graph, ubodt=small)
    xy = np.array([m.xy(n) for n in "abcdhg" if n in m.nodes])
    pts = np.array([a + (b - a) * f for a, b in itertools.pairwise(xy) for f in (0.2, 0.5, 0.8)])
    ll = np.array([m.lonlat(x, y) for x, y in pts])
    t = Track("w", np.arange(len(pts)) * 20.0, ll[:, 1], ll[:, 0])
    a, b = plain.match(t), fast.match(t)
    assert a.routes == b.routes and [p.edge for p in a.points] == [p.edge for p in b.points]
    for bad in (0, -5):
        with pytest.raises(ValueError, match="max_bytes"):
            Ubodt.build(m.graph, 400.0, max_bytes=bad)
    with pytest.raises(ValueError, match="delta"):
        Ubodt.build(m.graph, float("nan"))


def test_the_route_table_size_is_estimated_from_a_sample_of_rows(tmp_path) -> None:
    import json

    from graph.build import build_map
    from mapmatch.route_table import ESTIMATE_SAMPLE, Ubodt, ubodt_estimate

    # a 40 x 40 street grid, 80 m blocks, drawn as GIS centre lines: more edges than the sample
    n, step, x0, y0 = 40, 80.0, 24.90, 60.15
    dlon, dlat = step / 55_600.0, step / 111_300.0
    lines = []
    for i in range(n):
        for j in range(n - 1):
            lines.append([[x0 + j * dlon, y0 + i * dlat], [x0 + (j + 1) * dlon, y0 + i * dlat]])
            lines.append([[x0 + i * dlon, y0 + j * dlat], [x0 + i * dlon, y0 + (j + 1) * dlat]])
    feats = [
        {"type": "Feature", "properties": {}, "geometry": {"type": "LineString", "coordinates": c}}
        for c in lines
    ]
    path = tmp_path / "grid.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    g = build_map(path)
    assert g.n_edges > 4 * ESTIMATE_SAMPLE
    for delta in (300.0, 900.0):
        est, table = ubodt_estimate(g, delta), Ubodt.build(g, delta)
        assert abs(est - table.nbytes) <= 0.1 * table.nbytes, (delta, est, table.nbytes)
    budget = ubodt_estimate(g, 300.0) + 1
    fit = Ubodt.build(g, 900.0, max_bytes=budget)
    # the largest bound that fits, to within the bisection's last step (450 m / 64)
    assert ubodt_estimate(g, fit.delta) <= budget < ubodt_estimate(g, fit.delta + 450.0 / 64)
    assert 300.0 <= fit.delta < 900.0 and fit.nbytes <= 1.1 * budget


def test_a_whole_edge_of_a_route_is_its_vertices_and_a_part_is_cut_from_its_segments() -> None:
    from mapmatch.arena import Arena
    from mapmatch.batch.arrays import EdgeGeometry
    from mapmatch.batch.lattice import segment_lengths
    from mapmatch.batch.route import pieces_xy

    # edge 0: a bent line of 5 + 6 + 5 m with a repeated vertex; edge 1: 10 m on from its end
    seg_xy = np.array(
        [[0.1, 0.3], [3.1, 4.3], [3.1, 10.3], [3.1, 10.3], [8.1, 10.3], [8.1, 10.3], [18.1, 10.3]]
    )
    seg_ptr = np.array([0, 5, 7])
    geom = EdgeGeometry(seg_xy, seg_ptr, segment_lengths(seg_xy, seg_ptr))
    edge_len = np.array([16.0, 10.0])
    # the whole of edge 0, then edge 1 up to 4 m; then a new piece of edge 0 from 2 m to 13 m
    pe, ps, pend = np.array([0, 1, 0]), np.array([0.0, 0.0, 2.0]), np.array([16.0, 4.0, 13.0])
    xy, ptr = pieces_xy(pe, ps, pend, geom, edge_len, Arena.new())
    np.testing.assert_array_equal(xy[ptr[0] : ptr[1]], seg_xy[[0, 1, 2, 4]])  # exact, once each
    np.testing.assert_allclose(xy[ptr[1] : ptr[2]], [[12.1, 10.3]])  # edge 1's start is edge 0's end
    np.testing.assert_allclose(xy[ptr[2] : ptr[3]], [[1.3, 1.9], [3.1, 4.3], [3.1, 10.3], [5.1, 10.3]])
