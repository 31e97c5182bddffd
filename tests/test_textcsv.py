"""The core's CSV reading (stdlib csv and numpy) gives the tracks and fixes a pandas reading of
the same files gives: ids, times (seconds, ISO 8601 with zones and fractions), numbers, gaps."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mapmatch.errors import ValidationError
from mapmatch.io import (
    DEFAULT_COLUMNS,
    TrackInputError,
    read_fixes,
    read_tracks,
    resolve_columns,
    tracks_from_frame,
)
from mapmatch.textcsv import inferred_text, numbers, read_table, times

FILES = {
    "seconds": "id,time,lat,lon,speed\na,0,60.1,24.9,3\na,1.5,60.10001,24.90001,\nb,2,60.2,24.8,4.25\n",
    "leading-zero ids": "id,time,lat,lon\n007,0,60.1,24.9\n007,1,60.1,24.9\n010,2,60.1,24.9\n",
    "decimal ids": "id,time,lat,lon\n1,0,60.1,24.9\n2.5,1,60.1,24.9\n1,2,60.1,24.9\n",
    "iso times": "track_id,timestamp,latitude,lng\n"
    "x,2024-05-01T10:00:00Z,60.1,24.9\n"
    "x,2024-05-01T10:00:00.25Z,60.1,24.9\n"
    "x,2024-05-01 12:00:01.123456+02:00,60.1,24.9\n"
    "x,2024-05-01T10:00:02,60.1,24.9\n"
    "x,not a time,60.1,24.9\n",
    "nanosecond times": "id,time,lat,lon\n"
    "q,2024-05-01T10:00:00.123456789Z,60.1,24.9\n"
    "q,2024-05-01T10:00:01Z,60,24\n",
    "bad numbers and NA": "id,time,lat,lon,heading\nz,0,60.1,24.9,NA\nz,1,x,24.9,90\nz,2,1e1,-.5,inf\n",
    "blank lines and quotes": 'id,time,lat,lon\n\n"a,1",0,60.1,24.9\n\n"a,1",1,60.1,24.9\n',
    "short row": "id,time,lat,lon,speed\na,0,60.1,24.9\n",
}


def _pandas_tracks(path: Path, sep: str = ",") -> list[tuple[object, ...]]:
    df = pd.read_csv(path, sep=sep)
    cols = resolve_columns(df.columns, DEFAULT_COLUMNS)
    return [_key(t) for t in tracks_from_frame(df, columns=cols, default_id=path.stem)]


def _key(t: object) -> tuple[object, ...]:
    def arr(a: object) -> str | None:
        return None if a is None else np.asarray(a, dtype=np.float64).tobytes().hex()

    return (t.track_id, arr(t.time), arr(t.lat), arr(t.lon), arr(t.heading), arr(t.speed))  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", sorted(FILES))
def test_tracks_as_pandas_reads_them(tmp_path: Path, name: str) -> None:
    path = tmp_path / "t.csv"
    path.write_text(FILES[name], encoding="utf-8")
    assert [_key(t) for t in read_tracks(path)] == _pandas_tracks(path)


def test_gzip_bom_and_semicolons(tmp_path: Path) -> None:
    text = "\ufeffid;time;lat;lon\na;0;60.1;24.9\na;1;60.2;24.8\n"
    path = tmp_path / "t.csv.gz"
    with gzip.open(path, "wt", encoding="utf-8") as f:
        f.write(text)
    plain = tmp_path / "p.csv"
    plain.write_text(text, encoding="utf-8")
    assert [_key(t) for t in read_tracks(path)] == _pandas_tracks(plain, sep=";")


def test_cells_numbers_times_and_ids() -> None:
    cells = ["1", "+2", " 3 ", "1_000", "0x10", "nan", "inf", ".5", "5.", "1e", ""]
    got = numbers(cells)
    want = pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce").to_numpy(dtype=np.float64)
    assert got.tobytes() == want.tobytes()
    iso = ["2024-01-01T00:00:00.123456Z", "2024-06-01T10:00:00+0200", "20240101T101010", "2024-13-01"]
    ref = pd.to_datetime(pd.Series(iso, dtype=object), errors="coerce", utc=True, format="ISO8601")
    secs = (ref - pd.Timestamp(0, tz="UTC")).dt.total_seconds().to_numpy(dtype=np.float64, na_value=np.nan)
    assert times(iso).tobytes() == secs.tobytes()
    assert inferred_text(["007", "10"]) == ["7", "10"]
    assert inferred_text(["1", None]) == ["1.0", "nan"]
    assert inferred_text(["true", "False"]) == ["True", "False"]
    assert inferred_text(["a", "007"]) == ["a", "007"]


def test_table_errors_name_the_line(tmp_path: Path) -> None:
    path = tmp_path / "t.csv"
    path.write_text("a,b\n1,2\n1,2,3\n")
    with pytest.raises(ValueError, match="Expected 2 fields in line 3, saw 3"):
        read_table(path)
    with pytest.raises(TrackInputError, match="not a readable CSV file"):
        read_tracks(path)
    (tmp_path / "e.csv").write_text("\n\n")
    with pytest.raises(ValidationError, match="is empty"):
        read_fixes(tmp_path / "e.csv")


def test_fixes_cells_and_messages(tmp_path: Path) -> None:
    path = tmp_path / "f.csv"
    path.write_text(
        "vehicle_id, time, lat, lon, heading, gps_valid\n"
        " car ,2024-05-01T10:00:00Z, 60.1, 24.9,,yes\n"
        "car,2024-05-01T10:00:01.5Z,60.2,24.8,90,\n"
    )
    (fixes,) = read_fixes(path).values()
    assert [f.time for f in fixes] == [1714557600.0, 1714557601.5]
    assert math.isnan(fixes[0].heading) and fixes[1].heading == 90.0
    assert [f.gps_valid for f in fixes] == [True, None]
    path.write_text("vehicle_id,time,lat,lon,heading\ncar,0,60.1,nan,0\n")
    with pytest.raises(ValidationError, match="lon: not a number on line 2: 'nan'"):
        read_fixes(path)
    path.write_text("vehicle_id,time,lat,lon,heading\ncar,0,60.1,24.9,0\ncar,,60.1,24.9,0\n")
    with pytest.raises(ValidationError, match="neither seconds nor an ISO 8601 time on line 3"):
        read_fixes(path)
