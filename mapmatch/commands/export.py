"""``mapmatch export``: write a prepared map's roads as GIS lines that ``prep`` reads back."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Write the roads of a prepared map (or of a source file, built on the fly) to a GIS file:
.gpkg (layers roads and nodes), .geojson, .fgb (FlatGeobuf) or .parquet (GeoParquet).

Each road is one line per way piece, a two-way road once with oneway=false, so
`mapmatch prep FILE` gives the same map back. The columns are listed in docs/formats.md
("Exported roads"). The file is written atomically."""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "export",
        help="write a prepared map's roads to GeoPackage, GeoJSON, FlatGeobuf or GeoParquet",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("map", type=Path, metavar="MAP", help="prepared map file (from mapmatch prep)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="FILE",
        help="FILE.gpkg, .geojson, .fgb or .parquet",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graph.artifact import open_map
    from graph.export import EXPORT_SUFFIXES, export_map
    from mapmatch.cli import CommandError

    if args.output.suffix.lower() not in EXPORT_SUFFIXES:
        raise CommandError(f"unknown export format {args.output.name} (use {', '.join(EXPORT_SUFFIXES)})")
    if args.output.is_dir():
        raise CommandError(f"output {args.output} is a directory")
    graph = open_map(args.map)
    if not args.quiet:
        print(f"exporting {graph.n_edges:,} edges to {args.output}", file=sys.stderr, flush=True)
    export_map(graph, args.output)
    print(f"export: {args.output} ({args.output.stat().st_size / 1e6:.1f} MB)")
    return 0
