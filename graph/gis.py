"""GIS road centre lines (GeoJSON, GeoPackage, Shapefile, FlatGeobuf, GeoParquet) -> raw network.

The lines are read batch by batch from pyogrio's Arrow stream (pyarrow's for GeoParquet)
straight into coordinate arrays; only the attribute fields the build uses are kept, and no
GeoDataFrame is made. Topology comes from shared line endpoints (within a snap tolerance); crossings without a
shared vertex stay unconnected (bridges) unless noding is asked for. One-way comes from a
configurable field and value convention.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import shapely
from numpy.typing import NDArray

from mapmatch.graph.components import union_find
from mapmatch.graph.errors import InputError
from mapmatch.graph.keys import dense_labels, unique, unique_inverse
from mapmatch.graph.projection import utm_crs
from mapmatch.graph.raw_network import RawNetwork, compact_raw
from mapmatch.graph.road_graph import Labels
from mapmatch.graph.simplify import _text

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
    directed
        Every line is one way, in the direction it is drawn: a network of directed arcs, where
        a two-way road is two lines (FMM's and fastmm's network files, routing-engine exports).
        No one-way field is read then.
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
    directed: bool = False


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


class Lines(NamedTuple):
    """Line features as arrays (multi-part lines split into one line per part, in WGS84).

    Line ``i`` runs through ``lonlat[ptr[i]:ptr[i+1]]`` and came from source row ``row[i]``;
    ``columns`` holds the attribute columns that were read, one value per source row.
    """

    lonlat: NDArray[np.float64]
    ptr: NDArray[np.int64]
    row: NDArray[np.int64]
    columns: dict[str, Any]
    fields: list[str]

    @property
    def n_lines(self) -> int:
        return len(self.row)

    def column(self, name: str) -> Any:
        """The values of one attribute column per line (a pyarrow array)."""
        return self.columns[name].take(self.row)


ReadProgress = Callable[[int, int], None]
"""Called with (features read so far, features in the source; 0 when unknown)."""


def _geoparquet_meta(pf: Any, path: Path) -> dict[str, Any]:
    import json

    raw = (pf.schema_arrow.metadata or {}).get(b"geo")
    if raw is None:
        raise InputError(f"{path.name} is a Parquet file without GeoParquet metadata")
    geo: dict[str, Any] = json.loads(raw)
    col = geo["columns"][geo["primary_column"]]
    if str(col.get("encoding", "WKB")).upper() != "WKB":
        raise InputError(f"{path.name}: GeoParquet encoding {col.get('encoding')!r} is not read (only WKB)")
    return geo


def _geoparquet_crs(geo: dict[str, Any]) -> Any:
    """The primary column's CRS: PROJJSON, or lon/lat when the key is absent (the spec's default)."""
    col = geo["columns"][geo["primary_column"]]
    if "crs" not in col:
        return "OGC:CRS84"
    return col["crs"]


BATCH_ROWS = 65_536
"""Features per batch read: the geometry objects of one batch at a time exist."""


def read_lines(
    src: Source, opts: GisOptions, *, want: Iterable[str | None] = (), progress: ReadProgress | None = None
) -> tuple[Lines, dict[str, int]]:
    """Read line features into arrays, batch by batch through pyogrio's Arrow reader (pyarrow
    for GeoParquet): each batch's WKB becomes coordinates and is dropped.

    ``want`` names the attribute fields to read (the others are not). Returns the lines
    and counts of dropped features by reason.
    """
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    path, fields, src_crs, total, batches = src
    cols = [c for c in dict.fromkeys(w for w in want if w is not None) if c in fields]
    counts_by: dict[str, int] = {}
    parts_ll: list[NDArray[np.float64]] = []
    parts_n: list[NDArray[np.int64]] = []
    parts_row: list[NDArray[np.int64]] = []
    col_parts: dict[str, list[Any]] = {c: [] for c in cols}
    n_rows = 0
    n_lines_in = 0

    def _drop(reason: str, n: int) -> None:
        counts_by[reason] = counts_by.get(reason, 0) + n

    try:
        for attrs, wkb in batches(cols):
            for c in cols:
                col_parts[c].append(attrs[c])
            n_batch = len(wkb)
            fast = _plain_linestrings(wkb)
            if fast is not None:  # every feature a 2D LineString: no geometry objects
                ll, n_pts = fast
                parts_ll.append(ll)
                parts_n.append(n_pts)
                parts_row.append(n_rows + np.arange(n_batch, dtype=np.int64))
                n_lines_in += n_batch
                n_rows += n_batch
                if progress is not None:
                    progress(n_rows, total)
                continue
            geom = shapely.from_wkb(wkb.to_numpy(zero_copy_only=False))
            del wkb
            types = shapely.get_type_id(geom)
            is_line = (types == 1) | (types == 5)  # LineString, MultiLineString
            missing = shapely.is_missing(geom)
            _drop("no geometry", int(missing.sum()))
            _drop("not a line", int((~is_line & ~missing).sum()))
            n_lines_in += int(is_line.sum())
            rows = np.nonzero(is_line)[0]
            geom = geom[rows]
            lines, part_of = shapely.get_parts(geom, return_index=True)
            del geom
            ll, owner = shapely.get_coordinates(lines, return_index=True)
            del lines
            parts_ll.append(ll)
            parts_n.append(np.bincount(owner, minlength=len(part_of)).astype(np.int64))
            parts_row.append(n_rows + rows[part_of])
            n_rows += len(types)
            if progress is not None:
                progress(n_rows, total)
    except InputError:
        raise
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"cannot read {path.name} as GIS data: {msg}") from exc
    if n_lines_in == 0:
        raise InputError(f"{path.name} has no line features (LineString or MultiLineString)")
    lonlat = np.concatenate(parts_ll) if parts_ll else np.zeros((0, 2))
    counts = np.concatenate(parts_n) if parts_n else np.zeros(0, dtype=np.int64)
    row = np.concatenate(parts_row) if parts_row else np.zeros(0, dtype=np.int64)
    del parts_ll, parts_n, parts_row
    import pyarrow as pa

    columns = {
        c: pa.concat_arrays([_chunk(x) for x in v]) if v else pa.array([]) for c, v in col_parts.items()
    }
    # CRS: the source's, the one given, or lon/lat when the coordinates fit
    crs: Any = src_crs
    if opts.crs is not None:
        try:
            crs = CRS.from_user_input(opts.crs)
        except CRSError as exc:
            raise InputError(f"unreadable CRS {opts.crs!r}: {exc}") from exc
    if crs is None:
        x0, y0 = np.nanmin(lonlat, axis=0) if len(lonlat) else (0.0, 0.0)
        x1, y1 = np.nanmax(lonlat, axis=0) if len(lonlat) else (0.0, 0.0)
        if -180 <= x0 <= x1 <= 180 and -90 <= y0 <= y1 <= 90:
            log.warning("%s has no CRS; its coordinates look like lon/lat, assuming EPSG:4326", path.name)
            crs = "EPSG:4326"
        else:
            raise InputError(
                f"{path.name} has no readable CRS and its coordinates are not lon/lat; give the CRS (--crs)"
            )
    try:
        crs = CRS.from_user_input(crs)
        if not crs.equals(CRS.from_epsg(4326)):
            from pyproj import Transformer

            tf = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
            lon, lat = tf.transform(lonlat[:, 0], lonlat[:, 1])
            lonlat = np.column_stack([lon, lat])
    except Exception as exc:
        raise InputError(f"{path.name}: cannot transform from its CRS to lon/lat: {exc}") from exc
    short = counts < 2
    if opts.bbox is not None:  # keep the features with a part that meets the box
        ok = ~short
        part_lines = shapely.linestrings(
            lonlat[np.repeat(ok, counts)], indices=np.repeat(np.arange(int(ok.sum())), counts[ok])
        )
        hit = np.zeros(n_rows, dtype=bool)
        hit[row[ok][shapely.intersects(part_lines, shapely.box(*opts.bbox))]] = True
        hit[row[short]] |= ~np.isin(row[short], row[ok])
        del part_lines
        had = np.zeros(n_rows, dtype=bool)
        had[row] = True
        _drop("outside the bbox", int((had & ~hit).sum()))
        inside = hit[row]
        if not inside.any():
            raise InputError(f"{path.name} has no line features inside the bbox")
        lonlat, counts, row, short = (
            lonlat[np.repeat(inside, counts)],
            counts[inside],
            row[inside],
            short[inside],
        )
    if short.any():
        _drop("fewer than 2 points", int(short.sum()))
        keep_pt = np.repeat(~short, counts)
        lonlat, counts, row = lonlat[keep_pt], counts[~short], row[~short]
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    reasons = ("no geometry", "not a line", "outside the bbox", "fewer than 2 points")
    dropped = {k: counts_by[k] for k in reasons if counts_by.get(k)}
    return Lines(
        lonlat=np.ascontiguousarray(lonlat, dtype=np.float64),
        ptr=ptr,
        row=row,
        columns=columns,
        fields=fields,
    ), dropped


def _plain_linestrings(wkb: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]] | None:
    """Coordinates and point counts straight from a WKB column whose features are all
    little-endian 2D LineStrings (GDAL's and GeoParquet's usual output); None otherwise.

    Such a WKB is a 9-byte header (byte order, type 2, point count) and the points as float64
    pairs, so the column's data without the headers is the coordinate array.
    """
    import pyarrow as pa

    if isinstance(wkb, pa.ChunkedArray):
        wkb = wkb.combine_chunks()
    if (
        wkb.null_count
        or not len(wkb)
        or not (pa.types.is_binary(wkb.type) or pa.types.is_large_binary(wkb.type))
    ):
        return None
    _, off_buf, data_buf = wkb.buffers()
    off_type = np.int64 if pa.types.is_large_binary(wkb.type) else np.int32
    off = np.frombuffer(off_buf, dtype=off_type)[wkb.offset : wkb.offset + len(wkb) + 1].astype(np.int64)
    data = np.frombuffer(data_buf, dtype=np.uint8)
    size = np.diff(off)
    if (size < 9).any():
        return None
    head = off[:-1]
    le = data[head] == 1
    kind = data[head + 1].astype(np.uint32) | data[head + 2].astype(np.uint32) << 8
    kind |= data[head + 3].astype(np.uint32) << 16 | data[head + 4].astype(np.uint32) << 24
    n = data[head + 5].astype(np.int64) | data[head + 6].astype(np.int64) << 8
    n |= data[head + 7].astype(np.int64) << 16 | data[head + 8].astype(np.int64) << 24
    if not (le.all() and (kind == 2).all() and (size == 9 + 16 * n).all()):
        return None
    keep = np.ones(int(off[-1] - off[0]), dtype=bool)
    keep[(head - off[0])[:, None] + np.arange(9)] = False
    coords = data[off[0] : off[-1]][keep].view(np.float64).reshape(-1, 2)
    return coords, n


def _chunk(a: Any) -> Any:
    """One pyarrow Array from an Array or ChunkedArray."""
    import pyarrow as pa

    return a.combine_chunks() if isinstance(a, pa.ChunkedArray) else a


TOPOLOGIES = ("auto", "endpoints", "ids")


def lines_to_graph(
    path: Path, opts: GisOptions
) -> tuple[nx.MultiDiGraph, str, dict[str, int], dict[str, Any]]:
    """Read GIS road lines into a raw MultiDiGraph in the local UTM CRS (see :func:`lines_to_raw`)."""
    from mapmatch.graph.raw_network import raw_to_nx

    raw, dropped, info = lines_to_raw(path, opts)
    return raw_to_nx(raw), raw.crs, dropped, info


def lines_to_raw(
    path: Path, opts: GisOptions, *, progress: ReadProgress | None = None
) -> tuple[RawNetwork, dict[str, int], dict[str, Any]]:
    """Read GIS road lines into a raw network (arrays) in the local UTM CRS.

    Returns
    -------
    raw, dropped, info
        The raw network (every vertex a node), dropped features by reason, and the fields
        that were used.
    """
    if opts.topology not in TOPOLOGIES:
        raise InputError(f"unknown topology {opts.topology!r} (use {', '.join(TOPOLOGIES)})")
    with open_source(path, opts) as source:
        fields = source.fields
        if opts.directed and opts.oneway_field is not None:
            raise InputError("directed lines have no one-way field: give one of the two, not both")
        oneway_f = (
            None
            if opts.directed
            else _pick(fields, opts.oneway_field, ("oneway", "one_way", "dir", "direction"), "one-way")
        )
        name_f = _pick(fields, opts.name_field, ("name",), "name")
        speed_f = _pick(fields, opts.speed_field, ("maxspeed", "speed", "speed_kph"), "speed")
        hw_f = _pick(fields, opts.highway_field, ("highway", "class", "fclass"), "highway")
        id_f = _pick(fields, opts.id_field, ("id", "way_id", "osm_id", "fid"), "id")
        uv_f = _node_id_fields(fields, opts)
        info: dict[str, Any] = {
            "directed": opts.directed,
            "oneway_field": oneway_f,
            "name_field": name_f,
            "speed_field": speed_f,
            "highway_field": hw_f,
        }
        lines, dropped = read_lines(
            source, opts, want=(oneway_f, name_f, speed_f, hw_f, id_f, *(uv_f or ())), progress=progress
        )
    return _lines_to_raw(lines, dropped, info, (oneway_f, name_f, speed_f, hw_f, id_f), uv_f, opts)


def _lines_to_raw(
    lines: Lines,
    dropped: dict[str, int],
    info: dict[str, Any],
    picked: tuple[str | None, ...],
    uv_f: tuple[str, str] | None,
    opts: GisOptions,
) -> tuple[RawNetwork, dict[str, int], dict[str, Any]]:
    """:func:`lines_to_raw` once the lines are read (``picked``: the one-way, name, speed,
    class and id fields)."""
    from mapmatch.graph.projection import to_xy

    oneway_f, name_f, speed_f, hw_f, id_f = picked

    n_feat = lines.n_lines
    fid = _int_column(lines, id_f) if id_f is not None else None
    if fid is None and opts.id_field is not None:
        raise InputError(f"the id field {opts.id_field!r} does not hold integers on every line")
    info["id_field"] = id_f if fid is not None else None  # None: ids are row numbers
    if fid is None:
        fid = np.arange(n_feat, dtype=np.int64)
    if oneway_f is not None:
        inv, uniq = _factorize(lines.column(oneway_f))
        ucodes = [opts.oneway_convention.code(v) for v in uniq]
        bad = sum(int((inv == i).sum()) for i, c in enumerate(ucodes) if c is None)
        if bad:
            dropped["unrecognised one-way value (read as two-way)"] = bad
        direction = np.array([BOTH if c is None else c for c in ucodes], dtype=np.int8)[inv]
    else:
        direction = np.full(n_feat, FORWARD if opts.directed else BOTH, dtype=np.int8)
    names = _labels(lines, name_f)
    hws = _labels(lines, hw_f)
    if speed_f:
        inv, uniq = _factorize(lines.column(speed_f))
        speeds = np.array([_parse_speed(v) for v in uniq], dtype=np.float64)[inv]
    else:
        speeds = np.full(n_feat, math.nan)

    lo, hi = np.nanmin(lines.lonlat, axis=0), np.nanmax(lines.lonlat, axis=0)
    crs = utm_crs(float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2))

    src_ids = None
    if uv_f is not None and not opts.node_crossings and len(unique(lines.row)) == n_feat:
        src_ids = _endpoint_id_values(lines, uv_f)
    if opts.node_crossings:
        import shapely

        owner0 = np.repeat(np.arange(n_feat), np.diff(lines.ptr))
        geoms, src = _node_lines(shapely.linestrings(lines.lonlat, indices=owner0))
        fid, direction, speeds = fid[src], direction[src], speeds[src]
        names, hws = names.take(src), hws.take(src)
        n_feat = len(geoms)
        ll, owner = shapely.get_coordinates(geoms, return_index=True)
        del geoms
    else:
        ll = lines.lonlat
        owner = np.repeat(np.arange(n_feat), np.diff(lines.ptr))
    del lines
    xy = to_xy(crs, ll[:, 0], ll[:, 1])
    counts = np.bincount(owner, minlength=n_feat)
    start = np.zeros(n_feat + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    first, last = start[:-1], start[1:] - 1
    ends = np.concatenate([first, last])
    end_xy = xy[ends]
    place_of_end, places = _places(end_xy)
    node_of_end, end_ids = None, None
    if opts.topology == "ids" or (opts.topology == "auto" and src_ids is not None):
        node_of_end, end_ids = _nodes_from_ids(src_ids, end_xy, opts)
    if node_of_end is None:
        node_of_end = _nodes_from_coords(places, place_of_end, opts.snap_tolerance)
        end_ids = _consistent_ids(src_ids, node_of_end)
        info["topology"] = "shared endpoints"
    else:
        info["topology"] = "node id fields"
    n_end_nodes = int(node_of_end.max()) + 1 if len(node_of_end) else 0
    # node position: mean of its endpoints
    node_xy = np.zeros((n_end_nodes, 2))
    np.add.at(node_xy, node_of_end, end_xy)
    node_xy /= np.bincount(node_of_end, minlength=n_end_nodes)[:, None]
    node_ll = ll[ends][unique_inverse(node_of_end)[1]]
    info["merged_endpoints"] = len(places) - n_end_nodes
    del place_of_end, places

    # every vertex is a node: endpoints shared, interior vertices private to their feature
    vnode = np.empty(len(xy), dtype=np.int64)
    interior = np.ones(len(xy), dtype=bool)
    interior[ends] = False
    vnode[ends] = node_of_end
    vnode[interior] = n_end_nodes + np.arange(int(interior.sum()))
    all_xy = np.vstack([node_xy, xy[interior]])
    all_ll = np.vstack([node_ll, ll[interior]])
    del ll, node_ll, node_xy, end_xy
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
    del d, xy, vnode, interior
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
        edge_src=src[use].astype(np.int64, copy=False),
        edge_dst=dst[use].astype(np.int64, copy=False),
        edge_feat=feat[use].astype(np.int64, copy=False),
        edge_oneway=(direction[feat[use]] != BOTH),
        feat_way_id=fid.astype(np.int64, copy=False),
        feat_name=names,
        feat_highway=hws,
        feat_speed_kph=speeds.astype(np.float64),
    )
    # features that collapsed to one point
    flen = np.bincount(f, weights=seg_len, minlength=n_feat)
    collapsed = int((flen <= opts.snap_tolerance).sum())
    if collapsed:
        dropped["zero length after snapping"] = collapsed
    return compact_raw(raw), dropped, info


def _factorize(column: Any) -> tuple[NDArray[np.int64], list[Any]]:
    """Codes into the distinct values of a pyarrow column (missing values, NaN included, one value)."""
    import pyarrow.compute as pc

    enc = pc.dictionary_encode(column, null_encoding="encode")
    codes = np.asarray(enc.indices.to_numpy(zero_copy_only=False), dtype=np.int64)
    vals = [None if isinstance(v, float) and v != v else v for v in enc.dictionary.to_pylist()]
    # NaN and null read alike: give them one code
    first: dict[Any, int] = {}
    remap = np.array(
        [
            first.setdefault(("<missing>",) if v is None else (type(v) is bool, v), i)
            for i, v in enumerate(vals)
        ],
        dtype=np.int64,
    )
    if len(remap) and (remap != np.arange(len(remap))).any():
        codes = remap[codes]
    return codes, vals


def _labels(lines: Lines, name: str | None) -> Labels:
    """A text column per line as :class:`Labels` (each distinct value read as text once)."""
    if name is None:
        return Labels(np.full(lines.n_lines, -1, dtype=np.int32), [])
    import pyarrow.compute as pc

    enc = pc.dictionary_encode(lines.columns[name])
    table: dict[str, int] = {}
    texts = [_text(v) for v in enc.dictionary.to_pylist()]
    code_of = np.array(
        [-1 if t is None else table.setdefault(t, len(table)) for t in texts] + [-1], dtype=np.int32
    )
    idx = np.asarray(enc.indices.fill_null(-1).to_numpy(zero_copy_only=False), dtype=np.int64)
    return Labels(code_of[idx][lines.row], list(table))


class Source(NamedTuple):
    """A GIS source open for reading: its fields, CRS (None: none given), feature count
    (0: unknown) and its batches: ``batches(columns)`` yields (attribute columns, WKB
    geometry column) as pyarrow arrays."""

    path: Path
    fields: list[str]
    crs: Any
    total: int
    batches: Callable[[list[str]], Iterator[tuple[dict[str, Any], Any]]]


@contextmanager
def open_source(path: Path, opts: GisOptions) -> Iterator[Source]:
    """Open the layer to read (a GeoPackage's ``roads`` or first layer unless given) as one
    Arrow stream (pyogrio; pyarrow for GeoParquet, which this GDAL cannot read); an
    unreadable source is an InputError."""
    with ExitStack() as stack:
        try:
            if path.suffix.lower() in (".parquet", ".geoparquet"):
                src = _parquet_source(path)
            else:
                src = _ogr_source(path, opts, stack)
        except InputError:
            raise
        except Exception as exc:  # pyogrio and pyarrow raise several unrelated types for unreadable files
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(f"cannot read {path.name} as GIS data: {msg}") from exc
        yield src


def _parquet_source(path: Path) -> Source:
    import pyarrow.parquet as pq

    pf = pq.ParquetFile(path)
    geo = _geoparquet_meta(pf, path)
    gcol = geo["primary_column"]

    def batches(columns: list[str]) -> Iterator[tuple[dict[str, Any], Any]]:
        for batch in pf.iter_batches(batch_size=BATCH_ROWS, columns=[*columns, gcol]):
            yield {c: batch.column(c) for c in columns}, batch.column(gcol)

    fields = [c for c in pf.schema_arrow.names if c != gcol]
    return Source(path, fields, _geoparquet_crs(geo), pf.metadata.num_rows, batches)


def _ogr_source(path: Path, opts: GisOptions, stack: ExitStack) -> Source:
    import pyogrio

    layer = opts.layer
    if layer is None and path.suffix.lower() == ".gpkg":
        names = [str(n) for n in pyogrio.list_layers(path)[:, 0]]
        layer = "roads" if "roads" in names else names[0] if names else None
    total = 0
    if path.suffix.lower() not in (".geojson", ".json"):  # GeoJSON would be parsed twice
        total = max(int(pyogrio.read_info(path, layer=layer).get("features") or 0), 0)
    meta, reader = stack.enter_context(
        pyogrio.open_arrow(path, layer=layer, use_pyarrow=True, batch_size=BATCH_ROWS)
    )
    gcol = meta.get("geometry_name") or "wkb_geometry"

    def batches(columns: list[str]) -> Iterator[tuple[dict[str, Any], Any]]:
        for batch in reader:
            yield {c: batch.column(c) for c in columns}, batch.column(gcol)

    return Source(path, [str(f) for f in meta["fields"]], meta.get("crs"), total, batches)


def _node_id_fields(fields: list[str], opts: GisOptions) -> tuple[str, str] | None:
    """The fields with each line's first and last node id: given, or ``u`` and ``v``."""
    if opts.node_id_fields is not None:
        if any(f not in fields for f in opts.node_id_fields):
            raise InputError(f"node id fields {', '.join(opts.node_id_fields)} are not in the data")
        return opts.node_id_fields
    cols = {c.lower(): c for c in fields}
    return (cols["u"], cols["v"]) if "u" in cols and "v" in cols else None


def _int_column(lines: Lines, name: str) -> NDArray[np.int64] | None:
    """An integer column per line as int64: integers, whole floats or integer text (a DBF's
    character field); None when it has nulls or other values."""
    import pyarrow as pa

    col = lines.columns[name]
    if col.null_count:
        return None
    if pa.types.is_integer(col.type):
        return np.asarray(col.to_numpy(), dtype=np.int64)[lines.row]
    try:
        if pa.types.is_floating(col.type):
            f = np.asarray(col.to_numpy(), dtype=np.float64)
            if not (np.isfinite(f).all() and (f == np.round(f)).all()):
                return None
            vals = f.astype(np.int64)
        elif pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            vals = np.asarray([int(v) for v in col.to_pylist()], dtype=np.int64)
        else:
            return None
    except (TypeError, ValueError, OverflowError):
        return None
    return vals[lines.row]


def _endpoint_id_values(lines: Lines, fields: tuple[str, str]) -> NDArray[np.int64] | None:
    """Ids of every line's first then last node from the u/v fields, or None when unusable
    (not integers, nulls, or negative)."""
    import pyarrow as pa

    out = []
    for f in fields:
        col = lines.columns[f]
        if col.null_count:
            return None
        if pa.types.is_integer(col.type) or pa.types.is_floating(col.type):
            vals = np.asarray(col.to_numpy(), dtype=np.int64)
        else:
            try:
                vals = np.asarray(col.to_pylist(), dtype=np.int64)
            except (TypeError, ValueError, OverflowError):
                return None
        out.append(vals[lines.row])
    ids = np.concatenate(out)
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
    uniq, _, inv = unique_inverse(ids)
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


def _places(end_xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Distinct endpoint positions (rounded to the micrometre, sorted by x then y) and the
    place of each endpoint."""
    r = np.round(end_xy, 6)
    order = np.lexsort((r[:, 1], r[:, 0]))  # as np.unique(axis=0) orders them, much faster
    rs = r[order]
    new = np.ones(len(rs), dtype=bool)
    new[1:] = (rs[1:] != rs[:-1]).any(axis=1)
    inv = np.empty(len(r), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    return inv, rs[new]


def _nodes_from_coords(uniq: NDArray[np.float64], inv: NDArray[np.int64], tol: float) -> NDArray[np.int64]:
    """Endpoint -> node: identical positions (``uniq[inv]``) first, then snapping within
    ``tol`` metres."""
    if tol > 0 and len(uniq) > 1:
        pa, pb = _pairs_within(uniq, tol)
        lab = union_find(len(uniq), pa, pb)
        _, lab = dense_labels(lab, len(uniq))
    else:
        lab = np.arange(len(uniq))
    return np.asarray(lab, dtype=np.int64).ravel()[inv]


def _pairs_within(xy: NDArray[np.float64], tol: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """All pairs ``a < b`` of points at most ``tol`` apart: points hashed to cells of side
    ``tol``, each cell compared with itself and the neighbours ahead of it (an STRtree when
    the cells would not fit 64-bit keys)."""
    lo = xy.min(axis=0)
    cell = np.floor((xy - lo) / tol).astype(np.int64)
    width = int(cell[:, 1].max()) + 3
    if (int(cell[:, 0].max()) + 3) * width >= 2**62:
        tree = shapely.STRtree(shapely.points(xy))
        pa, pb = tree.query(shapely.points(xy), predicate="dwithin", distance=tol)
        keep = pa < pb
        return pa[keep].astype(np.int64), pb[keep].astype(np.int64)
    key = cell[:, 0] * width + cell[:, 1] + 1
    del cell
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out_a, out_b = [], []
    for dx, dy in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
        want = key + dx * width + dy
        first = np.searchsorted(skey, want, side="left")
        n = np.searchsorted(skey, want, side="right") - first
        a = np.repeat(np.arange(len(xy), dtype=np.int64), n)
        b = order[np.repeat(first, n) + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)]
        near = np.hypot(xy[a, 0] - xy[b, 0], xy[a, 1] - xy[b, 1]) <= tol
        a, b = a[near], b[near]
        out_a.append(np.minimum(a, b)[a != b])
        out_b.append(np.maximum(a, b)[a != b])
    pa, pb = np.concatenate(out_a), np.concatenate(out_b)
    pair = unique(pa * len(xy) + pb)
    return pair // len(xy), pair % len(xy)


def _consistent_ids(
    ids: NDArray[np.int64] | None, node_of_end: NDArray[np.int64]
) -> NDArray[np.int64] | None:
    """One id per node when the u/v fields agree with the coordinate topology, else None."""
    if ids is None or not len(node_of_end):
        return None
    n = int(node_of_end.max()) + 1
    out = np.full(n, -1, dtype=np.int64)
    out[node_of_end] = ids
    if (out < 0).any() or not np.array_equal(out[node_of_end], ids) or len(unique(out)) != n:
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
