"""Export a RoadGraph as GIS road lines that ``mapmatch prep`` reads back into the same map.

Every road is written once, one feature per way piece: a two-way road (an edge and its
reverse) as one line along its lower-numbered edge with ``oneway`` false, a one-way road as
a line in its direction of travel with ``oneway`` true. ``u``/``v`` name the nodes at the
line's ends (the map's node ids at intersections and dead ends, fresh ids above them where a
piece boundary falls inside an edge), so the import's topology comes from the ids and the
simplification joins the pieces of an edge again. Coordinates are WGS84 lon/lat.

Formats by suffix: ``.gpkg`` (layers ``roads`` then ``nodes``), ``.geojson``/``.json``,
``.fgb`` (FlatGeobuf) and ``.parquet`` (GeoParquet), the last three with ``roads`` only.
Written to a temporary file, then renamed. The columns are documented in ``docs/formats.md``
("Exported roads").
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.errors import GraphError
from graph.extras import require_prep
from graph.projection import to_lonlat
from graph.road_graph import RoadGraph

EXPORT_SUFFIXES = (".geojson", ".json", ".gpkg", ".fgb", ".parquet", ".geoparquet")
ROAD_COLUMNS = (
    "way_id",
    "name",
    "highway",
    "maxspeed",
    "oneway",
    "u",
    "v",
    "edge",
    "reverse_edge",
    "piece",
    "offset_m",
    "length_m",
    "edge_length_m",
)
NODE_COLUMNS = ("node", "osm_id", "lon", "lat", "out_degree", "in_degree")


def _piece_vertices(graph: RoadGraph) -> NDArray[np.int64]:
    """For each piece, the index in ``seg_xy`` of the vertex where it starts."""
    seg, ptr = graph.seg_xy, graph.edge_seg_ptr
    d = np.hypot(*np.diff(seg, axis=0).T) if len(seg) > 1 else np.zeros(0)
    cum = np.concatenate([[0.0], np.cumsum(d)])  # monotone over all edges (joins included)
    edge = np.repeat(np.arange(graph.n_edges), np.diff(graph.piece_ptr))
    target = cum[ptr[edge]] + graph.piece_start
    a = np.clip(np.searchsorted(cum, target - 1e-6), ptr[edge], ptr[edge + 1] - 1)
    b = np.clip(a - 1, ptr[edge], None)
    closer = np.abs(cum[b] - target) < np.abs(cum[a] - target)
    return np.where(closer, b, a)


def roads_frame(graph: RoadGraph) -> Any:
    """The ``roads`` table: one row per way piece of every road (two-way roads once)."""
    import geopandas as gpd
    import shapely

    e_all = np.arange(graph.n_edges)
    rev = graph.edge_reverse
    keep = (rev < 0) | (e_all < rev)
    pe = np.repeat(e_all, np.diff(graph.piece_ptr))  # edge of each piece
    rank = np.arange(graph.n_pieces) - graph.piece_ptr[pe]
    first_v = _piece_vertices(graph)
    last_edge_piece = np.r_[pe[1:] != pe[:-1], True] if graph.n_pieces else np.zeros(0, bool)
    end_v = np.where(last_edge_piece, graph.edge_seg_ptr[pe + 1] - 1, np.r_[first_v[1:], 0])
    sel = keep[pe]
    p = np.nonzero(sel)[0]
    a, b = first_v[p], end_v[p]
    counts = b - a + 1
    owner = np.repeat(np.arange(len(p)), counts)
    vert = np.repeat(a - np.r_[0, np.cumsum(counts)[:-1]], counts) + np.arange(int(counts.sum()))
    xy = graph.seg_xy[vert]
    ll = to_lonlat(graph.crs, xy[:, 0], xy[:, 1]) if len(xy) else np.empty((0, 2))
    lines = shapely.linestrings(ll, indices=owner) if len(p) else np.empty(0, dtype=object)
    # node ids at the ends: the map's ids at nodes, fresh ids at boundaries inside an edge
    ids = graph.node_id.astype(np.int64).copy()
    base = int(max(ids.max(initial=-1), -1)) + 1
    neg = ids < 0
    ids[neg] = base + np.arange(int(neg.sum()))  # generated (negative) ids cannot be GIS node ids
    base += int(neg.sum())
    inner = ~last_edge_piece[p]  # a boundary after this piece, inside its edge
    inner_id = base + np.cumsum(inner) - 1
    u = np.where(rank[p] == 0, ids[graph.edge_u[pe[p]]], np.r_[0, inner_id[:-1]])
    v = np.where(inner, inner_id, ids[graph.edge_v[pe[p]]])
    names = np.array([*graph.names, None], dtype=object)
    hws = np.array([*graph.highways, None], dtype=object)
    start = graph.piece_start[p]
    end = graph.piece_end(p) if len(p) else np.zeros(0)
    speed = graph.piece_speed_kph[p].astype(np.float64)
    return gpd.GeoDataFrame(
        {
            "way_id": graph.piece_way_id[p],
            "name": names[graph.piece_name_idx[p]],
            "highway": hws[graph.piece_highway_idx[p]],
            "maxspeed": np.where(np.isfinite(speed), np.round(speed, 3), np.nan),
            "oneway": rev[pe[p]] < 0,
            "u": u.astype(np.int64),
            "v": v.astype(np.int64),
            "edge": pe[p].astype(np.int64),
            "reverse_edge": rev[pe[p]].astype(np.int64),
            "piece": rank[p].astype(np.int64),
            "offset_m": np.round(start, 3),
            "length_m": np.round(end - start, 3),
            "edge_length_m": np.round(graph.edge_len[pe[p]], 3),
        },
        geometry=lines,
        crs="EPSG:4326",
    )


def nodes_frame(graph: RoadGraph) -> Any:
    """The ``nodes`` table: one row per node (GeoPackage only)."""
    import geopandas as gpd
    import shapely

    n = graph.n_nodes
    return gpd.GeoDataFrame(
        {
            "node": np.arange(n, dtype=np.int64),
            "osm_id": graph.node_id,
            "lon": graph.node_lonlat[:, 0],
            "lat": graph.node_lonlat[:, 1],
            "out_degree": np.diff(graph.out_ptr),
            "in_degree": np.diff(graph.in_ptr),
        },
        geometry=shapely.points(graph.node_lonlat) if n else np.empty(0, dtype=object),
        crs="EPSG:4326",
    )


def export_map(graph: RoadGraph, path: str | os.PathLike[str]) -> None:
    """Write the roads (and for GeoPackage the nodes) of ``graph`` to ``path``.

    Raises
    ------
    GraphError
        Unknown suffix, or the file cannot be written; :class:`graph.errors.MissingExtraError`
        when the ``prep`` extra is not installed.
    """
    require_prep(needed_for="map export", modules=("geopandas", "pyogrio"))
    import pyogrio

    dest = Path(path)
    suffix = dest.suffix.lower()
    if suffix not in EXPORT_SUFFIXES:
        raise GraphError(f"export: unknown format {dest.name} (use {', '.join(EXPORT_SUFFIXES)})")
    roads = roads_frame(graph)
    tmp = ""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=suffix, dir=dest.parent)
        os.close(fd)
        os.unlink(tmp)
        if suffix == ".gpkg":
            pyogrio.write_dataframe(roads, tmp, layer="roads", driver="GPKG")
            pyogrio.write_dataframe(nodes_frame(graph), tmp, layer="nodes", driver="GPKG", append=True)
        elif suffix in (".parquet", ".geoparquet"):
            roads.to_parquet(tmp, index=False)
        elif suffix == ".fgb":
            pyogrio.write_dataframe(roads, tmp, layer="roads", driver="FlatGeobuf")
        else:
            pyogrio.write_dataframe(roads, tmp, layer="roads", driver="GeoJSON")
        os.replace(tmp, dest)
    except Exception as exc:
        if tmp:
            Path(tmp).unlink(missing_ok=True)
        raise GraphError(f"export to {dest} failed: {exc}") from exc
