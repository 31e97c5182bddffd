"""Online matcher on REAL GPS: the shared Kubicka tracks as fused drives (``mapmatch.sim.realgps``).

Each track's real 1 Hz fixes are the GPS-aided positions; heading and odometer come from the true
path with noise, bias and scale error; the seed papers' five outages (60, 90, 92, 83, 48 s,
spread over the drive) are dead-reckoned with a gyro bias. Each drive runs at 1 Hz and 10 Hz,
with the outages and GPS-only, through ``OnlineMatcher.update`` in-process. Scored, summed over
drives (as the held-out test sums fixes and intersections):

* intersections traversed: true junctions found in the matched junction sequence, split by
  whether the vehicle passed them with GPS or in an outage;
* correct road per fix: all fixes and fixes without GPS, counted only where the truth is known
  (``truth_known``: not in long gaps of the track, nor where the vehicle was off the mapped
  roads, e.g. parked in a yard or before the true route begins; see
  :mod:`mapmatch.sim.realgps`); the fixes left out are counted. A fix matched to the route
  edge before or after the true one, with the true position within ``STRADDLE_M`` (half a car
  length) of the crossing between them, is on the right road: the car straddles the crossing,
  and the truth's own place along the road (from the smoothed fixes) is no surer. The strict
  figure (the true edge only) is printed too;
* error at outage end: distance from the snapped position to the true one at the last fix of
  each outage (and 5 s after GPS returns), median and p90;

each as reported live and after applying the matcher's corrections. ``--breakdown`` classifies
every wrong-road fix: start-up, outage drift, along-track (a route edge just before or after
the true one) at a straight crossing or at a turn, fork (a branch leaving the true route at a
node near the vehicle), parallel road (a road off the route within 40 m at a similar bearing),
reverse, other.

    python bench/bench_online_real.py                    # all tracks, 1 + 10 Hz
    python bench/bench_online_real.py --rates 1 --breakdown
    python bench/bench_online_real.py --tracks 00000007 00000014 --rates 1
    python bench/bench_online_real.py --docs       # also write the table into the docs (bench/report.py)
    python bench/bench_online_real.py --cv --grid model.beta=3,5,8   # out-of-fold beside in-sample

``--cv`` scores every setting of ``--grid`` (on the current defaults and ``--set``) on every
track's drive with the outages, chooses on four of the folds of ``bench/folds.py`` and scores
the fifth (``bench/crossval.py``), and prints the out-of-fold table beside the in-sample ones
(``--docs``: the fragment ``cv_online`` at 1 Hz, ``cv_online_10hz`` at 10 Hz; ``--json``:
every setting's rows of every track).

``--calibration`` runs every track's drive with the outages at each rate (1 and 10 Hz unless
``--rates``) with the confidence model off (the matcher reports the road probability), keeps
per fix the features the model weighs, and measures probabilities against whether the fix is
on the right road (as scored above, where the truth is known and the fix is placed on a road):
the reliability table, the ECE (over its bins and over 20 bins of equal numbers of fixes), the
log-loss, the wrong share among the fixes marked ``usable``, the share of right fixes marked
usable and the trade-off curve (right fixes usable at a wrong share of 0.05-0.3 %)
(``bench/calibration.py``), for the road probability, it mapped by isotonic regression out of
fold, the configured model (what the matcher reports: the same numbers, computed from the
features), and the model's coefficients and usable threshold fitted on all tracks (in-sample)
and on four folds of ``bench/folds.py`` and applied to the fifth (out of fold), pooled over
the rates unless ``--per-rate`` (``bench/confidence_fit.py``: the L2 prior chosen by CV, the
threshold judged on out-of-fold probabilities), with the matcher's usable test on each, and
the model out of fold with each term left out. The wrong fixes at road probability
``>= 0.999`` and the wrong usable ones are broken down by class, by whether the reported edge
is next to the true one, GPS or outage, distance to the nearer node and whether another road
lies near (:data:`CALIB_COLUMNS`).
``--save-fixes`` writes the per-fix table (CSV), ``--load-fixes`` reports from one or more
(e.g. one per rate) without running (``--docs``: the fragment ``calibration``).

    python bench/bench_online_real.py --calibration --docs
    python bench/bench_online_real.py --calibration --load-fixes 1hz.csv 10hz.csv --docs
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import calibration  # noqa: E402
import confidence_fit as cfit  # noqa: E402
import crossval  # noqa: E402
import folds  # noqa: E402
from bench_online import corrected_edges, run_drive  # noqa: E402

from graph.artifact import load_map, save_map  # noqa: E402
from graph.build import build_map  # noqa: E402
from graph.index import project_to_edge  # noqa: E402
from graph.projection import to_xy  # noqa: E402
from graph.road_graph import RoadGraph  # noqa: E402
from mapmatch.config import DEFAULT_CONFIG, MatchConfig  # noqa: E402
from mapmatch.errors import ConfigError  # noqa: E402
from mapmatch.evaluate import edge_path, is_junction, matched_junctions, path_nodes  # noqa: E402
from mapmatch.online import OnlineMatcher  # noqa: E402
from mapmatch.sim.drive import Drive  # noqa: E402
from mapmatch.sim.realgps import real_drive  # noqa: E402
from mapmatch.types import SnapResult, State  # noqa: E402

KUBICKA = folds.KUBICKA  # MAPMATCH_SHARED, else the folder beside the repository
STARTUP_S = 30.0
RECOVERY_S = 10.0
PARALLEL_M = 40.0
PARALLEL_DEG = 30.0
FORK_DEG = 45.0
STRADDLE_M = 2.5


def right_road(drive: Drive, edges: np.ndarray, *, straddle_m: float = STRADDLE_M) -> np.ndarray:
    """Per fix: the true edge, or the route edge next to it with the true position within
    ``straddle_m`` of the crossing between them."""
    tr = drive.truth
    te = tr["edge"].to_numpy()
    ok = edges == te
    route, start = drive.route.edges, drive.route.edge_start
    s = tr["route_s"].to_numpy()
    k = np.clip(np.searchsorted(start, s, side="right") - 1, 0, len(route) - 1)
    before = (k > 0) & (s - start[k] <= straddle_m)
    after = (k < len(route) - 1) & (start[k + 1] - s <= straddle_m)
    ok |= before & (edges == route[np.maximum(k - 1, 0)])
    ok |= after & (edges == route[np.minimum(k + 1, len(route) - 1)])
    return ok


def _angle(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def true_junctions(graph: RoadGraph, drive: Drive) -> tuple[list[int], np.ndarray]:
    """The true junction sequence and the time each is passed."""
    nodes = drive.node_index
    keep = is_junction(graph)[nodes] if len(nodes) else np.zeros(0, dtype=bool)
    return nodes[keep].tolist(), drive.node_time[keep]


def snapped_xy(graph: RoadGraph, results: list[SnapResult]) -> np.ndarray:
    lon = np.array([r.lon for r in results], dtype=float)
    lat = np.array([r.lat for r in results], dtype=float)
    out = np.full((len(results), 2), np.nan)
    ok = ~np.isnan(lon) & ~np.isnan(lat)
    if ok.any():
        out[ok] = to_xy(graph.crs, lon[ok], lat[ok])
    return out


def corrected_xy(
    graph: RoadGraph, results: list[SnapResult], edges: np.ndarray, xy: np.ndarray
) -> np.ndarray:
    """Snapped positions moved onto the corrected edge where a correction changed it."""
    out = xy.copy()
    for i, r in enumerate(results):
        if edges[i] >= 0 and edges[i] != r.edge and not np.isnan(xy[i, 0]):
            _, _, px, py = project_to_edge(graph, int(edges[i]), float(xy[i, 0]), float(xy[i, 1]))
            out[i] = (px, py)
    return out


def outage_end_errors(drive: Drive, xy: np.ndarray, *, after_s: float = 0.0) -> list[float]:
    """Snapped-position error at the last fix of each outage (or ``after_s`` after its end)."""
    t = drive.truth["time"].to_numpy() - float(drive.truth["time"].iloc[0])
    txy = drive.truth[["x", "y"]].to_numpy()
    out = []
    for a, d in drive.outages:
        if a + d > t[-1]:
            continue
        i = (
            int(np.searchsorted(t, a + d - 1e-6)) - 1
            if after_s == 0
            else int(np.searchsorted(t, a + d + after_s))
        )
        if 0 <= i < len(t) and not np.isnan(xy[i, 0]):
            out.append(float(np.hypot(*(xy[i] - txy[i]))))
    return out


def junction_hits(
    graph: RoadGraph, drive: Drive, edges: np.ndarray, times: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(found, in_outage) per true junction."""
    tn, tt = true_junctions(graph, drive)
    mnodes = path_nodes(graph, edge_path(graph, edges, times=times))
    found = matched_junctions(tn, mnodes)
    ft = drive.truth["time"].to_numpy()
    gout = drive.truth["gps_outage"].to_numpy() > 0
    k = np.clip(np.searchsorted(ft, tt), 0, len(ft) - 1)
    return found, gout[k]


def outage_clock(drive: Drive) -> tuple[np.ndarray, np.ndarray]:
    """Per fix: whether it is in an outage, and seconds since the last outage fix (inf before
    the first)."""
    tr = drive.truth
    t = tr["time"].to_numpy() - float(tr["time"].iloc[0])
    gout = tr["gps_outage"].to_numpy() > 0
    last = np.where(gout, t, -np.inf)
    out_end = np.maximum.accumulate(last) if len(t) else last
    return gout, t - out_end


def wrong_kinds(graph: RoadGraph, drive: Drive, edges: np.ndarray) -> np.ndarray:
    """Per fix, the class of a wrong-road fix (see the module docstring), prefixed ``gps`` or
    ``outage``; empty for a right one or where the truth is not known."""
    tr = drive.truth
    te = tr["edge"].to_numpy()
    t = tr["time"].to_numpy() - float(tr["time"].iloc[0])
    gout, since = outage_clock(drive)
    route = drive.route.edges
    pos: dict[int, list[int]] = {}
    for i, e in enumerate(route.tolist()):
        pos.setdefault(e, []).append(i)
    route_s = tr["route_s"].to_numpy()
    ridx = np.clip(np.searchsorted(drive.route.edge_start, route_s, side="right") - 1, 0, len(route) - 1)
    turn = np.abs(
        (graph.edge_bearing_start[route[1:]] - graph.edge_bearing_end[route[:-1]] + 180.0) % 360.0 - 180.0
    )
    known = tr["truth_known"].to_numpy(dtype=bool)
    res = np.full(len(t), "", dtype=object)
    for i in np.flatnonzero(~right_road(drive, edges) & known).tolist():
        e, k = int(edges[i]), int(ridx[i])
        gps = "outage" if gout[i] else "gps"
        if t[i] < STARTUP_S:
            kind = "start-up"
        elif gout[i] or since[i] <= RECOVERY_S:
            kind = "outage drift" if gout[i] else "outage recovery"
        elif e < 0:
            kind = "unmatched"
        elif e in pos and any(abs(j - k) <= 3 for j in pos[e]):
            j = min(pos[e], key=lambda j: abs(j - k))
            node = min(j, k)  # the crossing between them
            straight = turn[min(node, len(turn) - 1)] <= 30.0 if len(turn) else True
            kind = "along-track " + ("straight" if straight else "turn")
        elif int(graph.edge_reverse[te[i]]) == e:
            kind = "reverse"
        else:
            u = int(graph.edge_u[e])
            near = route[max(0, k - 3) : k + 2]
            fork = [r for r in near.tolist() if int(graph.edge_u[r]) == u]
            if (
                fork
                and _angle(float(graph.edge_bearing_start[e]), float(graph.edge_bearing_start[fork[0]]))
                <= FORK_DEG
            ):
                kind = "fork"
            else:
                x, y = float(tr["x"].iloc[i]), float(tr["y"].iloc[i])
                _, dist, _, _ = project_to_edge(graph, e, x, y)
                b = float(tr["heading"].iloc[i])
                be = float(graph.edge_bearing_start[e])
                kind = "parallel" if dist <= PARALLEL_M and _angle(b, be) <= PARALLEL_DEG else "other"
        res[i] = f"{gps:6} {kind}"
    return res


def classify(graph: RoadGraph, drive: Drive, edges: np.ndarray) -> dict[str, int]:
    """Wrong-road fixes by class (see the module docstring)."""
    res: dict[str, int] = {}
    for key in wrong_kinds(graph, drive, edges).tolist():
        if key:
            res[key] = res.get(key, 0) + 1
    return res


def run_one(
    graph: RoadGraph, matcher: OnlineMatcher, folder: Path, *, rate: float, outages: bool, seed: int
) -> dict[str, object]:
    drive = real_drive(graph, folder, rate_hz=rate, outages=outages, seed=seed)
    return score_drive(graph, matcher, drive, track=folder.name, rate=rate)


def score_drive(
    graph: RoadGraph, matcher: OnlineMatcher, drive: Drive, *, track: str, rate: float
) -> dict[str, object]:
    """Run ``drive`` through ``matcher`` and score it: one row of the table's sums."""
    res, dt = run_drive(matcher, drive)
    t = np.array([r.time for r in res])
    live = np.array([r.edge for r in res], dtype=np.int64)
    fin = corrected_edges(graph, res)
    te = drive.truth["edge"].to_numpy()
    gout = drive.truth["gps_outage"].to_numpy() > 0
    known = drive.truth["truth_known"].to_numpy(dtype=bool)
    xy = snapped_xy(graph, res)
    xy2 = corrected_xy(graph, res, fin, xy)
    row: dict[str, object] = {
        "track": track,
        "hz": rate,
        "outages": len(drive.outages),
        "fixes": len(res),
    }
    row["scored"] = int(known.sum())
    row["fixes_out"] = int((gout & known).sum())
    for tag, ed, pxy in (("live", live, xy), ("fin", fin, xy2)):
        found, in_out = junction_hits(graph, drive, ed, t)
        row[f"jn_gps_{tag}"] = int(found[~in_out].sum())
        row[f"jn_out_{tag}"] = int(found[in_out].sum())
        ok = right_road(drive, ed) & known
        row[f"ok_{tag}"] = int(ok.sum())
        row[f"ok_out_{tag}"] = int(ok[gout].sum())
        row[f"strict_{tag}"] = int(((ed == te) & known).sum())
        row[f"end_{tag}"] = outage_end_errors(drive, pxy)
        row[f"end5_{tag}"] = outage_end_errors(drive, pxy, after_s=5.0)
    found, in_out = junction_hits(graph, drive, live, t)
    row["jn_gps"] = int((~in_out).sum())
    row["jn_out"] = int(in_out.sum())
    row["us"] = (dt * 1e6).tolist()
    row["breakdown_live"] = classify(graph, drive, live)
    row["breakdown_fin"] = classify(graph, drive, fin)
    return row


def _pct(a: float, b: float) -> str:
    return f"{100.0 * a / b:6.2f} %" if b else "    - "


def _q(v: list[float]) -> str:
    return f"{np.median(v):5.1f} m / {np.percentile(v, 90):5.1f} m" if v else "-"


def cells(g: pd.DataFrame, tag: str) -> list[str]:
    """The summed scores of rows ``g`` (live or ``fin``: corrections applied) as table cells:
    intersections with GPS / in outages, correct road all / in outages, outage-end error
    median / p90, 5 s after, strict."""
    s = g.sum(numeric_only=True)
    ends = [x for v in g[f"end_{tag}"] for x in v]
    ends5 = [x for v in g[f"end5_{tag}"] for x in v]
    return [
        f"{_pct(s[f'jn_gps_{tag}'], s['jn_gps'])} / {_pct(s[f'jn_out_{tag}'], s['jn_out'])}",
        f"{_pct(s[f'ok_{tag}'], s['scored'])} / {_pct(s[f'ok_out_{tag}'], s['fixes_out'])}",
        _q(ends),
        _q(ends5),
        _pct(s[f"strict_{tag}"], s["scored"]),
    ]


def table(rows: list[dict[str, object]]) -> str:
    df = pd.DataFrame(rows)
    lines = [
        "| rate | outages | | intersections, with GPS / in outages | correct road per fix, all / in outages "
        "| error at outage end, median / p90 | 5 s after GPS returns | correct road, strict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (hz, no), g in df.groupby(["hz", df["outages"] > 0]):
        for tag, name in (("live", "live"), ("fin", "corrections applied")):
            lines.append(f"| {hz:g} Hz | {'yes' if no else 'no'} | {name} | {' | '.join(cells(g, tag))} |")
    s = df.sum(numeric_only=True)
    lines.append(
        f"\ncorrect road is counted on {int(s['scored'])} of {int(s['fixes'])} fixes "
        f"(the truth is not known on the others)"
    )
    return "\n".join(lines)


CV_GRID = ("model.beta=3,5,8", "online.region.switch_penalty=5,8,12")
"""The default grid of ``--cv``: the transition scale β and the cost of jumping to a road the
filter did not follow (the fixes carry their own σ, so ``model.gps_sigma`` is only a fallback)."""


def online_loss(records: list[list[dict[str, object]]]) -> float:
    """What ``--cv`` minimises over tracks' rows: the share of scored fixes on the wrong road
    plus the share of true intersections missed, live."""
    g = pd.DataFrame([r for rec in records for r in rec]).sum(numeric_only=True)
    wrong = 1.0 - g["ok_live"] / max(g["scored"], 1)
    missed = 1.0 - (g["jn_gps_live"] + g["jn_out_live"]) / max(g["jn_gps"] + g["jn_out"], 1)
    return float(wrong + missed)


def cv_scores(
    names: list[str], settings: list[tuple[str, ...]], base: MatchConfig, args: argparse.Namespace
) -> dict[tuple[str, ...], dict[str, list[dict[str, object]]]]:
    """Every setting's rows of every track (its drives with the outages, at each rate): each
    drive is made once and run through a matcher per setting."""
    scores: dict[tuple[str, ...], dict[str, list[dict[str, object]]]] = {s: {} for s in settings}
    configs = {s: base.with_settings(list(s)) for s in settings}
    for n, name in enumerate(names):
        folder = KUBICKA / name
        graph = load_graph(folder, args.map_cache)
        drives = [real_drive(graph, folder, rate_hz=r, outages=True, seed=int(name)) for r in args.rates]
        for s in settings:
            matcher = OnlineMatcher(graph, config=configs[s])
            rows = [
                score_drive(graph, matcher, d, track=name, rate=r)
                for d, r in zip(drives, args.rates, strict=True)
            ]
            for r in rows:
                r.pop("us")
            scores[s][name] = rows
        print(
            f"# cv {n + 1}/{len(names)} {name}: {len(settings)} settings, load {os.getloadavg()[0]:.2f}",
            flush=True,
        )
    return scores


def cv_table(result: crossval.CvResult, defaults: list[dict[str, object]], *, n_tracks: int) -> str:
    """In-sample (current defaults; the grid's best chosen on all tracks) beside out-of-fold."""
    named = (
        ("current defaults, all tracks", defaults),
        (
            f"chosen on all {n_tracks} tracks ({crossval.label(result.in_sample) or 'defaults'})",
            [r for rec in result.in_sample_records for r in rec],
        ),
        (
            "out of fold (chosen on 4 folds, scored on the 5th)",
            [r for rec in result.oof_records for r in rec],
        ),
    )
    lines = [
        "| rate | | | intersections, with GPS / in outages | correct road per fix, all / in outages "
        "| error at outage end, median / p90 | 5 s after GPS returns | correct road, strict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for hz in sorted({float(r["hz"]) for r in defaults}):  # type: ignore[arg-type]
        for name, rows in named:
            df = pd.DataFrame(rows)
            g = df[df["hz"] == hz]
            for tag, what in (("live", "live"), ("fin", "corrections applied")):
                lines.append(f"| {hz:g} Hz | {name} | {what} | {' | '.join(cells(g, tag))} |")
    return "\n".join(lines)


def run_cv(names: list[str], base: MatchConfig, args: argparse.Namespace) -> str:
    """``--cv``: score the grid on every track, cross-validate over the folds of
    ``bench/folds.py``, print and return the report."""
    grid = crossval.parse_grid(args.grid)
    settings = crossval.settings_grid(grid)
    settings.sort(key=lambda s: base.with_settings(list(s)) != base)  # the current default first
    load0 = os.getloadavg()
    scores = cv_scores(names, settings, base, args)
    if args.json:  # every setting's rows of every track, to check or re-summarise the choice
        args.json.write_text(
            json.dumps({";".join(k) or "defaults": v for k, v in scores.items()}, default=str)
        )
    fold_ids = folds.folds(names)
    result = crossval.cross_validate(scores, fold_ids, loss=online_loss)
    current = next((s for s in settings if base.with_settings(list(s)) == base), None)
    if current is None:
        raise SystemExit("error: --grid must hold the current value of each field")
    defaults = [r for name in names for r in scores[current][name]]
    rates = ", ".join(f"{r:g} Hz" for r in args.rates)
    head = (
        f"REAL GPS: {len(names)} Kubicka tracks as fused drives with the five outages ({rates}); "
        f"{len(fold_ids)} folds by track (`bench/folds.py`, seed {folds.SEED}); grid "
        f"{'; '.join(f'`{g}`' for g in args.grid)} ({len(settings)} settings); chosen by the least "
        "share of wrong-road fixes plus share of missed intersections, live, summed over the "
        f"training tracks. Load average {load0[0]:.2f} at the start, "
        f"{os.getloadavg()[0]:.2f} at the end ({os.cpu_count()} cores).\n\n"
    )
    text = (
        head
        + cv_table(result, defaults, n_tracks=len(names))
        + "\n\nThe choice of each fold, and each setting's loss (wrong share + missed share) "
        + "over all tracks:\n\n"
        + crossval.choice_table(result)
    )
    print(text)
    return text


CALIB_COLUMNS = (
    "track",
    "hz",
    "fold",
    "p",
    "right",
    "usable",
    "gate",
    "ambiguous",
    "kind",
    "adjacent",
    "node_dist",
    "along_sigma",
    "cross_dist",
    "gps",
    "since_outage",
    "n_cands",
    "true_dist",
    "alt_dist",
    "along_err",
    "p_path",
    "p2",
    "held",
    "edge_len",
    "fix_sigma",
    "speed",
    "head_diff",
    "fix_along",
    "since_gps",
    "dr_dist",
    "cross_sig",
    "alongside",
    "other_sig",
    "since_amb",
    "since_change",
    "cand2_gap",
    "cand2_head",
)
"""The per-fix table of ``--calibration``: the track, rate and fold; the reported road
probability; whether the answer is on the right road; the matcher's ``usable``; whether the
answer passes the gate's tests that do not look at the probability (on a road, not
(re)initialising, settled); and whether the matcher was in an ambiguous region. Then the
diagnostics: the class of a wrong fix (``wrong_kinds``; empty when right); whether the
reported edge shares a node with the true one (not being it); the answer's distance along the
reported edge to its nearer end; the measurement's along-track σ; the fix's distance to the
reported road; GPS-aided or not; seconds since the last outage fix; the number of candidate
edges; the true position's distance to the reported edge (wrong fixes only); the fix's
distance to the nearest other road within ``PARALLEL_M`` at a bearing within ``PARALLEL_DEG``
of the reported one (:func:`alternative_dist`; NaN: none); the true position's signed distance
along the road from the answer (positive: the vehicle is ahead of it)."""


def along_error(graph: RoadGraph, drive: Drive, results: list[SnapResult]) -> np.ndarray:
    """Per fix, the true position's signed distance along the road's bearing at the answer
    from the answer (positive: the vehicle is ahead of it)."""
    xy = snapped_xy(graph, results)
    rad = np.radians(np.array([r.bearing for r in results], dtype=float))
    txy = drive.truth[["x", "y"]].to_numpy()
    return (txy[:, 0] - xy[:, 0]) * np.sin(rad) + (txy[:, 1] - xy[:, 1]) * np.cos(rad)


def alternative_dist(graph: RoadGraph, drive: Drive, edges: np.ndarray) -> np.ndarray:
    """Per fix, the distance from the fused fix to the nearest road other than the reported
    edge and its reverse, within ``PARALLEL_M`` and at a bearing within ``PARALLEL_DEG`` of the
    reported edge's there; an edge sharing a node with it counts only where the fix projects
    inside it (not onto the shared node). NaN where there is none or no edge is reported."""
    from graph.index import EdgeIndex

    xy = np.column_stack([drive.fused.x, drive.fused.y])
    c = EdgeIndex(graph).query(xy, PARALLEL_M, k=24)
    out = np.full(len(edges), np.nan)
    rev = graph.edge_reverse
    for pt, e2, d, off in zip(
        c.point.tolist(), c.edge.tolist(), c.dist.tolist(), c.offset.tolist(), strict=True
    ):
        e = int(edges[pt])
        if e < 0 or e2 == e or e2 == int(rev[e]) or not (d < out[pt] or np.isnan(out[pt])):
            continue
        nodes = {int(graph.edge_u[e]), int(graph.edge_v[e])}
        if {int(graph.edge_u[e2]), int(graph.edge_v[e2])} & nodes and (
            off < 1.0 or off > float(graph.edge_len[e2]) - 1.0
        ):
            continue
        if _angle(float(graph.edge_bearing_start[e2]), float(graph.edge_bearing_start[e])) > PARALLEL_DEG:
            continue
        out[pt] = d
    return out


def calibration_fixes(
    matcher: OnlineMatcher, drive: Drive, results: list[SnapResult]
) -> dict[str, np.ndarray]:
    """The columns ``p`` .. ``true_dist`` of :data:`CALIB_COLUMNS` for a drive's fixes that
    are placed on a road where the truth is known."""
    graph = matcher.graph
    edges = np.array([r.edge for r in results], dtype=np.int64)
    known = drive.truth["truth_known"].to_numpy(dtype=bool)
    keep = known & (edges >= 0)
    aided = [r.map_aided for r in results]
    reason = np.array([m.reason for m in aided])
    right = right_road(drive, edges)
    te = drive.truth["edge"].to_numpy()
    e0 = np.maximum(edges, 0)
    t0 = np.maximum(te, 0)
    eu, ev = graph.edge_u[e0], graph.edge_v[e0]
    tu, tv = graph.edge_u[t0], graph.edge_v[t0]
    offset = np.array([r.offset for r in results], dtype=float)
    gout, since = outage_clock(drive)
    true_dist = np.full(len(edges), np.nan)
    txy = drive.truth[["x", "y"]].to_numpy()
    for i in np.flatnonzero(~right & keep).tolist():
        true_dist[i] = project_to_edge(graph, int(edges[i]), float(txy[i, 0]), float(txy[i, 1]))[1]
    cols = {
        "p": np.array([m.probability for m in aided], dtype=float),
        "right": right,
        "usable": np.array([m.usable for m in aided], dtype=bool),
        "gate": ~np.isin(reason, ("off_road", "initialising", "settling")),
        "ambiguous": np.array([r.state == State.AMBIGUOUS for r in results], dtype=bool),
        "kind": np.array([k.split(" ", 1)[-1].strip() for k in wrong_kinds(graph, drive, edges)]),
        "adjacent": (edges != te) & ((eu == tu) | (eu == tv) | (ev == tu) | (ev == tv)),
        "node_dist": np.minimum(offset, graph.edge_len[e0] - offset),
        "along_sigma": np.array([m.along_sigma for m in aided], dtype=float),
        "cross_dist": np.array([r.dist for r in results], dtype=float),
        "gps": ~gout,
        "since_outage": since,
        "n_cands": np.array([len(r.candidates) for r in results], dtype=np.int64),
        "true_dist": true_dist,
        "alt_dist": alternative_dist(graph, drive, edges),
        "along_err": along_error(graph, drive, results),
        **answer_features(matcher, drive, results),
    }
    return {k: v[keep] for k, v in cols.items()}


def answer_features(matcher: OnlineMatcher, drive: Drive, results: list[SnapResult]) -> dict[str, np.ndarray]:
    """Per fix, what the matcher knows at answer time besides ``p``: the path's probability
    (the reported edge's candidate share, 1 for a single hypothesis), the second-best edge's,
    whether the answer is held at a node, the edge's length, the fix's σ, speed and heading
    difference to the road, the fix's signed along-track distance from the answer, and the
    time and odometer distance since the last GPS-aided fix; the fix's distance from the road
    in its σ and whether a road runs alongside, as the matcher's confidence model sees them
    (:func:`mapmatch.online.report.agreement`); the seconds since the last answer in an
    ambiguous region and since the reported edge last changed; and the second-best candidate's
    distance from the fix and heading disagreement, less the answer's (in σ and degrees; inf
    and NaN without one)."""
    graph, cfg = matcher.graph, matcher.config
    fixes = drive.fix_objects()
    n = len(results)
    p_path, p2 = np.ones(n), np.zeros(n)
    c2_dist, c2_head = np.full(n, np.inf), np.full(n, np.nan)
    road = matcher.road
    for i, r in enumerate(results):
        for c in r.candidates:
            if c.edge == r.edge:
                p_path[i] = c.probability
            elif c.probability > p2[i]:
                p2[i] = c.probability
                c2_dist[i] = c.dist
                hd = float(fixes[i].heading) - road.bearing_at(c.edge, c.offset)
                c2_head[i] = abs((hd + 180.0) % 360.0 - 180.0)
    e0 = np.maximum(np.array([r.edge for r in results], dtype=np.int64), 0)
    off = np.array([r.offset for r in results], dtype=float)
    elen = graph.edge_len[e0].astype(float)
    held = (off <= 1e-6) | (off >= elen - 1e-6)
    xy = snapped_xy(graph, results)
    rad = np.radians(np.array([r.bearing for r in results], dtype=float))
    fxy = np.column_stack([drive.fused.x, drive.fused.y])
    fix_along = (fxy[:, 0] - xy[:, 0]) * np.sin(rad) + (fxy[:, 1] - xy[:, 1]) * np.cos(rad)
    t = np.array([f.time for f in fixes], dtype=float)
    gps = np.array([bool(f.gps_valid) for f in fixes])
    dist = np.nan_to_num(np.array([f.distance for f in fixes], dtype=float))
    last_t = np.maximum.accumulate(np.where(gps, t, -np.inf))
    cum = np.cumsum(dist)
    last_c = np.maximum.accumulate(np.where(gps, cum, -np.inf))
    head = np.array([f.heading for f in fixes], dtype=float)
    bear = np.array([r.bearing for r in results], dtype=float)
    sig = np.array([f.pos_sigma for f in fixes], dtype=float)
    sig = np.maximum(np.where(sig > 0, sig, cfg.model.gps_sigma), cfg.online.evidence.pos_sigma_floor)
    amb = np.array([r.state == State.AMBIGUOUS for r in results], dtype=bool)
    change = np.r_[True, e0[1:] != e0[:-1]]
    par = matcher.parallel
    beside = [r.edge >= 0 and bool(par.alongside(r.edge, r.offset, cfg)) for r in results]
    other = [
        par.nearest(r.edge, r.offset, float(x), float(y), cfg) if b else np.inf
        for r, b, x, y in zip(results, beside, drive.fused.x, drive.fused.y, strict=True)
    ]
    return {
        "other_sig": np.array(other, dtype=float) / sig,
        "cross_sig": np.array([r.dist for r in results], dtype=float) / sig,
        "alongside": np.array(beside, dtype=bool),
        "p_path": p_path,
        "p2": p2,
        "held": held,
        "edge_len": elen,
        "fix_sigma": np.array([f.pos_sigma for f in fixes], dtype=float),
        "speed": np.array([f.speed for f in fixes], dtype=float),
        "head_diff": np.abs((head - bear + 180.0) % 360.0 - 180.0),
        "fix_along": fix_along,
        "since_gps": t - last_t,
        "dr_dist": cum - last_c,
        "since_amb": t - np.maximum.accumulate(np.where(amb, t, -np.inf)),
        "since_change": t - np.maximum.accumulate(np.where(change, t, -np.inf)),
        "cand2_gap": c2_dist / sig - np.array([r.dist for r in results], dtype=float) / sig,
        "cand2_head": c2_head - np.abs((head - bear + 180.0) % 360.0 - 180.0),
    }


def collect_calibration(names: list[str], cfg: MatchConfig, args: argparse.Namespace) -> pd.DataFrame:
    """Run every track's drive with the outages at each rate; the per-fix table of
    :data:`CALIB_COLUMNS` (the fold from ``bench/folds.py``)."""
    fold = folds.assign_folds(names)
    parts = []
    for n, name in enumerate(names):
        folder = KUBICKA / name
        graph = load_graph(folder, args.map_cache)
        matcher = OnlineMatcher(graph, config=cfg.with_settings(list(cfit.IDENTITY)))
        for rate in args.rates:
            drive = real_drive(graph, folder, rate_hz=rate, outages=True, seed=int(name))
            res, _ = run_drive(matcher, drive)
            cols = calibration_fixes(matcher, drive, res)
            df = pd.DataFrame(cols)
            df.insert(0, "fold", fold[name])
            df.insert(0, "hz", rate)
            df.insert(0, "track", name)
            parts.append(df)
        print(f"# calibration {n + 1}/{len(names)} {name}: load {os.getloadavg()[0]:.2f}", flush=True)
    return pd.concat(parts, ignore_index=True)[list(CALIB_COLUMNS)]


def _reliability_lines(p: np.ndarray, right: np.ndarray) -> list[str]:
    lines = ["| reported p | fixes | mean p | right share |", "|---|---|---|---|"]
    for b in calibration.reliability(p, right):
        hi = "]" if b.hi == 1.0 else ")"
        mp = f"{b.mean_p:.4f}" if b.fixes else "-"
        rs = f"{b.right_share:.4f}" if b.fixes else "-"
        lines.append(f"| [{b.lo:g}, {b.hi:g}{hi} | {b.fixes} | {mp} | {rs} |")
    return lines


Scored = tuple[np.ndarray, np.ndarray]  # a probability per fix and the usable flag on it


def calibration_probabilities(g: pd.DataFrame, fit: cfit.ModelFit, cfg: MatchConfig) -> dict[str, Scored]:
    """One rate's probabilities to compare, each with its usable flags: the road's (the model
    off, usable at 0.9), isotonic on it out of fold, the configured model (what the matcher
    reports), and the model and threshold fitted on all tracks (in-sample) and on four folds
    and applied to the fifth (out of fold); ``fit`` holds the fixes of ``g``, in its order."""
    p = g["p"].to_numpy()
    right = g["right"].to_numpy()
    q_cfg = calibration.logistic_apply(cfit.configured(cfg), cfit.features(g, cfg.confidence))
    return {
        "road probability (model off, usable at 0.9)": (p, cfit.gate(g, p, 0.9)),
        "isotonic on it, out of fold": (
            (iso := calibration.out_of_fold(p, right, g["fold"].to_numpy())),
            cfit.gate(g, iso, cfg.measurement.min_probability),
        ),
        "confidence model as configured (as reported)": (
            q_cfg,
            cfit.gate(g, q_cfg, cfg.measurement.min_probability),
        ),
        "confidence model fitted on all tracks (in-sample)": (fit.q_in, fit.u_in),
        "confidence model and threshold fitted on 4 folds, applied to the 5th (out of fold)": (
            fit.q_oof,
            fit.u_oof,
        ),
    }


def calibration_summary(
    g: pd.DataFrame, fit: cfit.ModelFit, cfg: MatchConfig
) -> tuple[str, list[dict[str, object]]]:
    """One rate's reliability tables and a figures row per probability: ECE (fixed and
    equal-mass bins), log-loss, wrong share among usable, right share usable."""
    right = g["right"].to_numpy()
    text: list[str] = []
    figures: list[dict[str, object]] = []
    for name, (q, usable) in calibration_probabilities(g, fit, cfg).items():
        wrong, kept = calibration.usable_shares(usable, right)
        figures.append(
            {
                "probability": name,
                "ece": calibration.ece(q, right),
                "ece20": calibration.ece_equal_mass(q, right),
                "log_loss": calibration.log_loss(q, right),
                "usable": int(usable.sum()),
                "wrong_usable": wrong,
                "right_usable": kept,
                "curve": cfit.trade_off(q, g),
            }
        )
        text += [f"\n{name}:\n", *_reliability_lines(q, right)]
    return "\n".join(text), figures


_ADJACENT = {True: "adjacent", False: "not adjacent"}


def _shares(x: pd.Series, n: int) -> str:
    return ", ".join(f"{k} {100.0 * v / max(n, 1):.1f} %" for k, v in x.value_counts().items())


def wrong_breakdown(g: pd.DataFrame) -> str:
    """What the wrong fixes at road probability ``p >= 0.999`` and the wrong usable fixes
    (``usable``: the configured model's) are: shares
    by class, by whether the reported edge is next to the true one, GPS-aided or not, and by
    the answer's distance to the nearer node of its edge in along-track σ."""
    if "kind" not in g.columns:
        return ""
    wrong = g[~g["right"].astype(bool)]
    lines = []
    for name, sel in (
        ("wrong at road probability >= 0.999", wrong[wrong["p"] >= 0.999]),
        ("wrong and usable (the configured model)", wrong[wrong["usable"].astype(bool)]),
    ):
        n = len(sel)
        z = sel["node_dist"] / sel["along_sigma"]
        zb = pd.cut(
            z, [-np.inf, 0.5, 1.0, 2.0, 3.0, np.inf], labels=["<0.5σ", "0.5-1σ", "1-2σ", "2-3σ", ">3σ"]
        )
        nd = pd.cut(
            sel["node_dist"],
            [-np.inf, 5, 10, 20, 40, np.inf],
            labels=["<5m", "5-10m", "10-20m", "20-40m", ">40m"],
        )
        td = pd.cut(sel["true_dist"], [-np.inf, 3, 10, 30, np.inf], labels=["<3m", "3-10m", "10-30m", ">30m"])
        lines += [
            f"- {name}: {n} fixes ({100.0 * n / max(len(g), 1):.2f} % of all)",
            f"  - class: {_shares(sel['kind'].fillna(''), n)}",
            f"  - edge next to the true one: {_shares(sel['adjacent'].map(_ADJACENT), n)}",
            f"  - GPS: {_shares(sel['gps'].map({True: 'GPS-aided', False: 'outage'}), n)}",
            f"  - distance to the nearer node, in along-track σ: {_shares(zb.astype(str), n)}",
            f"  - distance to the nearer node: {_shares(nd.astype(str), n)}",
            f"  - true position's distance to the reported edge: {_shares(td.astype(str), n)}",
            f"  - another road at a similar bearing within {PARALLEL_M:g} m: "
            f"{100.0 * np.isfinite(sel['alt_dist']).mean() if n else 0:.1f} % (all fixes "
            f"{100.0 * np.isfinite(g['alt_dist']).mean():.1f} %), nearer to the fix than the "
            f"answer: {100.0 * (sel['alt_dist'] <= sel['cross_dist']).mean() if n else 0:.1f} % "
            f"(all {100.0 * (g['alt_dist'] <= g['cross_dist']).mean():.1f} %)",
            f"  - along-track σ median {sel['along_sigma'].median():.1f} m (all fixes "
            f"{g['along_sigma'].median():.1f} m); fix to road median {sel['cross_dist'].median():.1f} m "
            f"(all {g['cross_dist'].median():.1f} m); candidates > 1: "
            f"{100.0 * (sel['n_cands'] > 1).mean() if n else 0:.1f} %",
        ]
    return "\n".join(lines)


def _figure_rows(hz: float, n: int, figures: list[dict[str, Any]]) -> tuple[list[str], list[str]]:
    """The summary rows and the trade-off rows of one rate's figures."""
    rows, curve = [], []
    for f in figures:
        rows.append(
            f"| {hz:g} Hz | {f['probability']} | {n} | {f['ece']:.4f} | {f['ece20']:.4f} "
            f"| {f['log_loss']:.4f} | {f['usable']} | {100 * f['wrong_usable']:.3f} % "
            f"| {100 * f['right_usable']:.2f} % |"
        )
        curve.append(
            f"| {hz:g} Hz | {f['probability']} | " + " | ".join(f"{100 * c:.2f} %" for c in f["curve"]) + " |"
        )
    return rows, curve


def _ablation_lines(rows: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| model | rate | wrong among usable | right usable | ECE | log-loss |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['hz']:g} Hz | {100 * r['wrong_usable']:.3f} % "
            f"| {100 * r['right_usable']:.2f} % | {r['ece']:.4f} | {r['log_loss']:.4f} |"
        )
    return lines


def calibration_head(df: pd.DataFrame, cfg: MatchConfig, *, pooled: bool, load0: float) -> str:
    """The paragraph that says what the calibration tables are."""
    rates = ", ".join(f"{h:g} Hz" for h in sorted(df["hz"].unique()))
    how = "pooled over the rates (a fix weighs 1 / rate)" if pooled else "per rate"
    return (
        f"REAL GPS: {df['track'].nunique()} Kubicka tracks as fused drives with the five "
        f"outages, at {rates}; scored on the fixes placed on a road where the truth is known. "
        f"The matcher runs with the confidence model off (it reports the road probability); "
        f"the model's probability is computed from the same features per fix, as the matcher "
        f"computes it. The model is fitted {how} by maximum likelihood with an L2 prior whose "
        f"weight is chosen by the out-of-fold log-loss; out of fold over {df['fold'].nunique()} "
        f"folds by track (`bench/folds.py`, seed {folds.SEED}): the coefficients are fitted on "
        f"four folds and applied to the fifth, with the threshold chosen on the four folds' own "
        f"out-of-fold probabilities. The threshold is the least `measurement.min_probability` "
        f"whose wrong share among usable fixes is at most {100 * cfit.WRONG_USABLE_TARGET:g} % "
        f"at each rate, judged out of fold; usable is the matcher's test on the probability "
        f"(configured: `measurement.min_probability` {cfg.measurement.min_probability:g}). ECE "
        f"over the bins of the reliability tables and over 20 bins of equal numbers of fixes. "
        f"Load average {load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end "
        f"({os.cpu_count()} cores).\n"
    )


def calibration_report(df: pd.DataFrame, cfg: MatchConfig, *, load0: float, pooled: bool = True) -> str:
    """``--calibration``: the figures, trade-off curve, fitted coefficients, each term left
    out and the reliability tables of each rate, as markdown."""
    df = df.reset_index(drop=True)
    groups = [df] if pooled else [g for _, g in df.groupby("hz")]
    summary = [
        "| rate | probability | fixes | ECE | ECE (equal-mass) | log-loss | usable fixes "
        "| wrong share among usable | share of right fixes usable |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    shares = " | ".join(f"at {100 * s:g} %" for s in cfit.WRONG_SHARES)
    curve = [f"| rate | probability | {shares} |", "|---|---|" + "---|" * len(cfit.WRONG_SHARES)]
    tables, fits, ablation = [], [], []
    for grp in groups:
        fit = cfit.fit_model(grp, cfg, pooled=pooled)
        name = "all rates" if pooled else f"{grp['hz'].iloc[0]:g} Hz"
        fits.append(
            f"\nModel fitted on {name} (L2 prior weight {fit.ridge:g}):\n\n{cfit.coefficient_table(fit)}"
        )
        ablation += cfit.without_each_term(grp, cfg, pooled=pooled, ridge=fit.ridge)
        for hz, g in grp.groupby("hz"):
            text, figures = calibration_summary(g.reset_index(drop=True), _local(fit, grp, g), cfg)
            rows, crows = _figure_rows(float(hz), len(g), figures)
            summary += rows
            curve += crows
            tables.append(f"\nReliability at {hz:g} Hz ({len(g)} fixes):\n{text}")
            q_cfg = calibration.logistic_apply(cfit.configured(cfg), cfit.features(g, cfg.confidence))
            diag = wrong_breakdown(g.assign(usable=cfit.gate(g, q_cfg, cfg.measurement.min_probability)))
            if diag:
                tables.append(f"\nWrong fixes at {hz:g} Hz:\n\n{diag}")
    return (
        calibration_head(df, cfg, pooled=pooled, load0=load0)
        + "\n".join(
            [
                "",
                *summary,
                "",
                "Share of right fixes usable at a wrong share among usable fixes "
                "of at most (the best single threshold on each probability, all tracks; the out-of-fold "
                "row is the trade-off curve on tracks the model has not seen):",
                "",
                *curve,
            ]
        )
        + "\n"
        + "\n".join(fits)
        + "\n\nOut of fold, with each term left out (thresholds chosen as above):\n\n"
        + "\n".join(_ablation_lines(ablation))
        + "\n"
        + "\n".join(tables)
        + "\n"
    )


def _local(fit: cfit.ModelFit, grp: pd.DataFrame, g: pd.DataFrame) -> cfit.ModelFit:
    """``fit`` (of the fixes of ``grp``) restricted to the fixes of ``g``, a part of it,
    indexed from 0 like ``g`` after its index is reset."""
    k = grp.index.get_indexer(g.index)
    return cfit.ModelFit(
        fit.ridge, fit.q_in[k], fit.u_in[k], fit.q_oof[k], fit.u_oof[k], fit.coef, fit.threshold, fit.rows
    )


def run_calibration(names: list[str], cfg: MatchConfig, args: argparse.Namespace) -> str:
    """``--calibration``: collect (or load with ``--load-fixes``) the per-fix table, print and
    return the report."""
    load0 = os.getloadavg()[0]
    if args.load_fixes is not None:
        parts = [pd.read_csv(f, dtype={"track": str, "kind": str}) for f in args.load_fixes]
        df = pd.concat(parts, ignore_index=True)
    else:
        df = collect_calibration(names, cfg, args)
    if args.save_fixes is not None:
        tmp = args.save_fixes.with_name(f".{args.save_fixes.name}.tmp")
        df.to_csv(tmp, index=False)
        os.replace(tmp, args.save_fixes)
    text = calibration_report(df, cfg, load0=load0, pooled=not args.per_rate)
    print(text)
    return text


def load_graph(folder: Path, cache: Path | None) -> RoadGraph:
    """The map of a track, built from its ``roads.geojson`` (saved in and read from ``cache``)."""
    if cache is not None and (cache / f"{folder.name}.map").is_file():
        return load_map(cache / f"{folder.name}.map")
    graph = build_map(folder / "roads.geojson")
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        save_map(graph, cache / f"{folder.name}.map")
    return graph


def parse_args() -> argparse.Namespace:
    """The command line of this bench."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tracks", nargs="*", default=None, help="track folder names (default: all)")
    ap.add_argument("--rates", nargs="*", type=float, default=None, help="Hz (default: 1 and 10)")
    ap.add_argument("--no-gps-only", action="store_true", help="skip the drives without outages")
    ap.add_argument("--breakdown", action="store_true", help="classify the wrong-road fixes")
    ap.add_argument("--json", type=Path, default=None, help="also write all rows here")
    ap.add_argument("--map-cache", type=Path, default=None, help="keep the prepared maps in this folder")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE", help="matcher parameters")
    ap.add_argument("--docs", action="store_true", help="also write the table to docs/benchmarks/")
    ap.add_argument(
        "--cv",
        action="store_true",
        help="cross-validate --grid over the folds of bench/folds.py (outages; 1 Hz unless --rates)",
    )
    ap.add_argument("--grid", nargs="*", default=list(CV_GRID), metavar="SECTION.FIELD=V1,V2,...")
    ap.add_argument(
        "--calibration",
        action="store_true",
        help="reliability of the reported road probability, in-sample and out of fold (outages)",
    )
    ap.add_argument(
        "--per-rate", action="store_true", help="--calibration: fit per rate (default: pooled over the rates)"
    )
    ap.add_argument("--save-fixes", type=Path, default=None, help="--calibration: write the per-fix table")
    ap.add_argument(
        "--load-fixes", type=Path, nargs="+", default=None, help="--calibration: read them instead of running"
    )
    return ap.parse_args()


def run_drives(names: list[str], cfg: MatchConfig, args: argparse.Namespace) -> list[dict[str, object]]:
    """Every track's drive at each rate, GPS-only and with the outages: one printed row each."""
    rows: list[dict[str, object]] = []
    for name in names:
        folder = KUBICKA / name
        t0 = time.perf_counter()
        graph = load_graph(folder, args.map_cache)
        matcher = OnlineMatcher(graph, config=cfg)
        if not rows:  # warm-up: compile the kernels before anything is timed
            run_drive(matcher, real_drive(graph, folder, rate_hz=1.0, outages=True, seed=0))
        print(f"# {name}: {graph.n_edges} edges, built in {time.perf_counter() - t0:.1f} s", flush=True)
        for rate in args.rates:
            for outages in (False, True) if not args.no_gps_only else (True,):
                row = run_one(graph, matcher, folder, rate=rate, outages=outages, seed=int(name))
                rows.append(row)
                print(
                    f"{name} {rate:4.0f} Hz outages {row['outages']}: fixes {row['fixes']}, "
                    f"junctions {row['jn_gps_live']}/{row['jn_gps']} gps, "
                    f"{row['jn_out_live']}/{row['jn_out']} "
                    f"outage (live); correct road {_pct(row['ok_live'], row['scored'])} live, "  # type: ignore[arg-type]
                    f"{_pct(row['ok_fin'], row['scored'])} corrected (of {row['scored']} scored); "  # type: ignore[arg-type]
                    f"outage end {_q(row['end_live'])}",  # type: ignore[arg-type]
                    flush=True,
                )
    return rows


def print_rows(rows: list[dict[str, object]], *, docs: bool) -> None:
    """The table summed over drives and the per-fix update time (``docs``: also as a fragment)."""
    print("\n## REAL GPS (Kubicka), summed over drives\n")
    print(table(rows))
    us = np.concatenate([np.asarray(r["us"]) for r in rows])
    timing = (
        f"per-fix update time (in-process, not the speed benchmark): median {np.median(us):.1f} µs, "
        f"p99 {np.percentile(us, 99):.1f} µs, {len(us)} fixes"
    )
    print(f"\n{timing}")
    if docs:
        from report import run_header, write_fragment

        fragment = f"{run_header()}{table(rows)}\n\n{timing}."
        print(f"wrote {write_fragment('online_real', fragment)}")


def print_breakdown(rows: list[dict[str, object]]) -> None:
    """The wrong-road fixes by class, per rate, GPS-only or with outages, live and corrected."""
    for tag in ("live", "fin"):
        for hz, with_out in sorted({(float(r["hz"]), bool(r["outages"])) for r in rows}):  # type: ignore[arg-type]
            kinds: dict[str, int] = {}
            n = 0
            for r in rows:
                if r["hz"] != hz or bool(r["outages"]) != with_out:
                    continue
                n += int(r["scored"])  # type: ignore[call-overload]
                for k, v in r[f"breakdown_{tag}"].items():  # type: ignore[attr-defined]
                    kinds[k] = kinds.get(k, 0) + v
            what = "with outages" if with_out else "GPS only"
            print(f"\n## wrong-road fixes by class, {hz:g} Hz {what}, {tag}, of {n} scored fixes")
            for k, v in sorted(kinds.items(), key=lambda kv: -kv[1]):
                print(f"{v:7d} {100.0 * v / max(n, 1):5.2f} %  {k}")


def cv_fragment(rates: list[float]) -> str:
    """The docs fragment of ``--cv --docs`` at these rates: ``cv_online`` at 1 Hz, else named by
    the rates (``cv_online_10hz``), so a run at other rates keeps the 1 Hz table."""
    if [float(r) for r in rates] == [1.0]:
        return "cv_online"
    return "cv_online_" + "_".join(f"{r:g}hz" for r in rates)


def run(args: argparse.Namespace) -> int:
    """Check the options, then run the mode asked for; the exit status."""
    try:
        cfg = DEFAULT_CONFIG.with_settings(args.set)
    except ConfigError as exc:
        print(f"error: --set: {exc}", file=sys.stderr)
        return 2
    if not KUBICKA.is_dir():
        print(f"error: needs the shared Kubicka tracks in {KUBICKA}", file=sys.stderr)
        return 2
    names = args.tracks or folds.track_ids(KUBICKA)
    if args.rates is None:
        args.rates = [1.0] if args.cv else [1.0, 10.0]
    if args.calibration:
        text = run_calibration(names, cfg, args)
        if args.docs:
            from report import run_header, write_fragment

            print(f"wrote {write_fragment('calibration', run_header() + text)}")
        return 0
    if args.cv:
        try:
            text = run_cv(names, cfg, args)
        except (ConfigError, ValueError) as exc:
            print(f"error: --grid: {exc}", file=sys.stderr)
            return 2
        if args.docs:
            from report import run_header, write_fragment

            print(f"wrote {write_fragment(cv_fragment(args.rates), run_header() + text)}")
        return 0
    rows = run_drives(names, cfg, args)
    print_rows(rows, docs=args.docs)
    if args.breakdown:
        print_breakdown(rows)
    if args.json:
        for r in rows:
            r.pop("us")
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


def main() -> int:
    """Parse the command line and run the bench."""
    return run(parse_args())


if __name__ == "__main__":
    sys.exit(main())
