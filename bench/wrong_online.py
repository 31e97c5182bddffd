"""Where the online matcher is on the wrong road, and why its position is off at an outage's end.

Runs every shared Kubicka track as a fused drive with the five outages
(:func:`mapmatch.sim.realgps.real_drive`, as ``bench_online_real.py``) through
``OnlineMatcher.update`` and keeps one row per fix (``--save``: a CSV, re-read with ``--load``
without running), then breaks the wrong-road fixes (live, where the truth is known; the right
road as ``bench_online_real.right_road`` scores it) down by

* GPS or outage (and the first ``RECOVERY_S`` seconds after one), start-up (the first
  ``STARTUP_S`` seconds) or just after a re-initialisation;
* place: within ``NEAR_M`` metres along the true route of a junction (split by its class, as
  the vehicle meets it: ``cross`` four or more arms, ``T``, ``fork`` two branches ahead
  within ``FORK_DEG`` of straight on and neither straight, ``ramp`` one branch straight on and
  the other within ``FORK_DEG`` of it, ``merge`` the vehicle's road meets another at a small
  angle) or mid-edge;
* what the answer is: on the true route but behind the true edge (held on the incoming road
  too long) or ahead of it (switched early), on a branch leaving the route at a junction near
  the vehicle (wrong branch), on a road alongside (within ``bench_online_real.PARALLEL_M`` at a
  similar bearing), the reverse edge, other;
* track;

and the error at each outage's end into along-track and cross-track parts (along the true
heading), with the share explained by the odometer's scale error left (the drive's scale error
less the matcher's learnt correction, times the distance driven in the outage) and whether
the answer is on the wrong road there.

    python bench/wrong_online.py --map-cache /tmp/maps --save /tmp/wrong1.csv
    python bench/wrong_online.py --load /tmp/wrong1.csv             # report from the table
    python bench/wrong_online.py --load /tmp/wrong1.csv --docs      # and write the fragment
    python bench/wrong_online.py --rates 10 --map-cache /tmp/maps --save /tmp/wrong10.csv
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import folds  # noqa: E402
from bench_online_real import (  # noqa: E402
    KUBICKA,
    RECOVERY_S,
    STARTUP_S,
    load_graph,
    outage_clock,
    right_road,
    snapped_xy,
    wrong_kinds,
)

from graph.road_graph import RoadGraph  # noqa: E402
from mapmatch.config import DEFAULT_CONFIG, MatchConfig  # noqa: E402
from mapmatch.online import OnlineMatcher  # noqa: E402
from mapmatch.sim.drive import Drive  # noqa: E402
from mapmatch.sim.realgps import real_drive  # noqa: E402
from mapmatch.types import State  # noqa: E402

NEAR_M = 40.0
"""Metres along the true route from a junction within which a fix is "near" it."""
FORK_DEG = 45.0
"""Branches ahead within this of straight on make a fork (or ramp)."""
STRAIGHT_DEG = 12.0
"""A branch within this of straight on goes straight on (the main road past a ramp)."""
REINIT_S = 30.0
"""Seconds after a re-initialisation that count as "just after" one."""


def _diff(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def node_arms(graph: RoadGraph, node: int) -> list[tuple[int, float]]:
    """The roads at ``node``: (neighbour node, bearing leaving ``node`` towards it), one per
    neighbour."""
    arms: dict[int, float] = {}
    for e in np.flatnonzero(graph.edge_u == node).tolist():
        arms.setdefault(int(graph.edge_v[e]), float(graph.edge_bearing_start[e]))
    for e in np.flatnonzero(graph.edge_v == node).tolist():
        arms.setdefault(int(graph.edge_u[e]), (float(graph.edge_bearing_end[e]) + 180.0) % 360.0)
    return list(arms.items())


def junction_class(graph: RoadGraph, e_in: int, e_out: int) -> str:
    """The class of the node between route edges ``e_in`` and ``e_out`` as the vehicle meets
    it (see the module docstring); ``""`` for a node that is no junction."""
    node = int(graph.edge_v[e_in])
    arms = node_arms(graph, node)
    if len(arms) <= 2:
        return ""
    if len(arms) >= 4:
        return "cross"
    came = int(graph.edge_u[e_in])
    back = (float(graph.edge_bearing_end[e_in]) + 180.0) % 360.0  # towards where it came from
    heading = float(graph.edge_bearing_end[e_in])
    ahead = [abs(_diff(b, heading)) for n, b in arms if n != came]
    others = [b for n, b in arms if n != came]
    if len(ahead) == 2 and max(ahead) <= FORK_DEG:
        return "ramp" if min(ahead) <= STRAIGHT_DEG else "fork"
    if any(abs(_diff(b, back)) <= FORK_DEG for b in others):
        return "merge"
    return "T"


def route_junctions(graph: RoadGraph, drive: Drive) -> tuple[np.ndarray, list[str]]:
    """Route distance of each node between consecutive route edges that is a junction, and
    its class."""
    route = drive.route.edges
    s, cls = [], []
    for k in range(len(route) - 1):
        c = junction_class(graph, int(route[k]), int(route[k + 1]))
        if c:
            s.append(float(drive.route.edge_start[k + 1]))
            cls.append(c)
    return np.array(s), cls


def place_of(graph: RoadGraph, drive: Drive) -> tuple[np.ndarray, np.ndarray]:
    """Per fix: the signed route distance to the nearest junction (negative: before it) and
    its class, ``mid-edge`` beyond ``NEAR_M``."""
    js, cls = route_junctions(graph, drive)
    s = drive.truth["route_s"].to_numpy()
    out_d = np.full(len(s), np.nan)
    out_c = np.full(len(s), "mid-edge", dtype=object)
    if len(js) == 0:
        return out_d, out_c
    k = np.clip(np.searchsorted(js, s), 1, len(js)) if len(js) > 1 else np.ones(len(s), dtype=int)
    for i in range(len(s)):
        cand = [j for j in (k[i] - 1, min(k[i], len(js) - 1)) if 0 <= j < len(js)]
        j = min(cand, key=lambda j: abs(s[i] - js[j]))
        out_d[i] = s[i] - js[j]
        if abs(out_d[i]) <= NEAR_M:
            out_c[i] = cls[j]
    return out_d, out_c


def answer_kind(graph: RoadGraph, drive: Drive, edges: np.ndarray, wrong: np.ndarray) -> np.ndarray:
    """Per wrong fix, what the answer is (see the module docstring): ``behind`` / ``ahead`` on
    the route, ``wrong branch``, ``parallel``, ``reverse``, ``other``, ``unmatched``."""
    tr = drive.truth
    route = drive.route.edges
    pos: dict[int, list[int]] = {}
    for i, e in enumerate(route.tolist()):
        pos.setdefault(e, []).append(i)
    rs = tr["route_s"].to_numpy()
    ridx = np.clip(np.searchsorted(drive.route.edge_start, rs, side="right") - 1, 0, len(route) - 1)
    kinds = wrong_kinds(graph, drive, edges)
    te = tr["edge"].to_numpy()
    route_nodes = set(graph.edge_u[route].tolist()) | set(graph.edge_v[route].tolist())
    out = np.full(len(edges), "", dtype=object)
    for i in np.flatnonzero(wrong).tolist():
        e, k = int(edges[i]), int(ridx[i])
        if e < 0:
            out[i] = "unmatched"
        elif e in pos and any(abs(j - k) <= 3 for j in pos[e]):
            j = min(pos[e], key=lambda j: abs(j - k))
            out[i] = "behind" if j < k else "ahead"
        elif int(graph.edge_reverse[te[i]]) == e:
            out[i] = "reverse"
        elif "parallel" in kinds[i]:
            out[i] = "parallel"
        elif int(graph.edge_u[e]) in route_nodes:
            out[i] = "wrong branch"
        else:
            out[i] = "other"
    return out


def drive_rows(matcher: OnlineMatcher, drive: Drive, *, track: str, rate: float) -> pd.DataFrame:
    """One row per fix of ``drive`` run through ``matcher`` (a new session)."""
    graph = matcher.graph
    state = matcher.new_session()
    res, odo_k, odo_ksd = [], [], []
    for f in drive.fix_objects():
        res.append(matcher.update(state, f))
        odo_k.append(state.anchor.odo_k)
        odo_ksd.append(math.sqrt(state.anchor.odo_kvar))
    tr = drive.truth
    t = tr["time"].to_numpy() - float(tr["time"].iloc[0])
    edges = np.array([r.edge for r in res], dtype=np.int64)
    known = tr["truth_known"].to_numpy(dtype=bool)
    right = right_road(drive, edges)
    gout, since = outage_clock(drive)
    reinit = np.array([r.state == State.REINITIALISED for r in res])
    last_re = np.maximum.accumulate(np.where(reinit, t, -np.inf))
    dist, jcls = place_of(graph, drive)
    wrong = known & ~right
    xy = snapped_xy(graph, res)
    txy = tr[["x", "y"]].to_numpy()
    rad = np.radians(tr["heading"].to_numpy(dtype=float))
    dx, dy = xy[:, 0] - txy[:, 0], xy[:, 1] - txy[:, 1]
    odo = np.cumsum(np.nan_to_num(drive.fused.distance))
    return pd.DataFrame(
        {
            "track": track,
            "hz": rate,
            "t": t,
            "known": known,
            "right": right,
            "gps": ~gout,
            "since_outage": since,
            "since_reinit": t - last_re,
            "state": [r.state.name for r in res],
            "n_cands": [len(r.candidates) for r in res],
            "p": [r.map_aided.probability if r.map_aided is not None else math.nan for r in res],
            "edge": edges,
            "true_edge": tr["edge"].to_numpy(),
            "junction_d": dist,
            "junction": jcls,
            "answer": answer_kind(graph, drive, edges, wrong),
            "along_err": dx * np.sin(rad) + dy * np.cos(rad),
            "cross_err": dx * np.cos(rad) - dy * np.sin(rad),
            "odo": odo,
            "odo_k": odo_k,
            "odo_ksd": odo_ksd,
            "true_scale": drive.sensors.true_odo_scale,
            "outage_end": _outage_end_mask(drive),
        }
    )


def _outage_end_mask(drive: Drive) -> np.ndarray:
    """The last fix of each outage (as ``bench_online_real.outage_end_errors`` picks it)."""
    t = drive.truth["time"].to_numpy() - float(drive.truth["time"].iloc[0])
    out = np.zeros(len(t), dtype=bool)
    for a, d in drive.outages:
        if a + d > t[-1]:
            continue
        i = int(np.searchsorted(t, a + d - 1e-6)) - 1
        if 0 <= i < len(t):
            out[i] = True
    return out


def collect(names: list[str], cfg: MatchConfig, args: argparse.Namespace) -> pd.DataFrame:
    """Every track's drive with the outages at each rate: the per-fix table."""
    parts = []
    for n, name in enumerate(names):
        folder = KUBICKA / name
        graph = load_graph(folder, args.map_cache)
        matcher = OnlineMatcher(graph, config=cfg)
        for rate in args.rates:
            drive = real_drive(graph, folder, rate_hz=rate, outages=True, seed=int(name))
            parts.append(drive_rows(matcher, drive, track=name, rate=rate))
        print(f"# {n + 1}/{len(names)} {name}: load {os.getloadavg()[0]:.2f}", flush=True)
    return pd.concat(parts, ignore_index=True)


def situation(g: pd.DataFrame) -> pd.Series:
    """Per fix: start-up, outage, after an outage, after a re-initialisation, or GPS."""
    s = np.where(g["gps"], "GPS", "outage")
    s = np.where(g["gps"] & (g["since_outage"] <= RECOVERY_S), "GPS, just after an outage", s)
    s = np.where(g["since_reinit"] <= REINIT_S, "just after a re-initialisation", s)
    s = np.where(g["t"] < STARTUP_S, "start-up", s)
    return pd.Series(s, index=g.index)


def _count_table(title: str, wrong: pd.Series, every: pd.Series, n_scored: int) -> list[str]:
    """A markdown table: wrong fixes per value, their share of the wrong and of the scored
    fixes, and the wrong share among the scored fixes of that value."""
    lines = [
        f"| {title} | wrong fixes | share of the wrong | of all scored fixes | wrong share there |",
        "|---|---|---|---|---|",
    ]
    n_wrong = len(wrong)
    counts = wrong.value_counts()
    base = every.value_counts()
    for k, v in counts.items():
        lines.append(
            f"| {k} | {v} | {100 * v / max(n_wrong, 1):.1f} % | {100 * v / max(n_scored, 1):.2f} % "
            f"| {100 * v / max(int(base.get(k, 0)), 1):.2f} % |"
        )
    return lines


def report(df: pd.DataFrame) -> str:
    """The breakdown of each rate as markdown."""
    out = []
    for hz, g in df.groupby("hz"):
        g = g[g["known"].astype(bool)].copy()
        g["situation"] = situation(g)
        g["where"] = g["junction"].fillna("mid-edge")
        w = g[~g["right"].astype(bool)]
        n = len(g)
        out.append(
            f"\n### {hz:g} Hz: {len(w)} wrong-road fixes of {n} scored ({100 * len(w) / n:.2f} %), "
            f"{df[df['hz'] == hz]['track'].nunique()} tracks\n"
        )
        out += _count_table("situation", w["situation"], g["situation"], n)
        out.append("")
        out += _count_table("place (true position)", w["where"], g["where"], n)
        out.append("")
        out += _count_table("answer", w["answer"], g["answer"], n)
        out.append("")
        gw = w[w["situation"] == "GPS"]
        cross = pd.crosstab(gw["where"], gw["answer"])
        out.append("With GPS (not start-up, outage or re-initialisation), place by answer:\n")
        out.append("| place | " + " | ".join(cross.columns) + " |")
        out.append("|---|" + "---|" * len(cross.columns))
        for k, row in cross.iterrows():
            out.append(f"| {k} | " + " | ".join(str(int(v)) for v in row.tolist()) + " |")
        out.append("")
        per = w.groupby("track").size().sort_values(ascending=False)
        top = per.head(5)
        out.append(
            "By track: "
            + ", ".join(f"{k} {v} ({100 * v / len(w):.0f} %)" for k, v in top.items())
            + f"; {int((per > 0).sum())} of {g['track'].nunique()} tracks have any; the 2 worst "
            f"hold {100 * per.head(2).sum() / max(len(w), 1):.0f} %, the 5 worst "
            f"{100 * top.sum() / max(len(w), 1):.0f} %."
        )
        out.append("")
        out += outage_end_report(df[df["hz"] == hz])
    return "\n".join(out)


def outage_end_report(d: pd.DataFrame) -> list[str]:
    """The error at each outage's end split into along- and cross-track, and the part the
    odometer's scale error left explains."""
    rows = []
    for track, g in d.groupby("track"):
        t = g["t"].to_numpy()
        gps = g["gps"].to_numpy()
        odo = g["odo"].to_numpy()
        for i in np.flatnonzero(g["outage_end"].to_numpy()).tolist():
            j = i
            while j > 0 and not gps[j - 1]:
                j -= 1
            start = max(j - 1, 0)
            left = (1.0 + float(g["true_scale"].iloc[i])) * (1.0 + float(g["odo_k"].iloc[start])) - 1.0
            along, cross = float(g["along_err"].iloc[i]), float(g["cross_err"].iloc[i])
            rows.append(
                {
                    "end": f"{track} at {t[i]:.0f} s",
                    "err": math.hypot(along, cross),
                    "along": along,
                    "cross": cross,
                    "scale_m": left * (odo[i] - odo[start]),
                    "wrong": bool(g["known"].iloc[i]) and not bool(g["right"].iloc[i]),
                    "dur": t[i] - t[start],
                    "dist": odo[i] - odo[start],
                }
            )
    e = pd.DataFrame(rows).dropna(subset=["err"])
    if e.empty:
        return []
    big = e[e["err"] > 6.0]
    lines = [
        f"Outage ends: {len(e)}; error median {e['err'].median():.1f} m, p90 "
        f"{np.percentile(e['err'], 90):.1f} m; |along-track| median {e['along'].abs().median():.1f} m, "
        f"p90 {np.percentile(e['along'].abs(), 90):.1f} m; |cross-track| median "
        f"{e['cross'].abs().median():.1f} m, p90 {np.percentile(e['cross'].abs(), 90):.1f} m. "
        f"Of the {len(big)} ends over 6 m: {int(big['wrong'].sum())} on the wrong road; along-track the "
        f"larger part in {int((big['along'].abs() >= big['cross'].abs()).sum())}; the odometer's "
        f"scale error left (drive's scale error less the learnt correction, times the distance "
        f"driven in the outage) median {big['scale_m'].abs().median():.1f} m against an "
        f"along-track error median {big['along'].abs().median():.1f} m there.",
        "",
        "| outage end | error | along-track | cross-track | scale error left × distance | wrong road |",
        "|---|---|---|---|---|---|",
    ]
    for _, r in e.sort_values("err", ascending=False).head(12).iterrows():
        lines.append(
            f"| {r['end']} | {r['err']:.1f} m | {r['along']:+.1f} m | {r['cross']:+.1f} m | "
            f"{r['scale_m']:+.1f} m | {'yes' if r['wrong'] else 'no'} |"
        )
    return lines


def main() -> int:
    """Run (or load) and report."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tracks", nargs="*", default=None)
    ap.add_argument("--rates", nargs="*", type=float, default=[1.0])
    ap.add_argument("--map-cache", type=Path, default=None)
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE")
    ap.add_argument("--save", type=Path, default=None, help="write the per-fix table (CSV)")
    ap.add_argument("--load", type=Path, default=None, help="report from a saved table")
    ap.add_argument("--docs", action="store_true", help="also write the report as the fragment wrong_online")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    if args.load is not None:
        df = pd.read_csv(args.load, dtype={"track": str})
    else:
        if not KUBICKA.is_dir():
            print(f"error: needs the shared Kubicka tracks in {KUBICKA}", file=sys.stderr)
            return 2
        cfg = DEFAULT_CONFIG.with_settings(args.set)
        df = collect(args.tracks or folds.track_ids(KUBICKA), cfg, args)
        if args.save is not None:
            tmp = args.save.with_name(f".{args.save.name}.tmp")
            df.to_csv(tmp, index=False)
            os.replace(tmp, args.save)
    text = (
        f"REAL GPS: {df['track'].nunique()} Kubicka tracks as fused drives with the five outages; "
        f"live answers, scored where the truth is known. Load average {load0:.2f} at the start, "
        f"{os.getloadavg()[0]:.2f} at the end ({os.cpu_count()} cores).\n" + report(df)
    )
    print(text)
    if args.docs:
        from report import run_header, write_fragment

        print(f"wrote {write_fragment('wrong_online', run_header() + text)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
