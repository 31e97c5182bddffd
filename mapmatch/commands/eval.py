"""``mapmatch eval``: score matched results against the simulator's truth; table and pictures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapmatch.cli import CommandError
from mapmatch.extras import EVAL_MODULES

if TYPE_CHECKING:
    import pandas as pd


DESCRIPTION = """\
Score matched results against the truth.

With --truth (from mapmatch simulate): intersection traversal accuracy, per-fix correct-edge
rate, route mismatch fraction and snapped position error of a results CSV (mapmatch replay or
send), with optional PNG and HTML maps.

With --route (a true route as GeoJSON (Multi)LineString, e.g. Kubicka's truth.geojson): the
route mismatch fraction of a matched route, from batch output (mapmatch match: .geojson,
.parquet, or its per-point .csv with --map) or online output (replay/send CSV, with --map)."""

EPILOG = """\
examples:
  mapmatch eval --map city.map --truth truth.csv --matched out.csv --png m.png --html m.html
  mapmatch match --map k.map track.csv -o routes.geojson
  mapmatch eval --route truth.geojson --matched routes.geojson
  mapmatch eval --route truth.geojson --matched replayed.csv --map k.map"""


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "eval",
        help="score matched results against the truth or a true route (table, PNG and HTML maps)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--map", help="the map the results refer to (needed with --truth, and for CSV results)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--truth", help="truth CSV or GeoJSON from mapmatch simulate")
    what.add_argument("--route", help="true route, GeoJSON (Multi)LineString in lon/lat (e.g. truth.geojson)")
    p.add_argument(
        "--matched", required=True, help="results: replay/send CSV, or match output (with --route)"
    )
    p.add_argument(
        "--fixes",
        help="the fixes (to draw them and report their error): the fused fixes CSV, or with --route "
        "any track file `match` reads",
    )
    p.add_argument("--vehicle-id", "--track-id", dest="vehicle_id",
                   help="the vehicle or track to score when the files hold several")  # fmt: skip
    p.add_argument("--tolerance", type=float, default=2.0, help="route mismatch tolerance, m (default 2)")
    p.add_argument("--all-nodes", action="store_true", help="count every node, not only junctions")
    p.add_argument(
        "--closed",
        nargs=2,
        metavar=("FIXES", "MATCHED"),
        help="compare open loop (--fixes, --matched) with a closed-loop run of the same drive: its fixes "
        "and results CSVs (mapmatch simulate --map-aided --matched)",
    )
    p.add_argument("--png", help="write a PNG map (with --route: true route, matched route and fixes)")
    p.add_argument("--html", help="write an interactive HTML map (self-contained: works offline)")
    p.set_defaults(func=run)


def run_route(args: argparse.Namespace) -> int:
    """``--route``: the route mismatch fraction of a matched route against a true route."""
    from mapmatch.evaluate import route_lonlat_from_results
    from mapmatch.route_score import read_route_geojson, score_route

    for name in ("route", "matched"):
        if not Path(getattr(args, name)).is_file():
            raise CommandError(f"--{name}: no such file: {getattr(args, name)}")
    _, truth, props = read_route_geojson(args.route)
    crs = f"EPSG:{props['utm_epsg']}" if isinstance(props.get("utm_epsg"), int) else None
    matched_path = Path(args.matched)
    name = matched_path.name.lower()
    points = unmatched = 0
    if name.endswith((".geojson", ".json")):
        track, parts, mprops = read_route_geojson(matched_path, track_id=args.vehicle_id)
        points, unmatched = int(mprops.get("n_points", 0)), int(mprops.get("n_unmatched", 0))
    elif name.endswith((".parquet", ".geoparquet")):
        track, parts, points, unmatched = _parquet_route(matched_path, args.vehicle_id)
    elif name.endswith(".csv"):
        if not args.map:
            raise CommandError("--map is needed to rebuild the route of CSV results")
        track, parts, points, unmatched = _csv_route(args, matched_path, route_lonlat_from_results)
    else:
        raise CommandError(f"--matched {matched_path}: unknown format (use .geojson, .parquet or .csv)")
    score = score_route(
        truth, parts, tolerance_m=args.tolerance, crs=crs, track_id=track, points=points,
        unmatched_points=unmatched,
    )  # fmt: skip
    print(score.table())
    if args.png or args.html:
        title = f"track {track}: route mismatch {100 * score.rmf.fraction:.2f} % (tol {args.tolerance:g} m)"
        _draw_route(args, truth, parts, track=track, title=title)
    return 0


def _draw_route(
    args: argparse.Namespace, truth: list[Any], matched: list[Any], *, track: str, title: str
) -> None:
    """``--route`` with ``--png``/``--html``: draw the true route, the matched route and the fixes."""
    import sys

    from mapmatch.plots import RoutePicture, draw_route_html, draw_route_png

    fixes = _route_fixes(args, track)
    if not len(fixes):
        print("eval: no fixes to draw (give --fixes, the track file that was matched)", file=sys.stderr)
    pic = RoutePicture(
        truth=truth, matched=matched, fixes=fixes, roads=_roads_near(args.map, truth + matched)
    )
    for path, draw in ((args.png, draw_route_png), (args.html, draw_route_html)):
        if not path:
            continue
        try:
            draw(pic, path, title=title)
        except ValueError as exc:
            raise CommandError(f"cannot draw {path}: {exc}") from None
        if not Path(path).is_file() or Path(path).stat().st_size == 0:
            raise CommandError(f"cannot draw {path}: nothing was written")
        print(f"wrote {path}")


def _route_fixes(args: argparse.Namespace, track: str) -> Any:
    """The fixes of ``track`` as ``(n, 2)`` lon/lat: from ``--fixes`` (any track file), else
    the raw positions of online results (``raw_lat``/``raw_lon``); empty when neither has them."""
    import numpy as np
    import pandas as pd

    from mapmatch.io import read_fixes

    if args.fixes:
        if not Path(args.fixes).exists():
            raise CommandError(f"--fixes: no such file: {args.fixes}")
        vehicles = read_fixes(args.fixes)
        name = args.vehicle_id if args.vehicle_id is not None else track
        fixes = vehicles.get(name) if len(vehicles) > 1 else next(iter(vehicles.values()), [])
        if fixes is None:
            raise CommandError(
                f"--fixes {args.fixes}: no vehicle or track {name!r} ({len(vehicles)} in the file)"
            )
        return np.array([[f.lon, f.lat] for f in fixes], dtype=np.float64).reshape(-1, 2)
    if str(args.matched).lower().endswith(".csv"):
        head = pd.read_csv(args.matched, nrows=0).columns
        if "raw_lat" in head and "raw_lon" in head:
            df = pd.read_csv(
                args.matched, usecols=[c for c in ("vehicle_id", "raw_lat", "raw_lon") if c in head]
            )
            if "vehicle_id" in df.columns and track:
                df = df[df["vehicle_id"].astype(str) == track]
            return df[["raw_lon", "raw_lat"]].to_numpy(dtype=np.float64)
    return np.empty((0, 2))


def _roads_near(map_path: str | None, parts: list[Any], margin_m: float = 300.0) -> list[Any]:
    """The roads of ``--map`` (lon/lat parts) near the routes; none without a map."""
    import numpy as np

    from graph.artifact import open_map
    from graph.projection import to_lonlat, to_xy

    if not map_path:
        return []
    graph = open_map(map_path)
    pts = np.vstack([p for p in parts if len(p)]) if any(len(p) for p in parts) else np.empty((0, 2))
    if not len(pts):
        return []
    xy = to_xy(graph.crs, pts[:, 0], pts[:, 1])
    lo, hi = np.nanmin(xy, axis=0) - margin_m, np.nanmax(xy, axis=0) + margin_m
    out = []
    for e in range(graph.n_edges):
        if graph.edge_reverse[e] >= 0 and graph.edge_reverse[e] < e:
            continue
        seg = graph.edge_xy(e)
        if (seg.max(0) >= lo).all() and (seg.min(0) <= hi).all():
            out.append(to_lonlat(graph.crs, seg[:, 0], seg[:, 1]))
    return out


def _parquet_route(path: Path, track_id: str | None) -> tuple[str, list[Any], int, int]:
    import shapely

    from mapmatch.io import read_results

    try:
        table = read_results(path)
    except Exception as exc:  # pyarrow raises several types for a bad file
        raise CommandError(f"--matched {path}: not a mapmatch match GeoParquet file ({exc})") from None
    if track_id is not None:
        table = table[table["track_id"].astype(str) == track_id]
    if len(table) != 1:
        raise CommandError(f"--matched {path}: {len(table)} track(s) match; name one with --track-id")
    row = table.iloc[0]
    geom = shapely.from_wkb(row["route_wkb"])
    lines = list(getattr(geom, "geoms", [geom])) if not geom.is_empty else []
    parts = [shapely.get_coordinates(g) for g in lines]
    return str(row["track_id"]), parts, int(row["n_points"]), int(row["n_unmatched"])


def _csv_route(args: argparse.Namespace, path: Path, rebuild: Any) -> tuple[str, list[Any], int, int]:
    import numpy as np
    import pandas as pd

    from graph.artifact import open_map
    from graph.projection import to_lonlat
    from mapmatch.evaluate import edge_path, read_matched_csv
    from mapmatch.route_score import path_geometry

    graph = open_map(args.map)
    head = pd.read_csv(path, nrows=0).columns
    if "track_id" in head and "status" in head:  # per-point CSV of mapmatch match
        df = pd.read_csv(path, dtype={"track_id": str})
        ids = df["track_id"].unique().tolist()
        tid = args.vehicle_id if args.vehicle_id is not None else (ids[0] if len(ids) == 1 else None)
        if tid is None:
            raise CommandError(f"--matched {path} holds {len(ids)} tracks; name one with --track-id")
        df = df[df["track_id"] == tid]
        from mapmatch.route_score import split_parts

        xy = path_geometry(graph, edge_path(graph, df["edge"].to_numpy(dtype=np.int64)))
        parts = [to_lonlat(graph.crs, p[:, 0], p[:, 1]) for p in split_parts(xy) if len(p) >= 2]
        return str(tid), parts, len(df), int((df["status"] == "unmatched").sum())
    df = read_matched_csv(path, vehicle_id=args.vehicle_id)
    vid = str(df["vehicle_id"].iloc[0]) if "vehicle_id" in df.columns and len(df) else ""
    placed = df["edge"].fillna(-1).to_numpy() >= 0 if "edge" in df.columns else np.zeros(len(df), bool)
    return vid, rebuild(graph, df), len(df), int((~placed).sum())


def run(args: argparse.Namespace) -> int:
    from mapmatch.extras import require_installed

    require_installed(*EVAL_MODULES, extra="eval", needed_for="mapmatch eval")
    from graph.artifact import open_map
    from mapmatch.evaluate import Scoring, evaluate, read_matched_csv
    from mapmatch.sim.demo import title_for
    from mapmatch.sim.drive import truth_paths

    if args.tolerance < 0:
        raise CommandError("--tolerance must be >= 0")
    if args.route:
        return run_route(args)
    if not args.map:
        raise CommandError("--map is needed with --truth")
    csv_path, gj_path = truth_paths(args.truth)
    if not csv_path.exists():
        raise CommandError(f"no per-fix truth {csv_path} (mapmatch simulate --truth writes it)")
    graph = open_map(args.map)
    truth = _read_csv(csv_path)
    matched = read_matched_csv(args.matched, vehicle_id=args.vehicle_id)
    fixes = _read_csv(Path(args.fixes)) if args.fixes else None
    if args.vehicle_id is not None:
        truth = truth[truth["vehicle_id"].astype(str) == args.vehicle_id].reset_index(drop=True)
        if fixes is not None and "vehicle_id" in fixes.columns:
            fixes = fixes[fixes["vehicle_id"].astype(str) == args.vehicle_id].reset_index(drop=True)
    if len(truth) == 0 or len(matched) == 0:
        raise CommandError("nothing to score: the truth or the results are empty for this vehicle")
    truth_path, truth_xy = _true_route(graph, gj_path)
    metrics = evaluate(
        graph,
        truth=truth,
        matched=matched,
        truth_path=truth_path,
        truth_xy=truth_xy,
        fixes=fixes,
        scoring=Scoring(tolerance_m=args.tolerance, junctions_only=not args.all_nodes),
    )
    print(metrics.table())
    if args.closed:
        from mapmatch.sim.loop_eval import compare_runs

        if fixes is None:
            raise CommandError("--closed needs --fixes (the open loop's fused fixes)")
        table = compare_runs(
            graph,
            truth=truth,
            open_fixes=fixes,
            open_matched=matched,
            closed_fixes=_read_csv(Path(args.closed[0])),
            closed_matched=read_matched_csv(args.closed[1], vehicle_id=args.vehicle_id),
            truth_path=truth_path,
        )
        print("\nopen vs closed loop (outage figures over the drive's outages, metres; heading degrees)")
        print(table.round(3).to_string(index=False))
    if args.png or args.html:
        _draw(args, graph, truth_xy, (truth, matched, fixes), title_for(metrics))
    return 0


def _true_route(graph: Any, gj_path: Path) -> tuple[Any, Any]:
    """The true edge path and polyline from the truth GeoJSON (None, None: not for this map)."""
    from graph.projection import to_xy

    if not gj_path.exists():
        return None, None
    props = json.loads(Path(gj_path).read_text())
    edges = props.get("properties", {}).get("edges")
    if not edges or max(edges) >= graph.n_edges:
        return None, None
    ll = props["geometry"]["coordinates"]
    return edges, to_xy(graph.crs, [c[0] for c in ll], [c[1] for c in ll])


def _draw(
    args: argparse.Namespace, graph: Any, truth_xy: Any, frames: tuple[Any, Any, Any], title: str
) -> None:
    """``--png`` and ``--html`` of a scored drive: the true route, the match and the fixes."""
    from mapmatch.evaluate import edge_path
    from mapmatch.plots import draw_html, draw_png, plot_data
    from mapmatch.route_score import path_geometry

    truth, matched, fixes = frames
    route_xy = (
        truth_xy
        if truth_xy is not None
        else path_geometry(graph, edge_path(graph, truth["edge"].to_numpy(), times=truth["time"].to_numpy()))
    )
    data = plot_data(
        graph,
        route_xy=route_xy,
        fixes=fixes if fixes is not None else _fixes_from_results(matched, truth),
        matched=matched,
        truth=truth,
    )
    if args.png:
        draw_png(graph, data, args.png, title=title)
        print(f"wrote {args.png}")
    if args.html:
        draw_html(graph, data, args.html, title=title)
        print(f"wrote {args.html}")


def _read_csv(path: Path) -> pd.DataFrame:
    import pandas as pd

    try:
        return pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise CommandError(f"{path} is not a readable CSV ({exc})") from None


def _fixes_from_results(matched: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """The matcher's input as far as the results tell it: raw positions, GPS flag from the truth."""
    import pandas as pd

    lat = matched["raw_lat"] if "raw_lat" in matched.columns else matched["lat"]
    lon = matched["raw_lon"] if "raw_lon" in matched.columns else matched["lon"]
    df = pd.DataFrame({"time": matched["time"], "lat": lat, "lon": lon})
    if "gps_outage" in truth.columns:
        from mapmatch.evaluate import align_by_time

        i = align_by_time(truth["time"].to_numpy(float), df["time"].to_numpy(float))
        out = truth["gps_outage"].to_numpy(int)[i.clip(0)]
        df["gps_valid"] = ((i < 0) | (out == 0)).astype(int)
    return df
