"""The load generator's own CPU per update: variants of ``bench_service.py``'s clients against
one server, interleaved.

The clients share the machine's cores with the server, so every µs they spend per update
queues the server. This starts one server (``mapmatch serve`` on the Helsinki map,
``--batch-processes 0``) and drives it with the same paced load (``--vehicles`` streams at
``--rate`` Hz, SIMULATED random walks) from each client variant in turn, the order reversed
every round: a variant is ``LOOP`` or ``LOOP/PROCESSES`` (the client processes' event loop,
``uvloop`` or ``asyncio``, and how many client processes share the streams; 2 by default).
Each line gives the clients' and the server's CPU per update, the p99 latency and the load
average; the last lines the medians over the rounds.

    python bench/bench_client_ab.py --variants asyncio,uvloop,uvloop/1 --rounds 3
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_service import Phase, ServerTree, drives, helsinki_map, run_phase, start_server  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="asyncio,uvloop", help="comma-separated LOOP or LOOP/PROCESSES")
    ap.add_argument("--vehicles", type=int, default=200)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--seconds", type=float, default=8.0, help="measured seconds per run")
    ap.add_argument("--warmup", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    variants = args.variants.split(",")
    total = args.warmup + args.seconds
    paced = drives(helsinki_map(), args.vehicles, int(total * args.rate) + 10, rate=args.rate, seed=1)
    proc, port = start_server(helsinki_map(), 20 * args.vehicles, 1000, 1, ("--batch-processes", "0"))
    server = ServerTree(proc.pid, 1)
    server.settle(quiet=2.0, timeout=60.0)
    rows: dict[str, list[tuple[float, float, float]]] = {v: [] for v in variants}
    try:
        for k in range(args.rounds):
            for v in variants if k % 2 == 0 else variants[::-1]:
                loop, _, clients = v.partition("/")
                phase = Phase(args.rate, 1, total, int(clients or 2), f"r{k}-{v}", loop=loop)
                r = run_phase(port, paced, phase, server=server)
                steady = r["at"] >= args.warmup
                n = max(r["n"], 1)
                row = (
                    1e6 * r["client_cpu_s"] / n,
                    1e6 * r["cpu_s"] / n,
                    float(np.percentile(r["lat"][steady] * 1e3, 99)) if steady.any() else float("nan"),
                )
                rows[v].append(row)
                print(
                    f"round {k + 1} {v:12s} client {row[0]:.0f} µs, server {row[1]:.0f} µs per update, "
                    f"p99 {row[2]:.1f} ms, {r['errors']} errors (load {os.getloadavg()[0]:.2f})",
                    flush=True,
                )
    finally:
        proc.terminate()
        proc.wait(30)
    for v, got in rows.items():
        a = np.array(got)
        print(
            f"{v:12s} medians over {len(got)} rounds: client {np.median(a[:, 0]):.0f} µs, "
            f"server {np.median(a[:, 1]):.0f} µs per update, p99 {np.median(a[:, 2]):.1f} ms"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
