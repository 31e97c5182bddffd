"""``mapmatch match``: batch map matching of historic tracks against a prepared map."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Match historic tracks to the road network of a prepared map (Viterbi over each whole track).

INPUT files are CSV (columns id,time,lat,lon plus heading and speed when present; names set
with --id-col etc.; time as seconds or ISO-8601), GPX (one track per <trk>), Parquet or
GeoParquet (lat/lon columns, or point geometry), or folders of Parquet parts.
OUT by suffix: .geojson (one feature per track: route, track id, length, confidence, edge
sequence with OSM way ids and names), .csv (one row per input point: matched edge, offset,
snapped lat/lon, distance, status matched/interpolated/unmatched), .parquet/.geoparquet (one
row per track, route geometry plus the per-point lists), or a folder (partitioned GeoParquet).

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
    p.add_argument("inputs", nargs="+", type=Path, metavar="INPUT", help="track files or Parquet folders")
    p.add_argument("--map", required=True, type=Path, metavar="MAP", help="map file from `mapmatch prep`")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUT", help="output file or folder")
    cols = p.add_argument_group("input columns (CSV and Parquet)")
    for name in ("id", "time", "lat", "lon", "heading", "speed"):
        cols.add_argument(f"--{name}-col", default=name, metavar="NAME", help=f"default: {name}")
    run = p.add_argument_group("execution")
    run.add_argument(
        "--workers", type=int, default=None, metavar="N", help="local processes (default: all cores)"
    )
    run.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this dask.distributed scheduler")
    run.add_argument("--partition-size", type=int, default=64, metavar="N", help="tracks per partition (64)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument(
        "--ubodt", type=float, default=None, metavar="METRES",
        help="precompute a route table up to this many metres per worker (faster; more memory)",
    )  # fmt: skip
    model = p.add_argument_group("model")
    model.add_argument(
        "--gps-sigma", type=float, default=None, metavar="M", help="position error σ in metres"
    )
    model.add_argument(
        "--search-radius", type=float, default=None, metavar="M", help="candidate radius in metres"
    )
    model.add_argument("--interpolate-distance", type=float, default=None, metavar="M",
                       help="points closer than this to the previous one are interpolated")  # fmt: skip
    p.set_defaults(func=run_match)


def run_match(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mapmatch.batch import BATCH_CONFIG
    from mapmatch.cli import CommandError
    from mapmatch.io import Columns
    from mapmatch.parallel import run_batch

    for inp in args.inputs:
        if not inp.exists():
            raise CommandError(f"no such input: {inp}")
    if args.workers is not None and args.workers < 1:
        raise CommandError("--workers must be at least 1")
    if args.partition_size < 1:
        raise CommandError("--partition-size must be at least 1")
    if args.ubodt is not None and not args.ubodt > 0:
        raise CommandError("--ubodt must be a positive number of metres")
    over = {
        k: v
        for k, v in (
            ("gps_sigma", args.gps_sigma),
            ("search_radius", args.search_radius),
            ("interpolate_distance", args.interpolate_distance),
        )
        if v is not None
    }
    config = BATCH_CONFIG.replace(**over)
    columns = Columns(
        id=args.id_col, time=args.time_col, lat=args.lat_col, lon=args.lon_col, heading=args.heading_col,
        speed=args.speed_col,
    )  # fmt: skip
    bar: Any = None

    def on_total(n: int) -> None:
        nonlocal bar
        if not args.no_progress:
            bar = tqdm(total=n, unit="pt", unit_scale=True, desc="matching", file=sys.stderr)

    def progress(points: int, tracks: int) -> None:
        if bar is not None:
            bar.update(points)

    try:
        s = run_batch(
            [str(i) for i in args.inputs], args.map, args.output, config=config, columns=columns,
            workers=args.workers, scheduler=args.scheduler, partition_size=args.partition_size,
            ubodt_delta=args.ubodt,
            progress=progress, on_total=on_total,
        )  # fmt: skip
    finally:
        if bar is not None:
            bar.close()
    resumed = f", {s.skipped} partition(s) resumed" if s.skipped else ""
    print(f"matched {s.tracks} track(s), {s.points} point(s) in {s.seconds:.1f} s{resumed} -> {s.output}")
    return 0
