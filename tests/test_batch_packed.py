"""The compiled answer's one array and its typed reading (:mod:`mapmatch.batch.packed`): every
field of an assembly comes back by name, with its exact bits."""

from __future__ import annotations

import numpy as np

from mapmatch.batch.arrays import Assembly
from mapmatch.batch.packed import decode, pack


def _assembly(nseg: int) -> Assembly:
    n = 4
    route_ptr = np.array([0, 2, 3][: nseg + 1], dtype=np.int64)
    rxy_ptr = np.array([0, 3, 4][: nseg + 1], dtype=np.int64)
    nxy = int(rxy_ptr[-1])
    return Assembly(
        p_edge=np.array([3, -1, 5, 7], dtype=np.int64),
        p_off=np.array([0.5, np.nan, 12.25, 1e-300]),
        p_xy=np.arange(2 * n, dtype=np.float64).reshape(n, 2) + 0.1,
        p_dist=np.array([1.0, np.nan, 2.0, 3.0]),
        status=np.array([1, 0, 2, 1], dtype=np.int64),
        splits=np.array([2] if nseg == 2 else [], dtype=np.int64),
        route_e=np.array([3, 4, 7][: int(route_ptr[-1])], dtype=np.int64),
        route_ptr=route_ptr,
        xy_all=np.arange(2 * nxy, dtype=np.float64).reshape(nxy, 2) * 1.5,
        rxy_ptr=rxy_ptr,
        length=123.456 if nseg else 0.0,
        conf=0.875,
    )


def test_every_field_comes_back_by_name_with_its_bits() -> None:
    a = _assembly(2)
    res = decode(pack(a))
    assert res.point_edge.tolist() == a.p_edge.tolist()
    assert res.status.tolist() == a.status.tolist()
    for got, want in ((res.point_offset, a.p_off), (res.point_xy, a.p_xy), (res.point_dist, a.p_dist)):
        assert got.shape == want.shape and got.tobytes() == want.tobytes()
    assert res.splits.tolist() == [2]
    assert res.routes() == [[3, 4], [7]]
    pieces = res.pieces_xy()
    assert pieces[0].tobytes() == a.xy_all[:3].tobytes()
    assert pieces[1].tolist() == [a.xy_all[3].tolist()] * 2  # one point: a line has two
    assert res.length == 123.456 and res.confidence == 0.875
    assert res.placed == 3
    status, edge, off, xy, dist = res.point_arrays()
    assert status.tolist() == a.status.tolist() and edge.tolist() == a.p_edge.tolist()
    assert off.tobytes() == a.p_off.tobytes() and xy.tobytes() == a.p_xy.tobytes()
    assert dist.tobytes() == a.p_dist.tobytes()
    assert all(np.shares_memory(x, res.packed) for x in (status, edge, off, xy, dist))  # views, no copy
    assert (res.n, res.n_splits, res.n_route_edges, res.n_pieces, res.n_route_xy) == (4, 1, 3, 2, 4)


def test_an_answer_with_no_route_has_no_pieces() -> None:
    res = decode(pack(_assembly(0)))
    assert res.routes() == [] and res.pieces_xy() == [] and res.splits.tolist() == []
    assert res.length == 0.0 and res.route_xy.shape == (0, 2)
