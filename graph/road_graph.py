"""The prepared road graph: dense arrays, CSR adjacency, external ids only at the edges.

Nodes are intersections and dead ends, indexed ``0..N-1``; directed edges are the roads
between them, indexed ``0..E-1``. Coordinates are metres in a local projected CRS
(``crs``, usually UTM). Edge polylines are flattened into ``seg_xy`` with ``edge_seg_ptr``
(shapely's ragged-array layout): edge ``e`` runs through ``seg_xy[edge_seg_ptr[e]:edge_seg_ptr[e+1]]``.

Nothing here imports osmnx or networkx: matchers and the service use this class alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.angles import bearings
from graph.errors import GraphError
from graph.keys import unique_inverse

RESTRICTION_NO = 0
RESTRICTION_ONLY = 1

ARRAY_FIELDS: tuple[str, ...] = (
    "node_xy",
    "node_lonlat",
    "node_id",
    "edge_u",
    "edge_v",
    "edge_len",
    "edge_bearing_start",
    "edge_bearing_end",
    "edge_way_id",
    "edge_name_idx",
    "edge_highway_idx",
    "edge_speed_kph",
    "edge_reverse",
    "seg_xy",
    "edge_seg_ptr",
    "out_ptr",
    "out_edges",
    "in_ptr",
    "in_edges",
    "restrictions",
    "piece_ptr",
    "piece_start",
    "piece_way_id",
    "piece_name_idx",
    "piece_highway_idx",
    "piece_speed_kph",
)
PIECE_FIELDS: tuple[str, ...] = ARRAY_FIELDS[-6:]
"""Way-piece arrays; map files written before they existed get one piece per edge on load."""


class Labels(NamedTuple):
    """A text column as codes into a table of distinct non-empty strings (-1: none)."""

    codes: NDArray[np.int32]
    table: list[str]

    @classmethod
    def of(cls, values: Sequence[Any]) -> Labels:
        """Codes of ``values`` in order of first appearance; false values (None, "") are none,
        others are read as text."""
        table: dict[str, int] = {}
        put = table.setdefault
        codes = [put(v if type(v) is str else str(v), len(table)) if v else -1 for v in values]
        return cls(np.asarray(codes, dtype=np.int32).reshape(-1), list(table))

    def take(self, index: NDArray[np.integer]) -> Labels:
        """The labels of rows ``index`` (same table)."""
        return Labels(self.codes[index], self.table)

    def values(self) -> list[str | None]:
        """The column as strings (None for none)."""
        t: list[str | None] = [*self.table, None]
        return [t[c] for c in self.codes.tolist()]


class Pieces(NamedTuple):
    """The ways (or GIS features) an edge is made of, one row per piece, ordered by edge and
    then by ``start`` (metres along the edge in travel direction; each edge's first is 0)."""

    edge: NDArray[np.int64]
    start: NDArray[np.float64]
    way_id: NDArray[np.int64]
    name: Sequence[str | None] | Labels
    highway: Sequence[str | None] | Labels
    speed_kph: NDArray[np.float32]


class Nodes(NamedTuple):
    """The nodes given to :meth:`RoadGraph.from_edges`.

    Attributes
    ----------
    xy : (N, 2)
        Positions in metres.
    lonlat : (N, 2) or None
        WGS84 positions; computed from ``xy`` with pyproj when None.
    id : (N,) or None
        External node ids; ``0..N-1`` when None.
    """

    xy: NDArray[np.float64] | Sequence[Sequence[float]]
    lonlat: NDArray[np.float64] | Sequence[Sequence[float]] | None = None
    id: NDArray[np.int64] | Sequence[int] | None = None


class Polylines(NamedTuple):
    """Edge polylines as one ragged array (shapely's layout): edge ``e`` runs through
    ``xy[ptr[e]:ptr[e+1]]``, at least 2 points each."""

    xy: NDArray[np.float64]
    ptr: NDArray[np.int64]


class Edges(NamedTuple):
    """The directed edges given to :meth:`RoadGraph.from_edges`: node indices, geometry and
    optional attributes.

    Attributes
    ----------
    u, v : (E,)
        Start and end node of each edge.
    geometry : Polylines, sequence of (k, 2) arrays, or None
        Each edge's polyline from ``u`` to ``v`` in metres (a polyline of fewer than 2
        points is straight); straight lines when None.
    way_id, speed_kph : (E,) or None
        Way (or feature) id, -1 when None; speed in km/h, NaN when None.
    name, highway : strings (None for none), :class:`Labels`, or None
        Road name and class.
    """

    u: NDArray[np.integer] | Sequence[int]
    v: NDArray[np.integer] | Sequence[int]
    geometry: Polylines | Sequence[NDArray[np.float64]] | None = None
    way_id: NDArray[np.int64] | Sequence[int] | None = None
    name: Sequence[str | None] | Labels | None = None
    highway: Sequence[str | None] | Labels | None = None
    speed_kph: NDArray[np.floating] | Sequence[float] | None = None


def merge_repeats(values: Sequence[Any]) -> list[Any]:
    """``values`` with runs of equal consecutive items merged into one."""
    out: list[Any] = []
    for v in values:
        if not out or out[-1] != v:
            out.append(v)
    return out


def _csr(keys: NDArray[np.int64], n: int) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
    order = np.argsort(keys, kind="stable").astype(np.int32)
    counts = np.bincount(keys, minlength=n)
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr, order


@dataclass(frozen=True, eq=False)
class RoadGraph:
    """A directed road graph held as parallel numpy arrays (read-only, thread-safe).

    Attributes
    ----------
    crs : str
        The projected CRS of ``node_xy`` and ``seg_xy`` (e.g. ``"EPSG:32635"``).
    node_xy, node_lonlat : (N, 2) float64
        Node positions in metres and in WGS84 lon/lat.
    node_id : (N,) int64
        The source's node id (OSM node id, or a GIS-derived id).
    edge_u, edge_v : (E,) int32
        Start and end node of each directed edge.
    edge_len : (E,) float64
        Polyline length in metres.
    edge_bearing_start, edge_bearing_end : (E,) float64
        Compass bearing in degrees of the first and last polyline segment, in travel direction.
    edge_way_id : (E,) int64
        OSM way id (or GIS feature id), -1 when unknown.
    edge_name_idx, edge_highway_idx : (E,) int32
        Indices into ``names`` and ``highways``; -1 when unknown.
    edge_speed_kph : (E,) float32
        Posted or default speed, NaN when unknown.
    edge_reverse : (E,) int32
        Index of the opposite-direction edge with the same geometry, or -1 (one-way).
    seg_xy : (S, 2) float64 and edge_seg_ptr : (E+1,) int64
        Flattened polylines.
    out_ptr, out_edges, in_ptr, in_edges
        CSR adjacency: edges leaving node ``n`` are ``out_edges[out_ptr[n]:out_ptr[n+1]]``.
    restrictions : (R, 4) int32
        Turn restrictions as rows ``(from_edge, via_node, to_edge, kind)`` with kind
        ``RESTRICTION_NO`` or ``RESTRICTION_ONLY``.
    names, highways : list of str
        Lookup tables.
    meta : dict
        Free-form build metadata (source, parameters); stored in the artifact manifest.
    piece_ptr : (E+1,) int64
        Way pieces: edge ``e`` is made of pieces ``piece_ptr[e]:piece_ptr[e+1]`` in travel
        order (at least one). ``edge_way_id`` and the other edge attributes are those of the
        edge's longest piece; answers about a point use :meth:`piece_at`.
    piece_start : (P,) float64
        Offset in metres along its edge where each piece begins (the next piece's start, or
        the edge length, is where it ends).
    piece_way_id, piece_name_idx, piece_highway_idx, piece_speed_kph : (P,)
        Each piece's way id (or GIS feature id), name and road class (indices into
        ``names`` and ``highways``, -1 unknown) and speed (NaN unknown).
    """

    crs: str
    node_xy: NDArray[np.float64]
    node_lonlat: NDArray[np.float64]
    node_id: NDArray[np.int64]
    edge_u: NDArray[np.int32]
    edge_v: NDArray[np.int32]
    edge_len: NDArray[np.float64]
    edge_bearing_start: NDArray[np.float64]
    edge_bearing_end: NDArray[np.float64]
    edge_way_id: NDArray[np.int64]
    edge_name_idx: NDArray[np.int32]
    edge_highway_idx: NDArray[np.int32]
    edge_speed_kph: NDArray[np.float32]
    edge_reverse: NDArray[np.int32]
    seg_xy: NDArray[np.float64]
    edge_seg_ptr: NDArray[np.int64]
    out_ptr: NDArray[np.int64]
    out_edges: NDArray[np.int32]
    in_ptr: NDArray[np.int64]
    in_edges: NDArray[np.int32]
    restrictions: NDArray[np.int32]
    names: list[str] = field(default_factory=list)
    highways: list[str] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)
    piece_ptr: NDArray[np.int64] = None  # type: ignore[assignment]
    piece_start: NDArray[np.float64] = None  # type: ignore[assignment]
    piece_way_id: NDArray[np.int64] = None  # type: ignore[assignment]
    piece_name_idx: NDArray[np.int32] = None  # type: ignore[assignment]
    piece_highway_idx: NDArray[np.int32] = None  # type: ignore[assignment]
    piece_speed_kph: NDArray[np.float32] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        given = [getattr(self, k) is not None for k in PIECE_FIELDS]
        if any(given) and not all(given):
            raise GraphError("give all way-piece arrays or none")
        if not any(given):  # one piece per edge, from the edge attributes
            e = len(self.edge_u)
            for k, v in (
                ("piece_ptr", np.arange(e + 1, dtype=np.int64)),
                ("piece_start", np.zeros(e, dtype=np.float64)),
                ("piece_way_id", self.edge_way_id),
                ("piece_name_idx", self.edge_name_idx),
                ("piece_highway_idx", self.edge_highway_idx),
                ("piece_speed_kph", self.edge_speed_kph),
            ):
                object.__setattr__(self, k, v)
        elif len(self.piece_ptr) != len(self.edge_u) + 1:
            raise GraphError("piece_ptr must have E+1 entries")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_edges(
        cls,
        crs: str,
        nodes: Nodes,
        edges: Edges,
        *,
        pieces: Pieces | None = None,
        restrictions: NDArray[np.integer] | Sequence[Sequence[int]] | None = None,
        meta: dict[str, Any] | None = None,
        copy: bool = True,
    ) -> RoadGraph:
        """Build a graph from directed edges, deriving lengths, bearings, CSR and reverses.

        Parameters
        ----------
        crs
            Projected CRS of the node positions and the geometries.
        nodes
            Positions, and optionally lon/lat and external ids (:class:`Nodes`).
        edges
            Directed edges as node indices (a two-way road is two edges), with their geometry
            and attributes (:class:`Edges`). Each polyline's ends are set to its nodes.
        pieces
            The ways each edge is made of; one piece per edge (its own attributes) when omitted.
        restrictions
            Rows ``(from_edge, via_node, to_edge, kind)``.
        meta
            Build metadata.
        copy
            False: a :class:`Polylines` geometry (float64, C order) is taken over and may be
            changed in place.
        """
        xy, lonlat, ids = _node_arrays(crs, nodes)
        u, v = _edge_ends(edges, len(xy))
        e = len(u)
        seg, ptr = _polylines(xy, u, v, edges.geometry, copy=copy)
        b_start, b_end = _end_bearings(seg, ptr)
        piece_arrays = _piece_arrays(pieces, e)
        p = len(piece_arrays.get("piece_start", ()))
        # one table each for names and classes, in order of first use: edges, then pieces
        name_idx, p_name, names = _tables(edges.name, e, pieces.name if pieces is not None else None, p)
        hw_idx, p_hw, highways = _tables(edges.highway, e, pieces.highway if pieces is not None else None, p)
        if pieces is not None:
            piece_arrays["piece_name_idx"] = p_name
            piece_arrays["piece_highway_idx"] = p_hw
        out_ptr, out_edges = _csr(u.astype(np.int64), len(xy))
        in_ptr, in_edges = _csr(v.astype(np.int64), len(xy))
        return cls(
            crs=crs,
            node_xy=xy,
            node_lonlat=lonlat,
            node_id=ids,
            edge_u=u,
            edge_v=v,
            edge_len=_edge_lengths(seg, ptr),
            edge_bearing_start=b_start,
            edge_bearing_end=b_end,
            edge_way_id=_column(edges.way_id, e, np.int64, -1),
            edge_name_idx=name_idx,
            edge_highway_idx=hw_idx,
            edge_speed_kph=_column(edges.speed_kph, e, np.float32, np.nan),
            edge_reverse=_reverse_edges(u, v, seg, ptr),
            seg_xy=seg,
            edge_seg_ptr=ptr,
            out_ptr=out_ptr,
            out_edges=out_edges,
            in_ptr=in_ptr,
            in_edges=in_edges,
            restrictions=_restriction_rows(restrictions),
            names=names,
            highways=highways,
            meta=dict(meta or {}),
            **piece_arrays,
        )

    # ------------------------------------------------------------------ sizes and lookups
    @property
    def n_nodes(self) -> int:
        return len(self.node_xy)

    @property
    def n_edges(self) -> int:
        return len(self.edge_u)

    def out_of(self, node: int) -> NDArray[np.int32]:
        """Edges leaving ``node``."""
        return self.out_edges[self.out_ptr[node] : self.out_ptr[node + 1]]

    def into(self, node: int) -> NDArray[np.int32]:
        """Edges entering ``node``."""
        return self.in_edges[self.in_ptr[node] : self.in_ptr[node + 1]]

    def edge_xy(self, edge: int) -> NDArray[np.float64]:
        """The polyline of ``edge`` in metres, from ``u`` to ``v``."""
        return self.seg_xy[self.edge_seg_ptr[edge] : self.edge_seg_ptr[edge + 1]]

    def edge_name(self, edge: int) -> str:
        i = int(self.edge_name_idx[edge])
        return self.names[i] if i >= 0 else ""

    def edge_highway(self, edge: int) -> str:
        i = int(self.edge_highway_idx[edge])
        return self.highways[i] if i >= 0 else ""

    @property
    def n_pieces(self) -> int:
        return len(self.piece_start)

    def piece_at(self, edges: Any, offsets: Any) -> NDArray[np.int64]:
        """The way piece under each point ``(edge, offset)`` (vectorised; -1 where edge < 0).

        A point exactly at a boundary belongs to the piece that begins there; offsets before
        0 or past the edge's end fall on its first or last piece.
        """
        e = np.asarray(edges, dtype=np.int64)
        off = np.asarray(offsets, dtype=np.float64)
        e, off = np.broadcast_arrays(e, off)
        shape = e.shape
        e, off = e.ravel(), off.ravel()
        ok = (e >= 0) & (e < self.n_edges)
        ec = np.where(ok, e, 0)
        if not self.n_edges:
            return np.full(shape, -1, dtype=np.int64)
        lo = self.piece_ptr[ec]
        n = self.piece_ptr[ec + 1] - lo
        out = lo.copy()
        for j in range(1, int(n.max()) if n.size else 0):  # few pieces per edge: loop over rank
            at = np.where(n > j, lo + j, 0)
            past = (n > j) & (self.piece_start[at] <= off)
            out[past] = at[past]
        return np.where(ok, out, -1).reshape(shape)

    def piece_end(self, piece: Any) -> NDArray[np.float64]:
        """Offset in metres where each piece ends (the next piece's start, or the edge end)."""
        p = np.asarray(piece, dtype=np.int64)
        edge = np.searchsorted(self.piece_ptr, p, side="right") - 1
        last = p + 1 >= self.piece_ptr[edge + 1]
        nxt = self.piece_start[np.minimum(p + 1, max(self.n_pieces - 1, 0))]
        return np.where(last, self.edge_len[edge], nxt)

    def piece_index(self, edge: int, offset: float) -> int:
        """Scalar :meth:`piece_at`: the way piece under ``(edge, offset)``; -1 for no edge."""
        if not 0 <= edge < self.n_edges:
            return -1
        lo, hi = int(self.piece_ptr[edge]), int(self.piece_ptr[edge + 1])
        if hi - lo <= 1:
            return lo
        return lo + int(np.searchsorted(self.piece_start[lo + 1 : hi], offset, side="right"))

    def piece_fields(self, piece: int) -> tuple[int, str, str, float]:
        """Way id, name, road class and speed (km/h, 0.0 when unknown) of one piece (-1: none)."""
        if piece < 0:
            return -1, "", "", 0.0
        n, h = int(self.piece_name_idx[piece]), int(self.piece_highway_idx[piece])
        v = float(self.piece_speed_kph[piece])
        return (
            int(self.piece_way_id[piece]),
            self.names[n] if n >= 0 else "",
            self.highways[h] if h >= 0 else "",
            v if v == v else 0.0,
        )

    def way_id_at(self, edge: int, offset: float) -> int:
        """Way id of the piece under ``(edge, offset)``; -1 for no edge."""
        return self.piece_fields(self.piece_index(edge, offset))[0]

    def name_at(self, edge: int, offset: float) -> str:
        """Name of the piece under ``(edge, offset)``; ``""`` when unknown."""
        return self.piece_fields(self.piece_index(edge, offset))[1]

    def highway_at(self, edge: int, offset: float) -> str:
        """Road class of the piece under ``(edge, offset)``; ``""`` when unknown."""
        return self.piece_fields(self.piece_index(edge, offset))[2]

    def speed_at(self, edge: int, offset: float) -> float:
        """Speed in km/h of the piece under ``(edge, offset)``; 0.0 when unknown."""
        return self.piece_fields(self.piece_index(edge, offset))[3]

    def route_pieces(
        self, edges: Sequence[int] | NDArray[np.integer], *, start: float = 0.0, end: float = np.inf
    ) -> NDArray[np.int64]:
        """The pieces a route runs through, in order: from the piece at ``start`` on its first
        edge to the piece at ``end`` on its last (whole edges in between)."""
        e = np.asarray(edges, dtype=np.int64)
        if not len(e):
            return np.zeros(0, dtype=np.int64)
        lo, hi = self.piece_ptr[e], self.piece_ptr[e + 1]
        lo = lo.copy()
        hi = hi.copy()
        lo[0] = self.piece_at(e[0], start)
        hi[-1] = self.piece_at(e[-1], min(end, float(self.edge_len[e[-1]]))) + 1
        if len(e) == 1:
            hi[0] = max(hi[0], lo[0] + 1)
        counts = np.maximum(hi - lo, 0)
        base = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        return base + np.arange(int(counts.sum()), dtype=np.int64)

    def route_ways(
        self, edges: Sequence[int] | NDArray[np.integer], *, start: float = 0.0, end: float = np.inf
    ) -> tuple[list[int], list[str]]:
        """A route's way ids and names in order, consecutive repeats merged (see :meth:`route_pieces`)."""
        p = self.route_pieces(edges, start=start, end=end)
        return merge_repeats(self.piece_way_id[p].tolist()), merge_repeats(
            [self.names[i] if i >= 0 else "" for i in self.piece_name_idx[p].tolist()]
        )

    @property
    def bbox(self) -> tuple[float, float, float, float]:
        """``(min_lon, min_lat, max_lon, max_lat)`` of the nodes."""
        if not self.n_nodes:
            return (0.0, 0.0, 0.0, 0.0)
        lo = self.node_lonlat.min(axis=0)
        hi = self.node_lonlat.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    def stats(self) -> dict[str, Any]:
        """Map statistics the online matcher needs, and counts for summaries."""
        two_way = self.edge_reverse >= 0
        # km of road: a two-way road counts once
        road_len = float(self.edge_len[~two_way].sum() + self.edge_len[two_way].sum() / 2.0)
        q = np.percentile(self.edge_len, [5, 25, 50, 75, 95]).tolist() if self.n_edges else [0.0] * 5
        return {
            "nodes": self.n_nodes,
            "edges": self.n_edges,
            "oneway_edges": int((~two_way).sum()),
            "road_km": road_len / 1000.0,
            "edge_len_max_m": float(self.edge_len.max()) if self.n_edges else 0.0,
            "edge_len_mean_m": float(self.edge_len.mean()) if self.n_edges else 0.0,
            "edge_len_p5_p25_p50_p75_p95_m": [float(x) for x in q],
            "restrictions": len(self.restrictions),
        }

    def arrays(self) -> dict[str, NDArray[Any]]:
        """The array fields by name (what the artifact stores)."""
        return {k: getattr(self, k) for k in ARRAY_FIELDS}

    def equals(self, other: RoadGraph) -> bool:
        """Exact equality of every array, table and the CRS."""
        if self.crs != other.crs or self.names != other.names or self.highways != other.highways:
            return False
        for k in ARRAY_FIELDS:
            a, b = getattr(self, k), getattr(other, k)
            if a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(a, b, equal_nan=True):
                return False
        return True


def _node_arrays(
    crs: str, nodes: Nodes
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Positions, lon/lat (projected back from the positions when not given) and ids."""
    xy = np.ascontiguousarray(nodes.xy, dtype=np.float64).reshape(-1, 2)
    if nodes.lonlat is None:
        from pyproj import Transformer

        tf = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lon, lat = tf.transform(xy[:, 0], xy[:, 1])
        lonlat = np.column_stack([lon, lat]).astype(np.float64)
    else:
        lonlat = np.ascontiguousarray(nodes.lonlat, dtype=np.float64).reshape(-1, 2)
    ids = np.arange(len(xy), dtype=np.int64) if nodes.id is None else np.asarray(nodes.id, dtype=np.int64)
    return xy, lonlat, ids


def _edge_ends(edges: Edges, n: int) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """The edges' start and end nodes, checked to be node indices in ``0..n-1``."""
    u = np.asarray(edges.u, dtype=np.int32).ravel()
    v = np.asarray(edges.v, dtype=np.int32).ravel()
    if len(v) != len(u):
        raise GraphError("edges.u and edges.v differ in length")
    if len(u) and (u.min() < 0 or v.min() < 0 or u.max() >= n or v.max() >= n):
        raise GraphError("edge endpoints must be node indices in 0..N-1")
    return u, v


def _restriction_rows(rows: NDArray[np.integer] | Sequence[Sequence[int]] | None) -> NDArray[np.int32]:
    """Turn restrictions as an (R, 4) int32 array."""
    if rows is None or len(rows) == 0:
        return np.empty((0, 4), dtype=np.int32)
    return np.asarray(rows, dtype=np.int32).reshape(-1, 4)


def _polylines(
    xy: NDArray[np.float64],
    u: NDArray[np.int32],
    v: NDArray[np.int32],
    geometry: Polylines | Sequence[NDArray[np.float64]] | None,
    *,
    copy: bool,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The edges' polylines as one ragged array ``(seg_xy, edge_seg_ptr)``, each starting and
    ending exactly at its nodes."""
    e = len(u)
    if isinstance(geometry, Polylines):
        ptr = np.asarray(geometry.ptr, dtype=np.int64)
        if len(ptr) != e + 1 or (e and np.diff(ptr).min() < 2):
            raise GraphError("the polylines' ptr must have E+1 entries and every polyline 2 points")
        seg = np.array(geometry.xy, dtype=np.float64, copy=copy or None).reshape(-1, 2)
        if e:
            seg[ptr[:-1]] = xy[u]
            seg[ptr[1:] - 1] = xy[v]
        return seg, ptr
    if geometry is None:
        seg = np.empty((2 * e, 2), dtype=np.float64)
        seg[0::2] = xy[u]
        seg[1::2] = xy[v]
        return seg, np.arange(0, 2 * e + 1, 2, dtype=np.int64)
    if len(geometry) != e:
        raise GraphError("the geometry must have one polyline per edge")
    parts = []
    for i, g in enumerate(geometry):
        a = np.asarray(g, dtype=np.float64).reshape(-1, 2)
        if len(a) < 2:
            a = np.vstack([xy[u[i]], xy[v[i]]])
        else:
            a = a.copy()
            a[0] = xy[u[i]]
            a[-1] = xy[v[i]]
        parts.append(a)
    lens = np.array([len(p) for p in parts], dtype=np.int64)
    ptr = np.zeros(e + 1, dtype=np.int64)
    np.cumsum(lens, out=ptr[1:])
    seg = np.vstack(parts) if parts else np.empty((0, 2), dtype=np.float64)
    return seg, ptr


def _edge_lengths(seg: NDArray[np.float64], ptr: NDArray[np.int64]) -> NDArray[np.float64]:
    """Sum of segment lengths inside each polyline (the joins between polylines count 0)."""
    seglen = np.hypot(seg[1:, 0] - seg[:-1, 0], seg[1:, 1] - seg[:-1, 1])
    seglen[ptr[1:-1] - 1] = 0.0
    cum = np.zeros(len(seglen) + 1)
    np.cumsum(seglen, out=cum[1:])
    del seglen
    elen = cum[ptr[1:] - 1] - cum[ptr[:-1]] if len(ptr) > 1 else np.empty(0)
    return np.asarray(elen, dtype=np.float64)


def _piece_arrays(pieces: Pieces | None, e: int) -> dict[str, Any]:
    """The way-piece arrays but names and classes (checked); empty without pieces."""
    if pieces is None:
        return {}
    pe = np.asarray(pieces.edge, dtype=np.int64)
    ps = np.asarray(pieces.start, dtype=np.float64)
    p = len(pe)
    if len(ps) != p or len(pieces.way_id) != p or len(pieces.speed_kph) != p:
        raise GraphError("piece arrays differ in length")
    if p and (np.any(np.diff(pe) < 0) or pe.min() < 0 or pe.max() >= e):
        raise GraphError("pieces must be ordered by edge index in 0..E-1")
    pptr = np.zeros(e + 1, dtype=np.int64)
    np.cumsum(np.bincount(pe, minlength=e), out=pptr[1:])
    if e and (np.diff(pptr) == 0).any():
        raise GraphError("every edge needs at least one piece")
    if p and (np.abs(ps[pptr[:-1]]) > 1e-9).any():
        raise GraphError("each edge's first piece must start at offset 0")
    return {
        "piece_ptr": pptr,
        "piece_start": ps,
        "piece_way_id": np.asarray(pieces.way_id, dtype=np.int64),
        "piece_speed_kph": np.asarray(pieces.speed_kph, dtype=np.float32),
    }


def _column(values: Any, e: int, dtype: Any, missing: float) -> NDArray[Any]:
    """An edge attribute as an array of ``dtype``; ``missing`` everywhere when None."""
    return np.full(e, missing, dtype=dtype) if values is None else np.asarray(values, dtype=dtype)


def _labels(vals: Sequence[str | None] | Labels | None, k: int) -> Labels:
    if vals is None:
        return Labels(np.full(k, -1, dtype=np.int32), [])
    lab = vals if isinstance(vals, Labels) else Labels.of(vals)
    if len(lab.codes) != k:
        raise GraphError("an attribute list has the wrong length")
    return lab


def _tables(
    edge_vals: Sequence[str | None] | Labels | None,
    e: int,
    piece_vals: Sequence[str | None] | Labels | None,
    p: int,
) -> tuple[NDArray[np.int32], NDArray[np.int32], list[str]]:
    """Edge and piece codes into one table of the strings in order of first use (edges first)."""
    a, b = _labels(edge_vals, e), _labels(piece_vals, p)
    # one code space: the pieces' table after the edges'
    both = np.concatenate(
        [a.codes.astype(np.int64), np.where(b.codes >= 0, b.codes.astype(np.int64) + len(a.table), -1)]
    )
    text = [*a.table, *b.table]
    used = both >= 0
    key, first, inv = unique_inverse(both[used])
    # the same string from both tables is one entry: keep its first use
    s_of = [text[i] for i in key.tolist()]
    first_use: dict[str, int] = {}
    for s, f in zip(s_of, first.tolist(), strict=True):
        if s not in first_use or f < first_use[s]:
            first_use[s] = f
    table = sorted(first_use, key=first_use.__getitem__)
    rank = {s: i for i, s in enumerate(table)}
    code_of_key = np.asarray([rank[s] for s in s_of], dtype=np.int32)
    out = np.full(len(both), -1, dtype=np.int32)
    out[used] = code_of_key[inv]
    return out[:e], out[e:], table


def _end_bearings(
    seg: NDArray[np.float64], ptr: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Bearing of the first and last non-degenerate segment of each polyline."""
    e = len(ptr) - 1
    start = np.zeros(e, dtype=np.float64)
    end = np.zeros(e, dtype=np.float64)
    if e == 0:
        return start, end
    # first and last segment; fall back to chord when the segment is degenerate
    ds = seg[ptr[:-1] + 1] - seg[ptr[:-1]]
    de = seg[ptr[1:] - 1] - seg[ptr[1:] - 2]
    dc = seg[ptr[1:] - 1] - seg[ptr[:-1]]
    bad_s = np.hypot(ds[:, 0], ds[:, 1]) < 1e-9
    bad_e = np.hypot(de[:, 0], de[:, 1]) < 1e-9
    ds[bad_s] = dc[bad_s]
    de[bad_e] = dc[bad_e]
    start[:] = bearings(ds[:, 0], ds[:, 1])
    end[:] = bearings(de[:, 0], de[:, 1])
    return start, end


_PAIR_CHUNK = 100_000
"""Edge pairs whose polylines are compared at once."""


def _reverse_edges(
    u: NDArray[np.int32], v: NDArray[np.int32], seg: NDArray[np.float64], ptr: NDArray[np.int64]
) -> NDArray[np.int32]:
    """For each edge, the edge running v -> u along the same polyline reversed (within 1 cm), or -1.

    Edges are paired in index order, each with the first free candidate. A pair of ends
    with one edge each way (nearly all) is settled with whole-array steps; ends with
    parallel edges or a loop go through the rule one edge at a time.
    """
    e = len(u)
    rev = np.full(e, -1, dtype=np.int32)
    if e == 0:
        return rev
    n = int(max(u.max(), v.max())) + 1
    a, b = u.astype(np.int64), v.astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    group = lo * n + hi  # the unordered pair of ends
    order = np.lexsort((np.arange(e), a != lo, group))  # per group: lo -> hi first, each by index
    g = group[order]
    new = np.ones(e, dtype=bool)
    new[1:] = g[1:] != g[:-1]
    gstart = np.nonzero(new)[0]
    gsize = np.diff(np.append(gstart, e))
    n_fwd = np.add.reduceat((a[order] == lo[order]).astype(np.int64), gstart)
    simple = (gsize == 2) & (n_fwd == 1) & (lo[order[gstart]] != hi[order[gstart]])
    i, j = order[gstart[simple]], order[gstart[simple] + 1]
    same_len = (ptr[i + 1] - ptr[i]) == (ptr[j + 1] - ptr[j])
    i, j = i[same_len], j[same_len]
    for c in range(0, len(i), _PAIR_CHUNK):  # in chunks: a few vertex arrays per chunk
        ic, jc = i[c : c + _PAIR_CHUNK], j[c : c + _PAIR_CHUNK]
        k = ptr[ic + 1] - ptr[ic]
        t = np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k)
        pa = np.repeat(ptr[ic], k) + t
        pb = np.repeat(ptr[jc + 1] - 1, k) - t
        del t
        bad = (np.abs(seg[pa, 0] - seg[pb, 0]) > 0.01) | (np.abs(seg[pa, 1] - seg[pb, 1]) > 0.01)
        ok = np.bincount(np.repeat(np.arange(len(ic)), k), weights=bad, minlength=len(ic)) == 0
        rev[ic[ok]] = jc[ok]
        rev[jc[ok]] = ic[ok]
    for s0, sz in zip(gstart[~simple].tolist(), gsize[~simple].tolist(), strict=True):
        members = np.sort(order[s0 : s0 + sz]).tolist()
        for x in members:
            if rev[x] >= 0:
                continue
            for y in members:
                if y == x or rev[y] >= 0 or a[y] != b[x] or b[y] != a[x]:
                    continue
                lx = ptr[x + 1] - ptr[x]
                if ptr[y + 1] - ptr[y] != lx:
                    continue
                fx = seg[ptr[x] : ptr[x + 1]]
                fy = seg[ptr[y] : ptr[y + 1]][::-1]
                if (np.abs(fx - fy) <= 0.01).all():
                    rev[x] = y
                    rev[y] = x
                    break
    return rev
