"""Per-fix ``OnlineMatcher.update`` time of two source trees, alternately, on a shared machine.

One run of ``bench_online.py`` on a busy machine says little: its median moves by 20 % with
the load and its p99 is the scheduler's time slice. This replays the speed bench's drive
(10 Hz SIMULATED, the paper's outages) in a fresh process per tree and round, ``--reps`` times
each, and keeps every fix's least time over the repeats (what the code costs, not the
machine's load); the rounds alternate the trees, so both see the same load. Each line gives
the median, p99 and mean of those least times.

    python bench/bench_online_ab.py --base /tmp/base-tree --maps helsinki 00000028
    # the base tree: e.g. ``git archive main | tar -x -C /tmp/base-tree``; the Kubicka maps
    # are read from ``../shared`` of each tree (link it there)

Both trees run with this interpreter; ``--fixes`` replays only the first fixes of the drive.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
sys.path.insert(0, sys.argv[1] + "/bench")
import numpy as np
import bench_online as bo
from mapmatch.online import OnlineMatcher

name, reps, n = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
import contextlib, io
with contextlib.redirect_stdout(io.StringIO()):
    g = bo.load(name)
route = bo.random_route(g, length_m=15000.0, rng=np.random.default_rng(1))
fixes = bo.simulate_drive(g, route, rate=10.0, outages="paper", seed=1).fix_objects()[:n]
m = OnlineMatcher(g)
clock = time.perf_counter_ns
best = np.full(len(fixes), np.inf)
for rep in range(reps + 1):  # the first: warm-up
    st = m.new_session()
    ts = np.empty(len(fixes))
    for i, f in enumerate(fixes):
        t0 = clock()
        m.update(st, f)
        ts[i] = clock() - t0
    if rep:
        best = np.minimum(best, ts * 1e-3)
print(f"median {np.median(best):6.1f} µs, p99 {np.percentile(best, 99):6.1f} µs, "
      f"mean {best.mean():6.1f} µs ({len(fixes)} fixes)")
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", type=Path, required=True, help="the other source tree")
    ap.add_argument("--new", type=Path, default=ROOT, help="this tree by default")
    ap.add_argument("--maps", nargs="*", default=["helsinki", "00000028"])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reps", type=int, default=4, help="replays per process (least time per fix)")
    ap.add_argument("--fixes", type=int, default=10**9)
    args = ap.parse_args()
    for name in args.maps:
        for r in range(args.rounds):
            for label, tree in (("base", args.base), ("new", args.new)):
                out = subprocess.run(
                    [sys.executable, "-c", CHILD, str(tree.resolve()), name, str(args.reps), str(args.fixes)],
                    cwd=tree,
                    capture_output=True,
                    text=True,
                    check=True,
                ).stdout.strip()
                print(f"{name:>9} round {r + 1} {label:>4}: {out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
