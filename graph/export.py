"""Export a RoadGraph's nodes and edges with their ids to GeoJSON or GeoPackage (for QGIS).

GeoPackage gets two layers, ``edges`` and ``nodes``. GeoJSON gets one FeatureCollection with
both (property ``kind`` is ``"edge"`` or ``"node"``; QGIS offers them as two sub-layers).
Coordinates are WGS84 lon/lat. Written to a temporary file, then renamed.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from graph.errors import GraphError
from graph.projection import to_lonlat
from graph.road_graph import RoadGraph

EXPORT_SUFFIXES = (".geojson", ".json", ".gpkg")


def _frames(graph: RoadGraph) -> tuple[Any, Any]:
    import geopandas as gpd
    import shapely

    e = graph.n_edges
    ll = (
        to_lonlat(graph.crs, graph.seg_xy[:, 0], graph.seg_xy[:, 1])
        if len(graph.seg_xy)
        else np.empty((0, 2))
    )
    owner = np.repeat(np.arange(e), np.diff(graph.edge_seg_ptr))
    lines = shapely.linestrings(ll, indices=owner) if e else np.empty(0, dtype=object)
    names = np.array([*graph.names, ""], dtype=object)
    hws = np.array([*graph.highways, ""], dtype=object)
    edges = gpd.GeoDataFrame(
        {
            "kind": np.full(e, "edge", dtype=object),
            "edge": np.arange(e, dtype=np.int64),
            "u": graph.edge_u.astype(np.int64),
            "v": graph.edge_v.astype(np.int64),
            "u_osm": graph.node_id[graph.edge_u],
            "v_osm": graph.node_id[graph.edge_v],
            "way_id": graph.edge_way_id,
            "name": names[graph.edge_name_idx],
            "highway": hws[graph.edge_highway_idx],
            "length_m": np.round(graph.edge_len, 3),
            "oneway": graph.edge_reverse < 0,
            "reverse_edge": graph.edge_reverse.astype(np.int64),
            "speed_kph": graph.edge_speed_kph.astype(np.float64),
            "bearing_start": np.round(graph.edge_bearing_start, 2),
            "bearing_end": np.round(graph.edge_bearing_end, 2),
        },
        geometry=lines,
        crs="EPSG:4326",
    )
    n = graph.n_nodes
    nodes = gpd.GeoDataFrame(
        {
            "kind": np.full(n, "node", dtype=object),
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
    return edges, nodes


def _nullable(df: Any) -> Any:
    """Integer and bool columns as pandas nullable types, so the other kind's rows are null."""
    out = df.copy()
    for c in out.columns:
        if c == out.geometry.name:
            continue
        if out[c].dtype.kind in "iu":
            out[c] = out[c].astype("Int64")
        elif out[c].dtype.kind == "b":
            out[c] = out[c].astype("boolean")
    return out


def export_map(graph: RoadGraph, path: str | os.PathLike[str]) -> None:
    """Write nodes and edges of ``graph`` to ``path`` (``.geojson`` or ``.gpkg``).

    Raises
    ------
    GraphError
        Unknown suffix, or the file cannot be written.
    """
    import pandas as pd
    import pyogrio

    dest = Path(path)
    suffix = dest.suffix.lower()
    if suffix not in EXPORT_SUFFIXES:
        raise GraphError(f"export: unknown format {dest.name} (use .geojson or .gpkg)")
    edges, nodes = _frames(graph)
    tmp = ""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=suffix, dir=dest.parent)
        os.close(fd)
        os.unlink(tmp)
        if suffix == ".gpkg":
            pyogrio.write_dataframe(edges.drop(columns="kind"), tmp, layer="edges", driver="GPKG")
            pyogrio.write_dataframe(
                nodes.drop(columns="kind"), tmp, layer="nodes", driver="GPKG", append=True
            )
        else:
            both = pd.concat([_nullable(edges), _nullable(nodes)], ignore_index=True)
            pyogrio.write_dataframe(both, tmp, layer=dest.stem, driver="GeoJSON")
        os.replace(tmp, dest)
    except Exception as exc:
        if tmp:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, GraphError):
            raise
        raise GraphError(f"export to {dest} failed: {exc}") from exc
