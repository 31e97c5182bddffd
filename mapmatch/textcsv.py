"""CSV text tables read with the standard library: cells, numbers, times and ids.

The core install reads its CSV inputs (``mapmatch match``, ``replay``, ``send``) here, without
pandas. The rules are those of a spreadsheet-style reader: blank lines are skipped, a short row
is padded with empty cells, a long row is an error naming its line, a repeated column name gets
``.1``, ``.2``...; a number is decimal text (``1``, ``-2.5``, ``.5``, ``1e3``, ``inf``); a time
is seconds or ISO 8601 text (``2024-05-01T10:00:00.25Z``; no zone means UTC).
"""

from __future__ import annotations

import csv
import gzip
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from numpy.typing import NDArray

NA_CELLS = frozenset(
    ("", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
     "<NA>", "N/A", "NA", "NULL", "NaN", "None", "n/a", "nan", "null")
)  # fmt: skip
"""Cells that mean "no value" in a track file (read with ``na=True``)."""
_NUMBER = re.compile(r"\s*[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|inf(?:inity)?)\s*", re.I | re.A)
_INTEGER = re.compile(r"\s*[+-]?\d+\s*", re.A)
_BOOL = {"True": "True", "TRUE": "True", "true": "True", "False": "False", "FALSE": "False", "false": "False"}
_FRACTION = re.compile(r"(T?\d{2}:?\d{2}:?\d{2})[.,](\d+)", re.A)
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


class CsvError(ValueError):
    """A CSV text cannot be read as a table (empty, or a row longer than the header)."""


class EmptyCsvError(CsvError):
    """A CSV text holds no header line."""


@dataclass(frozen=True)
class TextTable:
    """The cells of a CSV file by column name (``None``: no value), in file order."""

    names: list[str]
    columns: dict[str, list[str | None]]
    rows: int

    def __contains__(self, name: object) -> bool:
        return name in self.columns


def read_table(
    path: str | os.PathLike[str], *, sep: str = ",", strip_space: bool = False, na: bool = False
) -> TextTable:
    """Read a CSV file (plain or ``.gz``, UTF-8, an optional byte-order mark) into cells.

    ``strip_space`` drops the spaces after each separator; ``na`` reads the :data:`NA_CELLS`
    as no value, else a missing cell (a short row) is the empty text.

    Raises
    ------
    CsvError
        The file holds no header, or a row has more cells than the header.
    UnicodeDecodeError
        The file is not UTF-8.
    """
    opener: Any = gzip.open if str(path).lower().endswith(".gz") else open
    with opener(path, "rt", encoding="utf-8-sig", newline="") as f:
        reader = csv.reader(f, delimiter=sep, skipinitialspace=strip_space)
        header = next((r for r in reader if _filled(r)), None)
        if header is None:
            raise EmptyCsvError("No columns to parse from file")
        names = _unique(header)
        rows: list[list[str]] = []
        for row in reader:
            if not _filled(row):
                continue
            if len(row) > len(names):
                raise CsvError(
                    f"Error tokenizing data. C error: Expected {len(names)} fields in line "
                    f"{reader.line_num}, saw {len(row)}"
                )
            rows.append(row)
    missing: str | None = None if na else ""
    columns: dict[str, list[str | None]] = {}
    for k, name in enumerate(names):
        cells = [r[k] if k < len(r) else missing for r in rows]
        columns[name] = [None if c is not None and c in NA_CELLS else c for c in cells] if na else cells
    return TextTable(names, columns, len(rows))


def _filled(row: list[str]) -> bool:
    return bool(row) and not (len(row) == 1 and not row[0].strip())


def _unique(header: list[str]) -> list[str]:
    """Column names with repeats numbered (``a``, ``a.1``, ``a.2``)."""
    seen: dict[str, int] = {}
    out = []
    for name in header:
        if name in seen:
            seen[name] += 1
            name = f"{name}.{seen[name]}"
        seen.setdefault(name, 0)
        out.append(name)
    return out


def number(cell: object) -> float:
    """The number a cell holds (decimal text, an int or a float), else NaN."""
    if isinstance(cell, (int, float, np.integer, np.floating)) and not isinstance(cell, bool):
        return float(cell)
    if isinstance(cell, str) and _NUMBER.fullmatch(cell):
        return float(cell)
    return float("nan")


def numbers(cells: Sequence[object]) -> NDArray[np.float64]:
    """:func:`number` of every cell."""
    return np.array([number(c) for c in cells], dtype=np.float64)


def is_number(cell: object) -> bool:
    """Whether a cell holds a number (:func:`number`; NaN text does not)."""
    if isinstance(cell, str):
        return _NUMBER.fullmatch(cell) is not None
    return isinstance(cell, (int, float, np.integer, np.floating)) and not isinstance(cell, bool)


def times(cells: Sequence[object]) -> NDArray[np.float64]:
    """Seconds of every cell: all numbers when every cell with a value is one, else ISO 8601
    times (no zone: UTC) as seconds since 1970; NaN for no value or a cell that is neither.

    Times with more than six decimals are counted in nanoseconds, others in microseconds (the
    last bit of a time as a double depends on the unit).
    """
    given = [c for c in cells if c is not None]
    if all(is_number(c) for c in given):
        return numbers([c if c is not None else "" for c in cells])
    ticks = [_iso_ticks(c) if isinstance(c, str) else None for c in cells]
    fine = any(t is not None and t[1] for t in ticks)
    out = np.full(len(cells), np.nan)
    for i, t in enumerate(ticks):
        if t is not None:
            out[i] = float(t[0]) / 1e9 if fine else float(t[0] // 1000) / 1e6
    return out


def _iso_ticks(text: str) -> tuple[int, bool] | None:
    """``(nanoseconds since 1970, whether finer than a microsecond)`` of ISO 8601 text, or None."""
    s = text.strip()
    nanos, fine = 0, False
    m = _FRACTION.search(s)
    if m is not None:
        digits = m.group(2)
        fine = len(digits) > 6
        nanos = int(digits[:9].ljust(9, "0"))
        s = s[: m.start(2) - 1] + s[m.end(2) :]
    try:
        dt = datetime.fromisoformat(s)
    except ValueError:
        return None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    delta = dt - _EPOCH
    return (delta.days * 86400 + delta.seconds) * 1_000_000_000 + nanos, fine


def inferred_text(cells: Sequence[str | None]) -> list[str]:
    """Cells as text the way a typed reader shows them: integers without leading zeros or sign
    (``007`` -> ``7``) when every cell is an integer, ``1.0`` when the column is numbers with
    a gap or a decimal, ``True``/``False`` for a column of booleans, else the text itself;
    ``nan`` for no value."""
    given = [c for c in cells if c is not None]
    if given and len(given) == len(cells) and all(_INTEGER.fullmatch(c) for c in given):
        return [str(int(c)) for c in given]
    if given and all(_NUMBER.fullmatch(c) for c in given):
        return [repr(number(c)) if c is not None else "nan" for c in cells]
    if given and len(given) == len(cells) and all(c in _BOOL for c in given):
        return [_BOOL[c] for c in given]
    return [c if c is not None else "nan" for c in cells]
