"""The protocol's own cost: server CPU per message of a ``StreamFixes`` that does no work.

A grpc.aio server whose ``StreamFixes`` answers every ``FixRequest`` with one fixed, typical
``SnapResponse`` (no session, no matcher, no interceptors) runs in its own process; client
processes push fixes over ``--streams`` bidirectional streams. Printed: messages answered,
the server's CPU seconds per message and the updates/s one core could answer at that cost.
This is the floor under ``bench_service.py``'s "server CPU per update": what is left above
it is ours (interceptors, conversion, sessions, the matcher). ``--style`` compares handler
styles: ``iter`` (async for / yield, as the service does), ``rw`` (context.read / write),
``sync`` (the thread-pool server).

    python bench/bench_grpc_floor.py
    python bench/bench_grpc_floor.py --style rw --messages 1000
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import random
import sys
import time
from concurrent import futures
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import grpc  # noqa: E402
import psutil  # noqa: E402
from grpc import aio  # noqa: E402

from service.gen import mapmatch_pb2 as pb  # noqa: E402
from service.gen import mapmatch_pb2_grpc as pbg  # noqa: E402


def _answer() -> Any:
    cands = [
        {"edge": 3, "u": 11, "v": 12, "probability": 0.9},
        {"edge": 4, "u": 12, "v": 13, "probability": 0.1},
    ]
    result = {
        "time": 1.0, "state": pb.STATE_ON_ROAD, "edge": 3, "u": 11, "v": 12, "way_id": 7, "offset": 10.0,
        "lat": 60.1, "lon": 24.9, "bearing": 90.0, "dist": 2.0, "candidates": cands, "raw_lat": 60.1,
        "raw_lon": 24.9, "name": "Mannerheimintie", "road_class": "primary", "speed_kph": 50.0,
        "map_aided": {"lat": 60.1, "lon": 24.9, "cov": [4.0, 0.0, 4.0], "probability": 0.9, "usable": True},
    }  # fmt: skip
    return pb.SnapResponse(map_id="hel", vehicle_id="v1", seq=1, result=result)


ANSWER = _answer()


class IterStyle(pbg.MapMatchServicer):
    async def StreamFixes(self, it: Any, context: Any) -> Any:
        async for _ in it:
            yield ANSWER


class ReadWriteStyle(pbg.MapMatchServicer):
    async def StreamFixes(self, it: Any, context: Any) -> None:
        while True:
            req = await context.read()
            if req is aio.EOF:
                return
            await context.write(ANSWER)


class SyncStyle(pbg.MapMatchServicer):
    def StreamFixes(self, it: Any, context: Any) -> Any:
        for _ in it:
            yield ANSWER


def serve(style: str, port_q: Any, options: tuple[tuple[str, Any], ...] = ()) -> None:
    style, _, loop = style.partition("+")
    if style == "sync":
        server = grpc.server(futures.ThreadPoolExecutor(max_workers=256), options=options)
        pbg.add_MapMatchServicer_to_server(SyncStyle(), server)
        port_q.put(server.add_insecure_port("127.0.0.1:0"))
        server.start()
        server.wait_for_termination()
        return

    async def main() -> None:
        server = aio.server(options=options)
        pbg.add_MapMatchServicer_to_server(IterStyle() if style == "iter" else ReadWriteStyle(), server)
        port_q.put(server.add_insecure_port("127.0.0.1:0"))
        await server.start()
        await server.wait_for_termination()

    if loop == "uvloop":
        import uvloop

        uvloop.run(main())
    else:
        asyncio.run(main())


def client(port: int, streams: int, messages: int, out_q: Any, rate: float = 0.0) -> None:
    fix = pb.Fix(time=1.0, lat=60.1, lon=24.9, heading=90.0, speed=10.0)
    req = pb.FixRequest(map_id="hel", vehicle_id="v1", seq=1, fix=fix)

    async def one(stub: Any) -> int:
        call = stub.StreamFixes()

        async def read() -> int:
            n = 0
            async for _ in call:
                n += 1
            return n

        reader = asyncio.ensure_future(read())
        t0 = time.perf_counter() + random.random() / rate if rate else 0.0
        for k in range(messages):
            if rate:  # paced: one fix every 1/rate s, as a vehicle sends them
                await asyncio.sleep(max(0.0, t0 + k / rate - time.perf_counter()))
            await call.write(req)
        await call.done_writing()
        return await reader

    async def main() -> None:
        async with aio.insecure_channel(f"127.0.0.1:{port}") as ch:
            stub = pbg.MapMatchStub(ch)
            t, c = time.perf_counter(), time.process_time()
            n = await asyncio.gather(*[one(stub) for _ in range(streams)])
            out_q.put((sum(n), time.perf_counter() - t, time.process_time() - c))

    asyncio.run(main())


def measure(
    style: str,
    *,
    clients: int,
    streams: int,
    messages: int,
    rate: float = 0.0,
    options: tuple[tuple[str, Any], ...] = (),
) -> tuple[int, float, float, float]:
    """(messages answered, server CPU seconds per message, wall seconds, client CPU seconds
    per message)."""
    ctx = mp.get_context("spawn")
    port_q, out_q = ctx.Queue(), ctx.Queue()
    server = ctx.Process(target=serve, args=(style, port_q, options), daemon=True)
    server.start()
    try:
        port = port_q.get(timeout=60)
        ps = psutil.Process(server.pid)
        warm = ctx.Process(target=client, args=(port, 4, 200, out_q))
        warm.start()
        out_q.get(timeout=120)
        warm.join()
        cpu0 = sum(ps.cpu_times()[:2])
        procs = [
            ctx.Process(target=client, args=(port, streams, messages, out_q, rate)) for _ in range(clients)
        ]
        for p in procs:
            p.start()
        res = [out_q.get(timeout=600) for _ in procs]
        for p in procs:
            p.join()
        cpu = sum(ps.cpu_times()[:2]) - cpu0
    finally:
        server.terminate()
        server.join()
    n = sum(r[0] for r in res)
    return n, cpu / max(n, 1), max(r[1] for r in res), sum(r[2] for r in res) / max(n, 1)


def _options(text: str) -> tuple[tuple[str, Any], ...]:
    """``name=value,name=value`` as gRPC server options (integer values as integers);
    ``env:NAME=value`` sets an environment variable of the server process instead."""
    out: list[tuple[str, Any]] = []
    for part in filter(None, text.split(",")):
        name, _, value = part.partition("=")
        if not name.startswith("env:"):
            out.append((name, int(value) if value.lstrip("-").isdigit() else value))
    return tuple(out)


def _env(text: str) -> dict[str, str]:
    """The ``env:NAME=value`` parts of an option set."""
    parts = (p.partition("=") for p in filter(None, text.split(",")))
    return {name[4:]: value for name, _, value in parts if name.startswith("env:")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--style",
        default="iter,rw,sync",
        help="comma-separated: iter, rw, sync; an aio style may end in +uvloop (its event loop)",
    )
    ap.add_argument("--clients", type=int, default=2, help="client processes")
    ap.add_argument("--streams", type=int, default=25, help="streams per client process")
    ap.add_argument("--messages", type=int, default=400, help="fixes per stream")
    ap.add_argument(
        "--rate", type=float, default=0.0, help="fixes per second per stream (0: as fast as answered)"
    )
    ap.add_argument(
        "--options",
        action="append",
        default=[],
        help="a set of server options, name=value,... or env:NAME=value (repeat: each set is a variant)",
    )
    ap.add_argument(
        "--repeat", type=int, default=2, help="runs per variant, interleaved (the least CPU is printed)"
    )
    a = ap.parse_args()
    load = " ".join(f"{x:.2f}" for x in psutil.getloadavg())
    print(f"load average before: {load} ({psutil.cpu_count()} cores)")
    variants = [(style, o) for style in a.style.split(",") for o in (a.options or [""])]
    runs: dict[tuple[str, str], list[tuple[int, float, float, float]]] = {v: [] for v in variants}
    kw = {"clients": a.clients, "streams": a.streams, "messages": a.messages, "rate": a.rate}
    for k in range(a.repeat):  # interleaved: the machine's load drifts alike over every variant
        for style, o in variants if k % 2 == 0 else variants[::-1]:
            saved = {k: os.environ.get(k) for k in _env(o)}
            os.environ.update(_env(o))  # inherited by the server process (and the clients)
            try:
                runs[(style, o)].append(measure(style, options=_options(o), **kw))
            finally:
                for name, value in saved.items():
                    if value is None:
                        os.environ.pop(name, None)
                    else:
                        os.environ[name] = value
    for (style, o), got in runs.items():
        n, per, wall, client_per = min(got, key=lambda r: r[1])
        print(
            f"{style:11s} {o or '(default options)'}: {n} messages, server CPU {per * 1e6:.1f} us per "
            f"message (one core: at most {1 / per:,.0f} messages/s; all runs "
            f"{', '.join(f'{r[1] * 1e6:.0f}' for r in got)}), client CPU {client_per * 1e6:.1f} us, "
            f"wall {wall:.1f} s (load {psutil.getloadavg()[0]:.2f})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
