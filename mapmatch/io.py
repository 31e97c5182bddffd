"""Track input (CSV, GPX, Parquet/GeoParquet) and batch-result output (GeoJSON, CSV, GeoParquet).

Results travel as one table with a row per track (:func:`result_rows`): the route geometry,
its edge sequence with OSM way ids and names, length, confidence, splits, and the per-point
placements as lists. Every writer goes through that table, so a partition written by a worker
and the final file hold exactly the same values. Files are written to a temporary name and
renamed, never left half-written.

CSV, GPX and GeoJSON need only the core install (CSV through :mod:`mapmatch.textcsv`);
Parquet, GeoParquet and pandas frames need the ``tables`` extra, GIS line files ``prep``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from graph.files import atomic_path
from graph.road_graph import RoadGraph
from mapmatch.errors import MatchError
from mapmatch.extras import require
from mapmatch.textbounds import MAX_COLUMNS as MAX_COLUMNS  # the readers' bounds, re-exported
from mapmatch.textbounds import MAX_LINE_BYTES as MAX_LINE_BYTES
from mapmatch.textbounds import MAX_QUOTE as MAX_QUOTE
from mapmatch.textbounds import InputTooLargeError as InputTooLargeError
from mapmatch.textbounds import LineBounds as LineBounds
from mapmatch.textbounds import check_text_input, quote, spool_stdin
from mapmatch.textbounds import clip as _clip
from mapmatch.textcsv import CsvError, EmptyCsvError, TextTable, inferred_text, numbers, read_table, times
from mapmatch.types import Track, TrackMatch

if TYPE_CHECKING:
    import pandas as pd

TABLES = "tables"
"""The extra of Parquet and GeoParquet files and of tables as pandas frames (pandas, pyarrow)."""


def _pandas(needed_for: str) -> Any:
    """pandas, or :class:`~mapmatch.extras.MissingExtraError` naming the ``tables`` extra."""
    return require("pandas", extra=TABLES, needed_for=needed_for)


def _pyarrow(needed_for: str) -> Any:
    """pyarrow.parquet, or :class:`~mapmatch.extras.MissingExtraError` naming ``tables``."""
    return require("pyarrow.parquet", extra=TABLES, needed_for=needed_for)


class TrackInputError(MatchError):
    """A track file cannot be read (missing column, unknown format, bad values)."""


@dataclass(frozen=True)
class Columns:
    """Column names of tabular track input (CSV, Parquet). Optional ones are used when present."""

    id: str = "id"
    time: str = "time"
    lat: str = "lat"
    lon: str = "lon"
    heading: str = "heading"
    speed: str = "speed"
    pos_sigma: str = "pos_sigma"
    distance: str = "distance"


DEFAULT_COLUMNS = Columns()
COLUMN_ALIASES: dict[str, tuple[str, ...]] = {
    "id": ("track_id", "trip_id", "vehicle_id", "track", "trip", "vehicle"),
    "vehicle_id": ("vehicle", "id", "track_id", "trip_id", "track", "trip"),
    "time": ("timestamp", "datetime", "date_time", "t", "ts", "time_s", "seconds"),
    "lat": ("latitude", "lat_deg"),
    "lon": ("lng", "long", "longitude", "lon_deg"),
    "heading": ("course", "bearing"),
}
"""Other common names of a column of :class:`Columns` or :class:`FixColumns`, tried
case-insensitively when a file lacks the default name (:func:`resolve_columns`). Speed is not
among them: its unit varies."""
log = logging.getLogger(__name__)
LINE_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp", ".fgb")
"""GIS files whose line features are tracks (one track per line, its vertices the points)."""
TRACK_SUFFIXES = (".csv", ".csv.gz", ".gpx", ".parquet", ".geoparquet", ".pq", *LINE_SUFFIXES)
WKT_COLUMNS = ("geom", "geometry", "wkt")
"""CSV columns read as WKT line tracks when there are no lat/lon columns (FMM's trips.csv)."""
LINE_TIME_COLUMNS = ("timestamp", "timestamps")
"""Fields tried after ``Columns.time`` for a line track's times, one per vertex."""
OUTPUT_SUFFIXES = (".geojson", ".json", ".csv", ".parquet", ".geoparquet")


STDIO = "-"
"""The file name that means standard input (when read) or standard output (when written)."""


# ---------------------------------------------------------------------- fused fixes
@dataclass(frozen=True)
class FixColumns:
    """Column names of a fused-fix file (``mapmatch replay``, ``mapmatch send``).

    The defaults are the documented names (:data:`mapmatch.fixes.REQUIRED_COLUMNS` and
    ``OPTIONAL_COLUMNS``). Without the vehicle column the file is one vehicle (``default_vehicle``);
    without the heading column every heading is unknown. lat, lon and time are required.
    """

    vehicle_id: str = "vehicle_id"
    time: str = "time"
    lat: str = "lat"
    lon: str = "lon"
    heading: str = "heading"
    pos_sigma: str = "pos_sigma"
    heading_sigma: str = "heading_sigma"
    speed: str = "speed"
    distance: str = "distance"
    gps_valid: str = "gps_valid"


ColumnsT = TypeVar("ColumnsT", Columns, FixColumns)


def read_fixes(
    source: str | os.PathLike[str], *, columns: FixColumns = FixColumns(), default_vehicle: str = ""
) -> dict[str, list[Any]]:
    """Fused fixes per vehicle from any file ``mapmatch match`` reads, with renamed columns.

    CSV (``"-"``: standard input) and Parquet files hold the fix columns (:class:`FixColumns`,
    common other names resolved as :func:`resolve_columns` does); GPX, GeoParquet points and
    GIS line files hold tracks (:func:`read_tracks`), each track a vehicle, its points the
    fixes (time, lat, lon, and heading, speed, pos_sigma and distance when recorded). A file
    without vehicle ids is one vehicle: ``default_vehicle``, else the file's name, or
    ``"stdin"`` for standard input. A CSV line or header beyond the bounds
    (:data:`MAX_LINE_BYTES`, :data:`MAX_COLUMNS`) is refused before parsing.

    Raises
    ------
    mapmatch.errors.ValidationError
        A required column is missing (named, with the file's columns) or a cell is not a number.
    TrackInputError
        The file cannot be read, or passes a bound (:class:`InputTooLargeError`).
    """
    import tempfile

    if str(source) == STDIO:
        with tempfile.TemporaryDirectory(prefix="mapmatch-") as tmp:
            spooled = Path(tmp) / "stdin.csv"
            spool_stdin(spooled)
            table = _read_fix_csv(spooled, name="standard input")
        return _fixes_from_cells(table, columns, default_vehicle or "stdin")
    p = Path(source)
    lower = p.name.lower()
    default = default_vehicle or _stem(p)
    if lower.endswith((".csv", ".csv.gz")):
        check_text_input(p)
        return _fixes_from_cells(_read_fix_csv(p, name=str(p)), columns, default)
    if lower.endswith((".parquet", ".pq", ".geoparquet")):
        pd = _pandas("reading Parquet files")
        _pyarrow("reading Parquet files")
        try:
            df = pd.read_parquet(p)
        except Exception as exc:  # pyarrow raises several types for a bad file
            raise TrackInputError(f"{p}: not a readable Parquet file ({exc})") from None
        resolved = resolve_columns(df.columns, columns)
        if resolved.lat in df.columns and resolved.lon in df.columns:
            return _fixes_from_cells(_frame_cells(df), columns, default)
    track_columns = Columns(
        id=columns.vehicle_id, time=columns.time, lat=columns.lat, lon=columns.lon,
        heading=columns.heading, speed=columns.speed, pos_sigma=columns.pos_sigma,
        distance=columns.distance,
    )  # fmt: skip
    tracks = read_tracks(p, columns=track_columns)
    stem = _stem(p)
    return {(default if t.track_id == stem else str(t.track_id)): fixes_of_track(t) for t in tracks}


def fixes_of_track(track: Track) -> list[Any]:
    """The fixes of a track: its points, with heading, speed, pos_sigma and distance when recorded."""
    from mapmatch.types import Fix

    def col(a: NDArray[np.float64] | None) -> NDArray[np.float64]:
        return np.full(len(track), np.nan) if a is None else np.asarray(a, dtype=np.float64)

    heading, speed, sigma, dist = (col(track.heading), col(track.speed), col(track.pos_sigma),
                                   col(track.distance))  # fmt: skip
    out = []
    for i in range(len(track)):
        out.append(
            Fix(
                time=float(track.time[i]),
                lat=float(track.lat[i]),
                lon=float(track.lon[i]),
                heading=float(heading[i]),
                pos_sigma=float(sigma[i]),
                speed=float(speed[i]),
                distance=float(dist[i]),
            )
        )
    return out


def _read_fix_csv(path: Path, *, name: str) -> TextTable:
    from mapmatch.errors import ValidationError

    try:
        return read_table(path, strip_space=True)
    except EmptyCsvError:
        raise ValidationError("file", f"{name} is empty") from None
    except (CsvError, UnicodeDecodeError) as exc:
        raise ValidationError("file", f"{name} is not a readable CSV ({quote(exc)})") from None


def _frame_cells(df: pd.DataFrame) -> TextTable:
    """A pandas frame's cells as text (no value: ``None``)."""
    cols = {
        str(c): [None if v is None or (isinstance(v, float) and v != v) else str(v) for v in df[c].tolist()]
        for c in df.columns
    }
    return TextTable(list(cols), cols, len(df))


def _fixes_from_cells(table: TextTable, columns: FixColumns, default_vehicle: str) -> dict[str, list[Any]]:
    """Fixes per vehicle from a table of text cells with the columns of ``columns``."""
    from mapmatch.errors import ValidationError
    from mapmatch.fixes import fixes_from_cells

    names = [str(c).strip() for c in table.names]
    cells = dict(zip(names, (table.columns[c] for c in table.names), strict=True))
    columns = resolve_columns(names, columns)
    for need in (columns.time, columns.lat, columns.lon):
        if need not in cells:
            raise ValidationError(
                "columns", f"missing column {need!r} (columns are: {_clip(', '.join(names)) or 'none'})"
            )
    wanted = {getattr(columns, f): f for f in FixColumns.__dataclass_fields__}
    fields: dict[str, list[str | None]] = {}
    for name in names:  # of two columns renamed alike, the first is read
        if name in wanted and wanted[name] not in fields:
            fields[wanted[name]] = [c if c else None for c in cells[name]]
    fields.setdefault("vehicle_id", [default_vehicle] * table.rows)
    fields.setdefault("heading", [None] * table.rows)
    return fixes_from_cells(fields, table.rows)


def copy_to_stdout(path: str | os.PathLike[str]) -> None:
    """Write a finished output file to standard output (for ``-o -``)."""
    import shutil
    import sys

    with open(path, "rb") as f:
        shutil.copyfileobj(f, sys.stdout.buffer)
    sys.stdout.flush()


# ---------------------------------------------------------------------- reading
def read_tracks(path: str | os.PathLike[str], *, columns: Columns = DEFAULT_COLUMNS) -> list[Track]:
    """Read every track of a CSV, GPX, (Geo)Parquet or GIS line file, or of a folder of Parquet parts."""
    p = Path(path)
    if p.is_dir():
        parts = sorted(q for q in p.iterdir() if q.name.lower().endswith((".parquet", ".geoparquet", ".pq")))
        if not parts:
            raise TrackInputError(f"{p}: no Parquet files in the folder")
        return [t for q in parts for t in read_tracks(q, columns=columns)]
    name = p.name.lower()
    if not p.exists():
        raise FileNotFoundError(2, "No such file", str(p))
    if name.endswith((".csv", ".csv.gz")):
        return read_tracks_csv(p, columns=columns)
    if name.endswith(".gpx"):
        return read_tracks_gpx(p)
    if name.endswith((".parquet", ".geoparquet", ".pq")):
        return read_tracks_parquet(p, columns=columns)
    if name.endswith(LINE_SUFFIXES):
        return read_tracks_lines(p, columns=columns)
    raise TrackInputError(f"{p}: unknown track format (use one of {', '.join(TRACK_SUFFIXES)})")


def read_tracks_csv(path: str | os.PathLike[str], *, columns: Columns = DEFAULT_COLUMNS) -> list[Track]:
    """Tracks from a CSV file with configurable column names; no id column means one track.

    Points are rows (lat/lon columns). Without lat/lon, a WKT column (``geom``, ``geometry`` or
    ``wkt``) of LINESTRINGs gives one track per row, as FMM's trajectory files do (``;``
    between fields, times in a ``timestamp`` column, see :func:`read_tracks_lines`).
    """
    check_text_input(path)
    try:
        table = read_table(path, sep=_csv_separator(path), na=True)
    except (CsvError, UnicodeDecodeError) as exc:
        raise TrackInputError(f"{path}: not a readable CSV file ({quote(exc)})") from exc
    columns = resolve_columns(table.names, columns)
    wkt = next((c for c in table.names if c.lower() in WKT_COLUMNS), None)
    if wkt is not None and not (columns.lat in table and columns.lon in table):
        import shapely

        try:
            geoms = shapely.from_wkt(np.array(inferred_text(table.columns[wkt]), dtype=object))
        except shapely.errors.GEOSException as exc:
            raise TrackInputError(f"{path}: column {wkt!r} is not WKT ({exc})") from None
        fields = {c: inferred_text(v) if c == columns.id else v for c, v in table.columns.items()}
        return _tracks_from_lines(fields, geoms, columns=columns, default_id=_stem(path), where=str(path))
    _need_columns(table.names, columns)
    cells = table.columns
    opt = {k: getattr(columns, k) for k in ("heading", "speed", "pos_sigma", "distance")}
    return split_tracks(
        TrackColumns(
            ids=np.array(inferred_text(cells[columns.id]), dtype=object)
            if columns.id in cells
            else np.full(table.rows, _stem(path), dtype=object),
            time=times(cells[columns.time]) if columns.time else np.full(table.rows, np.nan),
            lat=numbers(cells[columns.lat]),
            lon=numbers(cells[columns.lon]),
            optional={k: numbers(cells[c]) if c in cells else None for k, c in opt.items()},
        )
    )


def _csv_separator(path: str | os.PathLike[str]) -> str:
    """``;`` when the header line has semicolons and no commas (FMM's files), else ``,``."""
    import gzip

    opener: Any = gzip.open if str(path).lower().endswith(".gz") else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace") as f:
            head = f.readline()
    except OSError:
        return ","
    return ";" if ";" in head and "," not in head else ","


def read_tracks_lines(path: str | os.PathLike[str], *, columns: Columns = DEFAULT_COLUMNS) -> list[Track]:
    """One track per line feature of a GIS file (GeoJSON, GeoPackage, Shapefile, FlatGeobuf).

    The line's vertices, in drawn order, are the track's points (a MultiLineString's parts
    joined); features without geometry are skipped. The id is ``columns.id`` when the file has
    it, else the file name (numbered when there are several lines). Times come from the
    vertices' M values, else from a ``columns.time``, ``timestamp`` or ``timestamps`` field
    holding one time per vertex (a list, or text with commas, as FMM writes them), else there
    are none. Coordinates in a projected CRS are brought to lon/lat.
    """
    pyogrio = require("pyogrio", extra="prep", needed_for="reading GIS track files")
    try:
        df = pyogrio.read_dataframe(path)
    except Exception as exc:  # pyogrio/GDAL raise several types for a bad file
        why = str(exc).split(";")[0].strip()  # GDAL's first sentence, without its driver hint
        raise TrackInputError(f"{path}: not a readable GIS file ({why})") from exc
    if df.crs is not None and not df.crs.is_geographic:
        df = df.to_crs(4326)
    fields = {c: df[c].tolist() for c in df.columns if c != df.geometry.name}
    return _tracks_from_lines(
        fields, df.geometry.to_numpy(), columns=columns, default_id=_stem(path), where=str(path)
    )


def _tracks_from_lines(
    fields: Mapping[str, Sequence[Any]], geoms: NDArray[Any], *, columns: Columns, default_id: str, where: str
) -> list[Track]:
    import shapely

    kinds = shapely.get_type_id(geoms)
    keep = ~shapely.is_missing(geoms) & ~shapely.is_empty(geoms)
    bad = keep & ~np.isin(kinds, (1, 5))  # LineString, MultiLineString
    if bad.any():
        kind = int(shapely.get_type_id(geoms[bad][0]))
        names = {0: "Point", 3: "Polygon", 4: "MultiPoint", 6: "MultiPolygon", 7: "GeometryCollection"}
        raise TrackInputError(
            f"{where}: a track is a line, but {int(bad.sum())} feature(s) are "
            f"{names.get(kind, 'other')}s (points are rows of a CSV or Parquet file)"
        )
    rows = np.flatnonzero(keep)
    has_id = columns.id in fields
    tcol = next((c for c in (columns.time, *LINE_TIME_COLUMNS) if c and c in fields), None)
    out = []
    for k, i in enumerate(rows.tolist()):
        g = geoms[i]
        with_m = bool(shapely.has_m(g))
        xy = shapely.get_coordinates(g, include_m=with_m)
        if with_m:
            t = xy[:, 2].astype(np.float64)
        elif tcol is not None:
            t = _vertex_times(fields[tcol][i], len(xy), f"{where}: feature {i} field {tcol!r}")
        else:
            t = np.full(len(xy), np.nan)
        tid = str(fields[columns.id][i]) if has_id else default_id if len(rows) == 1 else f"{default_id}-{k}"
        out.append(Track(track_id=tid, time=t, lat=xy[:, 1].copy(), lon=xy[:, 0].copy()))
    return out


def _vertex_times(value: Any, n: int, what: str) -> NDArray[np.float64]:
    """One time per vertex from a list or comma-separated text; NaN when the field is empty."""
    if value is None or (isinstance(value, float) and np.isnan(value)) or value == "":
        return np.full(n, np.nan)
    items = value.split(",") if isinstance(value, str) else list(np.atleast_1d(value))
    if len(items) != n:
        raise TrackInputError(f"{what}: {len(items)} time(s) for {n} vertices")
    try:
        return times([x.strip() if isinstance(x, str) else x for x in items])
    except (TypeError, ValueError) as exc:
        raise TrackInputError(f"{what}: not times ({exc})") from None


def read_tracks_parquet(path: str | os.PathLike[str], *, columns: Columns = DEFAULT_COLUMNS) -> list[Track]:
    """Tracks from Parquet; GeoParquet point geometry is used when there are no lat/lon columns."""
    pq = _pyarrow("reading Parquet files")
    _pandas("reading Parquet files")
    try:
        table = pq.read_table(path)
    except Exception as exc:  # pyarrow raises several types for a bad file
        raise TrackInputError(f"{path}: not a readable Parquet file ({exc})") from exc
    meta = table.schema.metadata or {}
    df = table.to_pandas()
    columns = resolve_columns(df.columns, columns)
    if (columns.lat not in df or columns.lon not in df) and b"geo" in meta:
        import shapely

        geo = json.loads(meta[b"geo"])
        gcol = geo.get("primary_column", "geometry")
        pts = shapely.from_wkb(df[gcol].to_numpy())
        xy = shapely.get_coordinates(pts)
        if len(xy) != len(df):
            raise TrackInputError(f"{path}: geometry column {gcol!r} must hold one point per row")
        df[columns.lon] = xy[:, 0]
        df[columns.lat] = xy[:, 1]
    return tracks_from_frame(df, columns=columns, default_id=_stem(path))


def read_tracks_gpx(path: str | os.PathLike[str]) -> list[Track]:
    """One track per GPX ``<trk>`` (its segments joined) and per ``<rte>``; speed and course
    (the heading) when recorded."""
    import gpxpy
    import gpxpy.gpx

    try:
        with open(path, encoding="utf-8") as f:
            gpx = gpxpy.parse(f)
    except (gpxpy.gpx.GPXException, ValueError) as exc:
        raise TrackInputError(f"{path}: not a readable GPX file ({exc})") from exc
    out: list[Track] = []
    stem = _stem(path)
    for i, trk in enumerate(gpx.tracks):
        pts = [p for seg in trk.segments for p in seg.points]
        if pts:
            out.append(_gpx_track(trk.name or (stem if len(gpx.tracks) == 1 else f"{stem}-{i}"), pts))
    for i, rte in enumerate(gpx.routes):
        if rte.points:
            out.append(_gpx_track(rte.name or f"{stem}-route-{i}", rte.points))
    return out


def _gpx_track(name: str, pts: Sequence[Any]) -> Track:
    t = np.array([p.time.timestamp() if p.time else np.nan for p in pts], dtype=np.float64)
    speed = np.array([_gpx_value(p, "speed") for p in pts], dtype=np.float64)
    course = np.array([_gpx_value(p, "course") for p in pts], dtype=np.float64)
    return Track(
        track_id=str(name),
        time=t,
        lat=np.array([p.latitude for p in pts], dtype=np.float64),
        lon=np.array([p.longitude for p in pts], dtype=np.float64),
        heading=course % 360.0 if np.isfinite(course).any() else None,
        speed=speed if np.isfinite(speed).any() else None,
    )


def _gpx_value(point: Any, name: str) -> float:
    """A point's ``speed`` (m/s) or ``course`` (degrees clockwise from north), NaN if absent.

    GPX 1.0 has them as elements of the point; GPX 1.1 loggers write them in an extension
    (Garmin's TrackPointExtension v2: ``<gpxtpx:speed>``, ``<gpxtpx:course>``).
    """
    value = getattr(point, name, None)
    if value is None:
        for ext in point.extensions or ():
            for el in ext.iter():
                if el.tag.rsplit("}", 1)[-1].lower() == name and el.text:
                    value = el.text
                    break
            if value is not None:
                break
    try:
        out = float(value) if value is not None else np.nan
    except ValueError:
        return np.nan
    return out if np.isfinite(out) else np.nan


def resolve_columns(names: Iterable[Any], columns: ColumnsT) -> ColumnsT:
    """``columns`` (:class:`Columns` or :class:`FixColumns`) for a table with columns ``names``:
    a default name the table lacks becomes the table's one column that is that name in another
    case or one of its :data:`COLUMN_ALIASES` (``t``, ``timestamp``; ``latitude``; ``lng``,
    ...), when there is exactly one. Names the caller chose stay as they are."""
    present = [str(n) for n in names]
    by_lower: dict[str, list[str]] = {}
    for n in present:
        by_lower.setdefault(n.strip().lower(), []).append(n)
    defaults = type(columns)()
    changes: dict[str, str] = {}
    for field in dataclasses.fields(columns):
        aliases: tuple[str, ...] = COLUMN_ALIASES.get(field.name, ())
        name: str = getattr(columns, field.name)
        if name != getattr(defaults, field.name) or name in present:
            continue
        found = [n for a in dict.fromkeys((name, *aliases)) for n in by_lower.get(a, [])]
        if len(found) == 1:
            changes[field.name] = found[0]
            log.info("reading column %r as %s", found[0], field.name)
    return dataclasses.replace(columns, **changes) if changes else columns


@dataclass(frozen=True)
class TrackColumns:
    """A point table's values: the track id of each row, its time, lat, lon, and the optional
    ``heading``, ``speed``, ``pos_sigma`` and ``distance`` (``None`` when absent)."""

    ids: NDArray[Any]
    time: NDArray[np.float64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    optional: dict[str, NDArray[np.float64] | None]


def _need_columns(names: Sequence[Any], columns: Columns) -> None:
    """Refuse a point table without the lat, lon and time columns (named, with the table's)."""
    for need in (columns.lat, columns.lon, columns.time):
        if need and need not in names:
            hint = " (or an empty --time-col for tracks without times)" if need == columns.time else ""
            raise TrackInputError(
                f"missing column {need!r}{hint} (columns are: {_clip(', '.join(map(str, names)))})"
            )


def split_tracks(table: TrackColumns) -> list[Track]:
    """The tracks of a point table, one per id in order of first appearance, rows in order."""
    uniq, first, inv = np.unique(table.ids, return_index=True, return_inverse=True)
    order_ids = np.argsort(first, kind="stable")
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[order_ids] = np.arange(len(uniq))
    rows = np.argsort(rank[inv], kind="stable")
    bounds = np.searchsorted(rank[inv][rows], np.arange(len(uniq) + 1))
    out = []
    for k in range(len(uniq)):
        r = rows[bounds[k] : bounds[k + 1]]
        out.append(
            Track(
                track_id=str(uniq[order_ids[k]]),
                time=table.time[r],
                lat=table.lat[r],
                lon=table.lon[r],
                **{name: (a[r] if a is not None else None) for name, a in table.optional.items()},
            )
        )
    return out


def tracks_from_frame(
    df: pd.DataFrame, *, columns: Columns = DEFAULT_COLUMNS, default_id: str
) -> list[Track]:
    """Split a point table (a pandas frame) into tracks by the id column, in order of first
    appearance.

    The lat, lon and time columns are required (``columns.time == ""`` reads tracks without
    times), under the names of ``columns`` (the readers first resolve common other names:
    :func:`resolve_columns`); without the id column the table is one track named ``default_id``.
    """
    pd = _pandas("tables as pandas frames")
    _need_columns(list(df.columns), columns)
    n = len(df)

    def num(col: str) -> NDArray[np.float64] | None:
        if col not in df.columns:
            return None
        return pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=np.float64)

    lat, lon = num(columns.lat), num(columns.lon)
    assert lat is not None and lon is not None
    return split_tracks(
        TrackColumns(
            ids=df[columns.id].astype(str).to_numpy() if columns.id in df.columns else np.full(n, default_id),
            time=_time_seconds(df[columns.time]) if columns.time else np.full(n, np.nan),
            lat=lat,
            lon=lon,
            optional={k: num(getattr(columns, k)) for k in ("heading", "speed", "pos_sigma", "distance")},
        )
    )


def _time_seconds(s: pd.Series) -> NDArray[np.float64]:
    """Numeric seconds, or ISO-8601 / datetime values as seconds since the epoch."""
    pd = _pandas("tables as pandas frames")
    if pd.api.types.is_numeric_dtype(s):
        return s.to_numpy(dtype=np.float64)
    if pd.api.types.is_datetime64_any_dtype(s):
        dt = s
    else:
        num = pd.to_numeric(s, errors="coerce")
        if num.notna().sum() == s.notna().sum():
            return num.to_numpy(dtype=np.float64)
        dt = pd.to_datetime(s, errors="coerce", utc=True, format="ISO8601")
    if getattr(dt.dt, "tz", None) is None:
        dt = dt.dt.tz_localize("UTC")
    secs = (dt - pd.Timestamp(0, tz="UTC")).dt.total_seconds()
    return np.asarray(secs.to_numpy(dtype=np.float64, na_value=np.nan), dtype=np.float64)


def _stem(path: str | os.PathLike[str]) -> str:
    name = Path(path).name
    for suf in sorted(TRACK_SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(suf):
            return name[: -len(suf)]
    return Path(path).stem


def tracks_to_frame(tracks: Iterable[Track], *, columns: Columns = DEFAULT_COLUMNS) -> pd.DataFrame:
    """The point table of some tracks (the inverse of :func:`tracks_from_frame`)."""
    pd = _pandas("tables as pandas frames")
    frames = []
    for t in tracks:
        d: dict[str, Any] = {
            columns.id: np.full(len(t), t.track_id, dtype=object),
            columns.time: t.time,
            columns.lat: t.lat,
            columns.lon: t.lon,
        }
        for k in ("heading", "speed", "pos_sigma", "distance"):
            a = getattr(t, k)
            if a is not None:
                d[getattr(columns, k)] = a
        frames.append(pd.DataFrame(d))
    if not frames:
        return pd.DataFrame({columns.id: [], columns.time: [], columns.lat: [], columns.lon: []})
    return pd.concat(frames, ignore_index=True)


def write_tracks(
    path: str | os.PathLike[str], tracks: Iterable[Track], *, columns: Columns = DEFAULT_COLUMNS
) -> None:
    """Write tracks as CSV, Parquet or GPX (by suffix), atomically."""
    p = Path(path)
    name = p.name.lower()
    tracks = list(tracks)
    if name.endswith(".gpx"):
        import gpxpy.gpx

        gpx = gpxpy.gpx.GPX()
        for t in tracks:
            trk = gpxpy.gpx.GPXTrack(name=t.track_id)
            seg = gpxpy.gpx.GPXTrackSegment()
            for i in range(len(t)):
                tm = datetime.fromtimestamp(float(t.time[i]), tz=UTC) if np.isfinite(t.time[i]) else None
                sp = float(t.speed[i]) if t.speed is not None and np.isfinite(t.speed[i]) else None
                point = gpxpy.gpx.GPXTrackPoint(float(t.lat[i]), float(t.lon[i]), time=tm, speed=sp)
                if t.heading is not None and np.isfinite(t.heading[i]):
                    setattr(point, "course", float(t.heading[i]))  # noqa: B010 (typed None in gpxpy)
                seg.points.append(point)
            trk.segments.append(seg)
            gpx.tracks.append(trk)
        # GPX 1.0 is the version with <speed> and <course> elements
        motion = any(t.speed is not None or t.heading is not None for t in tracks)
        xml = gpx.to_xml(version="1.0" if motion else "1.1")
        with atomic_path(p) as tmp:
            tmp.write_text(xml, encoding="utf-8")
        return
    if not name.endswith((".parquet", ".geoparquet", ".pq", ".csv")):
        raise TrackInputError(f"{p}: unknown track format")
    df = tracks_to_frame(tracks, columns=columns)
    with atomic_path(p) as tmp:
        if name.endswith(".csv"):
            df.to_csv(tmp, index=False)
        else:
            _pyarrow("writing Parquet files")
            df.to_parquet(tmp, index=False)


# ---------------------------------------------------------------------- results
RESULT_COLUMNS = (
    "track_id", "n_points", "n_matched", "n_interpolated", "n_unmatched", "length_m", "confidence",
    "splits", "edges", "way_ids", "names", "route_wkb",
    "pt_status", "pt_edge", "pt_way_id", "pt_offset", "pt_lat", "pt_lon", "pt_dist", "pt_name",
)  # fmt: skip


ResultRows = list[dict[str, Any]]
"""A results table as rows: one dict per track, keyed by :data:`RESULT_COLUMNS`."""


def result_rows(results: Iterable[TrackMatch], graph: RoadGraph) -> ResultRows:
    """One row per track: route (WKB, lon/lat), edge sequence, way ids, names, and point lists.

    ``way_ids`` and ``names`` follow the way pieces the route runs along (consecutive repeats
    merged); ``pt_way_id`` and ``pt_name`` are those of the piece under each point.
    """
    import shapely

    from mapmatch.batch import point_ways, route_ways

    rows: ResultRows = []
    for r in results:
        edges = [e for piece in r.routes for e in piece]
        ways, names = route_ways(r, graph)
        pt_way, pt_name = point_ways(r, graph)
        lines = [np.asarray(p, dtype=np.float64) for p in r.route_lonlat if len(p) >= 2]
        if len(lines) == 1:
            geom = shapely.linestrings(lines[0])
        elif lines:
            geom = shapely.multilinestrings([shapely.linestrings(a) for a in lines])
        else:
            geom = shapely.from_wkt("LINESTRING EMPTY")
        st = [str(p.status) for p in r.points]
        pe = np.array([p.edge for p in r.points], dtype=np.int64)
        rows.append(
            {
                "track_id": r.track_id,
                "n_points": len(r.points),
                "n_matched": st.count("matched"),
                "n_interpolated": st.count("interpolated"),
                "n_unmatched": st.count("unmatched"),
                "length_m": float(r.length_m),
                "confidence": float(r.confidence),
                "splits": [int(s) for s in r.splits],
                "edges": edges,
                "way_ids": [int(w) for w in ways],
                "names": names,
                "route_wkb": shapely.to_wkb(geom),
                "pt_status": st,
                "pt_edge": pe.tolist(),
                "pt_way_id": pt_way,
                "pt_offset": [p.offset for p in r.points],
                "pt_lat": [p.lat for p in r.points],
                "pt_lon": [p.lon for p in r.points],
                "pt_dist": [p.dist for p in r.points],
                "pt_name": pt_name,
            }
        )
    return rows


def results_table(results: Iterable[TrackMatch], graph: RoadGraph) -> pd.DataFrame:
    """:func:`result_rows` as a pandas frame (the ``tables`` extra)."""
    return _rows_frame(result_rows(results, graph))


def _rows_frame(rows: ResultRows) -> pd.DataFrame:
    pd = _pandas("results as a table")
    if not rows:
        return pd.DataFrame({c: [] for c in RESULT_COLUMNS})
    return pd.DataFrame(rows, columns=list(RESULT_COLUMNS))


def _as_rows(table: pd.DataFrame | ResultRows) -> ResultRows:
    if isinstance(table, list):
        return table
    return [{str(k): v for k, v in r.items()} for r in table.to_dict("records")]


POINT_COLUMNS = ("track_id", "index", "status", "edge", "way_id", "name", "offset", "lat", "lon", "dist")
"""The columns of the per-point results (CSV output, :func:`points_frame`)."""


def points_frame(table: pd.DataFrame | ResultRows) -> pd.DataFrame:
    """The per-point rows of a results table (one row per input point)."""
    pd = _pandas("results as a table")
    if not isinstance(table, list):
        table = _as_rows(table)
    if not table:
        return pd.DataFrame({c: [] for c in POINT_COLUMNS})
    n = np.array([int(r["n_points"]) for r in table], dtype=np.int64)

    def flat(col: str) -> NDArray[Any]:
        return np.concatenate([np.asarray(r[col]) for r in table]) if n.sum() else np.empty(0)

    return pd.DataFrame(
        {
            "track_id": np.repeat(np.array([r["track_id"] for r in table], dtype=object), n),
            "index": np.concatenate([np.arange(k) for k in n]),
            "status": flat("pt_status"),
            "edge": flat("pt_edge").astype(np.int64),
            "way_id": flat("pt_way_id").astype(np.int64),
            "name": flat("pt_name").astype(object),
            "offset": flat("pt_offset"),
            "lat": flat("pt_lat"),
            "lon": flat("pt_lon"),
            "dist": flat("pt_dist"),
        }
    )


def _cell(x: Any) -> str:
    """A per-point number as CSV text: the shortest float that reads back, nothing for NaN."""
    if x is None:
        return ""
    f = float(x)
    return "" if f != f else repr(f)


def write_points_csv(path: str | os.PathLike[str], table: pd.DataFrame | ResultRows) -> None:
    """The per-point rows of a results table as CSV (:data:`POINT_COLUMNS`), atomically."""
    import csv

    with atomic_path(Path(path)) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(POINT_COLUMNS)
        for r in _as_rows(table):
            cols = [r[c] for c in ("pt_status", "pt_edge", "pt_way_id", "pt_name", "pt_offset", "pt_lat",
                                   "pt_lon", "pt_dist")]  # fmt: skip
            tid = str(r["track_id"])
            for k, (st, edge, way, name, *xs) in enumerate(zip(*cols, strict=True)):
                w.writerow([tid, k, st, int(edge), int(way), "" if name is None else name, *map(_cell, xs)])


def write_results(path: str | os.PathLike[str], table: pd.DataFrame | ResultRows) -> None:
    """Write a results table (:func:`result_rows`, or its frame) as GeoJSON (a feature per
    track), CSV (a row per point) or GeoParquet (the ``tables`` extra)."""
    p = Path(path)
    name = p.name.lower()
    if name.endswith((".geojson", ".json")):
        write_geojson(p, table)
    elif name.endswith(".csv"):
        write_points_csv(p, table)
    elif name.endswith((".parquet", ".geoparquet")):
        write_geoparquet(p, table)
    else:
        raise TrackInputError(f"{p}: unknown output format (use one of {', '.join(OUTPUT_SUFFIXES)})")


def write_rows_json(path: str | os.PathLike[str], rows: ResultRows) -> None:
    """Result rows as JSON lines, exactly (every float round-trips; the route as hex WKB),
    atomically: a batch run's partition file."""
    with atomic_path(Path(path)) as tmp, open(tmp, "w", encoding="utf-8") as f:
        for r in rows:
            f.write(json.dumps({**r, "route_wkb": bytes(r["route_wkb"]).hex()}, default=_json_value))
            f.write("\n")


def _json_value(x: Any) -> Any:
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


def read_rows_json(path: str | os.PathLike[str]) -> ResultRows:
    """Result rows back from :func:`write_rows_json`."""
    rows = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            r = json.loads(line)
            r["route_wkb"] = bytes.fromhex(r["route_wkb"])
            rows.append(r)
    return rows


def write_geojson(path: str | os.PathLike[str], table: pd.DataFrame | ResultRows) -> None:
    """A FeatureCollection with one (Multi)LineString feature per track."""
    import shapely

    feats = []
    rows = _as_rows(table)
    for row in rows:
        geom = shapely.from_wkb(row["route_wkb"])
        feats.append(
            {
                "type": "Feature",
                "geometry": json.loads(shapely.to_geojson(geom)) if not geom.is_empty else None,
                "properties": {
                    "track_id": row["track_id"],
                    "length_m": round(float(row["length_m"]), 3),
                    "confidence": round(float(row["confidence"]), 6),
                    "n_points": int(row["n_points"]),
                    "n_matched": int(row["n_matched"]),
                    "n_interpolated": int(row["n_interpolated"]),
                    "n_unmatched": int(row["n_unmatched"]),
                    "splits": [int(s) for s in row["splits"]],
                    "edges": [int(e) for e in row["edges"]],
                    "way_ids": [int(w) for w in row["way_ids"]],
                    "names": [str(s) for s in row["names"]],
                },
            }
        )
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(json.dumps({"type": "FeatureCollection", "features": feats}), encoding="utf-8")


def write_geoparquet(path: str | os.PathLike[str], table: pd.DataFrame | ResultRows) -> None:
    """GeoParquet: one row per track, the route as WKB ``geometry`` (EPSG:4326), all columns kept
    (the ``tables`` extra)."""
    pq = _pyarrow("GeoParquet output")
    import pyarrow as pa
    import shapely

    if isinstance(table, list):
        table = _rows_frame(table)
    df = table.rename(columns={"route_wkb": "geometry"})
    at = pa.Table.from_pandas(df, preserve_index=False)
    geoms = shapely.from_wkb(df["geometry"].to_numpy()) if len(df) else np.empty(0, dtype=object)
    types = sorted({g.geom_type for g in geoms if g is not None and not g.is_empty})
    bbox = list(shapely.total_bounds(geoms)) if len(df) else []
    geo = {
        "version": "1.0.0",
        "primary_column": "geometry",
        "columns": {
            "geometry": {
                "encoding": "WKB",
                "geometry_types": types,
                "crs": _crs_projjson(),
                **({"bbox": bbox} if bbox and np.all(np.isfinite(bbox)) else {}),
            }
        },
    }
    meta = dict(at.schema.metadata or {})
    meta[b"geo"] = json.dumps(geo).encode()
    at = at.replace_schema_metadata(meta)
    with atomic_path(Path(path)) as tmp:
        pq.write_table(at, tmp)


def read_results(path: str | os.PathLike[str]) -> pd.DataFrame:
    """A results table back from GeoParquet written by :func:`write_geoparquet`."""
    pd = _pandas("reading GeoParquet results")
    _pyarrow("reading GeoParquet results")
    df = pd.read_parquet(path)
    df = df.rename(columns={"geometry": "route_wkb"})
    if "pt_name" not in df.columns:  # written before per-point names
        df["pt_name"] = [[""] * len(v) for v in df["pt_edge"]]
    for c in ("splits", "edges", "way_ids", "names", "pt_status", "pt_edge", "pt_way_id", "pt_name"):
        df[c] = [list(v) for v in df[c]]
    for c in ("pt_offset", "pt_lat", "pt_lon", "pt_dist"):
        df[c] = [np.asarray(v, dtype=np.float64).tolist() for v in df[c]]
    return df[list(RESULT_COLUMNS)]


def _crs_projjson() -> dict[str, Any] | None:
    from pyproj import CRS

    return json.loads(CRS.from_epsg(4326).to_json())
