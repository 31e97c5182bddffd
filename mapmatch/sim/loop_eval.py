"""Open loop against closed loop on the same drive: fused error, outages, heading, matching.

For one drive (same route, same raw sensors) the open loop is the drive's own fused fixes
matched as they are; the closed loop re-fuses the sensors with the matcher's answers fed back
(:mod:`mapmatch.sim.closed_loop`). Both are scored the same way (:func:`loop_metrics`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from graph.angles import angle_diffs
from graph.projection import to_xy
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.evaluate import evaluate, results_frame
from mapmatch.sim.closed_loop import ClosedLoop, MatchFn, closed_loop_drive, in_process
from mapmatch.sim.drive import Drive
from mapmatch.sim.kalman import DEFAULT_KALMAN, KalmanConfig
from mapmatch.sim.sensors import SensorData
from mapmatch.types import SnapResult


@dataclass(frozen=True)
class LoopMetrics:
    """How one run (open or closed loop) did.

    ``error_gps_mean`` / ``error_gps_p90`` fused position error (m) at fixes outside the GPS
    outages; ``outage_end`` (m) the error at the last fix of each outage, ``outage_max`` (m) the
    largest during it; ``heading_mean`` mean absolute heading error (deg), ``heading_outage``
    the same within outages; ``intersections`` and ``correct_edge`` the matcher's intersection
    traversal accuracy and correct-edge rate (after its corrections); ``fed`` share of fixes
    whose measurement was fed back, ``gated`` share of those the filter's χ² gate rejected.
    """

    error_gps_mean: float
    error_gps_p90: float
    outage_end: list[float] = field(default_factory=list)
    outage_max: list[float] = field(default_factory=list)
    heading_mean: float = float("nan")
    heading_outage: float = float("nan")
    intersections: float = float("nan")
    correct_edge: float = float("nan")
    fed: float = 0.0
    gated: float = 0.0


def outage_runs(outage: np.ndarray) -> list[np.ndarray]:
    """The fix indices of each GPS outage (each run of ``outage`` true), in order."""
    idx = np.flatnonzero(outage)
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    return np.split(idx, breaks)


def frame_metrics(
    graph: RoadGraph,
    *,
    truth: pd.DataFrame,
    x: np.ndarray,
    y: np.ndarray,
    heading: np.ndarray,
    matched: pd.DataFrame,
    truth_path: Sequence[int] | None = None,
    outages: list[np.ndarray] | None = None,
) -> LoopMetrics:
    """Score one run from its fused positions ``x``/``y`` (map metres) and ``heading`` (deg) per
    truth row, and the matcher's results (``matched``, a results frame) against ``truth``
    (columns ``x``, ``y``, ``heading``, ``gps_outage``, ``edge``, ``time``). ``outages`` the
    row indices of each outage scored (default: each run of ``gps_outage``)."""
    err = np.hypot(x - truth["x"].to_numpy(), y - truth["y"].to_numpy())
    outage = truth["gps_outage"].to_numpy() > 0
    dh = np.abs(angle_diffs(heading, truth["heading"].to_numpy()))
    runs = outage_runs(outage) if outages is None else outages
    m = evaluate(graph, truth=truth, matched=matched, truth_path=truth_path)
    fin = m.corrected or m
    gps = ~outage
    return LoopMetrics(
        error_gps_mean=float(err[gps].mean()) if gps.any() else float("nan"),
        error_gps_p90=float(np.percentile(err[gps], 90)) if gps.any() else float("nan"),
        outage_end=[float(err[r[-1]]) for r in runs],
        outage_max=[float(err[r].max()) for r in runs],
        heading_mean=float(dh.mean()),
        heading_outage=float(dh[outage].mean()) if outage.any() else float("nan"),
        intersections=fin.intersections.accuracy,
        correct_edge=fin.correct_edge_rate,
    )


def loop_metrics(
    graph: RoadGraph, drive: Drive, results: Sequence[SnapResult | None], *, closed: ClosedLoop | None = None
) -> LoopMetrics:
    """Score one run of ``drive`` (its fused fixes) and the matcher's ``results`` for them."""
    vid = str(drive.fixes["vehicle_id"].iloc[0]) if len(drive.fixes) else ""
    frame = results_frame(vid, drive.fix_objects(), list(results))
    t = drive.fused.time
    # the outages put in (a real track's own gaps also lack GPS, but are not scored as outages)
    runs = [np.flatnonzero((t >= a) & (t < a + d)) for a, d in drive.outages]
    m = frame_metrics(
        graph,
        truth=drive.truth,
        x=drive.fused.x,
        y=drive.fused.y,
        heading=drive.fused.heading,
        matched=frame,
        truth_path=drive.route.edges.tolist(),
        outages=[r for r in runs if len(r)],
    )
    if closed is None or not len(closed.fed):
        return m
    fed = float(closed.fed.mean())
    gated = float(closed.rejected.sum() / max(closed.fed.sum(), 1))
    return dataclasses.replace(m, fed=fed, gated=gated)


def compare_runs(
    graph: RoadGraph,
    *,
    truth: pd.DataFrame,
    open_fixes: pd.DataFrame,
    open_matched: pd.DataFrame,
    closed_fixes: pd.DataFrame,
    closed_matched: pd.DataFrame,
    truth_path: Sequence[int] | None = None,
) -> pd.DataFrame:
    """Open against closed loop from files (``mapmatch eval --closed``): the fused fixes and
    results of each run, one truth (the same drive). One row per loop."""
    rows = []
    for loop, fixes, matched in (
        ("open", open_fixes, open_matched),
        ("closed", closed_fixes, closed_matched),
    ):
        if len(fixes) != len(truth):
            raise ValidationError(
                "fixes", f"the {loop}-loop fixes have {len(fixes)} rows, the truth {len(truth)}"
            )
        xy = to_xy(graph.crs, fixes["lon"].to_numpy(float), fixes["lat"].to_numpy(float))
        m = frame_metrics(
            graph,
            truth=truth,
            x=xy[:, 0],
            y=xy[:, 1],
            heading=fixes["heading"].to_numpy(float),
            matched=matched,
            truth_path=truth_path,
        )
        rows.append({"group": "drive", "loop": loop, **dataclasses.asdict(m)})
    return summary_table(rows).drop(columns=["group", "drives", "fed", "gated"])


def real_sensors(drive: Drive) -> SensorData:
    """The sensors a Kalman filter needs for a real-GPS drive (:mod:`mapmatch.sim.realgps`).

    Its GPS is the real receiver's fixes and its gyro and odometer the modelled
    dead-reckoning sensors; it has no compass and no GPS course. The fused heading it models
    where GPS is valid (the true heading lagged, with bias and noise) stands in as the heading
    aid: it is given as compass readings at the fused fixes with GPS (none in outages, where the
    gyro alone carries the heading). Open and closed loop both run
    :mod:`mapmatch.sim.kalman` on these sensors.
    """
    s = drive.sensors
    have = drive.fused.gps_valid
    return dataclasses.replace(
        s,
        compass_t=drive.fused.time[have].astype(np.float64),
        compass=drive.fused.heading[have].astype(np.float64),
    )


def compare_loops(
    graph: RoadGraph,
    drive: Drive,
    new_match: Callable[[], MatchFn],
    *,
    kalman: KalmanConfig = DEFAULT_KALMAN,
) -> tuple[LoopMetrics, LoopMetrics, ClosedLoop]:
    """Open and closed loop on ``drive``; ``new_match()`` gives a matcher on a fresh session
    (called once per loop). Both loops run the filter on the drive's raw sensors fix by fix,
    the open one without feeding anything back (for a simulated drive its fixes are the
    drive's own). Returns (open, closed, the closed-loop run)."""
    opened = closed_loop_drive(graph, drive, new_match(), kalman=kalman, feed="none")
    open_m = loop_metrics(graph, opened.drive, opened.results)
    run = closed_loop_drive(graph, drive, new_match(), kalman=kalman)
    closed_m = loop_metrics(graph, run.drive, run.results, closed=run)
    return open_m, closed_m, run


def run_map_aided(
    graph: RoadGraph,
    drive: Drive,
    *,
    match: MatchFn | None = None,
    kalman: KalmanConfig = DEFAULT_KALMAN,
) -> ClosedLoop:
    """The closed loop of ``drive`` with ``match`` (for example a server's
    :class:`service.client.ServerMatcher`), or by default the matcher in process."""
    if match is None:
        from mapmatch.online import OnlineMatcher

        match = in_process(OnlineMatcher(graph))
    return closed_loop_drive(graph, drive, match, kalman=kalman)


def summary_table(rows: Sequence[dict[str, object]]) -> pd.DataFrame:
    """Open against closed loop per group of drives (``rows``: one per drive and loop, with
    ``group``, ``loop`` and the :class:`LoopMetrics` fields): medians and p90s of the outage
    errors over all outages, mean errors with GPS, heading, intersections and correct road."""
    out = []
    df = pd.DataFrame(rows)
    for (group, loop), g in df.groupby(["group", "loop"], sort=False):
        ends = np.concatenate([np.asarray(v, dtype=float) for v in g["outage_end"]] or [np.zeros(0)])
        tops = np.concatenate([np.asarray(v, dtype=float) for v in g["outage_max"]] or [np.zeros(0)])
        pct = lambda a, q: float(np.percentile(a, q)) if len(a) else float("nan")  # noqa: E731
        out.append(
            {
                "group": group,
                "loop": loop,
                "drives": len(g),
                "outages": len(ends),
                "end_median_m": pct(ends, 50),
                "end_p90_m": pct(ends, 90),
                "max_median_m": pct(tops, 50),
                "max_p90_m": pct(tops, 90),
                "gps_mean_m": float(g["error_gps_mean"].mean()),
                "gps_p90_m": float(g["error_gps_p90"].mean()),
                "heading_deg": float(g["heading_mean"].mean()),
                "heading_outage_deg": float(g["heading_outage"].mean()),
                "intersections": float(g["intersections"].mean()),
                "correct_edge": float(g["correct_edge"].mean()),
                "fed": float(g["fed"].mean()),
                "gated": float(g["gated"].mean()),
            }
        )
    return pd.DataFrame(out)
