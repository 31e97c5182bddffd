"""GIS road centre lines (GeoJSON, GeoPackage, Shapefile) -> raw MultiDiGraph.

Topology comes from shared line endpoints (within a snap tolerance); crossings without a
shared vertex stay unconnected (bridges) unless noding is asked for. One-way comes from a
configurable field and value convention.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import shapely
from numpy.typing import NDArray

from mapmatch.graph.components import union_find
from mapmatch.graph.errors import InputError
from mapmatch.graph.projection import utm_crs
from mapmatch.graph.simplify import RawNetwork, _text, compact_raw

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)

GIS_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp", ".fgb", ".parquet", ".geoparquet")

FORWARD = 1
BOTH = 0
REVERSE = -1


@dataclass(frozen=True)
class OnewayConvention:
    """How the values of a one-way field read (case-insensitive, compared as text).

    ``forward`` values make the feature one-way in digitised direction, ``reverse`` values
    one-way against it, ``both`` two-way. A missing value (null) means two-way; any other
    value is counted as unrecognised and read as two-way.
    """

    forward: frozenset[str] = frozenset({"true", "yes", "1", "y", "t", "ft"})
    reverse: frozenset[str] = frozenset({"-1", "tf", "reverse", "r"})
    both: frozenset[str] = frozenset({"false", "no", "0", "n", "f", "b", "both", ""})

    def code(self, value: Any) -> int | None:
        """``FORWARD``, ``REVERSE`` or ``BOTH`` for one value; ``None`` when unrecognised."""
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return BOTH
        if isinstance(value, bool | np.bool_):
            return FORWARD if value else BOTH
        if isinstance(value, int | float | np.integer | np.floating) and float(value).is_integer():
            value = int(value)
        s = str(value).strip().lower()
        if s in self.forward:
            return FORWARD
        if s in self.reverse:
            return REVERSE
        if s in self.both:
            return BOTH
        return None

    @classmethod
    def parse(cls, spec: str) -> OnewayConvention:
        """Parse ``"forward=yes,1;reverse=-1;both=no,0"`` (omitted groups keep their defaults)."""
        kw: dict[str, frozenset[str]] = {}
        for part in filter(None, (p.strip() for p in spec.split(";"))):
            key, _, vals = part.partition("=")
            key = key.strip().lower()
            if key not in ("forward", "reverse", "both"):
                raise InputError(f"one-way convention: unknown group {key!r} (use forward/reverse/both)")
            kw[key] = frozenset(v.strip().lower() for v in vals.split(","))
        return cls(**kw)


@dataclass(frozen=True)
class GisOptions:
    """Options for reading GIS road lines (all keyword, all optional).

    Attributes
    ----------
    oneway_field
        Field holding one-way information; ``None`` tries ``oneway``, ``one_way``, ``ONEWAY``,
        ``dir``, ``direction`` and otherwise treats every road as two-way.
    oneway_convention
        How that field's values read.
    name_field, speed_field, highway_field, id_field
        Optional fields for the road name, speed (km/h), road class and feature id;
        ``None`` tries common names (``name``; ``maxspeed``/``speed``; ``highway``/``class``;
        ``id``/``osm_id``).
    snap_tolerance
        Endpoints closer than this many metres become one node.
    node_crossings
        Split lines where they cross without a shared vertex (off by default: bridges).
    crs
        CRS to assume when the file has none (e.g. ``"EPSG:4326"``).
    layer
        Layer of a multi-layer source (GeoPackage).
    bbox
        ``(west, south, east, north)`` in degrees: keep only lines that intersect it.
    node_id_fields
        Integer fields with the ids of each line's first and last node; ``None`` uses ``u``
        and ``v`` when present (osmnx exports, Kubicka data).
    topology
        ``"auto"`` (default): nodes from the node id fields when present and each id sits at
        one place, else from shared endpoints; ``"endpoints"``: always from shared endpoints
        (the ids are kept as node ids only if they agree); ``"ids"``: from the id fields, or
        an error. With ids, distinct nodes at the same position (grade-separated crossings)
        stay apart.
    """

    oneway_field: str | None = None
    oneway_convention: OnewayConvention = field(default_factory=OnewayConvention)
    name_field: str | None = None
    speed_field: str | None = None
    highway_field: str | None = None
    id_field: str | None = None
    snap_tolerance: float = 0.01
    node_crossings: bool = False
    crs: str | None = None
    layer: str | None = None
    bbox: tuple[float, float, float, float] | None = None
    node_id_fields: tuple[str, str] | None = None
    topology: str = "auto"


def _pick(columns: Iterable[str], wanted: str | None, candidates: tuple[str, ...], what: str) -> str | None:
    cols = list(columns)
    if wanted is not None:
        if wanted not in cols:
            raise InputError(f"the {what} field {wanted!r} is not in the data (fields: {', '.join(cols)})")
        return wanted
    lower = {c.lower(): c for c in cols}
    for c in candidates:
        if c in lower:
            return lower[c]
    return None


def _parse_speed(value: Any) -> float:
    """Speed in km/h from a number or text such as ``"50"``, ``"30 mph"``; NaN when unknown."""
    if value is None:
        return math.nan
    if isinstance(value, int | float | np.integer | np.floating):
        return float(value) if float(value) > 0 else math.nan
    m = re.match(r"\s*([\d.]+)\s*(mph|knots|km/h|kmh|kph)?", str(value).lower())
    if not m:
        return math.nan
    try:
        v = float(m.group(1))
    except ValueError:
        return math.nan
    unit = m.group(2)
    if unit == "mph":
        v *= 1.609344
    elif unit == "knots":
        v *= 1.852
    return v if v > 0 else math.nan


def read_lines(path: Path, opts: GisOptions) -> tuple[Any, dict[str, int]]:
    """Read line features into a GeoDataFrame (exploded to LineStrings, in WGS84).

    Returns the frame and counts of dropped features by reason.
    """
    import pyogrio
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        if path.suffix.lower() in (".parquet", ".geoparquet"):  # GeoParquet (GDAL here lacks the driver)
            import geopandas as gpd

            gdf = gpd.read_parquet(path)
        else:
            layer = opts.layer
            if layer is None and path.suffix.lower() == ".gpkg":
                layers = pyogrio.list_layers(path)
                names = [str(n) for n in layers[:, 0]]
                layer = "roads" if "roads" in names else names[0] if names else None
            gdf = pyogrio.read_dataframe(path, layer=layer)
    except Exception as exc:  # pyogrio raises several unrelated types for unreadable files
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"cannot read {path.name} as GIS data: {msg}") from exc
    dropped: dict[str, int] = {}
    if gdf.geometry is None or len(gdf) == 0:
        raise InputError(f"{path.name} has no line features")
    geom = gdf.geometry.values
    types = shapely.get_type_id(geom)
    is_line = np.isin(types, [1, 5])  # LineString, MultiLineString
    n_null = int(shapely.is_missing(geom).sum())
    if n_null:
        dropped["no geometry"] = n_null
    n_other = int((~is_line).sum()) - n_null
    if n_other:
        dropped["not a line"] = n_other
    if not is_line.any():
        raise InputError(f"{path.name} has no line features (LineString or MultiLineString)")
    gdf = gdf[is_line]
    crs = gdf.crs
    if opts.crs is not None:
        try:
            crs = CRS.from_user_input(opts.crs)
        except CRSError as exc:
            raise InputError(f"unreadable CRS {opts.crs!r}: {exc}") from exc
        gdf = gdf.set_crs(crs, allow_override=True)
    if crs is None:
        x0, y0, x1, y1 = gdf.total_bounds
        if -180 <= x0 <= x1 <= 180 and -90 <= y0 <= y1 <= 90:
            log.warning("%s has no CRS; its coordinates look like lon/lat, assuming EPSG:4326", path.name)
            gdf = gdf.set_crs("EPSG:4326")
        else:
            raise InputError(
                f"{path.name} has no readable CRS and its coordinates are not lon/lat; give the CRS (--crs)"
            )
    try:
        if not CRS.from_user_input(gdf.crs).equals(CRS.from_epsg(4326)):
            gdf = gdf.to_crs("EPSG:4326")
    except Exception as exc:
        raise InputError(f"{path.name}: cannot transform from its CRS to lon/lat: {exc}") from exc
    if opts.bbox is not None:
        inside = gdf.intersects(shapely.box(*opts.bbox))
        if not inside.all():
            dropped["outside the bbox"] = int((~inside).sum())
        gdf = gdf[inside]
        if len(gdf) == 0:
            raise InputError(f"{path.name} has no line features inside the bbox")
    if (shapely.get_type_id(gdf.geometry.values) != 1).any():  # MultiLineStrings: one row per part
        gdf = gdf.explode(index_parts=False)
    geom = gdf.geometry.values
    ncoords = shapely.get_num_coordinates(geom)
    short = ncoords < 2
    if short.any():
        dropped["fewer than 2 points"] = int(short.sum())
        gdf = gdf[~short]
    return gdf, dropped


TOPOLOGIES = ("auto", "endpoints", "ids")


def lines_to_graph(
    path: Path, opts: GisOptions
) -> tuple[nx.MultiDiGraph, str, dict[str, int], dict[str, Any]]:
    """Read GIS road lines into a raw MultiDiGraph in the local UTM CRS (see :func:`lines_to_raw`)."""
    from mapmatch.graph.simplify import raw_to_nx

    raw, dropped, info = lines_to_raw(path, opts)
    return raw_to_nx(raw), raw.crs, dropped, info


def lines_to_raw(path: Path, opts: GisOptions) -> tuple[RawNetwork, dict[str, int], dict[str, Any]]:
    """Read GIS road lines into a raw network (arrays) in the local UTM CRS.

    Returns
    -------
    raw, dropped, info
        The raw network (every vertex a node), dropped features by reason, and the fields
        that were used.
    """
    from mapmatch.graph.projection import to_xy

    if opts.topology not in TOPOLOGIES:
        raise InputError(f"unknown topology {opts.topology!r} (use {', '.join(TOPOLOGIES)})")
    gdf, dropped = read_lines(path, opts)
    cols = [c for c in gdf.columns if c != gdf.geometry.name]
    oneway_f = _pick(cols, opts.oneway_field, ("oneway", "one_way", "dir", "direction"), "one-way")
    name_f = _pick(cols, opts.name_field, ("name",), "name")
    speed_f = _pick(cols, opts.speed_field, ("maxspeed", "speed", "speed_kph"), "speed")
    hw_f = _pick(cols, opts.highway_field, ("highway", "class", "fclass"), "highway")
    id_f = _pick(cols, opts.id_field, ("id", "way_id", "osm_id", "fid"), "id")
    info: dict[str, Any] = {
        "oneway_field": oneway_f,
        "name_field": name_f,
        "speed_field": speed_f,
        "highway_field": hw_f,
    }

    lines = np.asarray(gdf.geometry.values)
    n_feat = len(lines)
    fid = (
        np.asarray(gdf[id_f], dtype=np.int64)
        if id_f is not None and np.issubdtype(np.asarray(gdf[id_f]).dtype, np.integer)
        else np.arange(n_feat, dtype=np.int64)
    )
    if oneway_f is not None:
        inv, uniq = _factorize(gdf[oneway_f])
        ucodes = [opts.oneway_convention.code(v) for v in uniq]
        bad = sum(int((inv == i).sum()) for i, c in enumerate(ucodes) if c is None)
        if bad:
            dropped["unrecognised one-way value (read as two-way)"] = bad
        direction = np.array([BOTH if c is None else c for c in ucodes], dtype=np.int8)[inv]
    else:
        direction = np.zeros(n_feat, dtype=np.int8)
    names = gdf[name_f].tolist() if name_f else [None] * n_feat
    hws = gdf[hw_f].tolist() if hw_f else [None] * n_feat
    if speed_f:
        inv, uniq = _factorize(gdf[speed_f])
        speeds = np.array([_parse_speed(v) for v in uniq], dtype=np.float64)[inv].tolist()
    else:
        speeds = [math.nan] * n_feat

    b = shapely.bounds(lines)
    lon0 = float((np.nanmin(b[:, 0]) + np.nanmax(b[:, 2])) / 2)
    lat0 = float((np.nanmin(b[:, 1]) + np.nanmax(b[:, 3])) / 2)
    crs = utm_crs(lon0, lat0)

    if opts.node_crossings:
        lines, src = _node_lines(lines)
        fid, direction = fid[src], direction[src]
        names = [names[i] for i in src]
        hws = [hws[i] for i in src]
        speeds = [speeds[i] for i in src]
        n_feat = len(lines)

    ll, owner = shapely.get_coordinates(lines, return_index=True)
    xy = to_xy(crs, ll[:, 0], ll[:, 1])
    counts = np.bincount(owner, minlength=n_feat)
    start = np.zeros(n_feat + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    first, last = start[:-1], start[1:] - 1
    ends = np.concatenate([first, last])
    end_xy = xy[ends]
    src_ids = _endpoint_id_values(gdf, opts, n_feat)
    del gdf, lines  # the geometry objects: the coordinates are all that is needed now
    node_of_end, end_ids = None, None
    if opts.topology == "ids" or (opts.topology == "auto" and src_ids is not None):
        node_of_end, end_ids = _nodes_from_ids(src_ids, end_xy, opts)
    if node_of_end is None:
        node_of_end = _nodes_from_coords(end_xy, opts.snap_tolerance)
        end_ids = _consistent_ids(src_ids, node_of_end)
        info["topology"] = "shared endpoints"
    else:
        info["topology"] = "node id fields"
    n_end_nodes = int(node_of_end.max()) + 1 if len(node_of_end) else 0
    # node position: mean of its endpoints
    node_xy = np.zeros((n_end_nodes, 2))
    np.add.at(node_xy, node_of_end, end_xy)
    node_xy /= np.bincount(node_of_end, minlength=n_end_nodes)[:, None]
    node_ll = ll[ends][np.unique(node_of_end, return_index=True)[1]]
    r = np.round(end_xy, 6)[np.lexsort((np.round(end_xy[:, 1], 6), np.round(end_xy[:, 0], 6)))]
    n_places = int(len(r) and 1 + (r[1:] != r[:-1]).any(axis=1).sum())
    info["merged_endpoints"] = n_places - n_end_nodes

    # every vertex is a node: endpoints shared, interior vertices private to their feature
    vnode = np.empty(len(xy), dtype=np.int64)
    interior = np.ones(len(xy), dtype=bool)
    interior[ends] = False
    vnode[ends] = node_of_end
    vnode[interior] = n_end_nodes + np.arange(int(interior.sum()))
    all_xy = np.vstack([node_xy, xy[interior]])
    all_ll = np.vstack([node_ll, ll[interior]])
    # node keys are the source ids: u/v fields when they name the endpoints consistently,
    # else 0..N-1; interior vertices get negative keys
    info["node_ids"] = "u/v fields" if end_ids is not None else "generated"
    keys = np.concatenate(
        [
            end_ids if end_ids is not None else np.arange(n_end_nodes, dtype=np.int64),
            -1 - np.arange(int(interior.sum()), dtype=np.int64),
        ]
    )

    seg_a = np.arange(len(xy) - 1)
    seg_a = seg_a[owner[seg_a] == owner[seg_a + 1]]
    a_n, b_n = vnode[seg_a], vnode[seg_a + 1]
    f = owner[seg_a]
    d = xy[seg_a + 1] - xy[seg_a]
    seg_len = np.hypot(d[:, 0], d[:, 1])
    ok = a_n != b_n
    a_n, b_n, fo = a_n[ok], b_n[ok], f[ok]
    dirn = direction[fo]
    fwd = (dirn == BOTH) | (dirn == FORWARD)
    bwd = (dirn == BOTH) | (dirn == REVERSE)
    # per segment: forward then backward, as the segments come
    src = np.stack([np.where(fwd, a_n, -1), np.where(bwd, b_n, -1)], axis=1).ravel()
    dst = np.stack([b_n, a_n], axis=1).ravel()
    feat = np.repeat(fo, 2)
    use = src >= 0
    raw = RawNetwork(
        crs=crs,
        node_key=keys,
        node_xy=all_xy,
        node_lonlat=all_ll,
        edge_src=src[use].astype(np.int64),
        edge_dst=dst[use].astype(np.int64),
        edge_feat=feat[use].astype(np.int64),
        edge_oneway=(direction[feat[use]] != BOTH),
        feat_way_id=fid.astype(np.int64),
        feat_name=[_text(x) for x in names],
        feat_highway=[_text(x) for x in hws],
        feat_speed_kph=np.asarray(speeds, dtype=np.float64),
    )
    # features that collapsed to one point
    flen = np.bincount(f, weights=seg_len, minlength=n_feat)
    collapsed = int((flen <= opts.snap_tolerance).sum())
    if collapsed:
        dropped["zero length after snapping"] = collapsed
    return compact_raw(raw), dropped, info


def _factorize(column: Any) -> tuple[NDArray[np.int64], list[Any]]:
    """Codes into the distinct values of a column (missing values, NaN included, kept as one)."""
    import pandas as pd

    codes, uniq = pd.factorize(column, use_na_sentinel=False)
    vals = [None if (isinstance(v, float) and v != v) or v is pd.NA else v for v in list(uniq)]
    return np.asarray(codes, dtype=np.int64), vals


def _endpoint_id_values(gdf: Any, opts: GisOptions, n_feat: int) -> NDArray[np.int64] | None:
    """Ids of every line's first then last node from the u/v fields, or None when unusable.

    Unusable: fields absent, not integers, negative, or lines split into parts or pieces
    (multi-part lines, noding), which have no ids of their own.
    """
    fields = opts.node_id_fields
    if fields is None:
        cols = {c.lower(): c for c in gdf.columns}
        if "u" not in cols or "v" not in cols:
            return None
        fields = (cols["u"], cols["v"])
    elif any(f not in gdf.columns for f in fields):
        raise InputError(f"node id fields {', '.join(fields)} are not in the data")
    if opts.node_crossings or gdf.index.has_duplicates or len(gdf) != n_feat:
        return None
    try:
        ids = np.concatenate(
            [np.asarray(gdf[fields[0]], dtype=np.int64), np.asarray(gdf[fields[1]], dtype=np.int64)]
        )
    except (TypeError, ValueError):
        return None
    return ids if (ids >= 0).all() else None


def _nodes_from_ids(
    ids: NDArray[np.int64] | None, end_xy: NDArray[np.float64], opts: GisOptions
) -> tuple[NDArray[np.int64] | None, NDArray[np.int64] | None]:
    """Endpoint -> node from the id fields, if every id sits at one place (within 1 m or the
    snap tolerance). Returns ``(None, None)`` for ``topology="auto"`` when that fails."""
    if ids is None:
        if opts.topology == "ids":
            raise InputError("topology from node ids needs integer u/v fields (see --node-id-fields)")
        return None, None
    uniq, inv = np.unique(ids, return_inverse=True)
    inv = inv.ravel()
    n = len(uniq)
    mean = np.zeros((n, 2))
    np.add.at(mean, inv, end_xy)
    mean /= np.bincount(inv, minlength=n)[:, None]
    spread = float(np.hypot(*(end_xy - mean[inv]).T).max()) if len(inv) else 0.0
    if spread > max(1.0, opts.snap_tolerance):
        if opts.topology == "ids":
            raise InputError(f"node id fields name line ends up to {spread:.1f} m apart: not node ids")
        log.warning("u/v fields name line ends up to %.1f m apart; using shared endpoints instead", spread)
        return None, None
    return inv.astype(np.int64), uniq.astype(np.int64)


def _nodes_from_coords(end_xy: NDArray[np.float64], tol: float) -> NDArray[np.int64]:
    """Endpoint -> node: identical positions first, then snapping within ``tol`` metres."""
    r = np.round(end_xy, 6)
    order = np.lexsort((r[:, 1], r[:, 0]))  # as np.unique(axis=0) orders them, much faster
    rs = r[order]
    new = np.ones(len(rs), dtype=bool)
    new[1:] = (rs[1:] != rs[:-1]).any(axis=1)
    uniq = rs[new]
    inv = np.empty(len(r), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    if tol > 0 and len(uniq) > 1:
        tree = shapely.STRtree(shapely.points(uniq))
        pa, pb = tree.query(shapely.points(uniq), predicate="dwithin", distance=tol)
        keep = pa < pb
        lab = union_find(len(uniq), pa[keep].astype(np.int64), pb[keep].astype(np.int64))
        _, lab = np.unique(lab, return_inverse=True)
    else:
        lab = np.arange(len(uniq))
    return np.asarray(lab, dtype=np.int64).ravel()[inv]


def _consistent_ids(
    ids: NDArray[np.int64] | None, node_of_end: NDArray[np.int64]
) -> NDArray[np.int64] | None:
    """One id per node when the u/v fields agree with the coordinate topology, else None."""
    if ids is None or not len(node_of_end):
        return None
    n = int(node_of_end.max()) + 1
    out = np.full(n, -1, dtype=np.int64)
    out[node_of_end] = ids
    if (out < 0).any() or not np.array_equal(out[node_of_end], ids) or len(np.unique(out)) != n:
        log.info("u/v fields do not match the shared endpoints; generating node ids")
        return None
    return out


def _node_lines(lines: NDArray[Any]) -> tuple[NDArray[Any], NDArray[np.int64]]:
    """Split lines at every crossing; each piece keeps the index of the line it came from."""
    pieces = shapely.get_parts(shapely.node(shapely.multilinestrings(lines)))
    tree = shapely.STRtree(lines)
    mid = shapely.line_interpolate_point(pieces, 0.5, normalized=True)
    pi, li = tree.query(mid, predicate="dwithin", distance=1e-9)
    src = np.full(len(pieces), -1, dtype=np.int64)
    src[pi[::-1]] = li[::-1]  # first match wins
    ok = src >= 0
    pieces, src = pieces[ok], src[ok]
    # orient each piece like its source line
    proj_a = shapely.line_locate_point(lines[src], shapely.get_point(pieces, 0))
    proj_b = shapely.line_locate_point(lines[src], shapely.get_point(pieces, -1))
    flip = proj_b < proj_a
    pieces[flip] = shapely.reverse(pieces[flip])
    return pieces, src
