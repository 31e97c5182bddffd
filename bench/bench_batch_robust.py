"""Batch matching robustness on REAL GPS: ours and the peers on more than one sub-sampling.

``bench_batch.py`` scores every S-th fix from fix 0, one draw of many. Here, on the shared Kubicka
tracks (1 Hz GPS with true routes, the peers' prepared work dirs), every engine matches
stress sets of runs (``bench/peers_robust.py`` defines them):

  phases  every S-th fix (S = 10, 30) from each start offset 0, 3, 6, ... < S, between the
          track's first and last fix;
  gaps    every 30th fix with one long gap cut out per run, from sub-fix g0 = 5, 30, 55, ...
          until the next kept fix is at least G m (3 km, 8 km) from g0 in a straight line,
          as a logger switched off while driving;
  noise   every S-th fix (S = 1, 10, 30) of the real track with extra drifting position error
          of σ N m (10, 20) added: real routes and fixes, SIMULATED extra error;
  jumps   every S-th fix (S = 1, 10) with SIMULATED multipath jumps: bursts of 1-5 s, starting
          at J % (1, 3) of the fixes, displaced 50-200 m.

Every run is scored by the peers' ``score.py`` (RMF, 3 m) with the run's own first and last fix.
Ours runs in this process (``bench/peers_adapter.py``), each peer in its own Python by
``bench/peers_robust.py`` as ``bench_batch.py`` runs ``peers_timing.py``. Prints per engine and
set: runs, mean, median and worst RMF, runs returned in more than one connected piece (split) or none,
and for phases the mean of offset 0 alone (the main bench's draw). One JSON line per run goes to
``--out``.

    python bench/bench_batch_robust.py                                # all 15 tracks, all engines
    python bench/bench_batch_robust.py --ids 0,21 --engines custom,osrm --sets gaps
    python bench/bench_batch_robust.py --summary ~/.cache/mapmatch-peers/results/robust.jsonl
    python bench/bench_batch_robust.py --sets phases --S 60,120,300 --step 1000   # sparse tracks
    python bench/bench_batch_robust.py --sets noise --noise 10,20                 # a worse receiver
    python bench/bench_batch_robust.py --sets jumps --jumps 1,3                   # multipath bursts
    python bench/bench_batch_robust.py --engines custom --set batch.route.route_speed=0 --sets phases --S 120
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import peers_adapter  # noqa: E402
from bench_batch import CACHE, PEERS, ROOT, WORK, engine_python, work_tracks, worker_env  # noqa: E402
from peers_robust import add_run_args, run_track  # noqa: E402

ENGINES = ("custom", "osrm", "valhalla", "fastmm")
WORKER = HERE / "peers_robust.py"


def installed(engines: list[str]) -> list[str]:
    """The engines whose Python runs and can load the engine (``peers_robust.py --check``)."""
    ok = []
    for eng in engines:
        if eng == "custom":
            ok.append(eng)
            continue
        py = engine_python(eng)
        r = None
        if Path(py).exists():
            cmd = [py, str(WORKER), eng, "--check", "--peers", str(PEERS)]
            r = subprocess.run(cmd, env=worker_env(), capture_output=True, text=True)
        if r is not None and r.returncode == 0:
            ok.append(eng)
        else:
            print(f"{eng}: not installed ({py}), left out", file=sys.stderr)
    return ok


def run_args(a: argparse.Namespace) -> list[str]:
    return [
        *("--sets", a.sets, "--S", a.S, "--step", str(a.step), "--gap-S", str(a.gap_S)),
        *("--gaps", a.gaps, "--gap-first", str(a.gap_first), "--gap-every", str(a.gap_every)),
        *("--noise", a.noise, "--noise-S", a.noise_S, "--noise-tau", str(a.noise_tau)),
        *("--jumps", a.jumps, "--jumps-S", a.jumps_S),
    ]


def run_ours(name: str, a: argparse.Namespace) -> list[dict[str, Any]]:
    rows = list(run_track(peers_adapter, WORK / name, a, str(PEERS), "custom"))
    gc.unfreeze()  # the adapter froze the map's objects; let this track's map go
    gc.collect()
    return rows


def run_peer(eng: str, name: str, a: argparse.Namespace) -> list[dict[str, Any]]:
    out = WORK / name / f"robust_{eng}.jsonl"
    out.unlink(missing_ok=True)
    cmd = [engine_python(eng), str(WORKER), eng, str(WORK / name), str(out), "--peers", str(PEERS)]
    try:
        r = subprocess.run(
            [*cmd, *run_args(a)], env=worker_env(), capture_output=True, text=True, timeout=a.timeout
        )
        if r.returncode != 0:
            print(f"{eng} on {name} failed: {r.stderr.strip().splitlines()[-3:]}", file=sys.stderr)
    except subprocess.TimeoutExpired:
        print(f"{eng} on {name}: timed out after {a.timeout:.0f} s, its runs so far kept", file=sys.stderr)
    if not out.exists():
        return []
    return [json.loads(x) for x in out.read_text().splitlines() if x.strip()]


def run(a: argparse.Namespace, engines: list[str], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w") as f:
        for name in work_tracks(a.ids):
            for eng in engines:
                t0 = time.perf_counter()
                rows = run_ours(name, a) if eng == "custom" else run_peer(eng, name, a)
                for row in rows:
                    f.write(json.dumps(row) + "\n")
                f.flush()
                dt = time.perf_counter() - t0
                print(f"{name} {eng}: {len(rows)} runs, {dt:.0f} s", file=sys.stderr, flush=True)


def summarise(path: Path) -> None:
    rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    by: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        if r["set"] == "phases":
            label = f"S={r['S']}"
        elif r["set"] in ("noise", "jumps"):
            label = f"{'N' if r['set'] == 'noise' else 'J'}={r['N']:g} S={r['S']}"
        else:
            label = f"G={r['G'] / 1000:g} km"
        by[(r["engine"], r["set"], label)].append(r)
    order = {e: i for i, e in enumerate(ENGINES)}

    def numbers(label: str) -> list[float]:  # "S=30", "G=3 km", "N=10 S=30": by number, not text
        return [float(w.split("=")[1]) for w in label.split() if "=" in w]

    rank = {"phases": 0, "gaps": 1, "noise": 2, "jumps": 3}
    keys = sorted(by, key=lambda k: (order.get(k[0], len(order)), k[0], rank.get(k[1], 3), numbers(k[2])))
    print(
        f"\n{'engine':9s} {'set':7s} {'S, G, N':>9s} {'runs':>5s} {'mean RMF':>9s} {'median':>8s} "
        f"{'worst':>7s} {'offset 0':>9s} {'split':>6s} {'none':>5s} {'failed':>6s}"
    )
    for eng, set_, label in keys:
        g = by[(eng, set_, label)]
        rmf = [1.0 if r.get("rmf") is None else r["rmf"] for r in g]  # a failed match scores 1
        off0 = [x for x, r in zip(rmf, g, strict=True) if r["offset"] == 0]
        first = f"{statistics.fmean(off0):9.4f}" if set_ == "phases" and off0 else f"{'':9s}"
        print(
            f"{eng:9s} {set_:7s} {label:>9s} {len(g):5d} {statistics.fmean(rmf):9.4f} "
            f"{statistics.median(rmf):8.4f} {max(rmf):7.4f} {first} {sum(r['pieces'] > 1 for r in g):6d} "
            f"{sum(r['pieces'] == 0 for r in g):5d} {sum(bool(r.get('failed')) for r in g):6d}"
        )
    print(
        "\nREAL GPS (Kubicka). RMF by the peers' score.py (3 m), a failed run counts 1; worst: the "
        "largest RMF of a run; offset 0: the mean of the runs from fix 0 alone (bench_batch.py's "
        "draw); split: the route came back in more than one connected piece; none: no route; "
        "failed: no route or an error. The noise and jumps sets are REAL GPS with SIMULATED extra "
        "error (N m, J % bursts)."
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--engines", help=f"default: all of {','.join(ENGINES)} that are installed")
    ap.add_argument("--out", type=Path, default=CACHE / "results" / "robust.jsonl", help="per-run rows")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per peer and track")
    ap.add_argument("--summary", type=Path, help="only summarise this file of an earlier run")
    ap.add_argument(
        "--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
        help="a setting of our batch config (repeatable), e.g. --set batch.route.route_speed=25",
    )  # fmt: skip
    add_run_args(ap)
    a = ap.parse_args()
    if a.set:
        from mapmatch.batch import BATCH_CONFIG
        from mapmatch.errors import ConfigError

        try:
            BATCH_CONFIG.with_settings(a.set)  # the adapter's config: fail here, not per track
        except ConfigError as exc:
            print(f"--set: {exc}", file=sys.stderr)
            return 2
        os.environ[peers_adapter.SETTINGS_ENV] = ",".join(a.set)
    if a.summary:
        summarise(a.summary)
        return 0
    if not PEERS.is_dir() or not WORK.is_dir():
        print(f"needs the peers folder {PEERS} and their work dirs {WORK}", file=sys.stderr)
        return 2
    engines = installed(a.engines.split(",") if a.engines else list(ENGINES))
    print(f"engines {','.join(engines)}; this tree {ROOT}; load average {os.getloadavg()[0]:.2f}")
    run(a, engines, a.out)
    print(f"rows: {a.out}")
    summarise(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
