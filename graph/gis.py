"""GIS road centre lines (GeoJSON, GeoPackage, Shapefile, FlatGeobuf, GeoParquet) -> raw network.

The lines are read batch by batch from pyogrio's Arrow stream (pyarrow's for GeoParquet)
straight into coordinate arrays; only the attribute fields the build uses are kept, and no
GeoDataFrame is made. Topology comes from shared line endpoints (within a snap tolerance); crossings without a
shared vertex stay unconnected (bridges) unless noding is asked for. One-way comes from a
configurable field and value convention. The options, field choice and reading are here;
:mod:`graph.gis_network` turns the lines read into the raw network.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import shapely
from numpy.typing import NDArray

from graph.errors import InputError
from graph.gis_network import BOTH, FORWARD, REVERSE, FieldChoice, lines_to_network

if TYPE_CHECKING:
    import networkx as nx

    from graph.raw_network import RawNetwork

log = logging.getLogger(__name__)

GIS_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp", ".fgb", ".parquet", ".geoparquet")


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
    cols = [c for c in dict.fromkeys(w for w in want if w is not None) if c in src.fields]
    parts = _read_parts(src, cols, progress)
    lonlat = _to_lonlat(parts.lonlat, src, opts)
    counts, row, dropped = parts.counts, parts.row, parts.dropped
    short = counts < 2
    if opts.bbox is not None:  # keep the features with a part that meets the box
        inside = _inside_bbox(lonlat, counts, row, short, opts.bbox, parts.n_rows, dropped)
        if not inside.any():
            raise InputError(f"{src.path.name} has no line features inside the bbox")
        lonlat, counts, row, short = (
            lonlat[np.repeat(inside, counts)],
            counts[inside],
            row[inside],
            short[inside],
        )
    if short.any():
        _count(dropped, "fewer than 2 points", int(short.sum()))
        keep_pt = np.repeat(~short, counts)
        lonlat, counts, row = lonlat[keep_pt], counts[~short], row[~short]
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    reasons = ("no geometry", "not a line", "outside the bbox", "fewer than 2 points")
    return Lines(
        lonlat=np.ascontiguousarray(lonlat, dtype=np.float64),
        ptr=ptr,
        row=row,
        columns=parts.columns,
        fields=src.fields,
    ), {k: dropped[k] for k in reasons if dropped.get(k)}


class _Parts(NamedTuple):
    """Line parts as read: coordinates in the source's CRS, point count and source row of each
    part, the attribute columns, the number of source rows and the dropped features by reason."""

    lonlat: NDArray[np.float64]
    counts: NDArray[np.int64]
    row: NDArray[np.int64]
    columns: dict[str, Any]
    n_rows: int
    dropped: dict[str, int]


def _count(dropped: dict[str, int], reason: str, n: int) -> None:
    dropped[reason] = dropped.get(reason, 0) + n


def _read_parts(src: Source, cols: list[str], progress: ReadProgress | None) -> _Parts:
    """Every batch of ``src`` as line parts (multi-part lines split), with columns ``cols``."""
    dropped: dict[str, int] = {}
    parts_ll: list[NDArray[np.float64]] = []
    parts_n: list[NDArray[np.int64]] = []
    parts_row: list[NDArray[np.int64]] = []
    col_parts: dict[str, list[Any]] = {c: [] for c in cols}
    n_rows = 0
    n_lines_in = 0
    try:
        for attrs, wkb in src.batches(cols):
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
            else:
                ll, n_pts, rows, n_line = _batch_parts(wkb, dropped)
                del wkb
                parts_ll.append(ll)
                parts_n.append(n_pts)
                parts_row.append(n_rows + rows)
                n_lines_in += n_line
            n_rows += n_batch
            if progress is not None:
                progress(n_rows, src.total)
    except InputError:
        raise
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"cannot read {src.path.name} as GIS data: {msg}") from exc
    if n_lines_in == 0:
        raise InputError(f"{src.path.name} has no line features (LineString or MultiLineString)")
    import pyarrow as pa

    return _Parts(
        lonlat=np.concatenate(parts_ll) if parts_ll else np.zeros((0, 2)),
        counts=np.concatenate(parts_n) if parts_n else np.zeros(0, dtype=np.int64),
        row=np.concatenate(parts_row) if parts_row else np.zeros(0, dtype=np.int64),
        columns={
            c: pa.concat_arrays([_chunk(x) for x in v]) if v else pa.array([]) for c, v in col_parts.items()
        },
        n_rows=n_rows,
        dropped=dropped,
    )


def _batch_parts(
    wkb: Any, dropped: dict[str, int]
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64], int]:
    """One batch's WKB of any geometry types through shapely: the coordinates, point count and
    row within the batch of each line part, and the number of line features (the rest counted
    in ``dropped``)."""
    geom = shapely.from_wkb(wkb.to_numpy(zero_copy_only=False))
    types = shapely.get_type_id(geom)
    is_line = (types == 1) | (types == 5)  # LineString, MultiLineString
    missing = shapely.is_missing(geom)
    _count(dropped, "no geometry", int(missing.sum()))
    _count(dropped, "not a line", int((~is_line & ~missing).sum()))
    rows = np.nonzero(is_line)[0]
    geom = geom[rows]
    lines, part_of = shapely.get_parts(geom, return_index=True)
    del geom
    ll, owner = shapely.get_coordinates(lines, return_index=True)
    del lines
    n_pts = np.bincount(owner, minlength=len(part_of)).astype(np.int64)
    return ll, n_pts, rows[part_of], int(is_line.sum())


def _to_lonlat(coords: NDArray[np.float64], src: Source, opts: GisOptions) -> NDArray[np.float64]:
    """``coords`` in WGS84 lon/lat: from the source's CRS, the one given, or as they are when
    there is none and they fit lon/lat."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    crs: Any = src.crs
    if opts.crs is not None:
        try:
            crs = CRS.from_user_input(opts.crs)
        except CRSError as exc:
            raise InputError(f"unreadable CRS {opts.crs!r}: {exc}") from exc
    name = src.path.name
    if crs is None:
        x0, y0 = np.nanmin(coords, axis=0) if len(coords) else (0.0, 0.0)
        x1, y1 = np.nanmax(coords, axis=0) if len(coords) else (0.0, 0.0)
        if -180 <= x0 <= x1 <= 180 and -90 <= y0 <= y1 <= 90:
            log.warning("%s has no CRS; its coordinates look like lon/lat, assuming EPSG:4326", name)
            crs = "EPSG:4326"
        else:
            raise InputError(
                f"{name} has no readable CRS and its coordinates are not lon/lat; give the CRS (--crs)"
            )
    try:
        crs = CRS.from_user_input(crs)
        if not crs.equals(CRS.from_epsg(4326)):
            from pyproj import Transformer

            tf = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
            lon, lat = tf.transform(coords[:, 0], coords[:, 1])
            coords = np.column_stack([lon, lat])
    except Exception as exc:
        raise InputError(f"{name}: cannot transform from its CRS to lon/lat: {exc}") from exc
    return coords


def _inside_bbox(
    lonlat: NDArray[np.float64],
    counts: NDArray[np.int64],
    row: NDArray[np.int64],
    short: NDArray[np.bool_],
    bbox: tuple[float, float, float, float],
    n_rows: int,
    dropped: dict[str, int],
) -> NDArray[np.bool_]:
    """Per line part, whether its feature has a part that meets ``bbox`` (a feature of short
    parts only is kept, to be dropped as such); the features outside counted in ``dropped``."""
    ok = ~short
    part_lines = shapely.linestrings(
        lonlat[np.repeat(ok, counts)], indices=np.repeat(np.arange(int(ok.sum())), counts[ok])
    )
    hit = np.zeros(n_rows, dtype=bool)
    hit[row[ok][shapely.intersects(part_lines, shapely.box(*bbox))]] = True
    hit[row[short]] |= ~np.isin(row[short], row[ok])
    del part_lines
    had = np.zeros(n_rows, dtype=bool)
    had[row] = True
    _count(dropped, "outside the bbox", int((had & ~hit).sum()))
    return hit[row]


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
    from graph.raw_network import raw_to_nx

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
        chosen = FieldChoice(oneway_f, name_f, speed_f, hw_f, id_f, _node_id_fields(fields, opts))
        info: dict[str, Any] = {
            "directed": opts.directed,
            "oneway_field": oneway_f,
            "name_field": name_f,
            "speed_field": speed_f,
            "highway_field": hw_f,
        }
        lines, dropped = read_lines(
            source,
            opts,
            want=(oneway_f, name_f, speed_f, hw_f, id_f, *(chosen.node_ids or ())),
            progress=progress,
        )
    return lines_to_network(lines, dropped, info, chosen, opts)


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
