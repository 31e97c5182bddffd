"""What checkpoint passes cost the fixes, in process: the lateness of paced fixes with and
without a checkpoint thread beside them.

The server's own update path (:meth:`service.servicer.MapMatchServicer.snap`, no gRPC) runs on
one thread, as the event loop runs it: ``--vehicles`` vehicles at ``--rate`` Hz (200 x 10 Hz:
2,000 fixes a second, SIMULATED random walks on the Helsinki map), each fix started at its
scheduled time and its lateness taken when its answer is ready (the time it waited for the
interpreter and the fixes before it, plus its own update). Every session first gets
``--fill`` fixes (30 s at 10 Hz), so checkpoints write sessions at their full size. Windows of
``--window`` s alternate between no checkpoint thread and a :class:`Checkpointer
<service.store_checkpoints.Checkpointer>` writing to a ``redis-server`` this bench starts
(checkpoint interval ``--interval``); the lateness p50/p99/max of each kind is printed with the
checkpoint thread's CPU per session written and the machine's load. Both kinds share the
machine's noise, so the A/B difference holds on a loaded machine where the service bench's
latencies do not.

    python bench/bench_checkpoint_stall.py              # 4 windows of each kind, 3 s each
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_fleet import redis_server  # noqa: E402
from bench_service import drives, helsinki_map  # noqa: E402


def servicer() -> Any:
    """A servicer on the Helsinki map with its session table (no gRPC server)."""
    from concurrent.futures import ThreadPoolExecutor

    from graph.artifact import load_map
    from service.maps import MapRegistry
    from service.servicer import MapMatchServicer
    from service.sessions import SessionStore

    maps = MapRegistry()
    maps.install(maps.prepare("helsinki", load_map(helsinki_map(), verify=False), source="bench"))
    sessions = SessionStore(max_sessions=100_000, ttl=600.0)
    return MapMatchServicer(maps=maps, sessions=sessions, executor=ThreadPoolExecutor(1))


def window(api: Any, reqs: list[list[Any]], at: int, seconds: float, rate: float) -> tuple[np.ndarray, int]:
    """Fixes ``at``, ``at + 1``, ... of every vehicle, paced; returns their lateness (s) and
    the next fix index."""
    n = len(reqs)
    ticks = int(seconds * rate)
    late = np.empty(ticks * n)
    gap = 1.0 / (rate * n)
    t0 = time.perf_counter() + 0.01
    k = 0
    for tick in range(ticks):
        for v in range(n):
            due = t0 + k * gap
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            api.snap(reqs[v][at + tick])
            late[k] = time.perf_counter() - due
            k += 1
    return late, at + ticks


def run(args: argparse.Namespace) -> int:
    from service.gen import mapmatch_pb2 as pb
    from service.store import RedisStore
    from service.store_checkpoints import Checkpointer, CheckpointSettings

    steps = args.fill + int(2 * args.windows * args.window * args.rate) + 10
    walks = drives(helsinki_map(), args.vehicles, steps, rate=args.rate, seed=5)
    reqs = [
        [pb.FixRequest(map_id="helsinki", vehicle_id=f"v{i}", fix=f) for f in fixes]
        for i, fixes in enumerate(walks)
    ]
    api = servicer()
    t = time.perf_counter()
    for k in range(args.fill):
        for v in reqs:
            api.snap(v[k])
    tree = Path(sys.modules["service"].__file__ or "").parents[1]
    print(f"# {args.vehicles} sessions filled with {args.fill} fixes each in {time.perf_counter() - t:.1f} s "
          f"(load {os.getloadavg()[0]:.2f}; code of {tree})", flush=True)  # fmt: skip
    got: dict[str, list[np.ndarray]] = {"off": [], "on": []}
    cpu = {"seconds": 0.0, "written": 0}
    at = args.fill
    with redis_server() as port:
        for _ in range(args.windows):
            for kind in ("off", "on"):
                ck = None
                if kind == "on":
                    store = RedisStore(f"redis://127.0.0.1:{port}/0", timeout=1.0)
                    settings = CheckpointSettings(interval=args.interval)
                    ck = Checkpointer(store=store, sessions=api.sessions, maps=api.maps, settings=settings)
                    ck.start()
                late, at = window(api, reqs, at, args.window, args.rate)
                got[kind].append(late)
                if ck is not None:
                    thread = ck._thread
                    ck._stopping = True  # no last pass: it would fall outside the window
                    ck._wake.set()
                    if thread is not None:
                        thread.join(10)
                    cpu["seconds"] += ck.counters.write_seconds
                    cpu["written"] += ck.counters.written
                    store.close()
    print(f"\n## {args.vehicles} vehicles x {args.rate:g} Hz in process, {args.windows} windows of "
          f"{args.window:g} s each kind, checkpoint interval {args.interval:g} s\n")  # fmt: skip
    for kind, lates in got.items():
        ms = 1000.0 * np.concatenate(lates)
        p50, p99 = np.percentile(ms, [50, 99])
        print(f"checkpoints {kind:3s}   fix lateness p50 {p50:.2f} ms, p99 {p99:.2f} ms, "
              f"max {ms.max():.1f} ms")  # fmt: skip
    per = 1e6 * cpu["seconds"] / max(cpu["written"], 1)
    print(f"checkpoint thread       {cpu['written']} sessions written, {per:.0f} µs wall per session "
          f"(encode + write; load {os.getloadavg()[0]:.2f})")  # fmt: skip
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--vehicles", type=int, default=200)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--fill", type=int, default=300, help="fixes per session before the windows")
    ap.add_argument("--windows", type=int, default=4, help="windows of each kind")
    ap.add_argument("--window", type=float, default=3.0, help="seconds per window")
    ap.add_argument("--interval", type=float, default=1.0, help="checkpoint interval (s)")
    return run(ap.parse_args())


if __name__ == "__main__":
    sys.exit(main())
