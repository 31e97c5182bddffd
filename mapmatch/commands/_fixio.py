"""What ``replay`` and ``send`` share: fused-fix column options, ``-`` for stdin/stdout, summaries."""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from mapmatch.io import FixColumns

STDIO = "-"  # as mapmatch.io.STDIO (not imported here: --help stays instant)


def add_fix_options(p: argparse.ArgumentParser) -> None:
    """The input/output arguments and the column-name options (as ``match`` has them)."""
    p.add_argument(
        "fixes", type=Path, metavar="FIXES.csv",
        help="fused fixes: CSV ('-': standard input), or any track file `match` reads (GPX, "
        "Parquet, GeoParquet, GeoJSON/GPKG/SHP/FGB lines)",
    )  # fmt: skip
    p.add_argument(
        "--vehicle-id", metavar="ID",
        help="the vehicle's id when the input is one vehicle (default: its vehicle column, else "
        "the file's name, or 'stdin')",
    )  # fmt: skip
    p.add_argument(
        "-o",
        "--output",
        required=True,
        type=Path,
        metavar="OUT.csv",
        help="result rows ('-': stdout)",
    )
    cols = p.add_argument_group("input columns (vehicle and heading are optional)")
    for name, help_ in (
        ("vehicle-id", "without it the file is one vehicle (see --vehicle-id)"),
        ("time", "required"),
        ("lat", "required"),
        ("lon", "required"),
        ("heading", "without it every heading is unknown"),
        ("pos-sigma", ""),
        ("heading-sigma", ""),
        ("speed", ""),
        ("distance", ""),
        ("gps-valid", ""),
    ):
        field = name.replace("-", "_")
        cols.add_argument(
            f"--{name}-col", dest=f"{field}_col", default=field, metavar="NAME",
            help=f"default: {field}" + (f"; {help_}" if help_ else ""),
        )  # fmt: skip


def check_csv_inputs(paths: list[Path]) -> None:
    """Refuse a CSV input with a line or header beyond the bounds (:mod:`mapmatch.textbounds`)
    before a command loads its heavier modules (a command's ``precheck``)."""
    from mapmatch.textbounds import check_text_input

    for path in paths:
        if path.is_file() and path.name.lower().endswith((".csv", ".csv.gz")):
            check_text_input(path)


COUNT_MAX = 1_000_000
""":func:`count_items` stops counting at this many items (more than any job run interpreted)."""

_ITEM_MARKS = {".csv": b"\n", ".gpx": b"<trkpt"}
"""What :func:`count_items` counts in a file, by suffix: a CSV's lines, a GPX file's points."""


def count_items(paths: list[Path]) -> int | None:
    """About how many fixes or points the files hold (for the kernel mode, so speed only):
    a CSV's lines after its header, a GPX file's points, at most :data:`COUNT_MAX`. ``None`` when unknown:
    standard input, a folder, a compressed or binary file (Parquet, GIS)."""
    total = 0
    for path in paths:
        mark = _ITEM_MARKS.get(path.suffix.lower())
        if str(path) == STDIO or mark is None or not path.is_file():
            return None
        with open(path, "rb") as f:
            while total < COUNT_MAX and (chunk := f.read(1 << 20)):
                total += chunk.count(mark)
        total -= mark == b"\n"  # the header
    return max(0, min(total, COUNT_MAX))


def prepared_map(args: argparse.Namespace) -> bool:
    """Whether ``--map`` names a prepared map file (``.map``), not a source to build first: a
    large map built from its source, or a route table, is work of the kernels' own, which
    :func:`count_items` does not count (so such a job compiles)."""
    return str(getattr(args, "map", "")).endswith(".map")


def fixes_items(args: argparse.Namespace) -> int | None:
    """``replay``: :func:`count_items` of the fixes file (``None`` with a map to build)."""
    return count_items([args.fixes]) if prepared_map(args) else None


def precheck_fixes(args: argparse.Namespace) -> None:
    """``replay`` and ``send``: :func:`check_csv_inputs` on the fixes file."""
    check_csv_inputs([args.fixes])


def fix_columns(args: argparse.Namespace) -> FixColumns:
    from mapmatch.io import FixColumns

    return FixColumns(**{f: getattr(args, f"{f}_col") for f in FixColumns.__dataclass_fields__})


def read_fixes_arg(args: argparse.Namespace) -> dict[str, list[Any]]:
    """The fixes per vehicle from ``args.fixes`` (a file or ``-``), the one vehicle renamed to
    ``args.vehicle_id`` when given; bad input is a CommandError."""
    from mapmatch.cli import CommandError
    from mapmatch.errors import ValidationError
    from mapmatch.io import read_fixes

    src = args.fixes
    if str(src) != STDIO and not src.exists():
        raise CommandError(f"no such file: {src}")
    name = "standard input" if str(src) == STDIO else str(src)
    try:
        vehicles = read_fixes(src, columns=fix_columns(args))
    except ValidationError as exc:
        raise CommandError(f"{name}: {exc}") from None
    vid = getattr(args, "vehicle_id", None)
    if vid is None:
        return vehicles
    if not vid.strip():
        raise CommandError("--vehicle-id must not be empty")
    if len(vehicles) > 1:
        first = ", ".join(list(vehicles)[:3])
        raise CommandError(
            f"--vehicle-id names one vehicle, but {name} holds {len(vehicles):,} ({first}, ...): "
            "drop --vehicle-id, or give one file per vehicle"
        )
    return {vid: next(iter(vehicles.values()), [])}


TIME_REJECTED = "time: must increase"
"""How a matcher's rejection of a fix whose time does not increase begins."""


@contextlib.contextmanager
def output_path(out: Path) -> Iterator[Path]:
    """The real file to write: ``out`` itself, or a temporary file copied to stdout for ``-``."""
    if str(out) != STDIO:
        yield out
        return
    from mapmatch.io import copy_to_stdout

    with tempfile.TemporaryDirectory(prefix="mapmatch-") as tmp:
        path = Path(tmp) / "out.csv"
        yield path
        copy_to_stdout(path)


def summary_stream(args: argparse.Namespace) -> TextIO:
    """Where the human summary goes: stderr when the results go to stdout."""
    return sys.stderr if str(args.output) == STDIO else sys.stdout


def rejected_failure(counts: dict[str, int], n: int, first_error: str) -> str:
    """The one-line failure summary when any fix was rejected, else ""."""
    bad = counts.get("rejected", 0)
    if n == 0:
        return "nothing matched: the file holds no fixes"
    if bad == 0:
        return ""
    return f"{bad:,} of {n:,} fix(es) rejected (first: {first_error})"
