"""``mapmatch eval``: score matched results against the simulator's truth; table and pictures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from mapmatch.cli import CommandError

if TYPE_CHECKING:
    import pandas as pd


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "eval",
        help="score matched results against the truth (table, PNG and HTML maps)",
        description=(
            "Intersection traversal accuracy, per-fix correct-edge rate, route mismatch fraction and "
            "snapped position error of a results CSV (mapmatch replay) against a truth written by "
            "mapmatch simulate."
        ),
    )
    p.add_argument("--map", required=True, help="the map the results and the truth refer to")
    p.add_argument("--truth", required=True, help="truth CSV or GeoJSON from mapmatch simulate")
    p.add_argument("--matched", required=True, help="results CSV from mapmatch replay")
    p.add_argument("--fixes", help="the fused fixes CSV (to draw them and report their error)")
    p.add_argument("--vehicle-id", help="the vehicle to score when the files hold several")
    p.add_argument("--tolerance", type=float, default=2.0, help="route mismatch tolerance, m (default 2)")
    p.add_argument("--all-nodes", action="store_true", help="count every node, not only junctions")
    p.add_argument("--png", help="write a PNG map")
    p.add_argument("--html", help="write an interactive HTML map")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graph.artifact import open_map
    from graph.projection import to_xy
    from mapmatch.evaluate import evaluate, read_matched_csv
    from mapmatch.plots import draw_html, draw_png, plot_data
    from mapmatch.sim.demo import title_for
    from mapmatch.sim.drive import truth_paths

    if args.tolerance < 0:
        raise CommandError("--tolerance must be >= 0")
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
    truth_path = truth_xy = None
    if gj_path.exists():
        props = json.loads(Path(gj_path).read_text())
        edges = props.get("properties", {}).get("edges")
        if edges and max(edges) < graph.n_edges:
            truth_path = edges
            ll = props["geometry"]["coordinates"]
            lon = [c[0] for c in ll]
            lat = [c[1] for c in ll]
            truth_xy = to_xy(graph.crs, lon, lat)
    metrics = evaluate(
        graph,
        truth=truth,
        matched=matched,
        truth_path=truth_path,
        truth_xy=truth_xy,
        fixes=fixes,
        tolerance_m=args.tolerance,
        junctions_only=not args.all_nodes,
    )
    print(metrics.table())
    if args.png or args.html:
        from mapmatch.evaluate import edge_path, path_geometry

        route_xy = (
            truth_xy
            if truth_xy is not None
            else path_geometry(
                graph, edge_path(graph, truth["edge"].to_numpy(), times=truth["time"].to_numpy())
            )
        )
        data = plot_data(
            graph,
            route_xy=route_xy,
            fixes=fixes if fixes is not None else _fixes_from_results(matched, truth),
            matched=matched,
            truth=truth,
        )
        title = title_for(metrics)
        if args.png:
            draw_png(graph, data, args.png, title=title)
            print(f"wrote {args.png}")
        if args.html:
            draw_html(graph, data, args.html, title=title)
            print(f"wrote {args.html}")
    return 0


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
