"""``mapmatch match``: batch map matching of historic tracks against a prepared map."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapmatch.config import UBODT_MAX_BYTES

if TYPE_CHECKING:
    from mapmatch.io import Columns

DESCRIPTION = """\
Match historic tracks to the road network of a prepared map (Viterbi over each whole track).

INPUT files are CSV (columns id,time,lat,lon plus heading and speed when present; names set
with --id-col etc., or common other names found: t, timestamp, latitude, lng, trip_id, ...;
time as seconds or ISO-8601; "-" reads CSV from standard input), GPX
(one track per <trk>), Parquet or GeoParquet (lat/lon columns, or point geometry), folders
of Parquet parts, or tracks drawn as lines: GIS files (.geojson, .gpkg, .shp, .fgb; one track
per line feature, its vertices the points, times from M values or a "timestamp" field) and
CSV with a WKT "geom" column (FMM's trips.csv, ';' between fields).
OUT by suffix: .geojson (one feature per track: route, track id, length, confidence, edge
sequence with OSM way ids and names), .csv (one row per input point: matched edge, offset,
snapped lat/lon, distance, status matched/interpolated/unmatched), .parquet/.geoparquet (one
row per track, route geometry plus the per-point lists), or a folder (partitioned GeoParquet);
"-o -" writes the per-point CSV to standard output (and the summary to stderr).

The run exits 1 (done with failures) when more than --max-unmatched of all points, or every
point of some track, is unmatched (or there is no point at all), with a one-line summary that
says why when a whole track's coordinates are not degrees, off the map, or lat/lon swapped.

Tracks run in parallel on the local cores, or on a Dask cluster with --scheduler. An
interrupted run, started again with the same arguments, resumes: finished partitions
(OUT.parts/ or the OUT folder) are kept, the rest is matched."""

EPILOG = """\
examples:
  mapmatch match --map city.map fleet.csv -o routes.geojson
  mapmatch match --map city.map a.gpx b.gpx -o points.csv --workers 2
  mapmatch match --map /shared/city.map /shared/tracks/ -o /shared/out/ --scheduler tcp://10.0.0.5:8786"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "match",
        help="batch-match historic tracks (CSV, GPX, Parquet) to a prepared map",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "inputs",
        nargs="+",
        type=Path,
        metavar="INPUT",
        help="track files or Parquet folders ('-': stdin)",
    )
    p.add_argument("--map", required=True, type=Path, metavar="MAP", help="map file from `mapmatch prep`")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        type=Path,
        metavar="OUT",
        help="output file or folder ('-': stdout)",
    )
    cols = p.add_argument_group("input columns (CSV and Parquet)")
    for name in ("id", "time", "lat", "lon", "heading", "speed"):
        cols.add_argument(f"--{name}-col", default=name, metavar="NAME", help=f"default: {name}")
    cols.add_argument(
        "--max-unmatched", type=float, default=0.05, metavar="FRACTION",
        help="exit 1 when more than this fraction of the points is unmatched (default 0.05)",
    )  # fmt: skip
    run = p.add_argument_group("execution")
    run.add_argument(
        "--workers", type=int, default=None, metavar="N", help="local processes (default: all cores)"
    )
    run.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this dask.distributed scheduler")
    run.add_argument("--partition-size", type=int, default=64, metavar="N", help="tracks per partition (64)")
    run.add_argument(
        "--no-progress", action="store_true", help="no progress bar (as -q, which also drops the summary)"
    )
    run.add_argument(
        "--ubodt", type=float, default=None, metavar="METRES",
        help="precompute a route table up to this many metres (faster; more memory; built once "
        "per run and mapped by every worker)",
    )  # fmt: skip
    run.add_argument(
        "--ubodt-max-mb", type=float, default=UBODT_MAX_BYTES / 2**20, metavar="MB",
        help="memory budget of the route table (1024); a shorter bound is used where "
        "the table would not fit, with the same matches",
    )  # fmt: skip
    model = p.add_argument_group("model")
    model.add_argument(
        "--gps-sigma", type=float, default=None, metavar="M", help="position error σ in metres"
    )
    model.add_argument(
        "--search-radius", type=float, default=None, metavar="M", help="candidate radius in metres"
    )
    model.add_argument(
        "--set", action="append", default=[], metavar="SECTION.FIELD=VALUE", dest="settings",
        help="any other matcher parameter by its full name in mapmatch.config (repeatable), "
        "e.g. --set batch.route.max_route_factor=5 lets routes go further round",
    )  # fmt: skip
    p.set_defaults(func=run_match, precheck=_precheck, kernel_items=_items)


def _items(args: argparse.Namespace) -> int | None:
    """The points to match, about (the kernel mode's job size); ``None`` on a Dask cluster,
    whose workers choose their own mode, and with a route table to build (``--ubodt``)."""
    from mapmatch.commands._fixio import count_items, prepared_map

    if args.scheduler or args.ubodt is not None or not prepared_map(args):
        return None
    return count_items(list(args.inputs))


def _precheck(args: argparse.Namespace) -> None:
    from mapmatch.commands._fixio import check_csv_inputs

    check_csv_inputs(list(args.inputs))


def run_match(args: argparse.Namespace) -> int:
    import tempfile

    from mapmatch.cli import CommandError

    if not 0.0 <= args.max_unmatched <= 1.0:
        raise CommandError("--max-unmatched must be a fraction between 0 and 1")
    stdin = [i for i in args.inputs if str(i) == "-"]
    if len(stdin) > 1:
        raise CommandError("standard input ('-') can be read only once")
    to_stdout = str(args.output) == "-"
    if not stdin and not to_stdout:
        return _match(args, args.inputs, args.output, out=sys.stdout)
    with tempfile.TemporaryDirectory(prefix="mapmatch-match-") as tmp:
        inputs = list(args.inputs)
        if stdin:
            from mapmatch.io import spool_stdin

            src = Path(tmp) / "stdin.csv"
            spool_stdin(src)
            inputs = [src if str(i) == "-" else i for i in inputs]
        output = Path(tmp) / "stdout.csv" if to_stdout else args.output
        rc = _match(args, inputs, output, out=sys.stderr if to_stdout else sys.stdout)
        if to_stdout:
            from mapmatch.io import copy_to_stdout

            copy_to_stdout(output)
        return rc


def _check_args(args: argparse.Namespace, inputs: list[Path]) -> None:
    """Refuse bad options and missing files before anything runs."""
    from mapmatch.cli import CommandError

    for inp in inputs:  # (CSV inputs were checked against the text bounds first: _precheck)
        if not inp.exists():
            raise CommandError(f"no such input: {inp}")
    if args.workers is not None and args.workers < 1:
        raise CommandError("--workers must be at least 1")
    if args.partition_size < 1:
        raise CommandError("--partition-size must be at least 1")
    if args.ubodt is not None and not args.ubodt > 0:
        raise CommandError("--ubodt must be a positive number of metres")
    if not (math.isfinite(args.ubodt_max_mb) and args.ubodt_max_mb > 0):
        raise CommandError("--ubodt-max-mb must be a positive number of megabytes")
    if args.scheduler:
        from mapmatch.extras import require

        require("distributed", extra="dask", needed_for="--scheduler (matching on a Dask cluster)")
    if not args.map.is_file():
        raise CommandError(f"no such map file: {args.map}")


def _config(args: argparse.Namespace) -> Any:
    """The batch config with the command's shortcuts and ``--set`` settings."""
    from mapmatch.batch import BATCH_CONFIG
    from mapmatch.cli import CommandError
    from mapmatch.errors import ConfigError

    over = {
        k: v
        for k, v in (
            ("gps_sigma", args.gps_sigma),
            ("search_radius", args.search_radius),
        )
        if v is not None
    }
    try:
        return BATCH_CONFIG.replace(**over).with_settings(args.settings)
    except ConfigError as exc:
        raise CommandError(str(exc)) from None


def _match(args: argparse.Namespace, inputs: list[Path], output: Path, *, out: Any) -> int:
    from tqdm import tqdm

    from mapmatch.cli import EXIT_OK, EXIT_PARTIAL
    from mapmatch.io import Columns
    from mapmatch.parallel import RunOptions, run_batch

    _check_args(args, inputs)
    if not getattr(args, "quiet", False) and args.scheduler is None:
        from mapmatch.kernels import announce

        announce("batch")
    config = _config(args)
    columns = Columns(
        id=args.id_col, time=args.time_col, lat=args.lat_col, lon=args.lon_col, heading=args.heading_col,
        speed=args.speed_col,
    )  # fmt: skip
    quiet = getattr(args, "quiet", False)
    bar: Any = None

    def on_total(n: int) -> None:
        nonlocal bar
        if not (args.no_progress or quiet):
            bar = tqdm(total=n, unit="pt", unit_scale=True, desc="matching", file=sys.stderr)

    def progress(points: int, tracks: int) -> None:
        if bar is not None:
            bar.update(points)

    try:
        options = RunOptions(
            workers=args.workers, scheduler=args.scheduler, partition_size=args.partition_size,
            ubodt_delta=args.ubodt, ubodt_max_bytes=int(args.ubodt_max_mb * 2**20),
        )  # fmt: skip
        s = run_batch(
            [str(i) for i in inputs], args.map, output, config=config, columns=columns, options=options,
            progress=progress, on_total=on_total,
        )  # fmt: skip
    finally:
        if bar is not None:
            bar.close()
    counts = [(t.track_id, t.points, t.unmatched) for t in s.track_summaries]
    resumed = f", {s.skipped} partition(s) resumed" if s.skipped else ""
    dest = "standard output" if str(args.output) == "-" else s.output
    if not quiet:
        print(
            f"matched {s.tracks} track(s), {s.points} point(s) in {s.seconds:.1f} s{resumed} -> {dest}",
            file=out,
        )
    failed = _failure(counts, args.max_unmatched)
    if failed:
        lost = next((t for t, n, u in counts if n > 0 and u == n), None)
        hint = _why_unmatched(inputs, columns, args.map, lost) if lost is not None else ""
        print(f"mapmatch match: error: {failed}{f'; track {lost}: {hint}' if hint else ''}", file=sys.stderr)
        return EXIT_PARTIAL
    return EXIT_OK


HINT_MAX_BYTES = 256 << 20
"""Input files up to this size are read again for :func:`_why_unmatched` (a hint is not worth
reading a fleet's history twice)."""


def _why_unmatched(inputs: list[Path], columns: Columns, map_path: str, track_id: str) -> str:
    """Why every point of track ``track_id`` is unmatched, when its coordinates tell: not degrees
    (projected coordinates, wrong columns), off the map, or on it with lat and lon swapped; ""
    when they do not (the points are on the map but far from its roads) or the track is not in
    a file of at most :data:`HINT_MAX_BYTES` that can be read."""
    from graph.artifact import read_manifest
    from mapmatch.commands._hints import coordinate_hint
    from mapmatch.io import read_tracks

    try:
        bbox = tuple(float(v) for v in read_manifest(map_path)["bbox"])
        track = None
        for inp in inputs:
            if str(inp) == "-" or not inp.is_file() or inp.stat().st_size > HINT_MAX_BYTES:
                continue
            track = next((t for t in read_tracks(inp, columns=columns) if str(t.track_id) == track_id), None)
            if track is not None:
                break
    except Exception:  # a hint only: the run's own error is already reported
        return ""
    if track is None or not len(track.lat) or len(bbox) != 4:
        return ""
    return coordinate_hint(track.lat, track.lon, bbox)  # type: ignore[arg-type]


def _failure(counts: list[tuple[str, int, int]], max_unmatched: float) -> str:
    """The one-line failure summary of a run, or "" when it counts as all done."""
    points = sum(n for _, n, _ in counts)
    if points == 0:
        return "nothing matched: the inputs hold no track points"
    bad = sum(u for _, _, u in counts)
    lost = [t for t, n, u in counts if n > 0 and u == n]
    if bad / points > max_unmatched or lost:
        first = f" (first: {lost[0]})" if lost else ""
        return (
            f"{bad:,} of {points:,} point(s) unmatched ({100 * bad / points:.1f} %, threshold "
            f"{100 * max_unmatched:g} %); {len(lost)} of {len(counts)} track(s) entirely unmatched{first}"
        )
    return ""
