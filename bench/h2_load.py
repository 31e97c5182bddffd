"""A lighter load generator for ``StreamFixes``: gRPC over HTTP/2 framed by the ``h2`` library.

grpcio's client spends more CPU per message than the server's own gRPC work (each message is
an operation of the C core whose completion wakes a poller thread and then the event loop).
This client speaks the same protocol directly on asyncio transports: per connection one
:class:`h2.connection.H2Connection`; per vehicle one HTTP/2 stream (a ``StreamFixes`` call)
whose requests are length-prefixed ``FixRequest`` messages written as they fall due, and
whose answers are parsed as they arrive (each answer's latency is taken from the send of its
``seq``). Every stream is still independent and paced, or keeps ``window`` fixes in flight,
as :func:`bench_service._vehicle` does. The windows this client grants the server are set
large once, so no ``WINDOW_UPDATE`` is sent per message.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

PATH = "/mapmatch.v1.MapMatch/StreamFixes"
BIG_WINDOW = 2**31 - 1


class _Conn(asyncio.Protocol):
    """One HTTP/2 connection and its streams (vehicles)."""

    def __init__(self, port: int, stats: dict[str, Any]) -> None:
        from h2.config import H2Configuration
        from h2.connection import H2Connection
        from h2.settings import SettingCodes, Settings

        self.h2 = H2Connection(H2Configuration(client_side=True, header_encoding=None))
        # sent with the connection's preface: the server may send this much on each stream
        self.h2.local_settings = Settings(
            client=True, initial_values={SettingCodes.INITIAL_WINDOW_SIZE: BIG_WINDOW}
        )
        self.port = port
        self.stats = stats
        self.ready = asyncio.get_running_loop().create_future()
        self.streams: dict[int, _Stream] = {}
        self.transport: Any = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport
        self.h2.initiate_connection()
        self.h2.increment_flow_control_window(BIG_WINDOW - 65_535)
        transport.write(self.h2.data_to_send())

    def open(self, stream: _Stream) -> int:
        sid = self.h2.get_next_available_stream_id()
        headers = [
            (b":method", b"POST"),
            (b":scheme", b"http"),
            (b":path", PATH.encode()),
            (b":authority", f"127.0.0.1:{self.port}".encode()),
            (b"content-type", b"application/grpc"),
            (b"te", b"trailers"),
        ]
        self.h2.send_headers(sid, headers)
        self.streams[sid] = stream
        self.transport.write(self.h2.data_to_send())
        return sid

    def send(self, sid: int, msg: bytes) -> None:
        self.h2.send_data(sid, b"\x00" + len(msg).to_bytes(4, "big") + msg)
        self.transport.write(self.h2.data_to_send())

    def end(self, sid: int) -> None:
        self.h2.end_stream(sid)
        self.transport.write(self.h2.data_to_send())

    def data_received(self, data: bytes) -> None:
        from h2 import events as ev

        for e in self.h2.receive_data(data):
            if isinstance(e, ev.DataReceived):
                self.streams[e.stream_id].feed(e.data)
            elif isinstance(e, ev.RemoteSettingsChanged) and not self.ready.done():
                self.ready.set_result(None)
            elif isinstance(e, ev.StreamEnded | ev.StreamReset):
                self.streams[e.stream_id].closed(reset=isinstance(e, ev.StreamReset))
        out = self.h2.data_to_send()
        if out:
            self.transport.write(out)

    def connection_lost(self, exc: Exception | None) -> None:
        for s in self.streams.values():
            s.closed(reset=True)


class _Stream:
    """One vehicle's ``StreamFixes`` call: its sends, its answers, their latencies."""

    def __init__(self, conn: _Conn, fixes: list[bytes], stats: dict[str, Any]) -> None:
        from service.gen import mapmatch_pb2 as pb

        self.conn, self.fixes, self.stats = conn, fixes, stats
        self.parse = pb.SnapResponse.FromString
        self.sent: dict[int, float] = {}
        self.buf = b""
        self.done = asyncio.get_running_loop().create_future()
        self.answered = asyncio.Event()
        self.sid = conn.open(self)

    def feed(self, data: bytes) -> None:
        buf = self.buf + data
        now = time.perf_counter()
        while len(buf) >= 5:
            n = int.from_bytes(buf[1:5], "big")
            if len(buf) < 5 + n:
                break
            resp = self.parse(buf[5 : 5 + n])
            buf = buf[5 + n :]
            t = self.sent.pop(resp.seq, None)
            if t is not None:
                self.stats["lat"].append(now - t)
                self.stats["at"].append(t)
            if resp.HasField("error"):
                self.stats["errors"] += 1
            self.stats["n"] += 1
            self.answered.set()
        self.buf = buf

    def closed(self, *, reset: bool) -> None:
        if self.sent and reset:
            self.stats["errors"] += len(self.sent)
            self.sent.clear()
        if not self.done.done():
            self.done.set_result(None)

    async def run(self, *, rate: float | None, window: int, t0: float, until: float, vid: str) -> None:
        clock = time.perf_counter
        start = t0 + (hash(vid) % 1000) / 1000.0 / (rate or 1.0)
        for k, msg in enumerate(self.fixes):
            if rate is not None:
                delay = start + k / rate - clock()
                if delay > 0:
                    await asyncio.sleep(delay)
            else:
                while len(self.sent) >= window:
                    self.answered.clear()
                    await self.answered.wait()
            now = clock()
            if now >= until:
                break
            self.sent[k] = now
            self.conn.send(self.sid, msg)
        deadline = clock() + 30.0
        while self.sent and clock() < deadline:  # the last answers
            self.answered.clear()
            try:
                await asyncio.wait_for(self.answered.wait(), deadline - clock())
            except TimeoutError:
                break
        self.conn.end(self.sid)
        await asyncio.wait_for(self.done, 30.0)


async def run_clients_h2(
    port: int,
    streams: list[tuple[str, list[bytes]]],
    *,
    rate: float | None,
    window: int,
    seconds: float,
    barrier: Any,
) -> dict[str, Any]:
    """Like :func:`bench_service._run_clients` for single-fix streams: ``streams`` are
    (vehicle id, serialised ``FixRequest`` messages); 4 connections; returns the stats."""
    stats: dict[str, Any] = {"lat": [], "at": [], "errors": 0, "n": 0}
    loop = asyncio.get_running_loop()
    conns: list[_Conn] = []
    for _ in range(4):
        _, proto = await loop.create_connection(lambda: _Conn(port, stats), "127.0.0.1", port)
        conns.append(proto)
    for c in conns:
        await c.ready
    vehicles = [(vid, _Stream(conns[i % 4], fixes, stats)) for i, (vid, fixes) in enumerate(streams)]
    ready, start = barrier
    ready.release()
    await loop.run_in_executor(None, start.wait)
    t0, c0 = time.perf_counter(), time.process_time()
    stats["t0"] = t0
    await asyncio.gather(
        *(s.run(rate=rate, window=window, t0=t0, until=t0 + seconds, vid=vid) for vid, s in vehicles)
    )
    stats["elapsed"] = time.perf_counter() - t0
    stats["cpu_s"] = time.process_time() - c0
    for c in conns:
        c.transport.close()
    return stats
