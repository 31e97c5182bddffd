"""Batch matching against the peers (Valhalla, OSRM, fastmm) on the shared Kubicka tracks.

Runs ``../shared/peers/run_peers.py`` (or ``$MAPMATCH_PEERS/run_peers.py``) with our matcher as the
custom engine (``bench/peers_adapter.py``), so every engine is timed the same way (the match call
only, map loaded) and scored by the peers' ``score.py``. Prints mean RMF and points/s per engine and S,
the ratio of our points/s to fastmm's, and our time per point on the largest vs the smallest map.

    python bench/bench_batch.py                       # all 15 tracks, S = 1, 10, 30
    python bench/bench_batch.py --ids 0,21 --engines custom,fastmm     # a quick check
    python bench/bench_batch.py --summary ~/.cache/mapmatch-peers/results/batch.jsonl
    python bench/bench_batch.py --routing --ids 0,28      # bounded search vs UBODT, in process
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PEERS = Path(os.environ.get("MAPMATCH_PEERS", ROOT.parent / "shared" / "peers"))
CACHE = Path(os.path.expanduser("~/.cache/mapmatch-peers"))
PEERS_PY = CACHE / "venvs" / "venv" / "bin" / "python"


def run(ids: str, engines: str, S: str, tag: str) -> Path:
    env = dict(os.environ)
    env["MM_PEERS_CUSTOM"] = str(ROOT / "bench" / "peers_adapter.py")
    env["MM_PEERS_CUSTOM_PY"] = sys.executable
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [str(PEERS_PY), str(PEERS / "run_peers.py"), "--engines", engines, "--S", S, "--tag", tag]
    if ids != "all":
        cmd += ["--ids", ids]
    subprocess.run(cmd, env=env, check=True)
    return CACHE / "results" / f"{tag}.jsonl"


def summarise(paths: list[Path]) -> None:
    recs = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line.strip()]
    recs = [r for r in recs if not r.get("skipped")]
    by: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for r in recs:
        by[(r["engine"], int(r["S"]))].append(r)
    print(
        f"\n{'engine':10s} {'S':>3s} {'tracks':>6s} {'fail':>4s} {'mean RMF':>9s} "
        f"{'points':>8s} {'pts/s':>10s}"
    )
    rate: dict[tuple[str, int], float] = {}
    for (eng, s), g in sorted(by.items(), key=lambda kv: (kv[0][0] != "custom", kv[0][0], kv[0][1])):
        rmf = [r["rmf"] if r.get("rmf") is not None else 1.0 for r in g]
        timed = [r for r in g if r.get("match_s")]
        pts = sum(r["n_points"] for r in timed)
        secs = sum(r["match_s"] for r in timed)
        rate[(eng, s)] = pts / secs if secs else 0.0
        fails = sum(1 for r in g if r.get("failed"))
        print(
            f"{eng:10s} {s:3d} {len(g):6d} {fails:4d} {sum(rmf) / len(rmf):9.4f} "
            f"{pts:8d} {rate[(eng, s)]:10.0f}"
        )
    for s in sorted({s for _, s in by}):
        ours, fm = rate.get(("custom", s)), rate.get(("fastmm", s))
        if ours and fm:
            print(f"S={s:2d}: our points/s / fastmm points/s = {ours / fm:.2f}")
    ours_recs = [r for r in recs if r["engine"] == "custom" and r.get("match_s")]
    if ours_recs:
        big = max(ours_recs, key=lambda r: r["arcs"])["arcs"]
        small = min(ours_recs, key=lambda r: r["arcs"])["arcs"]
        for s in sorted({r["S"] for r in ours_recs}):
            b = [r for r in ours_recs if r["arcs"] == big and r["S"] == s]
            m = [r for r in ours_recs if r["arcs"] == small and r["S"] == s]
            if b and m:
                ub, um = b[0]["match_s"] / b[0]["n_points"] * 1e6, m[0]["match_s"] / m[0]["n_points"] * 1e6
                print(
                    f"S={s:2d}: time per point on the largest map ({big} arcs) {ub:.2f} us, "
                    f"smallest ({small} arcs) {um:.2f} us, ratio {ub / um:.2f}"
                )


def compare_routing(ids: str, S: str, deltas: str) -> None:
    """Bounded Dijkstra vs UBODT tables: build time, size, points/s (best of 5), same routes."""
    import time

    import numpy as np

    sys.path.insert(0, str(ROOT / "bench"))
    import peers_adapter  # type: ignore[import-not-found]

    from mapmatch.batch import BatchMatcher
    from mapmatch.io import Columns, read_tracks
    from mapmatch.routing import Ubodt

    data = ROOT.parent / "shared" / "data" / "kubicka"
    names = sorted(p.name for p in data.iterdir() if p.is_dir())
    if ids != "all":
        names = [n for n in names if int(n) in {int(x) for x in ids.split(",")}]
    for name in names:
        graph = peers_adapter.load_graph(data / name)
        (track,) = read_tracks(data / name / "track.csv", columns=Columns(time="t"))
        variants: list[tuple[str, BatchMatcher]] = [("search", BatchMatcher(graph))]
        for d in (float(x) for x in deltas.split(",")):
            t0 = time.perf_counter()
            table = Ubodt.build(graph, d)
            build = time.perf_counter() - t0
            print(
                f"{name} edges={graph.n_edges} UBODT {d:.0f} m: "
                f"build {build:.2f} s, {table.nbytes / 1e6:.0f} MB"
            )
            variants.append((f"ubodt{d:.0f}", BatchMatcher(graph, ubodt=table)))
        for s in (int(x) for x in S.split(",")):
            idx = np.arange(0, len(track), s)
            sub = type(track)(track.track_id, track.time[idx], track.lat[idx], track.lon[idx])
            ref = variants[0][1].match(sub).routes
            row = []
            for label, m in variants:
                best = min(_timed(m, sub) for _ in range(5))
                same = m.match(sub).routes == ref
                row.append(f"{label} {len(idx) / best:9.0f} pts/s{'' if same else ' (DIFFERENT ROUTE)'}")
            print(f"  S={s:2d}: " + " | ".join(row))


def _timed(m: object, track: object) -> float:
    import time

    t0 = time.perf_counter()
    m.match(track)  # type: ignore[attr-defined]
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--engines", default="custom,osrm,valhalla,fastmm")
    ap.add_argument("--S", default="1,10,30")
    ap.add_argument("--tag", default="batch")
    ap.add_argument("--summary", nargs="+", type=Path, help="only summarise these result files")
    ap.add_argument("--routing", action="store_true", help="compare bounded search and UBODT in process")
    ap.add_argument("--deltas", default="1000,2000,3000", help="UBODT bounds in metres for --routing")
    a = ap.parse_args()
    if a.routing:
        compare_routing(a.ids, a.S, a.deltas)
        return 0
    if not PEERS.is_dir():
        print(f"needs the peers folder {PEERS}", file=sys.stderr)
        return 2
    paths = a.summary or [run(a.ids, a.engines, a.S, a.tag)]
    summarise(paths)
    return 0


if __name__ == "__main__":
    sys.exit(main())
