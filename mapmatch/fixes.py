"""Fused-fix files: read fixes per vehicle, write one result row per fix.

Input columns: ``vehicle_id``, ``time``, ``lat``, ``lon``, ``heading`` and optional
``pos_sigma``, ``heading_sigma``, ``speed``, ``distance``, ``gps_valid``. Times are seconds
(any epoch) or ISO 8601 timestamps. Empty cells are "not given". Output columns:
:data:`RESULT_COLUMNS` (documented in ``docs/formats.md``, "Online results").
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from graph.files import atomic_path
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.measurement import AIDED_COLUMNS, aided_cells
from mapmatch.textcsv import CsvError, EmptyCsvError, is_number, read_table, times
from mapmatch.types import Fix, SnapResult

REQUIRED_COLUMNS: tuple[str, ...] = ("vehicle_id", "time", "lat", "lon", "heading")
OPTIONAL_COLUMNS: tuple[str, ...] = ("pos_sigma", "heading_sigma", "speed", "distance", "gps_valid")
RESULT_COLUMNS: tuple[str, ...] = (
    "vehicle_id",
    "time",
    "state",
    "edge",
    "u",
    "v",
    "way_id",
    "offset",
    "lat",
    "lon",
    "bearing",
    "dist",
    "turn",
    "raw_lat",
    "raw_lon",
    "candidates",
    "correction",
    "correction_from",
    "correction_to",
    "correction_replaced",
    "correction_times",
    "error",
    *AIDED_COLUMNS,
)
_TRUE = {"1", "true", "t", "yes", "y"}
_FALSE = {"0", "false", "f", "no", "n"}


Cells = Mapping[str, Sequence[str | None]]
"""A table of text cells by column name (``None`` or ``""``: not given), in file order."""


def _given(cell: str | None) -> bool:
    return cell is not None and cell != ""


def _numeric(cells: Sequence[str | None] | None, n: int, col: str) -> np.ndarray:
    if cells is None:
        return np.full(n, np.nan)
    out = np.full(n, np.nan)
    for i, cell in enumerate(cells):
        if cell is None or not cell.strip():
            continue
        if not is_number(cell):
            from mapmatch.textbounds import quote

            raise ValidationError(col, f"not a number on line {i + 2}: {quote(cell)}")
        out[i] = float(cell)
    return out


def _times(cells: Sequence[str | None]) -> np.ndarray:
    if all(_given(c) and is_number(c) for c in cells):
        return np.array([float(c) for c in cells], dtype=np.float64)  # type: ignore[arg-type]
    out = times([c if _given(c) else None for c in cells])
    bad = np.flatnonzero(np.isnan(out))
    if len(bad):
        raise ValidationError("time", f"neither seconds nor an ISO 8601 time on line {int(bad[0]) + 2}")
    return out


def _gps_valid(cells: Sequence[str | None] | None, n: int) -> list[bool | None]:
    if cells is None:
        return [None] * n
    out: list[bool | None] = []
    for i, cell in enumerate(cells):
        v = str(cell if _given(cell) else None).strip().lower()
        if v in ("", "nan", "none"):
            out.append(None)
        elif v in _TRUE:
            out.append(True)
        elif v in _FALSE:
            out.append(False)
        else:
            raise ValidationError("gps_valid", f"not a boolean on line {i + 2}: {v!r}")
    return out


def read_fixes_csv(path: str | os.PathLike[str]) -> dict[str, list[Fix]]:
    """Read a fused-fix CSV into fixes per vehicle, in file order.

    Raises
    ------
    ValidationError
        A required column is missing or a cell is not a number (values themselves are
        validated by the matcher, fix by fix).
    """
    try:
        table = read_table(path, strip_space=True)
    except EmptyCsvError:
        raise ValidationError("file", f"{path} is empty") from None
    except (CsvError, UnicodeDecodeError) as exc:
        raise ValidationError("file", f"{path} is not a readable CSV ({exc})") from None
    cells = {name.strip(): table.columns[name] for name in table.names}
    return fixes_from_cells(cells, table.rows)


def fixes_from_cells(cells: Cells, n: int) -> dict[str, list[Fix]]:
    """Fixes per vehicle, in row order, from ``n`` rows of text cells with the fix columns
    (:data:`REQUIRED_COLUMNS`, and any of :data:`OPTIONAL_COLUMNS`).

    Raises
    ------
    ValidationError
        A required column is missing or a cell is not a number.
    """
    missing = [c for c in REQUIRED_COLUMNS if c not in cells]
    if missing:
        raise ValidationError("columns", f"missing {', '.join(missing)} (need {', '.join(REQUIRED_COLUMNS)})")
    t = _times(cells["time"])
    cols = {c: _numeric(cells.get(c), n, c) for c in ("lat", "lon", "heading", *OPTIONAL_COLUMNS[:-1])}
    gps = _gps_valid(cells.get("gps_valid"), n)
    out: dict[str, list[Fix]] = {}
    vids = [str(v if _given(v) else "nan").strip() for v in cells["vehicle_id"]]
    for i, vid in enumerate(vids):
        out.setdefault(vid, []).append(
            Fix(
                time=float(t[i]),
                lat=float(cols["lat"][i]),
                lon=float(cols["lon"][i]),
                heading=float(cols["heading"][i]),
                pos_sigma=float(cols["pos_sigma"][i]),
                heading_sigma=float(cols["heading_sigma"][i]),
                speed=float(cols["speed"][i]),
                distance=float(cols["distance"][i]),
                gps_valid=gps[i],
            )
        )
    return out


def _num(x: float, fmt: str) -> str:
    return "" if math.isnan(x) else format(x, fmt)


def result_row(vehicle_id: str, fix: Fix, result: SnapResult | None, error: str = "") -> list[str]:
    """One output row (strings, in :data:`RESULT_COLUMNS` order). ``result`` None = rejected fix."""
    if result is None:
        return [vehicle_id, repr(fix.time), "rejected", "-1", "", "", "", "", "", "", "", "", "none",
                _num(fix.lat, ".8f"), _num(fix.lon, ".8f"), "", "", "", "", "", "", error,
                *[""] * len(AIDED_COLUMNS)]  # fmt: skip
    placed = result.edge >= 0
    c = result.correction
    return [
        vehicle_id,
        repr(result.time),
        str(result.state),
        str(result.edge),
        str(result.u) if placed else "",
        str(result.v) if placed else "",
        str(result.way_id) if placed else "",
        _num(result.offset, ".3f"),
        _num(result.lat, ".8f"),
        _num(result.lon, ".8f"),
        _num(result.bearing, ".2f"),
        _num(result.dist, ".3f"),
        str(result.turn),
        _num(result.raw_lat, ".8f"),
        _num(result.raw_lon, ".8f"),
        ";".join(f"{k.edge}:{k.probability:.4f}" for k in result.candidates),
        "" if c is None else ";".join(map(str, c.edges)),
        "" if c is None else repr(c.time_from),
        "" if c is None else repr(c.time_to),
        "" if c is None else ";".join(map(str, c.replaced_edges)),
        "" if c is None else ";".join(map(repr, c.edge_times)),
        error,
        *aided_cells(result.map_aided),
    ]


def write_results_csv(
    path: str | os.PathLike[str],
    rows: Iterable[tuple[str, Fix, SnapResult | None] | tuple[str, Fix, SnapResult | None, str]],
    graph: RoadGraph | None = None,
) -> int:
    """Write one row per fix (atomic: a temp file renamed into place). Returns the row count.

    ``rows`` yields ``(vehicle_id, fix, result)`` or ``(vehicle_id, fix, None, error)`` for a
    rejected fix. ``graph`` is accepted for the shared signature; results already carry
    external ids.
    """
    n = 0
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(RESULT_COLUMNS)
        for row in rows:
            vid, fix, res = row[0], row[1], row[2]
            err = row[3] if len(row) > 3 else ""  # type: ignore[misc]
            w.writerow(result_row(vid, fix, res, err))
            n += 1
    return n
