"""Server CPU per online update of two source trees, loaded side by side, on a shared machine.

On a busy 2-core machine one ``bench_service.py`` run's CPU per update moves by 20-30 % with
the load, more than most changes to the per-fix path. This starts one server from each tree
(``mapmatch serve`` on the Helsinki map, ``--batch-processes 0``) and drives both at the same
time with the same paced load (``--vehicles`` streams at ``--rate`` Hz each, SIMULATED random
walks, from ``bench_service.py``'s client processes), so both see the same load; the rounds
swap which server starts first. Each line gives each tree's server CPU per update, its p99
latency and the load average; the last line the median difference over the rounds.

    git -C /work/main worktree add /tmp/base main     # or: git archive main | tar -x -C /tmp/base
    python bench/bench_service_ab.py --base /tmp/base --rounds 4
    python bench/bench_service_ab.py --base /tmp/base --session-store redis://127.0.0.1:6379/0

Both servers use this interpreter; ``--session-store`` gives both the same Redis (their
vehicle ids differ; its database is emptied before each round).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_service import Phase, ServerTree, drives, helsinki_map, run_phase  # noqa: E402


def start(tree: Path, extra: list[str]) -> tuple[subprocess.Popen[str], int]:
    """``mapmatch serve`` of ``tree`` on a free loopback port."""
    cmd = [
        sys.executable, "-m", "mapmatch", "serve", "--map", f"helsinki={helsinki_map()}",
        "--address", "127.0.0.1:0", "--max-sessions", "4000", "--no-reuse-port",
        "--batch-processes", "0", *extra,
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(tree)}
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=tree)
    assert p.stdout is not None
    line = p.stdout.readline()
    if "listening on" not in line:
        p.kill()
        raise SystemExit(f"server of {tree} failed to start: {line!r}")
    return p, int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])


def one_round(trees: list[Path], paced: list[list[Any]], args: argparse.Namespace) -> list[dict[str, float]]:
    """Both servers under the same paced load at once: CPU per update and p99 of each."""
    extra = [] if not args.session_store else ["--session-store", args.session_store]
    if args.session_store:  # every round starts its vehicles afresh, not from the last round's records
        import redis

        with redis.Redis.from_url(args.session_store) as db:
            db.flushdb()
    servers = [start(t, extra) for t in trees]
    try:
        tree_cpu = [ServerTree(p.pid, 1) for p, _ in servers]
        for sp in tree_cpu:
            sp.settle(quiet=2.0, timeout=60.0)
        phase = [Phase(args.rate, 1, args.warmup + args.seconds, 1, f"v{i}") for i in range(2)]
        res: list[dict[str, Any]] = [{}, {}]

        def go(i: int) -> None:
            res[i] = run_phase(servers[i][1], paced, phase[i], server=tree_cpu[i])

        threads = [threading.Thread(target=go, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        for p, _ in servers:
            p.terminate()
        for p, _ in servers:
            p.wait(30)
    out = []
    for r in res:
        steady = r["at"] >= args.warmup
        out.append(
            {
                "cpu_us": 1e6 * r["cpu_s"] / max(r["n"], 1),
                "p99": float(np.percentile(r["lat"][steady] * 1000.0, 99)) if steady.any() else float("nan"),
                "errors": r["errors"],
            }
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", type=Path, required=True, help="the other source tree (A); this one is B")
    ap.add_argument("--vehicles", type=int, default=100, help="streams per server")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--seconds", type=float, default=11.0, help="measured seconds (latency)")
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--session-store", default="", help="redis://... for both servers")
    args = ap.parse_args()
    trees = [args.base.resolve(), ROOT]
    steps = int((args.warmup + args.seconds) * args.rate) + 10
    paced = drives(helsinki_map(), args.vehicles, steps, rate=args.rate, seed=1)
    print(f"# A {trees[0]}, B {trees[1]}: {args.vehicles} streams x {args.rate:g} Hz each, side by side")
    diffs = []
    for k in range(args.rounds):
        order = [0, 1] if k % 2 == 0 else [1, 0]
        got = one_round([trees[i] for i in order], paced, args)
        a, b = (got[order.index(0)], got[order.index(1)])
        diffs.append(b["cpu_us"] - a["cpu_us"])
        print(
            f"round {k + 1}: A {a['cpu_us']:.0f} µs (p99 {a['p99']:.1f} ms), B {b['cpu_us']:.0f} µs "
            f"(p99 {b['p99']:.1f} ms), B - A {diffs[-1]:+.0f} µs; errors {a['errors']}/{b['errors']} "
            f"(load {os.getloadavg()[0]:.2f})",
            flush=True,
        )
    print(f"median B - A over {len(diffs)} rounds: {np.median(diffs):+.0f} µs of server CPU per update")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
