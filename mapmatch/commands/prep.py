"""``mapmatch prep``: build a prepared map file from OSM or GIS road data."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Build a prepared map for the matchers and the service from a city's road data.

SOURCE is an OpenStreetMap extract (.osm.pbf, .osm, .osm.bz2) or GIS road centre lines
(.geojson, .gpkg, .shp with LineString/MultiLineString features). Without SOURCE, --place or
--bbox downloads the drivable network through osmnx (needs the network).

OSM input keeps the drivable roads (osmnx's "drive" filter), their one-way rules, names,
road classes, max speeds and the turn restrictions (no_*/only_* relations). GIS input gets its
topology from shared line endpoints. Both are simplified to intersections and dead ends and
projected to the local UTM zone. Progress goes to stderr, a summary to stdout.
The map file is written atomically: a failed build leaves nothing behind."""

EPILOG = """\
one-way conventions (--oneway-convention), case-insensitive:
  default   forward: true yes 1 y t ft    reverse: -1 tf reverse r    both: false no 0 n f b both (empty)
  custom    "forward=FT;reverse=TF;both=B,N" (groups left out keep their defaults)

examples:
  mapmatch prep Helsinki.osm.pbf -o helsinki.map --export helsinki.gpkg
  mapmatch prep roads.shp -o city.map --oneway-field DIR --oneway-convention "forward=FT;reverse=TF;both=B"
  mapmatch prep --place "Monaco" -o monaco.map"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "prep",
        help="build a prepared map file from OSM or GIS road data",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("source", nargs="?", type=Path, metavar="SOURCE", help="road data file (see above)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="OUT",
        help="the prepared map file to write (replaced atomically if it exists), e.g. city.map",
    )
    where = p.add_argument_group("area")
    where.add_argument("--place", metavar="NAME", help="download this place's roads via osmnx (online)")
    where.add_argument(
        "--bbox",
        metavar="W,S,E,N",
        help="lon/lat box: download it when no SOURCE is given, else keep only roads inside it",
    )
    _add_graph_options(p)
    _add_gis_options(p)
    out = p.add_argument_group("output")
    out.add_argument(
        "--export",
        type=Path,
        metavar="FILE",
        help="also write the roads (see mapmatch export) to FILE.gpkg, .geojson, .fgb or .parquet",
    )
    out.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)


def _add_graph_options(p: Any) -> None:
    graph_opts = p.add_argument_group("graph")
    graph_opts.add_argument(
        "--network-type",
        default="drive",
        choices=("drive", "drive_service"),
        help="osmnx network type for OSM input (default: drive; drive_service adds service roads)",
    )
    graph_opts.add_argument(
        "--consolidate",
        type=float,
        default=None,
        metavar="METRES",
        help="merge intersection nodes within METRES (osmnx consolidate_intersections); default off",
    )


def _add_gis_options(p: Any) -> None:
    gis = p.add_argument_group("GIS input")
    gis.add_argument(
        "--snap-tolerance",
        type=float,
        default=0.01,
        metavar="METRES",
        help="line endpoints closer than this become one node (default 0.01)",
    )
    gis.add_argument(
        "--node-crossings",
        action="store_true",
        help="also connect lines where they cross without a shared vertex (off: bridges stay apart)",
    )
    gis.add_argument(
        "--oneway-field",
        metavar="FIELD",
        help="field with one-way information (default: oneway/one_way/dir/direction if present)",
    )
    gis.add_argument(
        "--directed",
        action="store_true",
        help="every line is one way, in the direction it is drawn (a network of directed arcs, "
        "a two-way road being two lines, as in FMM's network files); no one-way field is read",
    )
    gis.add_argument(
        "--oneway-convention",
        metavar="SPEC",
        help='how that field\'s values read, e.g. "forward=FT;reverse=TF;both=B" (see below)',
    )
    gis.add_argument("--name-field", metavar="FIELD", help="road name field (default: name if present)")
    gis.add_argument(
        "--speed-field",
        metavar="FIELD",
        help="speed field in km/h or text like '30 mph' (default: maxspeed/speed if present)",
    )
    gis.add_argument(
        "--highway-field", metavar="FIELD", help="road class field (default: highway/class/fclass if present)"
    )
    gis.add_argument(
        "--id-field",
        metavar="FIELD",
        help="integer feature id field (default: id/osm_id/fid, else row number)",
    )
    gis.add_argument(
        "--node-id-fields",
        metavar="U,V",
        help="integer fields with the ids of each line's first and last node "
        "(default: u,v when present and consistent, as in osmnx exports; else ids are generated)",
    )
    gis.add_argument(
        "--topology",
        choices=("auto", "endpoints", "ids"),
        default="auto",
        help="how line ends become nodes: 'ids' from the node id fields (distinct nodes at one "
        "position stay apart, e.g. at bridges), 'endpoints' from shared positions; 'auto' "
        "(default) uses ids when the fields exist and each id sits at one place",
    )
    gis.add_argument(
        "--crs",
        metavar="CRS",
        help="CRS of the input when the file has none (e.g. EPSG:3067); lon/lat is assumed if it fits",
    )
    gis.add_argument("--layer", metavar="NAME", help="layer to read from a multi-layer file (GeoPackage)")


def _parse_bbox(text: str) -> tuple[float, float, float, float]:
    from mapmatch.cli import CommandError

    try:
        w, s, e, n = (float(x) for x in text.split(","))
    except ValueError:
        raise CommandError(f"--bbox must be W,S,E,N in degrees, got {text!r}") from None
    if not (-180 <= w < e <= 180 and -90 <= s < n <= 90):
        raise CommandError(f"--bbox {text!r} is not a lon/lat box with W < E and S < N")
    return (w, s, e, n)


def _parse_fields(text: str) -> tuple[str, str]:
    from mapmatch.cli import CommandError

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or not all(parts):
        raise CommandError(f"--node-id-fields must be two field names U,V, got {text!r}")
    return (parts[0], parts[1])


def run(args: argparse.Namespace) -> int:
    from graph.artifact import save_map
    from graph.build import BuildOptions, OsmOptions, build_map
    from graph.export import EXPORT_SUFFIXES
    from graph.gis import GisOptions, OnewayConvention
    from mapmatch.cli import CommandError

    if args.source is None and args.place is None and args.bbox is None:
        raise CommandError("give a SOURCE file, --place or --bbox")
    if args.source is not None and args.place is not None:
        raise CommandError("give either SOURCE or --place, not both")
    if args.export is not None and args.export.suffix.lower() not in EXPORT_SUFFIXES:
        raise CommandError(f"--export: unknown format {args.export.name} (use {', '.join(EXPORT_SUFFIXES)})")
    if str(args.output) == "-" or str(args.source) == "-":
        # a map file is memory-mapped when loaded and a source is read by format (by its name)
        raise CommandError("'-' is not accepted here: give SOURCE and -o as file paths")
    if args.output.is_dir():
        raise CommandError(f"output {args.output} is a directory")
    bbox = _parse_bbox(args.bbox) if args.bbox else None
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - t0:6.1f}s] {msg}", file=sys.stderr, flush=True)

    graph = build_map(
        args.source,
        gis=GisOptions(
            oneway_field=args.oneway_field,
            oneway_convention=OnewayConvention.parse(args.oneway_convention or ""),
            name_field=args.name_field,
            speed_field=args.speed_field,
            highway_field=args.highway_field,
            id_field=args.id_field,
            snap_tolerance=args.snap_tolerance,
            node_crossings=args.node_crossings,
            crs=args.crs,
            layer=args.layer,
            bbox=bbox,
            node_id_fields=_parse_fields(args.node_id_fields) if args.node_id_fields else None,
            topology=args.topology,
            directed=args.directed,
        ),
        osm=OsmOptions(network_type=args.network_type, place=args.place, bbox=bbox),
        options=BuildOptions(consolidate_tolerance=args.consolidate),
        progress=progress,
    )
    if args.export is not None:
        from graph.export import export_map

        progress(f"exporting nodes and edges to {args.export}")
        export_map(graph, args.export)
    progress(f"writing {args.output}")
    save_map(graph, args.output)
    print(summary(graph, args.output, args.export))
    return 0


def summary(graph: Any, output: Path, export: Path | None = None) -> str:
    """The closing summary: sizes, km of road, components, restrictions, dropped features."""
    import numpy as np

    from graph.components import weak_components

    st = graph.stats()
    rep = graph.meta.get("report", {})
    comp = weak_components(graph)
    largest = int(np.bincount(comp).max()) if len(comp) else 0
    size = output.stat().st_size if output.exists() else 0
    q = st["edge_len_p5_p25_p50_p75_p95_m"]
    lines = [
        f"map: {output} ({size / 1e6:.1f} MB, {graph.crs})",
        f"nodes: {st['nodes']:,}   edges: {st['edges']:,} ({st['oneway_edges']:,} one-way)   "
        f"road: {st['road_km']:,.1f} km",
        f"components: {rep.get('weak_components', int(comp.max()) + 1 if len(comp) else 0):,} weak "
        f"(largest {largest:,} nodes), {rep.get('strong_components', 0):,} strong",
        f"edge length: max {st['edge_len_max_m']:,.0f} m, median {q[2]:,.0f} m, p95 {q[4]:,.0f} m",
    ]
    if rep.get("restrictions_read"):
        lines.append(
            f"turn restrictions: {rep['restrictions_read']:,} read, {st['restrictions']:,} rows on edges, "
            f"{rep.get('restrictions_unmapped', 0):,} not on the graph"
        )
    fields = rep.get("fields") or {}
    if fields.get("topology"):
        used = ", ".join(
            f"{k.removesuffix('_field')} from {v!r}"
            for k, v in fields.items()
            if k.endswith("_field") and v is not None
        )
        if fields.get("directed"):
            used = ", ".join(x for x in ("every line one way as drawn", used) if x)
        lines.append(f"GIS: nodes from {fields['topology']}; {used or 'no attribute fields used'}")
    if rep.get("self_loops_split"):
        lines.append(f"loops split into two edges: {rep['self_loops_split']:,}")
    dropped = dict(rep.get("dropped", {}))
    if rep.get("self_loops_dropped"):
        dropped["zero-length loops"] = rep["self_loops_dropped"]
    if dropped:
        lines.append("dropped: " + "; ".join(f"{v:,} {k}" for k, v in dropped.items()))
    else:
        lines.append("dropped: nothing")
    if export is not None:
        lines.append(f"export: {export}")
    return "\n".join(lines)
