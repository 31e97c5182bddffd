"""Accuracy of a match against the truth: the metrics and their table.

* **Intersection traversal accuracy** (the seed thesis): the true sequence of junctions passed
  and the matched one are aligned optimally (a longest common subsequence, rapidfuzz's
  ``LCSseq``; difflib's greedy longest-block alignment paired a route that drives a loop twice
  with the wrong pass); the accuracy is the share of true junctions found in the alignment,
  the precision the share of matched junctions that are true. A junction is a node with at
  least three distinct neighbours (where a driver has a choice); ``junctions_only=False``
  counts every node.
* **Correct-edge rate** per fix: the matched directed edge equals the true one. The reverse twin
  of a two-way road counts as wrong (the direction of travel is part of the answer); an
  unmatched fix counts as wrong.
* **Route mismatch fraction** (Newson & Krumm 2009), geometrically: :mod:`mapmatch.route_score`.
* **Snapped position error**: distance between each snapped position and the true position.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from rapidfuzz.distance import LCSseq

from graph.index import project_to_edge
from graph.projection import to_lonlat, to_xy
from graph.road_graph import RoadGraph
from mapmatch.errors import ValidationError
from mapmatch.route_score import RouteMismatch, path_geometry, route_mismatch, split_parts
from mapmatch.routing import shortest_path
from mapmatch.types import Correction, Fix, SnapResult

# --------------------------------------------------------------------------- paths and nodes


def edge_path(
    graph: RoadGraph,
    edges: ArrayLike,
    *,
    times: ArrayLike | None = None,
    max_speed: float = 40.0,
    slack_m: float = 50.0,
    max_gap_m: float = 3000.0,
) -> list[int]:
    """The driven edge path from per-fix edges: repeats and -1 dropped, gaps closed.

    Consecutive distinct edges that do not join are connected by the shortest legal path when
    it is drivable in the time between the two fixes (``max_speed`` · Δt + ``slack_m``; without
    ``times``, up to ``max_gap_m``); otherwise the path jumps, as the reported edges did.
    """
    e_arr = np.asarray(edges).astype(np.int64)
    t_arr = np.zeros(len(e_arr)) if times is None else np.asarray(times, dtype=np.float64)
    path: list[int] = []
    last_t = 0.0
    for e, t in zip(e_arr.tolist(), t_arr.tolist(), strict=True):
        if e < 0:
            continue
        if path and path[-1] == e:
            last_t = t
            continue
        if path and int(graph.edge_v[path[-1]]) != int(graph.edge_u[e]):
            bound = max_gap_m if times is None else min(max_gap_m, max_speed * (t - last_t) + slack_m)
            gap = shortest_path(graph, path[-1], int(graph.edge_u[e]), max_cost=bound)
            if gap:
                path.extend(gap)
        path.append(e)
        last_t = t
    return path


def is_junction(graph: RoadGraph) -> NDArray[np.bool_]:
    """Nodes with at least three distinct neighbours."""
    a = np.concatenate([graph.edge_u, graph.edge_v]).astype(np.int64)
    b = np.concatenate([graph.edge_v, graph.edge_u]).astype(np.int64)
    pairs = np.unique(a * graph.n_nodes + b)
    deg = np.bincount(pairs // graph.n_nodes, minlength=graph.n_nodes)
    return np.asarray(deg >= 3)


def path_nodes(graph: RoadGraph, path: Sequence[int], *, junctions_only: bool = True) -> list[int]:
    """Nodes passed along an edge path (between its edges; both ends at a jump)."""
    nodes: list[int] = []
    for a, b in itertools.pairwise(path):
        va, ub = int(graph.edge_v[a]), int(graph.edge_u[b])
        nodes.append(va)
        if ub != va:
            nodes.append(ub)
    if junctions_only:
        j = is_junction(graph)
        nodes = [n for n in nodes if j[n]]
    return nodes


@dataclass(frozen=True)
class IntersectionScore:
    """Aligned junction sequences: ``correct`` of ``true`` found, of ``matched`` reported."""

    true: int
    matched: int
    correct: int

    @property
    def accuracy(self) -> float:
        return self.correct / self.true if self.true else float("nan")

    @property
    def precision(self) -> float:
        return self.correct / self.matched if self.matched else float("nan")


def intersection_score(true_nodes: Sequence[int], matched_nodes: Sequence[int]) -> IntersectionScore:
    """Align the true and the matched junction sequences (a longest common subsequence) and
    count the agreement."""
    correct = int(LCSseq.similarity(list(true_nodes), list(matched_nodes)))
    return IntersectionScore(true=len(true_nodes), matched=len(matched_nodes), correct=correct)


def matched_junctions(true_nodes: Sequence[int], matched_nodes: Sequence[int]) -> NDArray[np.bool_]:
    """Which of the true junctions the aligned matched sequence found (as :func:`intersection_score`)."""
    found = np.zeros(len(true_nodes), dtype=bool)
    for b in LCSseq.editops(list(true_nodes), list(matched_nodes)).as_matching_blocks():
        found[b.a : b.a + b.size] = True
    return found


# --------------------------------------------------------------------------- matched results


def matched_edges_dense(graph: RoadGraph, matched: pd.DataFrame) -> NDArray[np.int64]:
    """Dense edge index per matched row, from ``edge`` or else from external ``u``, ``v``, ``way_id``."""
    if "edge" in matched.columns:
        e = pd.to_numeric(matched["edge"], errors="coerce").fillna(-1).to_numpy(dtype=np.int64)
        if len(e) and e.max() >= graph.n_edges:
            raise ValidationError(
                "edge", "matched edge index outside the map: was it matched on another map?"
            )
        return e
    if not {"u", "v"} <= set(matched.columns):
        raise ValidationError("matched", "needs an 'edge' column or 'u' and 'v' node ids")
    lookup: dict[tuple[int, int, int], int] = {}
    uid = graph.node_id[graph.edge_u]
    vid = graph.node_id[graph.edge_v]
    ptr, ways = graph.piece_ptr.tolist(), graph.piece_way_id.tolist()
    for i, (a, b) in enumerate(zip(uid.tolist(), vid.tolist(), strict=True)):
        for w in ways[ptr[i] : ptr[i + 1]]:  # an answer names the way piece under the point
            lookup.setdefault((a, b, w), i)
        lookup.setdefault((a, b, -2), i)
    way = matched["way_id"] if "way_id" in matched.columns else pd.Series(-2, index=matched.index)
    out = np.full(len(matched), -1, dtype=np.int64)
    for i, (a, b, w) in enumerate(zip(matched["u"], matched["v"], way, strict=True)):
        if pd.isna(a) or pd.isna(b) or int(a) < 0:
            continue
        key = (int(a), int(b), -2 if pd.isna(w) else int(w))
        out[i] = lookup.get(key, lookup.get((int(a), int(b), -2), -1))
    return out


def align_by_time(t_truth: ArrayLike, t_match: ArrayLike, *, tol: float = 0.05) -> NDArray[np.int64]:
    """For each matched time the index of the truth row at that time (-1 when none)."""
    tt = np.asarray(t_truth, dtype=np.float64)
    tm = np.asarray(t_match, dtype=np.float64)
    i = np.clip(np.searchsorted(tt, tm), 1, max(len(tt) - 1, 1)) if len(tt) > 1 else np.zeros(len(tm), int)
    if len(tt) > 1:
        left = i - 1
        use_left = np.abs(tt[left] - tm) <= np.abs(tt[i] - tm)
        i = np.where(use_left, left, i)
    ok = np.abs(tt[i] - tm) <= tol if len(tt) else np.zeros(len(tm), dtype=bool)
    return np.where(ok, i, -1).astype(np.int64)


def _text(col: pd.Series) -> pd.Series:
    """A column as text, empty where missing (an all-empty CSV column reads as float NaN)."""
    return col.astype(object).where(col.notna(), "").astype(str)


def apply_corrections(graph: RoadGraph, matched: pd.DataFrame) -> pd.DataFrame:
    """The matched rows as revised by the corrections the matcher emitted later.

    A correction says that from ``correction_from`` to ``correction_to`` the vehicle was on
    ``correction`` (edges in order, ``;``-separated), each from its ``correction_times`` entry
    on. Each row in that span is moved to the edge of its time (without ``correction_times``:
    the nearest of those edges to its raw position, else its snapped one) and re-snapped there.
    Later corrections override earlier ones.
    """
    if "correction" not in matched.columns or "correction_from" not in matched.columns:
        return matched
    out = matched.copy()
    out["edge"] = matched_edges_dense(graph, out)
    times = out["time"].to_numpy(dtype=np.float64)
    src = "raw" if {"raw_lat", "raw_lon"} <= set(out.columns) else ""
    lat = pd.to_numeric(out[f"{src}_lat" if src else "lat"], errors="coerce").to_numpy(float).copy()
    lon = pd.to_numeric(out[f"{src}_lon" if src else "lon"], errors="coerce").to_numpy(float).copy()
    miss = np.isnan(lat)
    lat[miss] = pd.to_numeric(out["lat"], errors="coerce").to_numpy(float)[miss]
    lon[miss] = pd.to_numeric(out["lon"], errors="coerce").to_numpy(float)[miss]
    ok = ~np.isnan(lat) & ~np.isnan(lon)
    xy = np.full((len(out), 2), np.nan)
    if ok.any():
        xy[ok] = to_xy(graph.crs, lon[ok], lat[ok])
    new_edge = out["edge"].to_numpy(dtype=np.int64).copy()
    snapped = np.full((len(out), 2), np.nan)
    touched = np.zeros(len(out), dtype=bool)
    corr = _text(out["correction"])
    starts = _text(out["correction_times"]) if "correction_times" in out.columns else None
    for i in np.flatnonzero(corr.str.strip() != "").tolist():
        try:
            edges = [int(e) for e in corr.iloc[i].split(";") if e.strip()]
            t0, t1 = float(out["correction_from"].iloc[i]), float(out["correction_to"].iloc[i])
            begins = [float(v) for v in starts.iloc[i].split(";") if v.strip()] if starts is not None else []
        except ValueError:
            continue
        if len(begins) != len(edges) or not all(0 <= e < graph.n_edges for e in edges):
            begins = []
        edges = [e for e in edges if 0 <= e < graph.n_edges]
        if not edges:
            continue
        for j in np.flatnonzero((times >= t0 - 1e-6) & (times <= t1 + 1e-6) & ok).tolist():
            cands = edges
            if begins:  # the edge of this fix's time
                cands = [Correction(t0, t1, tuple(edges), (), tuple(begins)).edge_at(times[j] + 1e-6)]
            best = min(
                (project_to_edge(graph, e, float(xy[j, 0]), float(xy[j, 1])) + (e,) for e in cands),
                key=lambda r: r[1],
            )
            new_edge[j] = best[4]
            snapped[j] = best[2], best[3]
            touched[j] = True
    out["edge"] = new_edge
    if touched.any():
        ll = to_lonlat(graph.crs, snapped[touched, 0], snapped[touched, 1])
        out.loc[touched, "lat"] = ll[:, 1]
        out.loc[touched, "lon"] = ll[:, 0]
    return out


@dataclass
class Metrics:
    """Every metric of one evaluation, and the table that prints them."""

    fixes: int
    intersections: IntersectionScore
    correct_edge_rate: float
    correct_edge_rate_gps: float
    correct_edge_rate_outage: float
    unmatched_fraction: float
    rmf: RouteMismatch
    tolerance_m: float
    snap_error_mean: float
    snap_error_median: float
    snap_error_p95: float
    fused_error_mean: float = float("nan")
    fused_error_outage_max: float = float("nan")
    corrections: int = 0
    corrected: Metrics | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def rows(self) -> list[tuple[str, str]]:
        s = self.intersections

        def pct(x: float) -> str:
            return "n/a" if np.isnan(x) else f"{100.0 * x:.1f} %"

        def m(x: float) -> str:
            return "n/a" if np.isnan(x) else f"{x:.1f} m"

        return [
            ("fixes", str(self.fixes)),
            ("intersection traversal accuracy", f"{pct(s.accuracy)} ({s.correct}/{s.true} true junctions)"),
            ("intersection precision", f"{pct(s.precision)} ({s.correct}/{s.matched} matched junctions)"),
            ("correct edge, all fixes", pct(self.correct_edge_rate)),
            ("correct edge, GPS valid", pct(self.correct_edge_rate_gps)),
            ("correct edge, GPS outage", pct(self.correct_edge_rate_outage)),
            ("unmatched fixes", pct(self.unmatched_fraction)),
            (
                f"route mismatch fraction (tol {self.tolerance_m:g} m)",
                f"{pct(self.rmf.fraction)} (missing {self.rmf.missing_m:.0f} m, "
                f"extra {self.rmf.extra_m:.0f} m of {self.rmf.truth_m:.0f} m)",
            ),
            (
                "snapped position error mean / median / p95",
                f"{m(self.snap_error_mean)} / {m(self.snap_error_median)} / {m(self.snap_error_p95)}",
            ),
            (
                "fused input error mean / max in outage",
                f"{m(self.fused_error_mean)} / {m(self.fused_error_outage_max)}",
            ),
            ("corrections emitted", str(self.corrections)),
        ] + (
            []
            if self.corrected is None
            else [
                ("after corrections: intersection accuracy", pct(self.corrected.intersections.accuracy)),
                ("after corrections: intersection precision", pct(self.corrected.intersections.precision)),
                ("after corrections: correct edge", pct(self.corrected.correct_edge_rate)),
                ("after corrections: route mismatch fraction", pct(self.corrected.rmf.fraction)),
            ]
        )

    def table(self) -> str:
        rows = self.rows()
        w = max(len(k) for k, _ in rows)
        line = "-" * (w + 2 + max(len(v) for _, v in rows))
        return "\n".join([line] + [f"{k.ljust(w)}  {v}" for k, v in rows] + [line])


@dataclass(frozen=True, slots=True)
class Scoring:
    """How :func:`evaluate` scores.

    Attributes
    ----------
    tolerance_m : float
        Tolerance of the route mismatch fraction (metres).
    junctions_only : bool
        Count only junctions in the intersection accuracy.
    with_corrections : bool
        Also score the results with the emitted corrections applied.
    """

    tolerance_m: float = 2.0
    junctions_only: bool = True
    with_corrections: bool = True


def evaluate(
    graph: RoadGraph,
    *,
    truth: pd.DataFrame,
    matched: pd.DataFrame,
    truth_path: Sequence[int] | None = None,
    truth_xy: ArrayLike | None = None,
    fixes: pd.DataFrame | None = None,
    scoring: Scoring = Scoring(),
) -> Metrics:
    """Score a match against the truth (as reported live and, when corrections were emitted,
    after applying them: :attr:`Metrics.corrected`).

    Parameters
    ----------
    graph
        The map both refer to (dense edge indices).
    truth
        One row per fix: ``time``, ``edge`` and the true ``x``, ``y`` (or ``lat``, ``lon``);
        ``gps_outage`` (0/1) when known.
    matched
        One row per fix: ``time``, ``edge`` (or ``u``, ``v``, ``way_id``) and the snapped
        ``lat``, ``lon``; ``correction`` (non-empty when a correction was emitted) optional.
    truth_path, truth_xy
        The true edge path and route polyline; derived from the per-fix truth when omitted.
    fixes
        The fused input (``lat``, ``lon``), to report its own error too.
    scoring
        The route tolerance, which nodes count, and whether corrections are scored too.
    """
    a = _aligned(graph, truth, matched)
    correct, outage = a.per_truth == a.t_edge, a.outage

    def rate(mask: NDArray[np.bool_]) -> float:
        return float(correct[mask].mean()) if mask.any() else float("nan")

    tpath = list(truth_path) if truth_path is not None else edge_path(graph, a.t_edge, times=a.t_time)
    mpath = edge_path(graph, a.m_edge, times=a.m_time)
    score = intersection_score(
        path_nodes(graph, tpath, junctions_only=scoring.junctions_only),
        path_nodes(graph, mpath, junctions_only=scoring.junctions_only),
    )
    tgeo = _truth_geometry(graph, truth, tpath, truth_xy)
    sxy = _snapped_xy(graph, matched)
    mgeo = _matched_geometry(graph, mpath, a.m_edge, sxy)
    rmf = route_mismatch(tgeo, mgeo, tolerance_m=scoring.tolerance_m)
    ok, mi = a.mi >= 0, a.mi
    err = np.full(len(matched), np.nan)
    err[ok] = np.hypot(*(sxy[ok] - a.txy[mi[ok]]).T)
    e = err[~np.isnan(err)]
    fused_mean, fused_out = _fused_error(graph, fixes, a.t_time, a.txy, outage)
    ncorr = _corrections(matched)
    corrected = None
    if scoring.with_corrections and ncorr:
        corrected = evaluate(
            graph,
            truth=truth,
            matched=apply_corrections(graph, matched),
            truth_path=truth_path,
            truth_xy=truth_xy,
            scoring=replace(scoring, with_corrections=False),
        )
    return Metrics(
        fixes=len(truth),
        intersections=score,
        correct_edge_rate=rate(np.ones(len(truth), dtype=bool)),
        correct_edge_rate_gps=rate(~outage),
        correct_edge_rate_outage=rate(outage),
        unmatched_fraction=float((a.per_truth < 0).mean()) if len(truth) else float("nan"),
        rmf=rmf,
        tolerance_m=scoring.tolerance_m,
        snap_error_mean=float(e.mean()) if len(e) else float("nan"),
        snap_error_median=float(np.median(e)) if len(e) else float("nan"),
        snap_error_p95=float(np.percentile(e, 95)) if len(e) else float("nan"),
        fused_error_mean=fused_mean,
        fused_error_outage_max=fused_out,
        corrections=ncorr,
        corrected=corrected,
    )


@dataclass(frozen=True)
class _Aligned:
    """The truth's and the match's per-fix arrays, and for each matched row its truth row
    (``mi``, -1: none) and for each truth row its matched edge (``per_truth``, -1: none)."""

    t_time: NDArray[np.float64]
    txy: NDArray[np.float64]
    t_edge: NDArray[np.int64]
    outage: NDArray[np.bool_]
    m_edge: NDArray[np.int64]
    m_time: NDArray[np.float64]
    mi: NDArray[np.int64]
    per_truth: NDArray[np.int64]


def _aligned(graph: RoadGraph, truth: pd.DataFrame, matched: pd.DataFrame) -> _Aligned:
    for col in ("time", "edge"):
        if col not in truth.columns:
            raise ValidationError("truth", f"missing column {col!r}")
    if "time" not in matched.columns:
        raise ValidationError("matched", "missing column 'time'")
    t_time = truth["time"].to_numpy(dtype=np.float64)
    outage = (
        truth["gps_outage"].to_numpy(dtype=bool)
        if "gps_outage" in truth.columns
        else np.zeros(len(truth), bool)
    )
    m_edge = matched_edges_dense(graph, matched)
    m_time = matched["time"].to_numpy(dtype=np.float64)
    mi = align_by_time(t_time, m_time)
    # a truth row without a match counts as unmatched
    per_truth = np.full(len(truth), -1, dtype=np.int64)
    ok = mi >= 0
    per_truth[mi[ok]] = m_edge[ok]
    t_edge = truth["edge"].to_numpy(dtype=np.int64)
    return _Aligned(t_time, _truth_xy(graph, truth), t_edge, outage, m_edge, m_time, mi, per_truth)


def _truth_geometry(
    graph: RoadGraph, truth: pd.DataFrame, tpath: list[int], truth_xy: ArrayLike | None
) -> NDArray[np.float64]:
    """The true route's polyline: as given, else along the true path from the first fix's
    offset to the last's."""
    if truth_xy is not None:
        return np.asarray(truth_xy, dtype=np.float64)
    o0 = float(truth["offset"].iloc[0]) if "offset" in truth.columns else 0.0
    o1 = float(truth["offset"].iloc[-1]) if "offset" in truth.columns else None
    return path_geometry(graph, tpath, start_offset=o0, end_offset=o1)


def _truth_xy(graph: RoadGraph, truth: pd.DataFrame) -> NDArray[np.float64]:
    """The true positions in the map's CRS (``x``, ``y``, else ``lon``, ``lat`` projected)."""
    if "x" in truth.columns:
        return truth[["x", "y"]].to_numpy(dtype=np.float64)
    return to_xy(graph.crs, truth["lon"].to_numpy(float), truth["lat"].to_numpy(float))


def _snapped_xy(graph: RoadGraph, matched: pd.DataFrame) -> NDArray[np.float64]:
    """The snapped positions in the map's CRS (NaN where not given)."""
    sxy = np.full((len(matched), 2), np.nan)
    if "lat" in matched.columns and "lon" in matched.columns:
        lat = pd.to_numeric(matched["lat"], errors="coerce").to_numpy(float)
        lon = pd.to_numeric(matched["lon"], errors="coerce").to_numpy(float)
        have = ~np.isnan(lat) & ~np.isnan(lon)
        if have.any():
            sxy[have] = to_xy(graph.crs, lon[have], lat[have])
    return sxy


def _matched_geometry(
    graph: RoadGraph, mpath: list[int], m_edge: NDArray[np.int64], sxy: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The matched route's polyline, from the first matched fix's place to the last's."""
    if not mpath:
        return np.empty((0, 2))
    valid = np.flatnonzero(m_edge >= 0)
    i0, i1 = valid[0], valid[-1]
    o0 = o1 = 0.0
    if not np.isnan(sxy[i0, 0]):
        o0 = project_to_edge(graph, int(m_edge[i0]), float(sxy[i0, 0]), float(sxy[i0, 1]))[0]
    if not np.isnan(sxy[i1, 0]):
        o1 = project_to_edge(graph, int(m_edge[i1]), float(sxy[i1, 0]), float(sxy[i1, 1]))[0]
    else:
        o1 = float(graph.edge_len[mpath[-1]])
    if mpath[0] != int(m_edge[i0]):
        o0 = 0.0
    if mpath[-1] != int(m_edge[i1]):
        o1 = float(graph.edge_len[mpath[-1]])
    return path_geometry(graph, mpath, start_offset=o0, end_offset=o1)


def _fused_error(
    graph: RoadGraph,
    fixes: pd.DataFrame | None,
    t_time: NDArray[np.float64],
    txy: NDArray[np.float64],
    outage: NDArray[np.bool_],
) -> tuple[float, float]:
    """The fused input's mean error and its largest error in an outage (NaN: not known)."""
    if fixes is None or not len(fixes):
        return float("nan"), float("nan")
    fi = align_by_time(t_time, fixes["time"].to_numpy(float))
    fok = fi >= 0
    fxy = to_xy(graph.crs, fixes["lon"].to_numpy(float), fixes["lat"].to_numpy(float))
    fe = np.hypot(*(fxy[fok] - txy[fi[fok]]).T)
    fo = outage[fi[fok]]
    return (float(fe.mean()) if len(fe) else float("nan")), (
        float(fe[fo].max()) if fo.any() else float("nan")
    )


def _corrections(matched: pd.DataFrame) -> int:
    """How many answers emitted a correction."""
    if "correction" not in matched.columns:
        return 0
    c = matched["correction"]
    return int((c.notna() & (c.astype(str).str.strip() != "") & (c.astype(str) != "0")).sum())


def results_frame(
    vehicle_id: str, fixes: Sequence[Fix], results: Sequence[SnapResult | None]
) -> pd.DataFrame:
    """Matched rows as ``mapmatch replay`` writes them (:data:`mapmatch.fixes.RESULT_COLUMNS`), in memory."""
    from mapmatch.fixes import RESULT_COLUMNS, result_row

    rows = [result_row(vehicle_id, f, r) for f, r in zip(fixes, results, strict=True)]
    df = pd.DataFrame(rows, columns=list(RESULT_COLUMNS))
    for col in ("time", "edge", "offset", "lat", "lon", "u", "v", "way_id"):
        df[col] = pd.to_numeric(df[col], errors="coerce")
    df["edge"] = df["edge"].fillna(-1).astype(np.int64)
    return df


def read_matched_csv(path: str | os.PathLike[str], *, vehicle_id: str | None = None) -> pd.DataFrame:
    """A results CSV from ``mapmatch replay`` (one vehicle: the given one or the only one)."""
    try:
        df = pd.read_csv(path, dtype={"correction": str, "correction_replaced": str, "candidates": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as exc:
        raise ValidationError("matched", f"{path} is not a readable results CSV ({exc})") from None
    if "vehicle_id" in df.columns:
        ids = df["vehicle_id"].astype(str).unique().tolist()
        if vehicle_id is not None:
            df = df[df["vehicle_id"].astype(str) == vehicle_id]
        elif len(ids) > 1:
            raise ValidationError("vehicle_id", f"{path} holds {len(ids)} vehicles; name one")
    if "time" not in df.columns:
        raise ValidationError("matched", f"{path}: missing column 'time'")
    return df.reset_index(drop=True)


# --------------------------------------------------------------------------- the route of online results


def route_lonlat_from_results(graph: RoadGraph, matched: pd.DataFrame) -> list[NDArray[np.float64]]:
    """The route driven according to online results (``mapmatch replay``/``send`` rows), lon/lat.

    The per-fix edges are joined by :func:`edge_path` (gaps closed by the shortest legal path
    drivable in the time between the fixes); corrections are applied first.
    """
    df = apply_corrections(graph, matched) if "correction" in matched.columns else matched
    edges = matched_edges_dense(graph, df)
    path = edge_path(graph, edges, times=df["time"].to_numpy(dtype=np.float64))
    xy = path_geometry(graph, path)
    return [to_lonlat(graph.crs, p[:, 0], p[:, 1]) for p in split_parts(xy) if len(p) >= 2]
