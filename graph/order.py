"""The order of a map's edges in memory: nearby roads get nearby indices.

Matching reads per-edge arrays at the indices of the roads near each fix: the grid's segments,
the route table's rows and the search's workspace. In source order (OSM way ids, GIS feature
order) a street's neighbours lie anywhere in those arrays; in the order of a Hilbert curve
through the edges' midpoints they mostly share cache lines and pages, which counts on large
maps.
The order decides only ties between equally good answers (equal distances, broken by index).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.road_graph import Edges, Labels, Pieces, Polylines

HILBERT_BITS = 16
"""Bits per axis of the curve's grid: cells of about 1.5 m on a 100 km map (finer changes little)."""


def hilbert_key(x: NDArray[np.int64], y: NDArray[np.int64], *, bits: int = HILBERT_BITS) -> NDArray[np.int64]:
    """Distance along the Hilbert curve of cells ``(x, y)`` in ``[0, 2**bits)`` (vectorised).

    Examples
    --------
    >>> hilbert_key(np.array([0, 0, 1, 1]), np.array([0, 1, 1, 0]), bits=1).tolist()
    [0, 1, 2, 3]
    """
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    n = np.int64(1) << bits
    d = np.zeros(len(x), dtype=np.int64)
    s = n >> 1
    while s > 0:
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx.astype(np.int64)) ^ ry.astype(np.int64))
        flip = ~ry & rx  # then x and y swap where ~ry
        fx = np.where(flip, n - 1 - x, x)
        fy = np.where(flip, n - 1 - y, y)
        x, y = np.where(ry, fx, fy), np.where(ry, fy, fx)
        s >>= 1
    return d


def spatial_edge_order(
    node_xy: NDArray[np.float64],
    edge_u: NDArray[np.integer],
    edge_v: NDArray[np.integer],
    *,
    bits: int = HILBERT_BITS,
) -> NDArray[np.int64]:
    """The edges' new order: by the Hilbert key of the midpoint of their end nodes, then by
    their lower end node (both directions of a road side by side), then by index."""
    if not 0 < bits <= 16:
        raise ValueError(f"bits must be 1 to 16 (the sort key holds 2 * bits and a node index), not {bits}")
    u = np.asarray(edge_u, dtype=np.int64)
    v = np.asarray(edge_v, dtype=np.int64)
    if len(u) == 0:
        return np.zeros(0, dtype=np.int64)
    mid = (node_xy[u] + node_xy[v]) / 2.0
    lo = mid.min(axis=0)
    span = float((mid.max(axis=0) - lo).max())
    scale = ((1 << bits) - 1) / span if span > 0 else 0.0
    cell = np.floor((mid - lo) * scale).astype(np.int64)
    key = hilbert_key(cell[:, 0], cell[:, 1], bits=bits)
    # one stable sort of (key, lower end node) in 63 bits: key < 2**(2 * bits), nodes < 2**31
    both = (key << np.int64(31)) | np.minimum(u, v)
    return np.argsort(both, kind="stable").astype(np.int64)


def _take_ragged(
    ptr: NDArray[np.int64], order: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Rows ``order`` of a ragged array's pointer: the new pointer and the old item of each new one."""
    counts = np.diff(ptr)[order]
    new_ptr = np.zeros(len(order) + 1, dtype=np.int64)
    np.cumsum(counts, out=new_ptr[1:])
    items = np.repeat(ptr[:-1][order] - new_ptr[:-1], counts) + np.arange(int(new_ptr[-1]), dtype=np.int64)
    return new_ptr, items


def _take_labels(v: Any, index: NDArray[np.int64]) -> Any:
    if v is None:
        return None
    if isinstance(v, Labels):
        return v.take(index)
    return [v[i] for i in index.tolist()]


def take_edges(kw: dict[str, Any], order: NDArray[np.int64]) -> dict[str, Any]:
    """:meth:`~graph.road_graph.RoadGraph.from_edges` arguments (edges with a
    :class:`~graph.road_graph.Polylines` geometry) with the edges in ``order``: new edge ``i``
    is old ``order[i]`` (geometry, attributes, way pieces and restrictions follow)."""
    out = dict(kw)
    e = len(order)
    inv = np.empty(e, dtype=np.int64)
    inv[order] = np.arange(e, dtype=np.int64)
    edges: Edges = kw["edges"]
    geom = edges.geometry
    if not isinstance(geom, Polylines):
        raise TypeError("take_edges needs the edges' geometry as Polylines")
    ptr, items = _take_ragged(np.asarray(geom.ptr, dtype=np.int64), order)
    out["edges"] = Edges(
        u=np.asarray(edges.u)[order],
        v=np.asarray(edges.v)[order],
        geometry=Polylines(np.asarray(geom.xy)[items], ptr),
        way_id=None if edges.way_id is None else np.asarray(edges.way_id)[order],
        name=_take_labels(edges.name, order),
        highway=_take_labels(edges.highway, order),
        speed_kph=None if edges.speed_kph is None else np.asarray(edges.speed_kph)[order],
    )
    rows = kw.get("restrictions")
    if rows is not None and len(rows):
        r = np.asarray(rows, dtype=np.int64).reshape(-1, 4).copy()
        r[:, 0] = inv[r[:, 0]]
        r[:, 2] = inv[r[:, 2]]
        out["restrictions"] = r
    p: Pieces | None = kw.get("pieces")
    if p is not None:
        pe = np.asarray(p.edge, dtype=np.int64)
        pptr = np.zeros(e + 1, dtype=np.int64)
        np.cumsum(np.bincount(pe, minlength=e), out=pptr[1:])
        new_pptr, rows_ = _take_ragged(pptr, order)
        out["pieces"] = Pieces(
            edge=np.repeat(np.arange(e, dtype=np.int64), np.diff(new_pptr)),
            start=np.asarray(p.start)[rows_],
            way_id=np.asarray(p.way_id)[rows_],
            name=_take_labels(p.name, rows_),
            highway=_take_labels(p.highway, rows_),
            speed_kph=np.asarray(p.speed_kph)[rows_],
        )
    return out
